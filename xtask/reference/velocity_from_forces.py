"""How much of a synthetic plume's velocity follows from its density's history through a
smoke solver's momentum step alone (issue 18, a diagnostic).

  python velocity_from_forces.py DATA FRAMES [--run RUN] [--buoyancy B|fit]
      [--inflow S[,S...]|fit] [--vorticity E] [--jacobi N] [--substeps K]
      [--start-from-truth T] [--assimilate G] [--fit-frames N] [--source-box BOX]
      [--blur CELLS] [--floor F] [--out DIR]          (needs numpy and scipy)

Starting from an empty, still box before frame 0 (or from the scene's own velocity at frame
T, `--start-from-truth`), a velocity is stepped forward frame by frame by a smoke step of
the scene's kind: the inflow's speed S (cells a frame) in the source disc, buoyancy B on the
density, vorticity confinement E, semi-Lagrangian self-advection and a wide-stencil
N-iteration Jacobi projection with the scene's walls and half-open top, K substeps a frame.
The density is not simulated: each frame starts from the given density of the frame before
(the scene's own, or with `--run` the run's splatted density grid), carried with the
velocity during the frame's substeps. The velocity is never fitted to anything unless
`--assimilate G` asks for it: then after each step it is refitted to the two frames'
densities' motion, started from and tied with weight G to the step's velocity
(`velocity_from_density.py`'s objective). FRAMES is a comma list. Per listed frame it prints
the relative error against the truth inside the true smoke (above 1% of its maximum), the
mean cosine, the speed over the truth's and the density-motion misfit of the frame (the
frame before's density carried over the frame against the frame's own, relative to no
motion); with `--run`, also the run's own velocity's error and its `velocity_estimate/`'s.

The inflow's seeded noise (the scene's horizontal kicks in the source and its density
jitter) is unknown to the step and left out, so even the scene's own density and settings
do not give the truth back exactly. `--buoyancy fit` chooses the buoyancy by the mean
misfit over frames 1 to N (`--fit-frames`, 36) alone, as a user without the truth would (a
ladder of factors of two, then a golden-section search); `--inflow fit` or a comma list
chooses the inflow's speed the same way. The run's density is in its own units, so its
buoyancy differs from the scene's. `--source-box x0,y0,z0,x1,y1,z1` (fractions of the box,
as a run's `[scene] inflow`) replaces the source disc; `--blur` and `--floor` blur the given
densities or zero them below a fraction of each frame's maximum. `--out DIR` writes every
frame's velocity as `DIR/frames/frame_TTT.safetensors` (`velocity` [x, y, z, 3], world
units per frame, a run's layout).
"""

import argparse
import os

import numpy as np
from scipy.ndimage import map_coordinates

from safetensors_f32 import read_safetensors as read, write_safetensors
from scene_truth import read_truth
from velocity_diagnosis import relative


def advect(field, vel, dt):
    """Semi-Lagrangian step of `field` [n, n, n] (x, y, z) by `vel` [n, n, n, 3] in cells per
    frame over `dt` frames: trilinear, clamped to the box, nothing back from above the open
    top."""
    n = field.shape[0]
    grid = np.indices(field.shape, dtype=np.float64)
    back = grid - dt * np.moveaxis(vel, -1, 0)
    out = map_coordinates(field, back, order=1, mode="nearest")
    out[back[1] > n - 1 + 0.5] = 0.0
    return out


def source_box(n, box):
    """The cells whose centres lie in `box` (x0, y0, z0, x1, y1, z1, fractions of the box),
    as a run's `[scene] inflow` gives its source."""
    centre = (np.arange(n) + 0.5) / n
    inside = [(centre >= box[a]) & (centre <= box[a + 3]) for a in range(3)]
    return inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]


def source_disc(n):
    """The source's cells: rows 1 to ceil(0.1 n) - 1 (at least row 1), within 0.12 n of the
    box's vertical axis."""
    x = np.arange(n) + 0.5 - 0.5 * n
    disc = (x[:, None] ** 2 + x[None, :] ** 2) <= (0.12 * n) ** 2
    mask = np.zeros((n, n, n), bool)
    rows = range(1, max(int(np.ceil(0.1 * n)), 2))
    for y in rows:
        mask[:, y, :] = disc
    return mask


