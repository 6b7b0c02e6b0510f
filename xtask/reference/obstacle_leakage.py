"""Independent check of eval's obstacle leakage, and how deep it sits (issue 20).

For each run folder of a scene with obstacles (`obstacle`, `ball`, `blocks`), reads every
`frames/frame_TTT.safetensors` (numpy only, no Rust code) and prints the mean over frames of
the share of the smoke density in grid cells whose centre lies inside an obstacle (eval's
`obstacle_density_fraction`), and of the share in cells more than one cell deep inside one,
beside those cells' share of the volume; then, per obstacle, the share inside it and in the
band of cells within two cells outside it (smoke Gaussians that paint a textured solid sit
there: their centres are kept out of it). The obstacles (spheres and boxes) and the box are
read from the data set the run names in `run.json` (`info.json` or `transforms_train.json`).

    python xtask/reference/obstacle_leakage.py RUN [RUN ...]
"""
import glob
import json
import os
import sys

import numpy as np

from safetensors_f32 import read_safetensors

def scene(run):
    """The run's smoke box and its data set's obstacles, as signed-distance functions."""
    meta = json.load(open(f"{run}/run.json"))
    lo, hi = np.array(meta["box_lo"]), np.array(meta["box_hi"])
    for name in ("info.json", "transforms_train.json"):
        path = os.path.join(meta["data"], name)
        if os.path.exists(path):
            obstacles = json.load(open(path)).get("obstacles", [])
            break
    else:
        sys.exit(f"{meta['data']}: neither info.json nor transforms_train.json")
    fields = []
    for item in obstacles:
        if "sphere" in item:
            centre, radius = np.array(item["sphere"]["centre"]), item["sphere"]["radius"]
            fields.append(lambda p, c=centre, r=radius: np.linalg.norm(p - c, axis=-1) - r)
        else:
            bmin, bmax = np.array(item["box"]["min"]), np.array(item["box"]["max"])

            def box(p, bmin=bmin, bmax=bmax):
                q = np.abs(p - 0.5 * (bmin + bmax)) - 0.5 * (bmax - bmin)
                return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)

            fields.append(box)
    return lo, hi, fields


def leakage(run):
    lo, hi, fields = scene(run)
    rows = []
    for path in sorted(glob.glob(f"{run}/frames/frame_*.safetensors")):
        density = read_safetensors(path)["density"].clip(0)
        shape = np.array(density.shape)
        cell = (hi - lo) / shape
        index = np.stack(np.meshgrid(*[np.arange(k) for k in shape], indexing="ij"), -1)
        centres = lo + (index + 0.5) * cell
        distances = [f(centres) for f in fields]
        distance = np.min(distances, axis=0)
        inside, deep = distance <= 0, distance <= -cell.max()
        total = density.sum()
        row = [density[inside].sum() / total, density[deep].sum() / total, inside.mean(), deep.mean()]
        for d in distances:
            band = (d > 0) & (d <= 2 * cell.max())
            row += [density[d <= 0].sum() / total, density[band].sum() / total]
        rows.append(row)
    return np.array(rows)


if __name__ == "__main__":
    for run in sys.argv[1:]:
        r = leakage(run)
        print(
            f"{run.rstrip('/').split('/')[-1]:28s} inside {r[:, 0].mean():.4f} "
            f"deeper than a cell {r[:, 1].mean():.4f} (volume shares {r[0, 2]:.4f}, {r[0, 3]:.4f})"
        )
        for k in range((r.shape[1] - 4) // 2):
            print(
                f"{'':28s} obstacle {k}: inside {r[:, 4 + 2 * k].mean():.4f}, "
                f"within two cells outside {r[:, 5 + 2 * k].mean():.4f}"
            )
