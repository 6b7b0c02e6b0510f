"""How true a velocity the scene's own 3D density can give (issue 18).

  python velocity_from_density.py DATA_DIR [FRAMES...] [--smooth A,A,...] [--div B]
      [--chain T0 T1 --inertia G [--buoyancy C] [--inflow S]] [--consistent]
      [--from-truth] [--cg N] [--passes N] [--density RUN_DIR]
      (needs numpy and scipy)

Our velocity is fitted to pictures of the smoke; the pictures see only how the density
moves. This asks what the best such fit could reach with far more than pictures give: the
scene's exact density at frames t-1 and t on its 3D grid. For each frame t it finds the
velocity u (cells per frame) that carries the true density of frame t-1 onto that of frame
t by one semi-Lagrangian step (each cell samples frame t-1 where u traced it back from,
trilinearly), regularised as a field of ours is:

    sum over cells (rho_{t-1}(x - u(x)) - rho_t(x))^2
        + A |grad u|^2 (forward differences, each component)
        + B |div u|^2 (central differences)
        + G |u - u_prior|^2 (with --chain only)

by Gauss-Newton with warping (the step's residual linearised about the current u; ten
passes, the densities smoothed by 2, 1, 0.5 and then 0 cells in turn, coarse to fine, so
that the linearisation holds for moves of a cell or more), each pass solved by conjugate
gradients. The densities are divided by frame t's maximum. Rows at and below the source's
top (0.1 of the box's height, plus one) are left out of the data term: the generator's
inflow sets them, not transport.

The defaults (A = 0.001, B = 1000, G = 0.01) erred least on the long plume among those
tried (docs/RESULTS.md, the bullet on how true a velocity the density's motion can give).
Independent mode (the default) fits each listed frame from u = 0 for each smoothness A.
`--chain T0 T1` instead tracks the velocity through the frames: frame t starts from, and
with weight G is tied to, the previous frame's estimate carried along itself
(`velocity_persistence.py`'s semi-Lagrangian step), as our trainer carries its velocity.
The first frame of the chain starts from zero. With `--buoyancy C` the carried estimate
also gains C times frame t-1's density (undivided) upwards before it is used, a model of
the generator's own buoyancy (0.2 a frame for the long plume): a force model as a prior.
`--inflow S` sets the carried estimate's upward component to S cells a frame in the
generator's source disc (radius 0.12 of the box, below 0.1 of its height), as the generator
drives its inflow (1 for the long plume).

Two checks of the measure itself. `--consistent` replaces frame t's density (above the source)
by frame t-1's carried by the true u^t in this script's own step, so that the truth fits the
data exactly and what is left is what the density's motion cannot tell apart. `--from-truth`
starts each independent fit from the true u^t, to see where the objective takes it. `--cg`
and `--passes` run the solver longer (more conjugate-gradient iterations per pass, more
unsmoothed passes): the solution depends on them, since many fields fit the motion equally.

`--density RUN_DIR` fits the run's own density grids (`RUN_DIR/frames/frame_TTT.safetensors`,
the Gaussians splatted on the velocity's grid, each divided by its maximum) in place of the
truth's, and also prints the run's own velocity's scores: whether the run's velocity falls
short of what its own density's motion gives, or its density is what holds it back.

Per frame and setting, inside the true smoke (density above 1% of frame t's maximum, as the
runs' `velocity_relative_error` measures): the relative error of the estimate against the
true u^t, its mean cosine with it, its RMS speed over the truth's, the same relative error
of grad rho . u alone (the part of the flow the density's motion shows, as
`velocity_diagnosis.py` measures it), and the data residual of the estimate and of the
truth's own u^t (relative to |rho_t - rho_{t-1}|): an estimate that fits the densities
better than the truth does is as true as the density's motion can tell.
"""

import argparse

import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
from scipy.ndimage import gaussian_filter, map_coordinates

from safetensors_f32 import read_safetensors as read
from scene_truth import read_truth
from velocity_persistence import departure_points, sample, transported

SMOOTHING_PASSES = (2.0, 2.0, 1.0, 1.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0)