def central(f, axis):
    """Central difference along `axis`; wrapped at the box's faces, so only interior cells
    are right (the callers zero the outer layer)."""
    return 0.5 * (np.roll(f, -1, axis) - np.roll(f, 1, axis))


def curl(vel):
    """Central-difference curl on interior cells, zero on the box's outer layer."""
    u, v, w = vel[..., 0], vel[..., 1], vel[..., 2]
    d = central
    omega = np.stack([d(w, 1) - d(v, 2), d(u, 2) - d(w, 0), d(v, 0) - d(u, 1)], axis=-1)
    omega[[0, -1], :, :] = 0
    omega[:, [0, -1], :] = 0
    omega[:, :, [0, -1]] = 0
    return omega


def confine(vel, eps, dt):
    """Vorticity confinement `eps dt (N x omega)` on interior cells."""
    omega = curl(vel)
    size = np.linalg.norm(omega, axis=-1)
    grad = np.stack([central(size, axis) for axis in range(3)], axis=-1)
    length = np.linalg.norm(grad, axis=-1, keepdims=True)
    push = eps * dt * np.cross(grad / np.maximum(length, 1e-30), omega)
    push[length[..., 0] < 1e-8] = 0
    push[[0, -1], :, :] = 0
    push[:, [0, -1], :] = 0
    push[:, :, [0, -1]] = 0
    return vel + push


def project(vel, iterations):
    """The scene's kind of projection: walls on the sides and floor, the top open with
    pressure 0 above it; central differences, the wide-stencil Poisson equation by Jacobi."""
    vel = vel.copy()
    n = vel.shape[0]
    vel[[0, -1], :, :, 0] = 0
    vel[:, 0, :, 1] = 0
    vel[:, :, [0, -1], 2] = 0
    padded = np.pad(vel, ((1, 1), (1, 1), (1, 1), (0, 0)))
    div = 0.5 * (padded[2:, 1:-1, 1:-1, 0] - padded[:-2, 1:-1, 1:-1, 0]
                 + padded[1:-1, 2:, 1:-1, 1] - padded[1:-1, :-2, 1:-1, 1]
                 + padded[1:-1, 1:-1, 2:, 2] - padded[1:-1, 1:-1, :-2, 2])
    i = np.arange(n)

    def neighbour(p, axis, step):
        # Zero-gradient past the walls and the floor (the cell's own value), 0 above the top.
        j = i + step
        inside = (j >= 0) & (j < n)
        taken = np.take(p, np.where(inside, j, i), axis=axis)
        if axis == 1 and step > 0:
            shape = [1, n, 1]
            taken = taken * inside.reshape(shape)
        return taken

    p = np.zeros((n, n, n))
    for _ in range(iterations):
        total = sum(neighbour(p, axis, s) for axis in range(3) for s in (2, -2))
        p = (total - 4.0 * div) / 6.0
    for axis in range(3):
        vel[..., axis] -= 0.5 * (neighbour(p, axis, 1) - neighbour(p, axis, -1))
    return vel


def step_frame(vel, density, args, buoyancy, disc):
    """One frame of `args.substeps` substeps; returns the velocity and the density carried."""
    dt = 1.0 / args.substeps
    for _ in range(args.substeps):
        density = np.where(disc, np.maximum(density, 1.0 * args.density_unit), density)
        vel = vel.copy()
        vel[..., 1][disc] = args.inflow_speed
        vel[..., 1] += buoyancy * dt * density
        if args.vorticity > 0:
            vel = confine(vel, args.vorticity, dt)
        vel = np.stack([advect(vel[..., c], vel, dt) for c in range(3)], axis=-1)
        vel = project(vel, args.jacobi)
        density = advect(density, vel, dt)
    return vel, density


