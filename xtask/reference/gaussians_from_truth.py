"""Gaussians that draw a synthetic scene's true density, as a frame file (issue 18).

  python gaussians_from_truth.py DATA FRAME COUNT OUT.safetensors [--std CELLS] [--blur CELLS]
      [--min-stride N] [--jitter CELLS] [--warp CELLS [--warp-length CELLS]] [--shift-y CELLS]
      [--noise FRACTION] [--dense-first] [--seed S]          (numpy; scipy for --blur, --warp)

Writes `OUT` in the layout of a run's `frames/frame_TTT.safetensors`, holding COUNT smoke
Gaussians, for `gausmoke-train train --set init_gaussians=OUT` (with `first_frame` = FRAME,
`frames = 1`): a fit that starts from the truth instead of a spread through the box. The
question it serves: does a state nearer the scene's 3D density picture the held-out view
better once it is fitted to the training views as hard as a frame fitted alone?

One isotropic Gaussian sits at the centre of each smoke cell of the true density
(`gt/frame_TTT.safetensors`, `[z][y][x]`, x fastest, cell centres at (i + 0.5) / n of the
box; smoke: above 1% of the largest density), with standard deviation `--std` cells (default
0.6: a lattice of such Gaussians sums to a smooth field) and the extinction that makes their
sum match the cell's, `sigma = density_scale * density` as the scene's ray marcher renders
it. When the smoke has more cells than COUNT, the lattice is coarsened to blocks of 2^3,
3^3, ... cells (their mean density, the Gaussians as much larger) until it fits. The
Gaussians left over are spread through the box at a negligible density, for the fit to use.
Colours are white, as the scene's smoke emits.

The options spoil that start in one way each, to measure how exact a carried state must be
to picture the held-out view better than a frame fitted alone: `--blur` blurs the true
density by a Gaussian of that many cells first; `--min-stride` coarsens the lattice at least
that far; `--jitter` moves each smoke Gaussian by its own random offset (that standard
deviation per axis, in cells); `--warp` moves them along a smooth random field (a Gaussian
filter of `--warp-length` cells over white noise, scaled to that rms length in cells), as a
smooth velocity error would; `--shift-y` moves them all up (down if negative); `--noise`
multiplies each one's extinction by exp(FRACTION times a standard normal).

`--dense-first` draws the smoke more finely than a uniform coarsening where it has more
cells than COUNT: one Gaussian per smoke cell in the 2^3-cell blocks whose densest cell is
densest, as many of those blocks as COUNT allows, and one per block elsewhere.
"""

import argparse
import json
import os

import numpy as np

from safetensors_f32 import write_safetensors
from scene_truth import read_truth, scene_box


def inverse_softplus(y):
    y = np.maximum(y, 1e-12)
    return np.where(y > 20.0, y, np.log(np.expm1(np.minimum(y, 20.0))))


def smooth_displacement(points, lo, cell, n, args, rng):
    """A smooth random displacement (cells) at `points`: white noise on the n^3 grid filtered
    by a Gaussian of `args.warp_length` cells (periodic), scaled to rms `args.warp`, read at
    the cell holding each point."""
    from scipy.ndimage import gaussian_filter

    field = np.stack(
        [gaussian_filter(rng.standard_normal((n, n, n)), args.warp_length, mode="wrap")
         for _ in range(3)],
        axis=-1,
    )
    field *= args.warp / np.sqrt((field**2).sum(axis=-1).mean())
    cells = np.clip(((points - lo) / cell).astype(int), 0, n - 1)
    return field[cells[:, 0], cells[:, 1], cells[:, 2]]


def uniform_lattice(density, count, min_stride):
    """The smoke's cells, coarsened by whole strides (at least `min_stride`) until its blocks
    fit in `count`: each block's centre (in cells), mean density and side (in cells), and the
    stride."""
    n = density.shape[0]
    stride = min_stride
    while True:
        m = n // stride
        blocks = density[: m * stride, : m * stride, : m * stride]
        blocks = blocks.reshape(m, stride, m, stride, m, stride).mean(axis=(1, 3, 5))
        smoke = blocks > 0.01 * blocks.max()
        if smoke.sum() <= count or m <= 2:
            break
        stride += 1
    chosen = np.argwhere(smoke)  # (x, y, z) of the blocks
    if len(chosen) > count:
        raise SystemExit(f"{len(chosen)} smoke blocks even at stride {stride}: raise COUNT")
    sides = np.full(len(chosen), float(stride))
    return (chosen + 0.5) * stride, blocks[tuple(chosen.T)], sides, stride


