"""How much of a synthetic scene's true velocity the previous frame's predicts (issue 18).

  python velocity_persistence.py DATA_DIR [FRAMES...] [--run RUN_DIR]   (needs numpy and scipy)

For each frame t, inside the true smoke (density above 1% of its maximum), the relative error
of four predictions of the true u^t from the true u^(t-1): holding it (what the paper's
update starts from), carrying it along itself for one frame (semi-Lagrangian, trilinear,
departure points clamped to the outermost cell centres: `transport_velocity = true`), the
same carried by a second-order scheme (MacCormack: the semi-Lagrangian step corrected by half
the error of carrying it back, limited to the values around the departure point), and zero.
What is left is what forces (buoyancy, pressure, the solver's vorticity confinement and
inflow) change in a frame: the best a reconstruction that only carries its velocity forward
could do. Also the kinetic energy in the smoke each transport keeps (the trilinear step's
loss is numerical diffusion, which the second-order one mostly avoids).

With `--run`, the same for the run's velocity: the energy over the box each transport keeps
of its u^(t-1), and the relative error against the true u^t of ours held, carried by either
scheme, and of ours' own u^t (what the joint iterations made of it).

Arrays come from the scene's `gt/frame_TTT.safetensors` (velocity [z, y, x, 3], x fastest,
world units per frame) and the run's `frames/frame_TTT.safetensors` (velocity [x, y, z, 3]);
speeds are reported in cells per frame.
"""

import argparse

import numpy as np
from scipy.ndimage import map_coordinates, maximum_filter, minimum_filter

from safetensors_f32 import read_safetensors as read
from scene_truth import read_truth as load


def departure_points(u_cells, sign=1.0):
    """Where each cell centre came from along `sign * u` in one frame, clamped to the
    outermost cell centres; `[3, nx, ny, nz]` in cells."""
    n = u_cells.shape[:3]
    departure = np.indices(n).astype(np.float64) - sign * np.moveaxis(u_cells, -1, 0)
    for axis, size in enumerate(n):
        departure[axis] = np.clip(departure[axis], 0, size - 1)
    return departure


def sample(field, points):
    return np.stack([map_coordinates(field[..., c], points, order=1) for c in range(3)], -1)


def transported(u_cells):
    return sample(u_cells, departure_points(u_cells))


def transported_maccormack(u_cells):
    """Forward step, backward step of its result, half the round trip's error added back,
    clamped per component to the 2x2x2 cell values around the departure point."""
    departure = departure_points(u_cells)
    forward = sample(u_cells, departure)
    back = sample(forward, departure_points(u_cells, -1.0))
    corrected = forward + 0.5 * (u_cells - back)
    n = u_cells.shape[:3]
    corner = np.floor(departure).astype(int)
    for axis, size in enumerate(n):
        corner[axis] = np.clip(corner[axis], 0, size - 1)
    # Each cell's min / max over itself and its +1 neighbours on every axis.
    lowest = np.stack(
        [minimum_filter(u_cells[..., c], size=2, origin=-1, mode="nearest") for c in range(3)], -1
    )
    highest = np.stack(
        [maximum_filter(u_cells[..., c], size=2, origin=-1, mode="nearest") for c in range(3)], -1
    )
    i, j, k = corner
    return np.clip(corrected, lowest[i, j, k], highest[i, j, k])


def main(data, frames, run):
    header = "frame  held  transported  maccormack  zero  rms speed (cells/frame)  energy kept SL / MC"
    if run:
        header += "  | ours: energy kept SL / MC; error held / SL / MC / own u^t"
    print(header)
    for t in frames:
        _, before = load(data, t - 1)
        density, after = load(data, t)
        cells = np.array(after.shape[:3], dtype=np.float64)  # the box is one world unit wide
        before, after = before * cells, after * cells
        smoke = density > 0.01 * density.max()
        truth = after[smoke]
        relative = lambda guess: np.sqrt(((guess[smoke] - truth) ** 2).sum() / (truth**2).sum())
        kept = lambda carried, of, where: (carried[where] ** 2).sum() / (of[where] ** 2).sum()
        speed = np.sqrt((truth**2).sum(1).mean())
        trilinear, second_order = transported(before), transported_maccormack(before)
        line = (
            f"{t:5}  {relative(before):.3f}  {relative(trilinear):11.3f}  "
            f"{relative(second_order):10.3f}  {relative(0 * after):.3f}  {speed:23.2f}  "
            f"{kept(trilinear, before, smoke):.3f} / {kept(second_order, before, smoke):.3f}"
        )
        if run:
            ours = lambda frame: read(f"{run}/frames/frame_{frame:03}.safetensors")[
                "velocity"
            ].astype(np.float64) * cells
            held, own = ours(t - 1), ours(t)
            everywhere = np.ones(smoke.shape, dtype=bool)
            ours_trilinear, ours_second = transported(held), transported_maccormack(held)
            line += (
                f"  | {kept(ours_trilinear, held, everywhere):.3f} / "
                f"{kept(ours_second, held, everywhere):.3f}; {relative(held):.3f} / "
                f"{relative(ours_trilinear):.3f} / {relative(ours_second):.3f} / "
                f"{relative(own):.3f}"
            )
        print(line)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("data", metavar="DATA_DIR")
    parser.add_argument("frames", metavar="FRAMES", type=int, nargs="*")
    parser.add_argument("--run", metavar="RUN_DIR")
    args = parser.parse_args()
    main(args.data, args.frames or [6, 12, 18, 24, 36, 48, 54, 71], args.run)
