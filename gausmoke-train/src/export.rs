//! Files other tools open: Gaussians as a 3DGS `.ply`, grids as VTK `.vti` (ParaView) and
//! NumPy `.npz`. Grids are `[nx, ny, nz, C]` row-major (z fastest), cell-centred on the
//! [`GridSpec`] box.

use std::io::Write;
use std::path::Path;

use gausmoke_model::GridSpec;

use crate::TrainError;
use crate::config::PlyAxes;
use gausmoke_render::HostGaussians;

/// Zeroth-order spherical-harmonic constant: 3DGS stores colour as `(rgb - 0.5) / C0`.
const SH_C0: f32 = 0.282_094_8;
/// Higher-order SH coefficients 3DGS viewers expect (degree 3: 15 per channel), all zero.
const SH_REST: usize = 45;

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> TrainError + '_ {
    move |source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Writes `path` via a temporary file, flushed to the disk, and a rename, so neither a crash
/// nor a power loss leaves a half or empty file under the final name.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), TrainError> {
    let tmp = path.with_extension("partial");
    let mut file = std::fs::File::create(&tmp).map_err(io_error(&tmp))?;
    file.write_all(bytes).map_err(io_error(&tmp))?;
    file.sync_all().map_err(io_error(&tmp))?;
    drop(file);
    std::fs::rename(&tmp, path).map_err(io_error(path))
}

/// Flushes a file, or a folder's entries, to the disk: a rename is only durable once the
/// renamed file's data and the folder holding the new name both are.
pub fn sync_to_disk(path: &Path) -> Result<(), TrainError> {
    match std::fs::File::open(path) {
        Ok(file) => file.sync_all().map_err(io_error(path)),
        // Folders cannot be opened for syncing on every platform; their files still are.
        Err(_) if path.is_dir() && !cfg!(unix) => Ok(()),
        Err(source) => Err(io_error(path)(source)),
    }
}

/// The Gaussians in the binary little-endian layout of the 3DGS reference implementation,
/// which common splat viewers read. Volumetric density has no exact 3DGS counterpart: the
/// `opacity` written is the logit of the alpha of a ray through the centre along a
/// direction of the geometric-mean scale, `1 - exp(-sigma sqrt(2 pi) s)`.
///
/// With [`PlyAxes::YDown`] every Gaussian is turned half a turn about x: centre
/// `(x, -y, -z)`, rotation `q_x(pi) q` (the scales, along the Gaussian's own axes, stay).
pub fn write_ply(path: &Path, gaussians: &HostGaussians, axes: PlyAxes) -> Result<(), TrainError> {
    let n = gaussians.len();
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {n}\n\
         property float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\n"
    );
    for i in 0..3 {
        header += &format!("property float f_dc_{i}\n");
    }
    for i in 0..SH_REST {
        header += &format!("property float f_rest_{i}\n");
    }
    header += "property float opacity\n";
    for i in 0..3 {
        header += &format!("property float scale_{i}\n");
    }
    for i in 0..4 {
        header += &format!("property float rot_{i}\n");
    }
    header += "end_header\n";
    let floats_per_vertex = 6 + 3 + SH_REST + 1 + 3 + 4;
    let mut bytes = Vec::with_capacity(header.len() + n * floats_per_vertex * 4);
    bytes.extend_from_slice(header.as_bytes());
    let mut push = |v: f32| bytes.extend_from_slice(&v.to_le_bytes());
    for i in 0..n {
        let turn = match axes {
            PlyAxes::World => [1.0, 1.0, 1.0],
            PlyAxes::YDown => [1.0, -1.0, -1.0],
        };
        for (sign, mean) in turn.iter().zip(&gaussians.means[3 * i..3 * i + 3]) {
            push(sign * mean);
        }
        for _ in 0..3 {
            push(0.0);
        }
        for a in 0..3 {
            push((gaussians.colors[3 * i + a] - 0.5) / SH_C0);
        }
        for _ in 0..SH_REST {
            push(0.0);
        }
        let raw = gaussians.raw_densities[i];
        let sigma = gausmoke_render::math::softplus(raw);
        let mean_log_scale = (0..3).map(|a| gaussians.log_scales[3 * i + a]).sum::<f32>() / 3.0;
        let alpha = (1.0
            - (-sigma * (2.0 * std::f32::consts::PI).sqrt() * mean_log_scale.exp()).exp())
        .clamp(1e-6, 1.0 - 1e-6);
        push((alpha / (1.0 - alpha)).ln());
        for a in 0..3 {
            push(gaussians.log_scales[3 * i + a]);
        }
        let q = &gaussians.rotations[4 * i..4 * i + 4];
        let rotation = match axes {
            PlyAxes::World => [q[0], q[1], q[2], q[3]],
            // (0, 1, 0, 0) * (w, x, y, z) = (-x, w, -z, y).
            PlyAxes::YDown => [-q[1], q[0], -q[3], q[2]],
        };
        for v in rotation {
            push(v);
        }
    }
    write_atomic(path, &bytes)
}

