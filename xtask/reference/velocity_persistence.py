"""How much of a synthetic scene's true velocity the previous frame's predicts (issue 18).

  python velocity_persistence.py DATA_DIR [FRAMES...]     (needs numpy and scipy)

For each frame t, inside the true smoke (density above 1% of its maximum), the relative error
of three predictions of the true u^t from the true u^(t-1): holding it (what the paper's
update starts from), carrying it along itself for one frame (semi-Lagrangian, trilinear,
departure points clamped to the outermost cell centres: `transport_velocity = true`), and zero.
What is left is what forces (buoyancy, pressure, the solver's vorticity confinement and
inflow) change in a frame: the best a reconstruction that only carries its velocity forward
could do. Arrays come from the scene's `gt/frame_TTT.safetensors` (velocity [z, y, x, 3],
x fastest, world units per frame); speeds are reported in cells per frame.
"""

import sys

import numpy as np
from scipy.ndimage import map_coordinates

from scene_truth import read_truth as load


def transported(u_cells):
    n = u_cells.shape[:3]
    departure = np.indices(n).astype(np.float64) - np.moveaxis(u_cells, -1, 0)
    for axis, size in enumerate(n):
        departure[axis] = np.clip(departure[axis], 0, size - 1)
    return np.stack(
        [map_coordinates(u_cells[..., c], departure, order=1) for c in range(3)], -1
    )


def main(data, frames):
    print("frame  held  transported  zero  rms speed (cells/frame)")
    for t in frames:
        _, before = load(data, t - 1)
        density, after = load(data, t)
        cells = np.array(after.shape[:3], dtype=np.float64)  # the box is one world unit wide
        before, after = before * cells, after * cells
        smoke = density > 0.01 * density.max()
        truth = after[smoke]
        relative = lambda guess: np.sqrt(((guess[smoke] - truth) ** 2).sum() / (truth**2).sum())
        speed = np.sqrt((truth**2).sum(1).mean())
        print(
            f"{t:5}  {relative(before):.3f}  {relative(transported(before)):11.3f}"
            f"  {relative(0 * after):.3f}  {speed:.2f}"
        )


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    frames = [int(f) for f in sys.argv[2:]] or [6, 12, 18, 24, 36, 48, 54, 71]
    main(sys.argv[1], frames)
