"""Independent check of eval's obstacle leakage, and how deep it sits (issue 20).

For each run folder of the `obstacle`/`ball` scenes, reads every `frames/frame_TTT.safetensors`
(numpy only, no Rust code) and prints the mean over frames of the share of the smoke density in
grid cells whose centre lies inside the scenes' sphere (eval's `obstacle_density_fraction`),
and of the share in cells more than one cell deep inside it, beside those cells' share of the
volume.

    python xtask/reference/obstacle_leakage.py RUN [RUN ...]
"""
import glob
import sys

import numpy as np

from safetensors_f32 import read_safetensors

# The `synth obstacle` / `synth ball` scenes: box and sphere in world units.
LO, HI = np.array([-0.5, 0.0, -0.5]), np.array([0.5, 1.0, 0.5])
CENTRE, RADIUS = np.array([0.04, 0.4, 0.0]), 0.14


def leakage(run):
    rows = []
    for path in sorted(glob.glob(f"{run}/frames/frame_*.safetensors")):
        density = read_safetensors(path)["density"].clip(0)
        shape = np.array(density.shape)
        cell = (HI - LO) / shape
        index = np.stack(np.meshgrid(*[np.arange(k) for k in shape], indexing="ij"), -1)
        distance = np.linalg.norm(LO + (index + 0.5) * cell - CENTRE, axis=-1) - RADIUS
        inside, deep = distance <= 0, distance <= -cell.max()
        total = density.sum()
        rows.append((density[inside].sum() / total, density[deep].sum() / total, inside.mean(), deep.mean()))
    return np.array(rows)


if __name__ == "__main__":
    for run in sys.argv[1:]:
        r = leakage(run)
        print(
            f"{run.rstrip('/').split('/')[-1]:28s} inside {r[:, 0].mean():.4f} "
            f"deeper than a cell {r[:, 1].mean():.4f} (volume shares {r[0, 2]:.4f}, {r[0, 3]:.4f})"
        )