/// Reorders a `[nx, ny, nz, C]` (z fastest) grid to VTK's x-fastest point order.
fn x_fastest(grid: &GridSpec, values: &[f32], channels: usize) -> Vec<f32> {
    let [nx, ny, nz] = grid.resolution();
    let mut out = Vec::with_capacity(values.len());
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let cell = (i * ny + j) * nz + k;
                out.extend_from_slice(&values[cell * channels..(cell + 1) * channels]);
            }
        }
    }
    out
}

/// Density `[nx, ny, nz]`, velocity `[nx, ny, nz, 3]` and each of `vectors` (a name and a
/// `[nx, ny, nz, 3]` field) as VTK XML ImageData with raw appended data: points at the cell
/// centres, spacing = cell size, world units.
pub fn write_vti(
    path: &Path,
    grid: &GridSpec,
    density: &[f32],
    velocity: &[f32],
    vectors: &[(&str, &[f32])],
) -> Result<(), TrainError> {
    let [nx, ny, nz] = grid.resolution();
    let cell = grid.cell_size();
    let origin = grid.lo() + 0.5 * cell;
    let mut fields = vec![("density", 1, x_fastest(grid, density, 1))];
    fields.push(("velocity", 3, x_fastest(grid, velocity, 3)));
    fields.extend(
        vectors
            .iter()
            .map(|(name, values)| (*name, 3, x_fastest(grid, values, 3))),
    );
    let mut arrays = String::new();
    let mut offset = 0u64;
    for (name, components, values) in &fields {
        arrays += &format!(
            "<DataArray type=\"Float32\" Name=\"{name}\" NumberOfComponents=\"{components}\" \
             format=\"appended\" offset=\"{offset}\"/>\n"
        );
        offset += 8 + 4 * values.len() as u64;
    }
    let header = format!(
        "<?xml version=\"1.0\"?>\n\
         <VTKFile type=\"ImageData\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\">\n\
         <ImageData WholeExtent=\"0 {} 0 {} 0 {}\" Origin=\"{} {} {}\" Spacing=\"{} {} {}\">\n\
         <Piece Extent=\"0 {} 0 {} 0 {}\">\n\
         <PointData Scalars=\"density\" Vectors=\"velocity\">\n{arrays}\
         </PointData>\n</Piece>\n</ImageData>\n<AppendedData encoding=\"raw\">\n_",
        nx - 1,
        ny - 1,
        nz - 1,
        origin.x,
        origin.y,
        origin.z,
        cell.x,
        cell.y,
        cell.z,
        nx - 1,
        ny - 1,
        nz - 1,
    );
    let mut bytes = header.into_bytes();
    for (_, _, values) in &fields {
        bytes.extend_from_slice(&(4 * values.len() as u64).to_le_bytes());
        values
            .iter()
            .for_each(|v| bytes.extend_from_slice(&v.to_le_bytes()));
    }
    bytes.extend_from_slice(b"\n</AppendedData>\n</VTKFile>\n");
    write_atomic(path, &bytes)
}

/// A ParaView time series (`.pvd`, VTK's "Collection" XML) of files beside it: `(time, file
/// name)` pairs, so ParaView's reader plays the `.vti` frames with their times.
pub fn write_pvd(path: &Path, datasets: &[(f64, String)]) -> Result<(), TrainError> {
    let escape = |name: &str| {
        name.replace('&', "&amp;")
            .replace('"', "&quot;")
            .replace('<', "&lt;")
            .replace('>', "&gt;")
    };
    let mut xml = String::from(
        "<?xml version=\"1.0\"?>\n\
         <VTKFile type=\"Collection\" version=\"0.1\" byte_order=\"LittleEndian\">\n\
         <Collection>\n",
    );
    for (time, file) in datasets {
        xml += &format!(
            "<DataSet timestep=\"{time}\" group=\"\" part=\"0\" file=\"{}\"/>\n",
            escape(file)
        );
    }
    xml += "</Collection>\n</VTKFile>\n";
    write_atomic(path, xml.as_bytes())
}