def difference_operators(n):
    """Forward differences `G` (3 per component, Neumann) and the central-difference
    divergence `D` on an n^3 grid, x slowest, for u stacked by component."""
    identity = sparse.identity(n, format="csr")
    forward = sparse.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n))
    central = sparse.lil_matrix((n, n))
    for i in range(n):
        low, high = max(i - 1, 0), min(i + 1, n - 1)
        central[i, low] -= 1.0 / (high - low)
        central[i, high] += 1.0 / (high - low)
    central = central.tocsr()

    def along(matrix, axis):
        factors = [identity, identity, identity]
        factors[axis] = matrix
        return sparse.kron(sparse.kron(factors[0], factors[1]), factors[2], format="csr")

    gradient = sparse.vstack([along(forward, axis) for axis in range(3)], format="csr")
    smoothness = sparse.block_diag([gradient.T @ gradient] * 3, format="csr")
    divergence = sparse.hstack([along(central, axis) for axis in range(3)], format="csr")
    return smoothness, divergence.T @ divergence


def carried(density, u):
    """One semi-Lagrangian step of `density` by `u` [n, n, n, 3] (cells per frame), and the
    gradient of `density` at the departure points; nothing comes back in above the top."""
    n = density.shape[0]
    departure = departure_points(u)
    above = np.arange(n)[None, :, None] - u[..., 1] > n - 0.5
    value = map_coordinates(density, departure, order=1)
    slope = sample(np.stack(np.gradient(density), axis=-1), departure)
    value[above] = 0.0
    slope[above] = 0.0
    return value, slope


def fit(before, after, smooth, div, inertia, prior, start, operators, data_rows, solver):
    """Gauss-Newton with warping; `solver` is (extra unsmoothed passes, CG iterations);
    returns u [n, n, n, 3] in cells per frame."""
    extra_passes, cg_iterations = solver
    n = before.shape[0]
    smoothness, divergence = operators
    regulariser = smooth * smoothness + div * divergence + inertia * sparse.identity(3 * n**3)
    u = start.copy()
    for sigma in SMOOTHING_PASSES + (0.0,) * extra_passes:
        source = gaussian_filter(before, sigma) if sigma else before
        target = gaussian_filter(after, sigma) if sigma else after
        value, slope = carried(source, u)
        residual = (value - target) * data_rows
        # d value / d u = -slope at the departure point.
        jacobian = -slope * data_rows[..., None]
        flat_u = np.moveaxis(u, -1, 0).ravel()
        flat_j = np.moveaxis(jacobian, -1, 0).reshape(3, -1)
        # J^T J couples the three components of one cell: a 3x3 block per cell.
        blocks = sparse.bmat(
            [[sparse.diags(flat_j[a] * flat_j[b]) for b in range(3)] for a in range(3)],
            format="csr",
        )
        rhs = -(flat_j * residual.ravel()).ravel() - regulariser @ flat_u
        if inertia:
            rhs += inertia * np.moveaxis(prior, -1, 0).ravel()
        step, _ = sparse_linalg.cg(blocks + regulariser, rhs, maxiter=cg_iterations, rtol=1e-6)
        u = u + np.moveaxis(step.reshape(3, n, n, n), 0, -1)
    return u


