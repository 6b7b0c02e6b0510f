//! The device projection's deferred convergence tests (`ConvergenceTests::Deferred`, what the
//! trainer runs): a solve that knows its iteration budget reads nothing and returns what a
//! solve that tests as it goes returns; the settlement judges it later, reports a budget that
//! was too short, and grows the next one. In a test binary of its own, because it counts the
//! process's device reads.
//!
//! Like the other GPU tests this FAILS without a GPU adapter rather than skip.

use gausmoke_model::{
    ConvergenceTests, DeferredSolves, DeviceSolve, ProjectionOptions, settle_deferred_solves,
};
use gausmoke_render::device_traffic::Traffic;
use gausmoke_tests::projection::{device_projection, gpu_device, grid, velocity};

#[test]
fn deferred_solves_read_nothing_and_are_judged_later() {
    let grid = grid();
    let (backend, device) = gpu_device();
    // PCG's budgets (the direct solve, the default without obstacles, has none).
    let immediate = ProjectionOptions {
        max_iterations: 397,
        device_solve: DeviceSolve::Iterative,
        ..Default::default()
    };
    let deferred = ProjectionOptions {
        convergence_tests: ConvergenceTests::Deferred,
        ..immediate.clone()
    };
    let input = velocity(&grid, 21);

    // No history of this solve's kind: the first deferred solve tests as it goes.
    let fresh = ProjectionOptions {
        max_iterations: 398,
        ..deferred.clone()
    };
    let first = device_projection(&input, &grid, &device, fresh.clone());
    assert_eq!(settle_deferred_solves(), DeferredSolves::default());
    let first_expected = device_projection(
        &input,
        &grid,
        &device,
        ProjectionOptions {
            convergence_tests: ConvergenceTests::Immediate,
            ..fresh.clone()
        },
    );
    assert_eq!(first, first_expected, "{backend}: first deferred solve");

    let expected = device_projection(&input, &grid, &device, immediate.clone());

    // Solves with a short history still test as they go; once enough in a row needed no more
    // than their budget, a solve reads nothing (the test's own read of the result is not the
    // library's and is not counted). Every result is the immediate one.
    let mut silent = 0;
    for attempt in 0..20 {
        let before = Traffic::now();
        let result = device_projection(&input, &grid, &device, deferred.clone());
        let reads = Traffic::now().since(before);
        assert_eq!(result, expected, "{backend}: deferred solve {attempt}");
        if reads.solver_reads == 0 {
            silent += 1;
        } else {
            assert_eq!(silent, 0, "a trusted solve went back to testing: {reads:?}");
        }
        assert_eq!(reads.reads, reads.solver_reads, "{reads:?}");
    }
    assert!(silent >= 5, "{silent} of 20 solves read nothing");
    let settled = settle_deferred_solves();
    assert_eq!(
        (settled.solves, settled.unconverged),
        (silent, 0),
        "{settled:?}"
    );

    // A field that needs many more iterations than a budget learnt from near-projected ones:
    // the short solve is reported at the settlement, and the next solve, no longer trusted,
    // tests as it goes and converges.
    let easy = expected.clone();
    for _ in 0..20 {
        let _ = device_projection(&easy, &grid, &device, deferred.clone());
    }
    assert_eq!(settle_deferred_solves().unconverged, 0);
    let before = Traffic::now();
    let short = device_projection(&input, &grid, &device, deferred.clone());
    assert_eq!(Traffic::now().since(before).reads, 0, "a trusted solve");
    let settled = settle_deferred_solves();
    assert_eq!((settled.solves, settled.unconverged), (1, 1), "{settled:?}");
    assert!(settled.worst_relative_residual > immediate.rel_tolerance);
    assert_ne!(short, expected);
    let before = Traffic::now();
    let retried = device_projection(&input, &grid, &device, deferred.clone());
    assert!(Traffic::now().since(before).solver_reads > 0, "tests again");
    assert_eq!(retried, expected);
    assert_eq!(settle_deferred_solves(), DeferredSolves::default());
}