/// One `.npy` (format 1.0, little-endian f32, C order).
fn npy(values: &[f32], shape: &[usize]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_text = if dims.len() == 1 {
        format!("({},)", dims[0])
    } else {
        format!("({})", dims.join(", "))
    };
    let mut dict = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape_text}, }}");
    // Magic (6) + version (2) + length (2) + dict + '\n' is padded to a multiple of 64.
    let unpadded = 10 + dict.len() + 1;
    dict += &" ".repeat(unpadded.next_multiple_of(64) - unpadded);
    dict.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    values
        .iter()
        .for_each(|v| out.extend_from_slice(&v.to_le_bytes()));
    out
}

/// What every `.npz` export says of its arrays' layout and units (its `layout` array).
pub const NPZ_LAYOUT: &str = "density[i, j, k] and velocity[i, j, k, :] belong to cell (i, j, k): \
i along world x, j along y, k along z (C order, so z is fastest in memory); the cell's centre \
is lo + (index + 0.5) * (hi - lo) / shape; density in the model's units (the Gaussians' summed \
densities), velocity in world units per frame, lo and hi in world units";

/// One `.npy` holding `text` as a NumPy unicode scalar (`np.load(path)["layout"]` reads it
/// without pickling).
fn npy_text(text: &str) -> Vec<u8> {
    let chars: Vec<char> = text.chars().collect();
    let mut dict = format!(
        "{{'descr': '<U{}', 'fortran_order': False, 'shape': (), }}",
        chars.len()
    );
    let unpadded = 10 + dict.len() + 1;
    dict += &" ".repeat(unpadded.next_multiple_of(64) - unpadded);
    dict.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    chars
        .iter()
        .for_each(|&c| out.extend_from_slice(&(c as u32).to_le_bytes()));
    out
}

/// `density [nx, ny, nz]`, `velocity [nx, ny, nz, 3]`, `lo`, `hi` (world box), `layout`
/// ([`NPZ_LAYOUT`]) and each of `vectors` (a name and a `[nx, ny, nz, 3]` field) in one
/// `.npz`: `np.load(path)["velocity"][i, j, k]` is the velocity of cell (i, j, k).
pub fn write_npz(
    path: &Path,
    grid: &GridSpec,
    density: &[f32],
    velocity: &[f32],
    vectors: &[(&str, &[f32])],
) -> Result<(), TrainError> {
    write_npz_members(path, npz_members(grid, density, velocity, vectors))
}

/// [`write_npz`] over an existing `.npz` at `path`: its arrays not named here (a run's
/// `refine_move`, say) are kept as they are.
pub fn rewrite_npz(
    path: &Path,
    grid: &GridSpec,
    density: &[f32],
    velocity: &[f32],
    vectors: &[(&str, &[f32])],
) -> Result<(), TrainError> {
    let mut members = npz_members(grid, density, velocity, vectors);
    if path.is_file() {
        let export_error = |reason: String| TrainError::Export {
            path: path.to_path_buf(),
            reason,
        };
        let file = std::fs::File::open(path).map_err(io_error(path))?;
        let mut old = zip::ZipArchive::new(file).map_err(|e| export_error(e.to_string()))?;
        for index in 0..old.len() {
            let mut member = old
                .by_index(index)
                .map_err(|e| export_error(e.to_string()))?;
            if members.iter().any(|(name, _)| name == member.name()) {
                continue;
            }
            let mut data = Vec::new();
            std::io::Read::read_to_end(&mut member, &mut data).map_err(io_error(path))?;
            members.push((member.name().to_string(), data));
        }
    }
    write_npz_members(path, members)
}

fn npz_members(
    grid: &GridSpec,
    density: &[f32],
    velocity: &[f32],
    vectors: &[(&str, &[f32])],
) -> Vec<(String, Vec<u8>)> {
    let [nx, ny, nz] = grid.resolution();
    let mut members: Vec<(String, Vec<u8>)> = vec![
        ("density.npy".into(), npy(density, &[nx, ny, nz])),
        ("velocity.npy".into(), npy(velocity, &[nx, ny, nz, 3])),
        ("lo.npy".into(), npy(&grid.lo().to_array(), &[3])),
        ("hi.npy".into(), npy(&grid.hi().to_array(), &[3])),
        ("layout.npy".into(), npy_text(NPZ_LAYOUT)),
    ];
    members.extend(
        vectors
            .iter()
            .map(|(name, values)| (format!("{name}.npy"), npy(values, &[nx, ny, nz, 3]))),
    );
    members
}