def scores(u, truth, before, after, true_after, data_rows):
    """Relative error, cosine, speed ratio, error of the flow along the gradient, and the
    data residual relative to the frames' difference, inside the true smoke (`true_after`,
    frame t's true density, which also gives the gradient)."""
    smoke = true_after > 0.01 * true_after.max()
    error = np.sqrt(((u[smoke] - truth[smoke]) ** 2).sum() / (truth[smoke] ** 2).sum())
    dot = (u[smoke] * truth[smoke]).sum(1)
    norms = np.linalg.norm(u[smoke], axis=1) * np.linalg.norm(truth[smoke], axis=1)
    cosine = np.mean(dot / np.maximum(norms, 1e-12))
    speed = np.sqrt((u[smoke] ** 2).sum() / (truth[smoke] ** 2).sum())
    gradient = np.stack(np.gradient(true_after / true_after.max()), -1)[smoke]
    seen_truth = (truth[smoke] * gradient).sum(1)
    seen = np.sqrt((((u[smoke] * gradient).sum(1) - seen_truth) ** 2).sum() / (seen_truth**2).sum())
    change = np.sqrt((((after - before) * data_rows) ** 2).sum())
    misfit = lambda v: np.sqrt((((carried(before, v)[0] - after) * data_rows) ** 2).sum()) / change
    return error, cosine, speed, seen, misfit(u), misfit(truth)


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("data", metavar="DATA_DIR")
    parser.add_argument("frames", metavar="FRAMES", type=int, nargs="*")
    parser.add_argument("--smooth", default="0.001", help="comma list of A")
    parser.add_argument("--div", type=float, default=1000.0, help="B")
    parser.add_argument("--chain", type=int, nargs=2, metavar=("T0", "T1"))
    parser.add_argument("--inertia", type=float, default=0.01, help="G, with --chain")
    parser.add_argument("--buoyancy", type=float, default=0.0, help="C, with --chain")
    parser.add_argument("--inflow", type=float, help="S, with --chain")
    parser.add_argument("--density", metavar="RUN_DIR", help="fit a run's densities")
    parser.add_argument("--cg", type=int, default=400, help="conjugate-gradient iterations")
    parser.add_argument("--passes", type=int, default=0, help="extra unsmoothed passes")
    parser.add_argument("--consistent", action="store_true",
                        help="replace frame t's density by frame t-1's carried by the true u^t "
                        "in this script's own step, so that the truth fits exactly")
    parser.add_argument("--from-truth", action="store_true",
                        help="start each fit from the true u^t (a check of the objective)")
    args = parser.parse_args()
    solver = (args.passes, args.cg)

    def frame(t):
        density, velocity = read_truth(args.data, t)
        n = density.shape[0]
        if args.density:
            ours = read(f"{args.density}/frames/frame_{t:03}.safetensors")["density"]
            density = ours.astype(np.float64) / ours.max() * density.max()
        return density, velocity * n  # the box is one world unit wide

    def print_run_velocity(t, truth, before, after, true_after):
        if args.density:
            ours = read(f"{args.density}/frames/frame_{t:03}.safetensors")["velocity"]
            s = scores(ours.astype(np.float64) * n, truth, before, after, true_after, data_rows)
            print(f"{t:5}  the run's own velocity " + report(s), flush=True)

    def pair(t):
        """Frames t-1 and t's densities as fitted, the true u^t, and frame t's true density
        (the smoke's mask)."""
        before, _ = frame(t - 1)
        after, truth = frame(t)
        true_after = read_truth(args.data, t)[0] if args.density else after
        if args.consistent:
            after = carried(before, truth)[0] * data_rows + after * (1 - data_rows)
        return before, after, truth, true_after

    n = frame(0)[0].shape[0]
    operators = difference_operators(n)
    data_rows = np.ones((n, n, n))
    data_rows[:, : int(np.ceil(0.1 * n)) + 1, :] = 0.0
    x, y, z = np.indices((n, n, n)) + 0.5
    source_disc = ((x - 0.5 * n) ** 2 + (z - 0.5 * n) ** 2 <= (0.12 * n) ** 2) & (
        (y >= 1.5) & (y < max(np.ceil(0.1 * n), 2) + 0.5)
    )
    print(
        "frame  A       G     error  cosine  speed  seen error  misfit ours / truth's"
    )
    smooth_values = [float(a) for a in args.smooth.split(",")]
    if args.chain:
        t0, t1 = args.chain
        for smooth in smooth_values:
            estimate = None
            for t in range(t0, t1 + 1):
                before, after, truth, true_after = pair(t)
                scale = after.max()
                zero = np.zeros_like(truth)
                prior = zero if estimate is None else transported(estimate)
                if estimate is not None:
                    prior[..., 1] += args.buoyancy * before
                    if args.inflow is not None:
                        prior[..., 1][source_disc] = args.inflow
                inertia = 0.0 if estimate is None else args.inertia
                estimate = fit(before / scale, after / scale, smooth, args.div, inertia,
                               prior, prior, operators, data_rows, solver)
                s = scores(estimate, truth, before / scale, after / scale, true_after,
                           data_rows)
                print(f"{t:5}  {smooth:<6} {inertia:<5} " + report(s), flush=True)
                print_run_velocity(t, truth, before / scale, after / scale, true_after)
        return
    for t in args.frames or [6, 12, 18, 24, 36, 48, 54, 71]:
        before, after, truth, true_after = pair(t)
        scale = after.max()
        for smooth in smooth_values:
            zero = np.zeros_like(truth)
            start = truth if args.from_truth else zero
            estimate = fit(before / scale, after / scale, smooth, args.div, 0.0, zero, start,
                           operators, data_rows, solver)
            s = scores(estimate, truth, before / scale, after / scale, true_after, data_rows)
            print(f"{t:5}  {smooth:<6} {'-':<5} " + report(s), flush=True)
        print_run_velocity(t, truth, before / scale, after / scale, true_after)


def report(s):
    error, cosine, speed, seen, ours, truths = s
    return f"{error:.3f}  {cosine:6.3f}  {speed:5.2f}  {seen:10.3f}  {ours:.3f} / {truths:.3f}"


if __name__ == "__main__":
    main()