def fit_buoyancy(mean_misfit, guide):
    """The buoyancy with the least mean misfit: a ladder of factors of two about `guide`,
    then a golden-section search in log b about the ladder's best."""
    ladder = [guide * 2.0**k for k in range(-4, 3)]
    values = [mean_misfit(b) for b in ladder]
    k = int(np.argmin(values))
    lo, hi = np.log(ladder[max(k - 1, 0)]), np.log(ladder[min(k + 1, len(ladder) - 1)])
    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    fa, fb = mean_misfit(np.exp(a)), mean_misfit(np.exp(b))
    for _ in range(8):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - ratio * (hi - lo)
            fa = mean_misfit(np.exp(a))
        else:
            lo, a, fa = a, b, fb
            b = lo + ratio * (hi - lo)
            fb = mean_misfit(np.exp(b))
    found = [(fa, np.exp(a)), (fb, np.exp(b))] + list(zip(values, ladder))
    misfit, buoyancy = min(found)
    return buoyancy, misfit


def source_region(n, args):
    if args.source_box:
        return source_box(n, [float(v) for v in args.source_box.split(",")])
    return source_disc(n)


def chain(densities, args, buoyancy, disc, start=None, assimilate=0.0):
    """The velocity of each frame from an empty, still box before frame 0 (or from `start` =
    (frame, velocity)), and the
    density-motion misfit of each frame (the frame before's density carried over the frame
    against the frame's own, relative to no motion)."""
    n = densities[0].shape[0]
    if start is None:
        # The scene starts empty and still; its frame 0 is already one frame in.
        first, (vel, _) = 0, step_frame(np.zeros((n, n, n, 3)), np.zeros((n, n, n)), args,
                                        buoyancy, disc)
    else:
        first, vel = start
    velocities, misfits = {first: vel}, {}
    if assimilate:
        from velocity_from_density import difference_operators, fit

        operators = difference_operators(n)
        data_rows = np.ones((n, n, n))
        data_rows[:, : int(np.ceil(0.1 * n)) + 1, :] = 0.0
    for t in range(first + 1, len(densities)):
        vel, carried = step_frame(vel, densities[t - 1], args, buoyancy, disc)
        if assimilate:
            # The step's velocity as the start of, and tied with weight G to, a fit of the
            # two frames' densities' motion (velocity_from_density.py's objective).
            scale = densities[t].max()
            vel = fit(densities[t - 1] / scale, densities[t] / scale, 0.001, 1000.0,
                      assimilate, vel, vel, operators, data_rows, (0, 400))
        velocities[t] = vel
        still = ((densities[t] - densities[t - 1]) ** 2).sum()
        misfits[t] = ((carried - densities[t]) ** 2).sum() / max(still, 1e-30)
    return velocities, misfits


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("data")
    parser.add_argument("frames", help="comma-separated frames to print")
    parser.add_argument("--run")
    parser.add_argument("--buoyancy", help="0.2 (the scene's) by default; fit with --run")
    parser.add_argument("--vorticity", type=float, default=0.3)
    parser.add_argument("--jacobi", type=int, default=40)
    parser.add_argument("--inflow", default="1", help="cells a frame, a comma list, or fit")
    parser.add_argument("--substeps", type=int, default=2)
    parser.add_argument("--start-from-truth", type=int)
    parser.add_argument("--out")
    parser.add_argument("--fit-frames", type=int, default=36,
                        help="the misfit that chooses the buoyancy and inflow: frames 1 to this")
    parser.add_argument("--blur", type=float, default=0.0,
                        help="blur the given densities by a Gaussian of this many cells")
    parser.add_argument("--floor", type=float, default=0.0,
                        help="zero each given density below this fraction of its maximum")
    parser.add_argument("--source-box", help="x0,y0,z0,x1,y1,z1 (fractions) for the disc")
    parser.add_argument("--assimilate", type=float, default=0.0, metavar="G")
    args = parser.parse_args()
    if args.buoyancy is None:
        args.buoyancy = "fit" if args.run else "0.2"
    shown = [int(f) for f in args.frames.split(",")]
    last = max(shown)
    truths = [read_truth(args.data, t) for t in range(last + 1)]
    n = truths[0][0].shape[0]
    cell = 1.0 / n
    true_vel = [v / cell for _, v in truths]
    if args.run:
        frames = [read(f"{args.run}/frames/frame_{t:03}.safetensors") for t in range(last + 1)]
        densities = [f["density"].astype(np.float64) for f in frames]
        # The run's density is in its own units: the source's floor in those units is its
        # mean inside the source over frames 1-36 (no truth read).
        disc = source_region(n, args)
        args.density_unit = float(np.mean([d[disc].mean() for d in densities[1:37]]))
    else:
        densities = [d.astype(np.float64) for d, _ in truths]
        disc = source_region(n, args)
        args.density_unit = 1.0
    if args.floor > 0:
        densities = [np.where(d > args.floor * d.max(), d, 0.0) for d in densities]
    if args.blur > 0:
        from scipy.ndimage import gaussian_filter

        densities = [gaussian_filter(d, args.blur) for d in densities]
    start = None
    if args.start_from_truth is not None:
        start = (args.start_from_truth, true_vel[args.start_from_truth])
    fitted = densities[: min(last, args.fit_frames) + 1]
    mean_misfit = lambda b: np.mean(list(chain(fitted, args, b, disc, start)[1].values()))
    inflows = ([float(v) for v in args.inflow.split(",")] if args.inflow != "fit"
               else [0.5, 0.625, 0.75, 0.875, 1.0, 1.25, 1.5])
    best = None
    for inflow in inflows:
        args.inflow_speed = inflow
        if args.buoyancy == "fit":
            # The ladder is centred on the scene's buoyancy in the density's units; it spans
            # a factor of 64, so the centre only saves search steps.
            buoyancy, misfit = fit_buoyancy(mean_misfit, 0.2 / args.density_unit)
        else:
            buoyancy = float(args.buoyancy)
            misfit = mean_misfit(buoyancy) if len(inflows) > 1 else float("nan")
        if len(inflows) > 1 or args.buoyancy == "fit":
            print(f"inflow {inflow:.4g}: buoyancy {buoyancy:.4g}, mean misfit {misfit:.4f}")
        if best is None or misfit < best[0]:
            best = (misfit, inflow, buoyancy)
    _, args.inflow_speed, buoyancy = best
    velocities, misfits = chain(densities, args, buoyancy, disc, start, args.assimilate)
    print(f"buoyancy {buoyancy:.4g}, vorticity {args.vorticity}, jacobi {args.jacobi}, "
          f"inflow {args.inflow_speed}, substeps {args.substeps}, assimilate "
          f"{args.assimilate}, density of {'run ' + args.run if args.run else 'the scene'}")
    if args.out:
        os.makedirs(os.path.join(args.out, "frames"), exist_ok=True)
        for t, vel in velocities.items():
            write_safetensors(os.path.join(args.out, "frames", f"frame_{t:03}.safetensors"),
                              {"velocity": (vel * cell).astype(np.float32)},
                              {"source": "velocity_from_forces.py"})
    for t in shown:
        if t not in velocities:
            continue
        smoke = truths[t][0] > 0.01 * truths[t][0].max()
        truth = true_vel[t][smoke]
        ours = velocities[t][smoke]
        cos = (ours * truth).sum(-1) / np.maximum(
            np.linalg.norm(ours, axis=-1) * np.linalg.norm(truth, axis=-1), 1e-12)
        speed = np.linalg.norm(ours, axis=-1).mean() / np.linalg.norm(truth, axis=-1).mean()
        line = (f"frame {t:3}: forced {relative(ours, truth):.3f} (cosine {cos.mean():.2f}, "
                f"speed {speed:.2f}, misfit {misfits.get(t, float('nan')):.3f})")
        if args.run:
            for name, folder in (("run", "frames"), ("estimate", "velocity_estimate")):
                try:
                    other = read(f"{args.run}/{folder}/frame_{t:03}.safetensors")["velocity"]
                except FileNotFoundError:
                    continue
                line += f", {name} {relative(other[smoke] / cell, truth):.3f}"
        print(line, flush=True)


if __name__ == "__main__":
    main()
