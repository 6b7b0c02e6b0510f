//! [`TrainConfig::validate`]: every range and combination checked before any work starts,
//! each refusal naming the key to change.

use gausmoke_model::projection::OpenFaces;

use super::{MAX_TIME_FREQUENCIES, ProjectionKind, TrainConfig, is_box_of_fractions};
use crate::TrainError;

/// The most steps any loop of a frame may take.
const MAX_ITERATIONS: usize = 1_000_000;
/// The most Gaussians of either kind: 10^8 would need over 100 GB.
const MAX_GAUSSIANS: usize = 50_000_000;

impl TrainConfig {
    /// Checks ranges before any work starts.
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |reason: String| {
            Err(TrainError::Config {
                origin: "configuration".into(),
                reason,
            })
        };
        if self.gaussians == 0 {
            return bad("gaussians must be at least 1".into());
        }
        if self.grid_resolution < 8 || !self.grid_resolution.is_multiple_of(4) {
            return bad(format!(
                "grid_resolution must be a multiple of 4 and at least 8, got {}",
                self.grid_resolution
            ));
        }
        // Positive, and no larger than any value that still trains: a learning rate above 1
        // moves a parameter by more than its own range in one step, a decay above 1 grows.
        let bounded = [
            ("learning_rates.velocity", self.learning_rates.velocity, 1.0),
            (
                "learning_rates.gaussians",
                self.learning_rates.gaussians,
                1.0,
            ),
            ("learning_rates.decay", self.learning_rates.decay, 1.0),
            ("dt", self.dt as f64, 10.0),
            ("projection.tolerance", self.projection.tolerance, 0.1),
        ];
        for (name, value, most) in bounded {
            if !(value.is_finite() && value > 0.0 && value <= most) {
                return bad(format!("{name} must be in (0, {most}], got {value}"));
            }
        }
        if let Some(lr) = self.learning_rates.log_scales
            && !(lr.is_finite() && (0.0..=1.0).contains(&lr))
        {
            return bad(format!(
                "learning_rates.log_scales must be in [0, 1] when set, got {lr}"
            ));
        }
        let weights = [
            ("joint.lambda_div", self.joint.lambda_div),
            ("joint.lambda_adv", self.joint.lambda_adv),
            ("refine.lambda", self.refine.lambda),
            ("refine.lambda_grid", self.refine.lambda_grid),
            ("joint.look_ahead.weight", self.joint.look_ahead.weight),
            ("joint.inertia.weight", self.joint.inertia.weight),
        ];
        for (name, value) in weights {
            if !(value.is_finite() && value >= 0.0) {
                return bad(format!("{name} must be >= 0, got {value}"));
            }
        }
        if !(0.0..=1000.0).contains(&self.joint.inertia.horizontal_weight) {
            return bad(format!(
                "joint.inertia.horizontal_weight must be in [0, 1000], got {}",
                self.joint.inertia.horizontal_weight
            ));
        }
        if self.joint.inertia.horizontal_weight != 1.0 && self.joint.inertia.weight == 0.0 {
            return bad(
                "joint.inertia.horizontal_weight weighs the inertia prior, which is off: set \
                 joint.inertia.weight > 0 too"
                    .into(),
            );
        }
        if !(0.0..=1.0).contains(&self.population.recycle.fraction) {
            return bad(format!(
                "population.recycle.fraction must be in [0, 1], got {}",
                self.population.recycle.fraction
            ));
        }
        if !(0.0..=1.0).contains(&self.population.split.fraction) {
            return bad(format!(
                "population.split.fraction must be in [0, 1], got {}",
                self.population.split.fraction
            ));
        }
        if !(self.population.recycle.threshold.is_finite()
            && self.population.recycle.threshold >= 0.0)
        {
            return bad(format!(
                "population.recycle.threshold must be >= 0, got {}",
                self.population.recycle.threshold
            ));
        }
        if let Some(region) = self.scene.inflow
            && !is_box_of_fractions(&region)
        {
            return bad(format!(
                "scene.inflow must be [x0, y0, z0, x1, y1, z1] with 0 <= lo < hi <= 1 on each \
                 axis (fractions of the smoke box), got {region:?}"
            ));
        }
        if !(1.0..=100.0).contains(&self.device.tile_list_headroom) {
            return bad(format!(
                "device.tile_list_headroom must be in [1, 100], got {}",
                self.device.tile_list_headroom
            ));
        }
        if self.learning_rates.decay_every == 0
            || self.output.every == 0
            || self.output.log_every == 0
            || self.unet_channels == 0
        {
            return bad(
                "learning_rates.decay_every, output.every, output.log_every and unet_channels must be >= 1".into(),
            );
        }
        if let Some([w, h]) = self.image_size
            && (w == 0 || h == 0)
        {
            return bad("image_size must not be empty".into());
        }
        let rates = &self.init.learning_rates;
        let init_rates = [
            ("init.learning_rates.means", rates.means),
            ("init.learning_rates.rotations", rates.rotations),
            ("init.learning_rates.log_scales", rates.log_scales),
            ("init.learning_rates.raw_densities", rates.raw_densities),
            ("init.learning_rates.colors", rates.colors),
        ];
        for (name, value) in init_rates {
            if !(value.is_finite() && value > 0.0 && value <= 1.0) {
                return bad(format!("{name} must be in (0, 1], got {value}"));
            }
        }
        // PE(t) uses frequencies 2^0 .. 2^(L-1): beyond 16 an f32 phase keeps no digits of t.
        if !(1..=MAX_TIME_FREQUENCIES).contains(&self.time_frequencies) {
            return bad(format!(
                "time_frequencies must be in 1..={MAX_TIME_FREQUENCIES}, got {}",
                self.time_frequencies
            ));
        }
        if self.projection.max_iterations == 0 {
            return bad("projection.max_iterations must be >= 1".into());
        }
        // Far beyond any useful run (the paper's largest is 2000), and each step keeps a row
        // of losses: a count beyond these is a typo, not a plan, and would exhaust memory.
        for (name, value) in [
            ("init.iterations", self.init.iterations),
            ("joint.iterations", self.joint.iterations),
            ("refine.iterations", self.refine.iterations),
            ("projection.max_iterations", self.projection.max_iterations),
            ("projection.penalty_steps", self.projection.penalty_steps),
        ] {
            if value > MAX_ITERATIONS {
                return bad(format!(
                    "{name} must be at most {MAX_ITERATIONS}, got {value}"
                ));
            }
        }
        for (name, value) in [
            ("gaussians", self.gaussians),
            ("static_gaussians", self.static_gaussians),
        ] {
            if value > MAX_GAUSSIANS {
                return bad(format!(
                    "{name} must be at most {MAX_GAUSSIANS}, got {value}"
                ));
            }
        }
        if self.projection.kind == ProjectionKind::Penalty && self.projection.penalty_steps == 0 {
            return bad(
                "projection.penalty_steps must be >= 1 with projection.kind = \"penalty\"".into(),
            );
        }
        let open = self.scene.open_face_names();
        if let Err(reason) = OpenFaces::from_names(open) {
            return bad(format!("scene.open_faces: {reason}"));
        }
        let flow = self.scene.flow();
        if !(flow > 0.0 && flow <= 1.0) {
            return bad(format!(
                "scene.open_face_flow must be in (0, 1], got {flow}"
            ));
        }
        if flow != 1.0 && self.scene.open_faces.as_ref().is_some_and(Vec::is_empty) {
            return bad(format!(
                "scene.open_face_flow = {flow} has no effect with no open faces: set \
                 scene.open_faces too, or scene.open_face_flow = 1"
            ));
        }
        if !open.is_empty() && self.projection.kind != ProjectionKind::Exact {
            return bad(
                "scene.open_faces needs projection.kind = \"exact\" (the penalty form has solid \
                 walls only); with the penalty form, also set scene.open_faces = []"
                    .into(),
            );
        }
        if self.first_frame > 0 && self.frames.is_none() {
            return bad(format!(
                "first_frame = {} needs frames (how many frames from there)",
                self.first_frame
            ));
        }
        if self.frames == Some(0) {
            return bad("frames must be >= 1 (or left out for all)".into());
        }
        for (name, views) in [
            ("train_views", &self.train_views),
            ("test_views", &self.test_views),
        ] {
            if views.as_ref().is_some_and(|v| v.is_empty()) {
                return bad(format!(
                    "{name} must name at least one view (or be left out)"
                ));
            }
            if let Some(views) = views
                && let Some(twice) = views
                    .iter()
                    .enumerate()
                    .find(|(i, view)| views[..*i].contains(view))
                    .map(|(_, view)| view)
            {
                return bad(format!("{name} names the view {twice:?} twice"));
            }
        }
        Ok(())
    }
}
