//! The scene's boundary and source: which faces of the smoke box the flow crosses, and the
//! inflow box where the smoke enters. They belong to the data, not to a method, so a run
//! takes them, key by key, from the first of:
//!
//! 1. the configuration (`[scene]` in `--config`, or `--set scene.KEY=...`);
//! 2. the data set's `scene.toml`, beside its `info.json` / `transforms*.json`:
//!    ```toml
//!    open_faces = ["y-", "y+"]      # faces the flow crosses; the others are solid walls
//!    open_face_flow = 1.0           # optional, see TrainConfig's scene.open_face_flow
//!    inflow = [0.4, 0.0, 0.4, 0.66, 0.15, 0.66]  # fractions of the box, low then high corner
//!    ```
//!    (a file that exists settles every key: one it leaves out is "none");
//! 3. an estimate from frame 0's fit ([`estimate`]), printed and written to the run's
//!    `config.toml` after frame 0.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::TrainError;

/// The name of the scene file beside a data set's cameras.
pub const SCENE_FILE: &str = "scene.toml";

/// `[scene]` of the configuration: each key unset until the data set's `scene.toml` or the
/// estimate settles it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SceneConfig {
    /// Box faces the flow may cross (`x-`, `x+`, `y-`, `y+`, `z-`, `z+`; `y+` is the top of
    /// a box with y up); the others are solid walls. Exact projection only.
    pub open_faces: Option<Vec<String>>,
    /// The velocity on the open faces as a fraction of the cell's inside them, in (0, 1]:
    /// 1 a zero-gradient outflow; 0.5 the mean of the cell's velocity and a still cell's
    /// outside, the discrete top of a collocated solver that reads zero velocity above an
    /// open face (the synthetic generator's). Unset: 1.
    pub open_face_flow: Option<f32>,
    /// `[x0, y0, z0, x1, y1, z1]`, fractions of the smoke box (its low corner, then its high
    /// one): where the smoke enters (a source, or an inlet through an open face). Recycled
    /// Gaussians go only there, and `velocity --forces` takes it as its source.
    pub inflow: Option<[f32; 6]>,
}

/// What a data set's `scene.toml` says (every key optional).
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    #[serde(default)]
    open_faces: Vec<String>,
    open_face_flow: Option<f32>,
    inflow: Option<[f32; 6]>,
}

impl SceneConfig {
    /// The keys this leaves unset, from the data set's `scene.toml` when it has one (which
    /// settles the scene: an inflow it does not name is none); `Ok(false)` when it has none
    /// (what is unset is still to be estimated).
    pub fn fill_from_data(&mut self, data: &Path) -> Result<bool, TrainError> {
        let path = data.join(SCENE_FILE);
        if !path.is_file() {
            return Ok(false);
        }
        let text = std::fs::read_to_string(&path).map_err(|source| TrainError::Io {
            path: path.clone(),
            source,
        })?;
        let file: SceneFile = toml::from_str(&text).map_err(|e| TrainError::Config {
            origin: path.display().to_string(),
            reason: e.to_string(),
        })?;
        // The file's flow belongs to the file's faces: with faces of its own, the
        // configuration's flow is the outflow's unless it says otherwise.
        let flow = match self.open_faces {
            None => file.open_face_flow.unwrap_or(1.0),
            Some(_) => 1.0,
        };
        self.fill(SceneConfig {
            open_faces: Some(file.open_faces),
            open_face_flow: Some(flow),
            inflow: file.inflow,
        });
        Ok(true)
    }

    /// The keys this leaves unset, from `other`.
    pub fn fill(&mut self, other: SceneConfig) {
        self.open_faces = self.open_faces.take().or(other.open_faces);
        self.open_face_flow = self.open_face_flow.or(other.open_face_flow);
        self.inflow = self.inflow.or(other.inflow);
    }

    /// The open faces (none while unset).
    pub fn open_face_names(&self) -> &[String] {
        self.open_faces.as_deref().unwrap_or_default()
    }

    /// The flow on the open faces (1 while unset).
    pub fn flow(&self) -> f32 {
        self.open_face_flow.unwrap_or(1.0)
    }
}

/// Fraction of the box's extent along a face's normal that an estimated inflow box spans.
const INFLOW_DEPTH: f32 = 0.15;

/// Share of the densest boundary cell's density a cell of the inflow layer needs to count as
/// the source's.
const INFLOW_SHARE: f32 = 0.25;