fn write_npz_members(path: &Path, members: Vec<(String, Vec<u8>)>) -> Result<(), TrainError> {
    let export_error = |e: zip::result::ZipError| TrainError::Export {
        path: path.to_path_buf(),
        reason: e.to_string(),
    };
    let mut buffer = std::io::Cursor::new(Vec::new());
    {
        let mut zip = zip::ZipWriter::new(&mut buffer);
        let options =
            zip::write::FileOptions::default().compression_method(zip::CompressionMethod::Stored);
        for (name, data) in members {
            zip.start_file(name, options)
                .and_then(|_| zip.write_all(&data).map_err(Into::into))
                .map_err(export_error)?;
        }
        zip.finish().map_err(export_error)?;
    }
    write_atomic(path, &buffer.into_inner())
}

/// The `.npz` at `path` as its members' names (without `.npy`) and their `.npy` headers and
/// data bytes, for tests that read exports back.
#[cfg(test)]
pub(crate) fn read_npz(path: &Path) -> std::collections::BTreeMap<String, (String, Vec<u8>)> {
    let mut archive = zip::ZipArchive::new(std::fs::File::open(path).unwrap()).unwrap();
    (0..archive.len())
        .map(|index| {
            let mut member = archive.by_index(index).unwrap();
            let mut bytes = Vec::new();
            std::io::Read::read_to_end(&mut member, &mut bytes).unwrap();
            let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
            let header = String::from_utf8(bytes[10..10 + header_len].to_vec()).unwrap();
            let name = member.name().trim_end_matches(".npy").to_string();
            (name, (header, bytes[10 + header_len..].to_vec()))
        })
        .collect()
}

