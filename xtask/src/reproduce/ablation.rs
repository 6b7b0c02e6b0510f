//! The paper's Table 3 ablations, and ours, as variants of a configuration.

use gausmoke_train::TrainConfig;

/// The paper's Table 3 ablations, named by the part of the method each switches off.
#[derive(Debug, Clone, Copy)]
pub enum Ablation {
    Physics,
    Refinement,
    Volumetric,
    /// Ours (issue 20): the data set's obstacles ignored by the projection.
    Solid,
    /// Ours (issue 20): no static Gaussians.
    Statics,
}

impl Ablation {
    pub const ALL: [Ablation; 3] = [
        Ablation::Physics,
        Ablation::Refinement,
        Ablation::Volumetric,
    ];

    /// Every ablation a record's group may end with (the paper's and ours).
    pub const KNOWN: [Ablation; 5] = [
        Ablation::Physics,
        Ablation::Refinement,
        Ablation::Volumetric,
        Ablation::Solid,
        Ablation::Statics,
    ];

    /// Appended to the full method's run key and group.
    pub fn suffix(self) -> &'static str {
        match self {
            Ablation::Physics => "-no-physics",
            Ablation::Refinement => "-no-refinement",
            Ablation::Volumetric => "-no-volumetric",
            Ablation::Solid => "-no-solid",
            Ablation::Statics => "-no-statics",
        }
    }

    pub fn label(self) -> &'static str {
        match self {
            Ablation::Physics => "w/o physical losses",
            Ablation::Refinement => "w/o refinement",
            Ablation::Volumetric => "w/o volumetric rendering",
            Ablation::Solid => "w/o solid obstacles",
            Ablation::Statics => "w/o static primitives",
        }
    }

    pub fn apply(self, config: TrainConfig) -> TrainConfig {
        match self {
            Ablation::Physics => {
                let mut config = config;
                config.joint.lambda_div = 0.0;
                config.joint.lambda_adv = 0.0;
                config
            }
            Ablation::Refinement => {
                let mut config = config;
                config.refine.iterations = 0;
                config
            }
            Ablation::Volumetric => TrainConfig {
                volumetric: false,
                ..config
            },
            Ablation::Solid => {
                let mut config = config;
                config.projection.obstacles = gausmoke_train::config::Obstacles::Ignore;
                config
            }
            Ablation::Statics => TrainConfig {
                static_gaussians: 0,
                ..config
            },
        }
    }
}
