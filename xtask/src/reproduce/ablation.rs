//! The paper's Table 3 ablations as variants of a configuration.

use gausmoke_train::TrainConfig;

/// The paper's Table 3 ablations, named by the part of the method each switches off.
#[derive(Debug, Clone, Copy)]
pub enum Ablation {
    Physics,
    Refinement,
    Volumetric,
}

impl Ablation {
    pub const ALL: [Ablation; 3] = [
        Ablation::Physics,
        Ablation::Refinement,
        Ablation::Volumetric,
    ];

    /// Appended to the full method's run key and group.
    pub fn suffix(self) -> &'static str {
        match self {
            Ablation::Physics => "-no-physics",
            Ablation::Refinement => "-no-refinement",
            Ablation::Volumetric => "-no-volumetric",
        }
    }

    pub fn label(self) -> &'static str {
        match self {
            Ablation::Physics => "w/o physical losses",
            Ablation::Refinement => "w/o refinement",
            Ablation::Volumetric => "w/o volumetric rendering",
        }
    }

    pub fn apply(self, config: TrainConfig) -> TrainConfig {
        match self {
            Ablation::Physics => TrainConfig {
                physics_losses: false,
                ..config
            },
            Ablation::Refinement => TrainConfig {
                refinement: false,
                ..config
            },
            Ablation::Volumetric => TrainConfig {
                volumetric: false,
                ..config
            },
        }
    }
}
