use super::*;

const WALLS: OpenFaces = OpenFaces::NONE;
/// Every face open with a zero-gradient outflow: a uniform move is divergence-free.
const OPEN: OpenFaces = OpenFaces {
    low: [true; 3],
    high: [true; 3],
    flow: 1.0,
};

/// The top face open, the others walls.
const OPEN_TOP: OpenFaces = OpenFaces {
    low: [false; 3],
    high: [false, true, false],
    flow: 1.0,
};

fn grid(n: usize, open: OpenFaces) -> MotionGrid {
    MotionGrid {
        resolution: [n, n + 2, n + 1],
        open,
    }
}

/// A smooth blob centred at `centre` (cell-index coordinates), `radius` cells wide.
fn blob(grid: &MotionGrid, centre: [f64; 3], radius: f64) -> Vec<f32> {
    (0..grid.cells())
        .map(|cell| {
            let at = grid.coordinates(cell);
            let r2: f64 = (0..3).map(|a| (at[a] as f64 - centre[a]).powi(2)).sum();
            (-0.5 * r2 / (radius * radius)).exp() as f32
        })
        .collect()
}

/// Deterministic values in [-1, 1].
fn noise(len: usize, seed: u64) -> Vec<f64> {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..len)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        })
        .collect()
}

/// The relative error of `moves` against a uniform `shift` where `after` holds smoke.
fn shift_error(moves: &[f64], shift: [f64; 3], after: &[f32]) -> f64 {
    let (mut error, mut norm) = (0.0, 0.0);
    for cell in (0..after.len()).filter(|&c| after[c] > 0.1) {
        for (a, s) in shift.iter().enumerate() {
            error += (moves[3 * cell + a] - s).powi(2);
            norm += s * s;
        }
    }
    (error / norm).sqrt()
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// The regulariser is a symmetric operator (the solver's conjugate gradients need it),
/// and positive: `x . R x` is the sum of its squared differences and divergences.
#[test]
fn the_regulariser_is_symmetric_and_positive() {
    let grid = grid(5, WALLS);
    let priors = MotionPriors {
        smoothness: 0.3,
        divergence: 7.0,
        inertia: 0.1,
        smoothed: Smoothed::Move,
    };
    let (x, y) = (noise(3 * grid.cells(), 1), noise(3 * grid.cells(), 2));
    let (mut rx, mut ry) = (vec![0.0; x.len()], vec![0.0; y.len()]);
    grid.regularise(&priors, &x, &mut rx);
    grid.regularise(&priors, &y, &mut ry);
    let (a, b) = (dot(&x, &ry), dot(&rx, &y));
    assert!((a - b).abs() <= 1e-9 * a.abs().max(1.0), "{a} vs {b}");
    assert!(dot(&x, &rx) > 0.0);
    // Only the divergence: through open faces a uniform move has none, so the operator
    // leaves it at zero; between walls it flows through them, which counts.
    let divergence_only = MotionPriors {
        smoothness: 0.0,
        divergence: 1.0,
        inertia: 0.0,
        smoothed: Smoothed::Move,
    };
    let uniform: Vec<f64> = (0..grid.cells()).flat_map(|_| [0.4, -1.1, 0.7]).collect();
    let mut out = vec![0.0; uniform.len()];
    let open = MotionGrid { open: OPEN, ..grid };
    open.regularise(&divergence_only, &uniform, &mut out);
    assert!(out.iter().all(|v| v.abs() < 1e-12));
    grid.regularise(&divergence_only, &uniform, &mut out);
    assert!(dot(&uniform, &out) > 1.0);
    // ... and an expansion has some.
    let expansion: Vec<f64> = (0..grid.cells())
        .flat_map(|cell| grid.coordinates(cell).map(|c| c as f64))
        .collect();
    grid.regularise(&divergence_only, &expansion, &mut out);
    assert!(dot(&expansion, &out) > 1.0);
}

/// The step's value moves with the move as minus the slope says (the Jacobian the
/// Gauss-Newton passes linearise with). On a linear density, where trilinear sampling and
/// central differences are both exact, the two agree to rounding away from the walls.
#[test]
fn the_slope_is_the_derivative_of_the_carried_value() {
    let grid = grid(8, WALLS);
    let density: Vec<f64> = (0..grid.cells())
        .map(|cell| {
            let [i, j, k] = grid.coordinates(cell).map(|c| c as f64);
            2.0 + 0.3 * i - 0.2 * j + 0.5 * k
        })
        .collect();
    let moves: Vec<f64> = noise(3 * grid.cells(), 3)
        .iter()
        .map(|v| 0.4 * v + 0.21)
        .collect();
    let (value, slope) = grid.carried(&density, &moves);
    let step = 1e-4;
    let mut checked = 0;
    for axis in 0..3 {
        let mut nudged = moves.clone();
        (0..grid.cells()).for_each(|cell| nudged[3 * cell + axis] += step);
        let (moved, _) = grid.carried(&density, &nudged);
        for cell in 0..grid.cells() {
            let at = grid.coordinates(cell);
            if !(0..3).all(|a| at[a] >= 1 && at[a] + 2 <= grid.resolution[a]) {
                continue;
            }
            let numeric = (moved[cell] - value[cell]) / step;
            let analytic = -slope[3 * cell + axis];
            assert!(
                (numeric - analytic).abs() < 1e-6,
                "axis {axis} cell {at:?}: {numeric} vs {analytic}"
            );
            checked += 1;
        }
    }
    assert!(checked > 100);
    assert!((slope[3 * grid.index([3, 3, 3]) + 2] - 0.5).abs() < 1e-9);
}

/// Past an open face there is clear air; past a wall the outermost cells are read.
#[test]
fn a_departure_past_an_open_face_brings_clear_air() {
    let grid = grid(4, OPEN_TOP);
    let density = vec![1.0; grid.cells()];
    let down = |dy: f64| -> Vec<f64> { (0..grid.cells()).flat_map(|_| [0.0, dy, 0.0]).collect() };
    // Moving down: the top row comes from above the box.
    let (value, _) = grid.carried(&density, &down(-1.0));
    let top = grid.resolution[1] - 1;
    for (cell, &v) in value.iter().enumerate() {
        let expected = if grid.coordinates(cell)[1] == top {
            0.0
        } else {
            1.0
        };
        assert_eq!(v, expected, "cell {:?}", grid.coordinates(cell));
    }
    // Moving up: the floor is a wall, so the bottom row reads the bottom row.
    let (value, _) = grid.carried(&density, &down(1.0));
    assert!(value.iter().all(|&v| v == 1.0));
}

/// Conjugate gradients solve a small symmetric positive system.
#[test]
fn conjugate_gradients_solve_a_positive_system() {
    let matrix = [[4.0, 1.0, 0.5], [1.0, 3.0, -0.2], [0.5, -0.2, 2.0]];
    let truth = [0.3, -1.2, 2.5];
    let apply = |x: &[f64], out: &mut [f64]| {
        for (row, o) in matrix.iter().zip(out.iter_mut()) {
            *o = dot(row, x);
        }
    };
    let mut rhs = [0.0; 3];
    apply(&truth, &mut rhs);
    let solve = conjugate_gradients(apply, |r, z| z.copy_from_slice(r), &rhs, 10);
    assert!(solve.relative_residual < 1e-9 && solve.iterations <= 3);
    let x = solve.x;
    for (a, b) in x.iter().zip(truth) {
        assert!((a - b).abs() < 1e-9, "{x:?}");
    }
}

/// The preconditioner inverts `c I + B D^T D` exactly.
#[test]
fn the_preconditioner_inverts_the_divergence_part() {
    let grid = grid(5, OPEN_TOP);
    let operator = grid.divergence();
    let solver = SpectralSolver::for_grid(&operator);
    let mut preconditioner = Preconditioner::new(&operator, &solver, 0.02, 1000.0);
    let r = noise(3 * grid.cells(), 7);
    let mut z = vec![0.0; r.len()];
    preconditioner.apply(&r, &mut z);
    let mut divergence = vec![0.0; grid.cells()];
    operator.apply(&z, &mut divergence);
    let mut back = vec![0.0; r.len()];
    operator.apply_transpose(&divergence, &mut back);
    for i in 0..r.len() {
        let rebuilt = 0.02 * z[i] + 1000.0 * back[i];
        assert!((rebuilt - r[i]).abs() < 1e-8, "{i}: {rebuilt} vs {}", r[i]);
    }
}

/// A blob moved by a uniform shift of more than a cell through a box with open faces
/// (where a uniform move is divergence-free): fitted from no move at all, the move inside
/// the blob is the shift, and the fit explains the frames' difference.
#[test]
fn the_fit_finds_a_uniform_shift() {
    let grid = grid(14, OPEN);
    let shift = [1.3, 0.8, -0.6];
    let centre = [6.5, 7.0, 7.5];
    let before = blob(&grid, centre, 2.2);
    let after = blob(&grid, [0, 1, 2].map(|a| centre[a] + shift[a]), 2.2);
    let fit = fit_density_motion(
        &grid,
        &before,
        &after,
        &vec![true; grid.cells()],
        &vec![0.0; 3 * grid.cells()],
        MotionPriors {
            smoothness: 0.001,
            divergence: 1000.0,
            inertia: 0.0,
            smoothed: Smoothed::Move,
        },
        400,
    );
    assert!(fit.misfit_prior > 0.99, "{}", fit.misfit_prior);
    assert!(fit.misfit_fitted < 0.1, "{}", fit.misfit_fitted);
    // Every pass's linear solve converged, within the cap of 400 iterations.
    assert!(
        fit.solver_residual <= CG_TOLERANCE,
        "{}",
        fit.solver_residual
    );
    assert!(
        fit.solver_iterations < 10 * 400,
        "{}",
        fit.solver_iterations
    );
    let relative = shift_error(&fit.moves, shift, &after);
    assert!(relative < 0.1, "relative error {relative}");
}

/// A velocity carried along itself: a uniform field stays as it is (inside and where the
/// departure points are clamped at the walls), and a field that varies along x takes, at
/// each cell, the value from where its own move came from.
#[test]
fn a_velocity_carried_along_itself() {
    let grid = grid(6, WALLS);
    let uniform: Vec<f64> = (0..grid.cells()).flat_map(|_| [0.7, -1.2, 0.4]).collect();
    let carried = grid.self_carried(&uniform);
    let largest = carried
        .iter()
        .zip(&uniform)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(largest < 1e-12, "{largest}");
    // u_x = 0.5 + 0.1 x, the others zero: the cell at x takes u_x at x - u_x(x).
    let ramp: Vec<f64> = (0..grid.cells())
        .flat_map(|cell| [0.5 + 0.1 * grid.coordinates(cell)[0] as f64, 0.0, 0.0])
        .collect();
    let carried = grid.self_carried(&ramp);
    let cell = grid.index([3, 2, 2]);
    let departure = 3.0 - 0.8;
    assert!((carried[3 * cell] - (0.5 + 0.1 * departure)).abs() < 1e-12);
    assert_eq!(&carried[3 * cell + 1..3 * cell + 3], &[0.0, 0.0]);
}

/// With no smoke in frame t there is nothing to fit: the prior comes back.
#[test]
fn no_smoke_keeps_the_prior() {
    let grid = grid(4, WALLS);
    let prior = noise(3 * grid.cells(), 4);
    let fit = fit_density_motion(
        &grid,
        &vec![1.0; grid.cells()],
        &vec![0.0; grid.cells()],
        &vec![true; grid.cells()],
        &prior,
        MotionPriors {
            smoothness: 1.0,
            divergence: 1.0,
            inertia: 1.0,
            smoothed: Smoothed::Move,
        },
        10,
    );
    assert_eq!(fit.moves, prior);
}

/// The tie holds the fit to the prior where the densities say nothing.
#[test]
fn the_tie_keeps_the_prior_where_nothing_moves() {
    let grid = grid(6, OPEN);
    let still = blob(&grid, [3.0, 3.5, 3.0], 1.5);
    let prior: Vec<f64> = (0..grid.cells()).flat_map(|_| [0.5, 0.0, 0.0]).collect();
    let fit = |inertia: f64| {
        fit_density_motion(
            &grid,
            &still,
            &still,
            &vec![false; grid.cells()],
            &prior,
            MotionPriors {
                smoothness: 0.001,
                divergence: 1000.0,
                inertia,
                smoothed: Smoothed::Move,
            },
            400,
        )
    };
    // No data term: the uniform prior (divergence-free through open faces) costs nothing
    // and stays.
    let tied = fit(0.01);
    for (a, b) in tied.moves.iter().zip(&prior) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
}

/// Where the densities say nothing, a smoothness on the move smooths a rough prior, while
/// one on the change from the prior carries it on as it is.
#[test]
fn a_smoothness_on_the_change_keeps_a_rough_prior() {
    let grid = grid(5, WALLS);
    // A uniform density: every move carries it onto itself, so there is no data term.
    let uniform = vec![1.0; grid.cells()];
    let prior = noise(3 * grid.cells(), 7);
    let fit = |smoothed| {
        fit_density_motion(
            &grid,
            &uniform,
            &uniform,
            &vec![true; grid.cells()],
            &prior,
            MotionPriors {
                smoothness: 0.1,
                divergence: 0.0,
                inertia: 0.01,
                smoothed,
            },
            400,
        )
    };
    let largest_change = |moves: &[f64]| {
        moves
            .iter()
            .zip(&prior)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()))
    };
    let on_change = fit(Smoothed::Change);
    assert!(largest_change(&on_change.moves) < 1e-6);
    let on_move = fit(Smoothed::Move);
    assert!(!on_move.kept_start);
    assert!(largest_change(&on_move.moves) > 0.1);
}