/// The scene as frame 0's density on the grid (`[nx, ny, nz]`, z fastest) shows it: the
/// inflow face is the box face whose layer of cells (the [`INFLOW_DEPTH`] next to it) holds the
/// most density, where the smoke enters at the start of a video; the inflow box spans the
/// cells of that layer with at least [`INFLOW_SHARE`] of its densest cell's density, a cell
/// more each side; the open faces are the inflow face and the one opposite it (the smoke comes
/// in through one and leaves through the other, as a plume rising through a box does). An
/// empty density gives no open face and no inflow.
pub fn estimate(density: &[f32], resolution: [usize; 3]) -> SceneConfig {
    let [nx, ny, nz] = resolution;
    let n = [nx, ny, nz];
    let at = |c: [usize; 3]| density[(c[0] * ny + c[1]) * nz + c[2]];
    let finite = |v: f32| if v.is_finite() { v.max(0.0) } else { 0.0 };
    // Layer depth in cells along each axis.
    let depth = n.map(|cells| ((INFLOW_DEPTH * cells as f32).round() as usize).clamp(1, cells));
    let in_layer = |c: [usize; 3], axis: usize, high: bool| {
        if high {
            c[axis] >= n[axis] - depth[axis]
        } else {
            c[axis] < depth[axis]
        }
    };
    let cells =
        || (0..nx).flat_map(move |i| (0..ny).flat_map(move |j| (0..nz).map(move |k| [i, j, k])));
    // Mass in each face's layer: [x-, x+, y-, y+, z-, z+].
    let mut mass = [0.0f64; 6];
    for c in cells() {
        let v = finite(at(c)) as f64;
        for (face, m) in mass.iter_mut().enumerate() {
            if in_layer(c, face / 2, face % 2 == 1) {
                *m += v;
            }
        }
    }
    let Some((face, &most)) = mass.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)) else {
        return SceneConfig::default();
    };
    if most <= 0.0 {
        return SceneConfig {
            open_faces: Some(Vec::new()),
            open_face_flow: Some(1.0),
            inflow: None,
        };
    }
    let (axis, high) = (face / 2, face % 2 == 1);
    let layer: Vec<[usize; 3]> = cells().filter(|&c| in_layer(c, axis, high)).collect();
    let peak = layer.iter().map(|&c| finite(at(c))).fold(0.0, f32::max);
    let mut lo = [usize::MAX; 3];
    let mut hi = [0usize; 3];
    for &c in layer
        .iter()
        .filter(|&&c| finite(at(c)) >= INFLOW_SHARE * peak)
    {
        for a in 0..3 {
            lo[a] = lo[a].min(c[a]);
            hi[a] = hi[a].max(c[a]);
        }
    }
    let mut inflow = [0.0f32; 6];
    for a in 0..3 {
        let (from, to) = if a == axis {
            if high {
                (n[a] - depth[a], n[a])
            } else {
                (0, depth[a])
            }
        } else {
            (lo[a].saturating_sub(1), (hi[a] + 2).min(n[a]))
        };
        inflow[a] = from as f32 / n[a] as f32;
        inflow[a + 3] = to as f32 / n[a] as f32;
    }
    let name = |face: usize| format!("{}{}", ["x", "y", "z"][face / 2], ["-", "+"][face % 2]);
    let opposite = face ^ 1;
    let mut open = vec![name(face.min(opposite)), name(face.max(opposite))];
    open.dedup();
    SceneConfig {
        open_faces: Some(open),
        open_face_flow: Some(1.0),
        inflow: Some(inflow),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plume entering through the floor of the box: the floor and the top are open and the
    /// inflow box is the floor's layer around the smoke, a cell more each side.
    #[test]
    fn a_plume_on_the_floor_enters_there_and_leaves_through_the_top() {
        let n = 20;
        let mut density = vec![0.0f32; n * n * n];
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    // A column over x, z in 8..12, densest at the bottom.
                    if (8..12).contains(&i) && (8..12).contains(&k) {
                        density[(i * n + j) * n + k] = 1.0 - j as f32 / n as f32;
                    }
                }
            }
        }
        let scene = estimate(&density, [n, n, n]);
        assert_eq!(scene.open_faces, Some(vec!["y-".into(), "y+".into()]));
        assert_eq!(scene.inflow, Some([0.35, 0.0, 0.35, 0.65, 0.15, 0.65]));
        // Turned on its side (the source at x+), the estimate turns with it.
        let mut sideways = vec![0.0f32; n * n * n];
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    if (8..12).contains(&j) && (8..12).contains(&k) {
                        sideways[(i * n + j) * n + k] = i as f32 / n as f32;
                    }
                }
            }
        }
        let scene = estimate(&sideways, [n, n, n]);
        assert_eq!(scene.open_faces, Some(vec!["x-".into(), "x+".into()]));
        assert_eq!(scene.inflow, Some([0.85, 0.35, 0.35, 1.0, 0.65, 0.65]));
        // No smoke: nothing open, no inflow.
        let empty = estimate(&vec![0.0; n * n * n], [n, n, n]);
        assert_eq!(empty.open_faces, Some(Vec::new()));
        assert_eq!(empty.inflow, None);
    }

    /// A data set's scene.toml fills what the configuration leaves unset, and settles the
    /// inflow as none when it names none; a bad key is refused naming the file.
    #[test]
    fn the_scene_file_fills_unset_keys() {
        let dir = tempfile::tempdir().unwrap();
        let mut scene = SceneConfig::default();
        assert!(!scene.fill_from_data(dir.path()).unwrap());
        std::fs::write(
            dir.path().join(SCENE_FILE),
            "open_faces = [\"y+\"]\nopen_face_flow = 0.5\ninflow = [0.3, 0, 0.3, 0.7, 0.15, 0.7]\n",
        )
        .unwrap();
        let mut scene = SceneConfig {
            open_faces: Some(vec!["y-".into()]),
            ..SceneConfig::default()
        };
        assert!(scene.fill_from_data(dir.path()).unwrap());
        assert_eq!(scene.open_faces, Some(vec!["y-".into()]));
        // The file's flow is its own faces', not the configuration's.
        assert_eq!(scene.open_face_flow, Some(1.0));
        assert_eq!(scene.inflow, Some([0.3, 0.0, 0.3, 0.7, 0.15, 0.7]));
        let mut scene = SceneConfig::default();
        scene.fill_from_data(dir.path()).unwrap();
        assert_eq!(scene.open_faces, Some(vec!["y+".into()]));
        assert_eq!(scene.open_face_flow, Some(0.5));
        std::fs::write(dir.path().join(SCENE_FILE), "inflw = [0, 0, 0, 1, 1, 1]\n").unwrap();
        let err = SceneConfig::default()
            .fill_from_data(dir.path())
            .unwrap_err()
            .to_string();
        assert!(err.contains("scene.toml") && err.contains("inflw"), "{err}");
    }
}