/// The f32 values of an `.npy`'s data bytes.
#[cfg(test)]
pub(crate) fn floats(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use gausmoke_core::glam::Vec3;

    #[test]
    fn npy_header_is_aligned_and_parsable() {
        let bytes = npy(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], &[2, 3]);
        let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + header_len) % 64, 0);
        let header = std::str::from_utf8(&bytes[10..10 + header_len]).unwrap();
        assert!(header.contains("'shape': (2, 3)") && header.ends_with('\n'));
        assert_eq!(bytes.len(), 10 + header_len + 24);
    }

    #[test]
    fn ply_has_the_3dgs_properties_and_one_record_per_gaussian() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("g.ply");
        let gaussians = HostGaussians {
            means: vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
            rotations: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            log_scales: vec![-3.0; 6],
            raw_densities: vec![0.0, 5.0],
            colors: vec![0.5; 6],
        };
        write_ply(&path, &gaussians, PlyAxes::World).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let end = b"end_header\n";
        let at = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
        let header = std::str::from_utf8(&bytes[..at]).unwrap();
        for name in ["f_dc_0", "f_rest_44", "opacity", "scale_2", "rot_3"] {
            assert!(
                header.contains(&format!("property float {name}\n")),
                "{name}"
            );
        }
        assert_eq!(bytes.len() - at, 2 * 62 * 4);
        // Second vertex starts with its centre (3, 4, 5).
        let second = &bytes[at + 62 * 4..];
        let x = f32::from_le_bytes(second[..4].try_into().unwrap());
        assert_eq!(x, 3.0);
    }

    #[test]
    fn y_down_ply_turns_centres_and_orientations_half_a_turn_about_x() {
        use gausmoke_core::glam::{Mat3, Quat};
        let dir = tempfile::tempdir().unwrap();
        let q = Quat::from_euler(gausmoke_core::glam::EulerRot::XYZ, 0.3, -0.7, 1.1);
        let gaussians = HostGaussians {
            means: vec![0.5, 1.5, -2.0],
            rotations: vec![q.w, q.x, q.y, q.z],
            log_scales: vec![-3.0, -2.0, -1.0],
            raw_densities: vec![1.0],
            colors: vec![0.5; 3],
        };
        let read = |axes: PlyAxes| -> Vec<f32> {
            let path = dir.path().join("g.ply");
            write_ply(&path, &gaussians, axes).unwrap();
            let bytes = std::fs::read(&path).unwrap();
            let end = b"end_header\n";
            let at = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
            bytes[at..]
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
                .collect()
        };
        let (world, down) = (read(PlyAxes::World), read(PlyAxes::YDown));
        assert_eq!(&down[..3], &[0.5, -1.5, 2.0]);
        assert_eq!(&down[55..58], &world[55..58], "scales stay");
        let rotation = |v: &[f32]| Mat3::from_quat(Quat::from_xyzw(v[1], v[2], v[3], v[0]));
        let turned = Mat3::from_rotation_x(std::f32::consts::PI) * rotation(&world[58..62]);
        let written = rotation(&down[58..62]);
        let error = (turned - written)
            .to_cols_array()
            .iter()
            .fold(0.0f32, |m, d| m.max(d.abs()));
        assert!(error < 1e-6, "{error}");
    }

    #[test]
    fn vti_reorders_to_x_fastest() {
        let grid = GridSpec::new(Vec3::ZERO, Vec3::new(2.0, 1.0, 1.0), [2, 1, 2], 1).unwrap();
        // Our layout: cell (i, j, k) at (i * ny + j) * nz + k; value = 10 i + k.
        let values = vec![0.0, 1.0, 10.0, 11.0];
        assert_eq!(x_fastest(&grid, &values, 1), vec![0.0, 10.0, 1.0, 11.0]);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("g.vti");
        write_vti(&path, &grid, &values, &[0.0; 12], &[]).unwrap();
        let text = String::from_utf8_lossy(&std::fs::read(&path).unwrap()).into_owned();
        assert!(text.contains("WholeExtent=\"0 1 0 0 0 1\""));
        assert!(text.contains("Spacing=\"1 1 0.5\""));
    }

    /// The `.npz` says its layout; rewriting one keeps the arrays it does not name.
    #[test]
    fn npz_carries_its_layout_and_a_rewrite_keeps_other_arrays() {
        let grid = GridSpec::new(Vec3::ZERO, Vec3::ONE, [1, 1, 2], 1).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("g.npz");
        let moves = [7.0; 6];
        write_npz(
            &path,
            &grid,
            &[1.0, 2.0],
            &[0.5; 6],
            &[("refine_move", &moves)],
        )
        .unwrap();
        let read = read_npz(&path);
        let (header, text) = &read["layout"];
        assert!(header.contains("'descr': '<U") && header.contains("'shape': ()"));
        let text: String = text
            .chunks_exact(4)
            .map(|c| char::from_u32(u32::from_le_bytes(c.try_into().unwrap())).unwrap())
            .collect();
        assert_eq!(text, NPZ_LAYOUT);
        rewrite_npz(
            &path,
            &grid,
            &[1.0, 2.0],
            &[3.0; 6],
            &[("grid_velocity", &[0.5; 6])],
        )
        .unwrap();
        let read = read_npz(&path);
        let names: Vec<&str> = read.keys().map(String::as_str).collect();
        assert_eq!(
            names,
            [
                "density",
                "grid_velocity",
                "hi",
                "layout",
                "lo",
                "refine_move",
                "velocity"
            ]
        );
        assert_eq!(floats(&read["velocity"].1), [3.0; 6]);
        assert_eq!(floats(&read["grid_velocity"].1), [0.5; 6]);
        assert_eq!(floats(&read["refine_move"].1), moves);
    }

    /// Each field of a `.vti` sits at the offset its header gives.
    #[test]
    fn vti_fields_sit_at_their_offsets() {
        let grid = GridSpec::new(Vec3::ZERO, Vec3::ONE, [1, 1, 2], 1).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("g.vti");
        let extra = [9.0f32; 6];
        write_vti(
            &path,
            &grid,
            &[1.0, 2.0],
            &[3.0; 6],
            &[("grid_velocity", &extra)],
        )
        .unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let text = String::from_utf8_lossy(&bytes).into_owned();
        let marker = b"encoding=\"raw\">\n_";
        let data = bytes
            .windows(marker.len())
            .position(|w| w == marker)
            .unwrap()
            + marker.len();
        for (name, first, count) in [
            ("density", 1.0, 2),
            ("velocity", 3.0, 6),
            ("grid_velocity", 9.0, 6),
        ] {
            let tag = format!("Name=\"{name}\"");
            let at = text.find(&tag).unwrap();
            let offset: usize = text[at..]
                .split("offset=\"")
                .nth(1)
                .unwrap()
                .split('"')
                .next()
                .unwrap()
                .parse()
                .unwrap();
            let start = data + offset;
            let length = u64::from_le_bytes(bytes[start..start + 8].try_into().unwrap());
            assert_eq!(length, 4 * count, "{name}");
            let value = f32::from_le_bytes(bytes[start + 8..start + 12].try_into().unwrap());
            assert_eq!(value, first, "{name}");
        }
    }
}
