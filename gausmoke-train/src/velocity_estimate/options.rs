//! What `velocity` (and a run's `velocity_estimate` stage) fits: the weights, the start and
//! the smoke step's forces.

use serde::{Deserialize, Serialize};

use crate::TrainError;

/// The fit's weights (see [`crate::density_motion`]): the smoothness `A` of each frame's
/// change from its start (the previous frame's estimate carried along itself; no motion for
/// frame 1), the divergence `B` and the tie `G` to that start; and whether the start is also
/// lifted along y (the world's up) in proportion to the density (`buoyancy`, see
/// [`super::buoyancy_coefficient`]), upward only for rising smoke or, with `sinking`, downward only
/// for smoke heavier than the air (fog).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EstimateOptions {
    /// Charged on each frame's change from its start, not on the estimate itself (with
    /// `forces`, on the estimate itself).
    pub smoothness: f64,
    pub divergence: f64,
    pub inertia: f64,
    #[serde(default)]
    pub buoyancy: bool,
    #[serde(default)]
    pub sinking: bool,
    /// Start each frame's fit from a smoke solver's step of the frame before's fit instead of
    /// from that fit carried along itself ([`crate::smoke_step`]); `buoyancy` then says
    /// whether the step has a buoyancy force, and `sinking` which way it and the inflow act.
    #[serde(default)]
    pub forces: Option<ForceOptions>,
    /// The run's density below this fraction of its frame's maximum is taken as none: the
    /// haze of Gaussians the views hardly see, which a smoke step would lift and carry as
    /// smoke (0: every density as it is).
    #[serde(default)]
    pub density_floor: f64,
}

/// The smoke step of [`EstimateOptions::forces`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ForceOptions {
    /// The source's exit speed (cells per frame); `None`: chosen by the density's motion
    /// among [`INFLOW_CHOICES`].
    pub inflow: Option<f64>,
    /// The buoyancy (cells per frame per frame at the source's density); `None`: chosen by
    /// the density's motion.
    pub buoyancy: Option<f64>,
    pub vorticity: f64,
    pub substeps: usize,
    /// The frames (1 to this) whose misfit chooses the forces.
    pub fit_frames: usize,
    /// The source, as fractions of the box (x0, y0, z0, x1, y1, z1); `None`: the run's inflow
    /// box (`scene.inflow`).
    pub source_box: Option<[f32; 6]>,
}

impl Default for ForceOptions {
    /// As the long plume's generator steps (two substeps, confinement 0.3); the forces
    /// chosen over its first 36 frames.
    fn default() -> Self {
        Self {
            inflow: None,
            buoyancy: None,
            vorticity: 0.3,
            substeps: 2,
            fit_frames: 36,
            source_box: None,
        }
    }
}

impl Default for EstimateOptions {
    /// The weights that erred least on the long plume: the divergence and the tie on the
    /// scene's exact density (`xtask/reference/velocity_from_density.py`), the smoothness on
    /// the preset runs' own densities (0.003 against 0.0001 to 0.1, three seeds; no less
    /// true on the obstacle scene; docs/RESULTS.md).
    fn default() -> Self {
        Self {
            smoothness: 0.003,
            divergence: 1000.0,
            inertia: 0.01,
            buoyancy: true,
            sinking: false,
            forces: None,
            density_floor: 0.0,
        }
    }
}

impl EstimateOptions {
    /// The weights that erred least on the long plume with the smoke step as each fit's
    /// start (`xtask/reference/velocity_from_forces.py --assimilate`): a tie of 0.03 (against
    /// 1, 0.1 and 0.01) and the smoothness on the velocity itself.
    pub fn forced() -> Self {
        Self {
            smoothness: 0.001,
            inertia: 0.03,
            forces: Some(ForceOptions::default()),
            ..Self::default()
        }
    }

    /// Where each frame's fit starts, as the CLI and the misfit chart name it.
    pub fn fits_start(&self) -> &'static str {
        if self.forces.is_some() {
            "smoke step"
        } else {
            "carried estimate"
        }
    }

    pub(super) fn validate(&self) -> Result<(), TrainError> {
        for (name, value) in [
            ("smoothness", self.smoothness),
            ("divergence", self.divergence),
            ("inertia", self.inertia),
        ] {
            if !(0.0..=1e6).contains(&value) {
                return Err(TrainError::Config {
                    origin: format!("velocity estimate --{name}"),
                    reason: format!("{value} is outside [0, 1e6]"),
                });
            }
        }
        if !(0.0..1.0).contains(&self.density_floor) {
            return Err(TrainError::Config {
                origin: "velocity estimate --density-floor".into(),
                reason: format!(
                    "{} is not a fraction of the frame's largest density in [0, 1)",
                    self.density_floor
                ),
            });
        }
        if let Some(forces) = &self.forces {
            let bad = |name: &str, reason: String| {
                Err(TrainError::Config {
                    origin: format!("velocity estimate --{name}"),
                    reason,
                })
            };
            if !(1..=16).contains(&forces.substeps) {
                return bad(
                    "substeps",
                    format!("{} is outside 1 to 16", forces.substeps),
                );
            }
            if forces.fit_frames == 0 {
                return bad("fit-frames", "the forces need at least one frame".into());
            }
            for (name, value) in [
                ("inflow", forces.inflow),
                ("force-buoyancy", forces.buoyancy),
                ("vorticity", Some(forces.vorticity)),
            ] {
                if let Some(v) = value
                    && !(0.0..=100.0).contains(&v)
                {
                    return bad(name, format!("{v} is outside [0, 100] cells per frame"));
                }
            }
            if let Some(b) = forces.source_box
                && !crate::config::is_box_of_fractions(&b)
            {
                return bad(
                    "source-box",
                    format!("{b:?} is not x0,y0,z0,x1,y1,z1 with 0 <= x0 < x1 <= 1 per axis"),
                );
            }
        }
        if self.sinking && !self.buoyancy && self.forces.is_none() {
            return Err(TrainError::Config {
                origin: "velocity estimate --sinking".into(),
                reason: "it sets which way the lift is read, and --no-buoyancy leaves the lift \
                         out: give one of them"
                    .into(),
            });
        }
        Ok(())
    }
}
