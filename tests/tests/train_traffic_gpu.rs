//! What one training iteration asks of the host on a GPU backend (wgpu; lavapipe in CI): the
//! device reads the library counts (`gausmoke_render::device_traffic`) are every read there is
//! (wgpu's own log of buffer maps, which every device-to-host copy goes through, agrees), and
//! an iteration reads nothing: the tile-list lengths that size the renderer's buffers are read
//! once per loop, for all its views, and checked on the device afterwards; the projection's
//! solves test their convergence later, all together (once a first solve of each kind has
//! taught them their iteration budgets); the losses and checks of all steps come back in one
//! read per `output.log_every` steps.
//!
//! Like the other GPU tests this FAILS without a GPU adapter rather than skip.

use std::sync::atomic::{AtomicU64, Ordering};

use gausmoke_data::synth::{SynthConfig, generate};
use gausmoke_render::backends::gpu_devices;
use gausmoke_render::device_traffic::Traffic;
use gausmoke_train::config::ProjectionSolve;
use gausmoke_train::sequence::Sequence;
use gausmoke_train::state::{LoopTraffic, Phase};
use gausmoke_train::{TrainConfig, Trainer};

/// Buffer maps wgpu-core has logged (`Buffer::map_async`, at trace level).
static MAPS: AtomicU64 = AtomicU64::new(0);

struct MapCounter;

impl log::Log for MapCounter {
    fn enabled(&self, metadata: &log::Metadata) -> bool {
        metadata.target().starts_with("wgpu_core")
    }

    fn log(&self, record: &log::Record) {
        if self.enabled(record.metadata())
            && record.args().to_string().starts_with("Buffer::map_async")
        {
            MAPS.fetch_add(1, Ordering::Relaxed);
        }
    }

    fn flush(&self) {}
}

fn loop_of(traffic: &[LoopTraffic], phase: Phase) -> LoopTraffic {
    *traffic
        .iter()
        .find(|l| l.phase == phase)
        .unwrap_or_else(|| panic!("no {phase:?} loop in {traffic:?}"))
}

/// Enough frames for the solves to learn their budgets (a few steps' worth) and then run
/// whole loops without testing.
const FRAMES: usize = 5;

