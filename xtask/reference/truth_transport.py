"""Whether a synthetic scene's density moves as its own velocity carries it (issue 18).

  python truth_transport.py DATA_DIR FRAMES [SIGMA]
      (FRAMES: comma list, each >= 1; SIGMA: cells, default 1; needs numpy)

For each frame t, the true density of frame t-1 is carried one frame and correlated with the
true density of frame t, both smoothed by a Gaussian of SIGMA cells (about our Gaussians'
size: one particle per cell, splatted, aliases below it), in three ways:
- still: not moved at all (what any motion has to beat);
- particles: one particle per cell, carrying the cell's density, moved by two half-frame
  Euler steps (the true velocity of frame t-1, then of frame t, read trilinearly) and
  splatted back trilinearly, as Lagrangian carriers that keep their size (our Gaussians) move;
- semi-Lagrangian: the grid sampled back along the velocity of frame t in two half steps, as
  the generator advects its density (`gausmoke-data` synth solver), with its numerical
  diffusion.
If the particles match the next frame as well as the semi-Lagrangian step, the scene's
density follows its velocity as a carrier without diffusion can, at that scale.

  python truth_transport.py DATA_DIR FRAMES --scales [S,S,...]

prints instead, per frame, how well particles carried by S times frame t's true velocity
match frame t, for each way of integrating one frame: one explicit Euler step (our
`integrator = "euler"`, Eq. 13), the explicit midpoint rule (`"rk2"`), and two implicit
half steps, each landing where a semi-Lagrangian sample would start (the generator's
scheme, followed by particles). The score is the relative error of the smoothed densities
in the middle of the box's height (0.2-0.8, away from the source, which re-injects smoke,
and from the top): a correlation hardly tells a carrier a quarter too fast from a right
one. The scale with the least error is the speed at which that integrator has to carry
the Gaussians for the scene's density to follow.
"""

import sys

import numpy as np

from scene_truth import read_truth


def trilinear(field, points):
    """`field` [n, n, n, ...] sampled at `points` [m, 3] in cell units (centres at i), edges
    clamped."""
    n = field.shape[0]
    p = np.clip(points, 0.0, n - 1.0)
    i0 = np.minimum(np.floor(p).astype(int), n - 2)
    f = p - i0
    out = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) * (
                    f[:, 2] if dz else 1 - f[:, 2])
                value = field[i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz]
                out = out + (w[:, None] * value if value.ndim == 2 else w * value)
    return out


def splat(points, mass, n):
    """Particles at `points` (cell units) spread onto an n^3 grid by trilinear weights; mass
    outside the grid is dropped."""
    grid = np.zeros((n, n, n))
    i0 = np.floor(points).astype(int)
    f = points - i0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) * (
                    f[:, 2] if dz else 1 - f[:, 2])
                idx = i0 + [dx, dy, dz]
                inside = np.all((idx >= 0) & (idx < n), axis=1)
                np.add.at(grid, tuple(idx[inside].T), (w * mass)[inside])
    return grid


def smoothed(grid, sigma):
    """`grid` convolved with a Gaussian of `sigma` cells along each axis (cut at 3 sigma,
    zero outside)."""
    if sigma <= 0:
        return grid
    r = int(np.ceil(3 * sigma))
    kernel = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    kernel /= kernel.sum()
    for axis in range(3):
        grid = np.apply_along_axis(lambda row: np.convolve(row, kernel, mode="same"), axis, grid)
    return grid


def correlation(a, b):
    return np.corrcoef(a.ravel(), b.ravel())[0, 1]


def carried(points, cells, scale, integrator):
    """`points` (cell units) carried one frame by `scale` times `cells` (the velocity in cells
    per frame, held over the frame)."""
    u = lambda p: scale * trilinear(cells, p)
    if integrator == "euler":
        return points + u(points)
    if integrator == "midpoint":
        return points + u(points + 0.5 * u(points))
    # Two implicit half steps, x = p + u(x) / 2 by fixed-point iteration: a particle lands
    # where a semi-Lagrangian sample taken at x would start.
    for _ in range(2):
        x = points + 0.5 * u(points)
        for _ in range(8):
            x = points + 0.5 * u(x)
        points = x
    return points


def scale_sweep(data, frames, scales, sigma=1.0):
    for t in frames:
        before, _ = read_truth(data, t - 1)
        after, velocity = read_truth(data, t)
        n = before.shape[0]
        middle = np.zeros(before.shape, bool)
        middle[:, int(0.2 * n) : int(0.8 * n), :] = True
        target = smoothed(after, sigma)
        smoke = before > 1e-4
        points = np.argwhere(smoke).astype(np.float64)
        mass = before[smoke]
        for integrator in ("euler", "midpoint", "two implicit halves"):
            errors = []
            for scale in scales:
                moved = carried(points, velocity * n, scale, integrator)
                grid = smoothed(splat(moved, mass, n), sigma)
                errors.append(
                    np.linalg.norm((grid - target)[middle]) / np.linalg.norm(target[middle])
                )
            best = scales[int(np.argmin(errors))]
            row = " ".join(f"{s:g}: {e:.4f}" for s, e in zip(scales, errors))
            print(f"frame {t} {integrator:>19}: {row}  (least at {best:g})", flush=True)


def main():
    if len(sys.argv) in (4, 5) and sys.argv[3] == "--scales":
        scales = sys.argv[4] if len(sys.argv) == 5 else "0.5,0.6,0.7,0.8,0.9,1,1.1"
        frames = [int(f) for f in sys.argv[2].split(",")]
        scale_sweep(sys.argv[1], frames, [float(s) for s in scales.split(",")])
        return
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    data = sys.argv[1]
    sigma = float(sys.argv[3]) if len(sys.argv) == 4 else 1.0
    for t in [int(f) for f in sys.argv[2].split(",")]:
        before, velocity_before = read_truth(data, t - 1)
        after, velocity_after = read_truth(data, t)
        target = smoothed(after, sigma)
        n = before.shape[0]
        # World units per frame on the unit box to cells per frame.
        cells_before, cells_after = velocity_before * n, velocity_after * n
        smoke = before > 1e-4
        points = np.argwhere(smoke).astype(np.float64)
        mass = before[smoke]
        moved = points + 0.5 * trilinear(cells_before, points)
        moved = moved + 0.5 * trilinear(cells_after, moved)
        particles = splat(moved, mass, n)
        cells = np.argwhere(np.ones((n, n, n), bool)).astype(np.float64)
        back = before
        for _ in range(2):
            back = trilinear(back, cells - 0.5 * cells_after.reshape(-1, 3)).reshape(n, n, n)
        score = lambda grid: correlation(smoothed(grid, sigma), target)
        print(f"frame {t}: still {score(before):.4f}, particles {score(particles):.4f}, "
              f"semi-Lagrangian {score(back):.4f}")


if __name__ == "__main__":
    main()