def dense_first(density, count):
    """The smoke drawn at one Gaussian per smoke cell in the 2^3-cell blocks whose densest
    cell is densest, as many of them as `count` allows, and one Gaussian per smoke block
    elsewhere: centres (in cells), densities and sides (in cells), full-resolution cells
    first."""
    n = density.shape[0]
    m = n // 2
    cells = density[: 2 * m, : 2 * m, : 2 * m]
    smoke = cells > 0.01 * cells.max()
    by_block = lambda a: a.reshape(m, 2, m, 2, m, 2).transpose(0, 2, 4, 1, 3, 5).reshape(
        m, m, m, 8)
    values, inside = by_block(cells), by_block(smoke)
    block_mean = values.mean(axis=-1)
    smoky = block_mean > 0.01 * block_mean.max()
    # Each block drawn cell by cell costs its smoke cells in place of its one Gaussian.
    full = np.zeros(m**3, bool)
    total = smoky.sum()
    for block in np.argsort(-values.max(axis=-1).ravel()):
        extra = inside.reshape(-1, 8)[block].sum() - smoky.ravel()[block]
        if total + extra > count:
            break
        full[block] = True
        total += extra
    full = full.reshape(m, m, m)
    centres, rho, sides = [], [], []
    for i, j, k in np.argwhere(full):
        for x, y, z in np.ndindex(2, 2, 2):
            cell = (2 * i + x, 2 * j + y, 2 * k + z)
            if smoke[cell]:
                centres.append(np.array(cell) + 0.5)
                rho.append(cells[cell])
                sides.append(1.0)
    for i, j, k in np.argwhere(smoky & ~full):
        centres.append((np.array([i, j, k]) + 0.5) * 2.0)
        rho.append(block_mean[i, j, k])
        sides.append(2.0)
    return np.array(centres), np.array(rho), np.array(sides)


def draw(density, count, scale, lo, extent, args):
    """`count` Gaussians drawing `density` ([x, y, z], the scene's units; times `scale` it is
    the extinction) in the box at `lo` of size `extent`, as the module describes, with `args`'
    drawing and spoiling options: the frame file's arrays, and what was drawn."""
    n = density.shape[0]
    cell = extent / n
    if not np.allclose(cell, cell[0]):
        raise SystemExit(f"the box's cells are not cubes ({cell})")
    if args.dense_first:
        centres, rho, sides = dense_first(density, count)
        drawn = f"{len(rho)} Gaussians, one a cell in the densest 2^3 blocks, one a block elsewhere"
    else:
        centres, rho, sides, stride = uniform_lattice(density, count, args.min_stride)
        drawn = f"{len(rho)} Gaussians on the smoke's blocks of {stride}^3 cells"
    rng = np.random.default_rng(args.seed)
    # Each perturbation draws from the generator only when asked for, so that the plain start
    # (and its spare Gaussians) stays what it was.
    if args.noise > 0:
        rho = rho * np.exp(args.noise * rng.standard_normal(len(rho)))
    side = sides * cell[0]
    means = lo + centres * cell[0]
    if args.jitter > 0:
        means = means + args.jitter * cell[0] * rng.standard_normal(means.shape)
    means[:, 1] += args.shift_y * cell[0]
    if args.warp > 0:
        means = means + cell[0] * smooth_displacement(means, lo, cell[0], n, args, rng)
    std = args.std * side
    # A Gaussian of peak extinction s and standard deviation std holds s (2 pi)^(3/2) std^3 of
    # extinction; the block holds scale * rho * side^3.
    peak = scale * rho * side**3 / ((2.0 * np.pi) ** 1.5 * std**3)
    rest = count - len(rho)
    spare = lo + rng.random((rest, 3)) * extent
    means = np.concatenate([means, spare])
    raw = np.concatenate([inverse_softplus(peak), np.full(rest, -9.0)])
    # The size a spread through the box starts with (GaussianModel::init_in_box).
    spare_std = 0.5 * (np.prod(extent) / count) ** (1.0 / 3.0)
    log_scales = np.concatenate(
        [np.repeat(np.log(std)[:, None], 3, axis=1), np.full((rest, 3), np.log(spare_std))]
    )
    arrays = {
        "means": means.astype(np.float32),
        "rotations": np.tile([1.0, 0.0, 0.0, 0.0], (count, 1)).astype(np.float32),
        "log_scales": log_scales.astype(np.float32),
        "raw_densities": raw.astype(np.float32),
        "colors": np.ones((count, 3), np.float32),
    }
    return arrays, f"{drawn}, {rest} spare; std {std.min():.4f} to {std.max():.4f}"


def options(parser):
    """The drawing and spoiling options (their defaults draw the truth as it is)."""
    parser.add_argument("--std", type=float, default=0.6, help="standard deviation, in cells")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--blur", type=float, default=0.0, help="cells")
    parser.add_argument("--min-stride", type=int, default=1)
    parser.add_argument("--dense-first", action="store_true")
    parser.add_argument("--jitter", type=float, default=0.0, help="cells, per axis")
    parser.add_argument("--warp", type=float, default=0.0, help="rms cells")
    parser.add_argument("--warp-length", type=float, default=3.0, help="cells")
    parser.add_argument("--shift-y", type=float, default=0.0, help="cells")
    parser.add_argument("--noise", type=float, default=0.0, help="log-normal sigma")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("data")
    parser.add_argument("frame", type=int)
    parser.add_argument("count", type=int)
    parser.add_argument("out")
    options(parser)
    args = parser.parse_args()

    info = json.load(open(os.path.join(args.data, "info.json")))
    scale = info["synth"]["density_scale"]
    lo, extent = scene_box(args.data)
    density = read_truth(args.data, args.frame)[0].astype(np.float64)  # [x, y, z]
    if args.blur > 0:
        from scipy.ndimage import gaussian_filter

        density = gaussian_filter(density, args.blur)
    arrays, drawn = draw(density, args.count, scale, lo, extent, args)
    write_safetensors(args.out, arrays, {})
    print(drawn)


if __name__ == "__main__":
    main()