#[test]
fn a_training_iteration_reads_nothing_back() {
    log::set_logger(&MapCounter).expect("no other logger in this test binary");
    log::set_max_level(log::LevelFilter::Trace);

    let (_, device) = gpu_devices()
        .into_iter()
        .next()
        .expect("this test binary is built with gausmoke-train's wgpu feature");
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    generate(&SynthConfig::tiny(), &data).unwrap();
    let (advect, refine) = (4, 3);
    let config = {
        let mut config = TrainConfig {
            gaussians: 300,
            grid_resolution: 8,
            frames: Some(FRAMES),
            unet_channels: 4,
            time_frequencies: 2,
            ..TrainConfig::default()
        };
        config.init.iterations = 5;
        config.joint.iterations = advect;
        config.refine.iterations = refine;
        config.output.log_every = 100;
        // PCG with deferred tests first: what its solves read, and when.
        config.device.projection_solve = ProjectionSolve::Iterative;
        config
    };
    let sequence = Sequence::open(&data, &config).unwrap();
    let mut trainer = Trainer::new(sequence, config.clone(), device.clone().autodiff())
        .unwrap()
        .quiet(true);

    let mut loops = Vec::new();
    for t in 0..FRAMES {
        let (maps_before, before) = (MAPS.load(Ordering::Relaxed), Traffic::now());
        let outcome = trainer.train_frame(t).unwrap();
        let maps = MAPS.load(Ordering::Relaxed) - maps_before;
        let counted = Traffic::now().since(before).reads;
        assert_eq!(
            maps, counted,
            "frame {t}: wgpu mapped {maps} buffers, the library counted {counted} reads"
        );
        // Outside its loops a frame reads at most the velocity for the projection report and
        // the refinement's move statistics (four numbers).
        let in_loops: u64 = outcome.traffic.iter().map(|l| l.reads).sum();
        assert!(
            counted - in_loops <= 2 * u64::from(t > 0),
            "frame {t}: {counted} reads, {in_loops} in the loops {:?}",
            outcome.traffic
        );
        loops.extend(outcome.traffic);
    }
    eprintln!("{loops:#?}");

    let init = loop_of(&loops, Phase::Init);
    // One read of all the views' list lengths per loop, at its first step.
    assert_eq!(init.tile_list_reads, 1, "{init:?}");
    assert_eq!(init.solver_reads, 0, "{init:?}");
    assert_eq!(
        init.reads - init.tile_list_reads,
        1,
        "one read of the losses: {init:?}"
    );

    // The first solves start without an iteration history and test as they go until enough
    // in a row needed no more than their budget; the last frame's are all deferred and judged
    // in one read with the losses.
    let joints: Vec<LoopTraffic> = loops
        .iter()
        .copied()
        .filter(|l| l.phase == Phase::Advect)
        .collect();
    assert_eq!(joints.len(), FRAMES - 1);
    assert!(joints[0].solver_reads >= 2, "{joints:?}");
    let joint = *joints.last().unwrap();
    assert_eq!(joint.tile_list_reads, 1, "{joint:?}");
    assert_eq!(
        joint.solver_reads, 1,
        "one settlement of the deferred solves: {joints:?}"
    );
    assert_eq!(
        joint.reads - joint.tile_list_reads - joint.solver_reads,
        1,
        "one read of the losses, checks, largest speed and clamped count: {joint:?}"
    );
    assert!(joint.launches > 0, "launches are counted: {joint:?}");

    let refinement = loop_of(&loops, Phase::Refine);
    assert_eq!(refinement.tile_list_reads, 1, "{refinement:?}");
    assert_eq!(
        refinement.reads - refinement.tile_list_reads,
        1,
        "{refinement:?}"
    );

    // The direct solve (the default): no solver read at all, and fewer launches a step.
    let direct = {
        let mut config = config.clone();
        config.frames = Some(2);
        config.device.projection_solve = ProjectionSolve::Direct;
        config
    };
    let sequence = Sequence::open(&data, &direct).unwrap();
    let mut trainer = Trainer::new(sequence, direct, device.clone().autodiff())
        .unwrap()
        .quiet(true);
    trainer.train_frame(0).unwrap();
    let outcome = trainer.train_frame(1).unwrap();
    let direct_joint = loop_of(&outcome.traffic, Phase::Advect);
    assert_eq!(direct_joint.solver_reads, 0, "{direct_joint:?}");
    assert_eq!(
        direct_joint.reads - direct_joint.tile_list_reads,
        1,
        "{direct_joint:?}"
    );
    let per_step = |l: &LoopTraffic| l.launches as f64 / l.iterations as f64;
    eprintln!(
        "launches per joint iteration: PCG (deferred) {:.0}, direct {:.0}",
        per_step(&joint),
        per_step(&direct_joint)
    );
    assert!(
        per_step(&direct_joint) < per_step(&joint),
        "{direct_joint:?} against {joint:?}"
    );

    // The list lengths are measured again after each read of the log, so the buffers follow
    // the Gaussians: 5 fitting steps read back every 2 measure at steps 0, 2 and 4.
    let config = {
        let mut config = config;
        config.output.log_every = 2;
        config
    };
    let sequence = Sequence::open(&data, &config).unwrap();
    let mut trainer = Trainer::new(sequence, config, device.autodiff())
        .unwrap()
        .quiet(true);
    let outcome = trainer.train_frame(0).unwrap();
    let init = loop_of(&outcome.traffic, Phase::Init);
    assert_eq!(init.tile_list_reads, 3, "{init:?}");
    assert_eq!(init.reads - init.tile_list_reads, 3, "{init:?}");
}
