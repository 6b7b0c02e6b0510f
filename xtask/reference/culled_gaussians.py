"""How much of a run's reconstruction the renderer culls (issue 18).

  python culled_gaussians.py RUN_DIR FRAMES [DATA_DIR]     (numpy)

The rasterizer skips a Gaussian on a ray where its alpha is below `alpha_min` (the
`alpha_min` setting; 3DGS's 1/255 by default). A Gaussian whose peak optical depth,
`sigma sqrt(2 pi) s_max`, stays under `-ln(1 - alpha_min)` is skipped on every ray of every
view: it gets no gradient from the pictures, so the fit leaves it where it parked, yet it is
carried by the flow and splatted into the density grid and the exports. For each frame in the
comma list FRAMES this prints the share of Gaussians and of their mass (sigma times volume)
under the run's own cull and under 1/255. With DATA_DIR (a synthetic scene with `gt/`), it
splats the Gaussians onto the truth's cells (every one, and only those the renderer can see)
and prints, for each, the correlation and relative error against the true density (scaled by
the scene's `synth.density_scale`) and the share of the mass in cells where the truth is under 1%
of its largest value.
"""

import json
import os
import sys

import numpy as np

from gaussian_sizes import rotation_matrices
from safetensors_f32 import read_safetensors as read
from scene_truth import read_truth


def run_settings(run):
    """The run's `alpha_min` (absent from configs written before it existed: 1/255) and box."""
    alpha_min = 1.0 / 255.0
    for line in open(os.path.join(run, "config.toml")):
        key, _, value = line.partition("=")
        if key.strip() == "alpha_min":
            alpha_min = float(value)
    info = json.load(open(os.path.join(run, "run.json")))
    return alpha_min, np.array(info["box_lo"]), np.array(info["box_hi"])


def splat(gaussians, rows, lo, hi, n):
    """Sum of the chosen Gaussians' densities at the centres of an n^3 grid over [lo, hi],
    `[x, y, z]`, each evaluated within three of its largest standard deviations."""
    cell = (hi - lo) / n
    scales = np.exp(gaussians["log_scales"][rows]).astype(np.float64)
    sigma = np.logaddexp(0.0, gaussians["raw_densities"][rows].astype(np.float64))
    means = gaussians["means"][rows].astype(np.float64)
    r = rotation_matrices(gaussians["rotations"][rows].astype(np.float64))
    precision = np.einsum("nij,nj,nkj->nik", r, 1.0 / scales**2, r)
    out = np.zeros((n, n, n))
    for mean, scale, density, inverse in zip(means, scales, sigma, precision):
        reach = 3.0 * scale.max()
        first = np.clip(np.floor((mean - reach - lo) / cell - 0.5).astype(int), 0, n)
        last = np.clip(np.ceil((mean + reach - lo) / cell - 0.5).astype(int) + 1, 0, n)
        if np.any(last <= first):
            continue
        axes = [lo[k] + (np.arange(first[k], last[k]) + 0.5) * cell[k] - mean[k] for k in range(3)]
        d = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
        out[first[0]:last[0], first[1]:last[1], first[2]:last[2]] += density * np.exp(
            -0.5 * np.einsum("...i,ij,...j->...", d, inverse, d)
        )
    return out


def main(run, frames, data):
    alpha_min, lo, hi = run_settings(run)
    scale = json.load(open(os.path.join(data, "info.json")))["synth"]["density_scale"] if data else None
    print(f"{run}: alpha_min {alpha_min:.3g}")
    for t in frames:
        gaussians = read(os.path.join(run, "frames", f"frame_{t:03}.safetensors"))
        scales = np.exp(gaussians["log_scales"].astype(np.float64))
        sigma = np.logaddexp(0.0, gaussians["raw_densities"].astype(np.float64))
        peak = sigma * np.sqrt(2.0 * np.pi) * scales.max(axis=1)
        mass = sigma * scales.prod(axis=1)
        line = f"frame {t:3}:"
        for name, cull in [("its cull", alpha_min), ("1/255", 1.0 / 255.0)]:
            culled = peak < -np.log1p(-cull)
            line += (f" under {name} {culled.mean():.2f} of Gaussians,"
                     f" {mass[culled].sum() / mass.sum():.2f} of mass;")
        print(line)
        if data is None:
            continue
        truth, _ = read_truth(data, t)
        truth = scale * truth.astype(np.float64)
        outside = truth < 0.01 * truth.max()
        visible = np.flatnonzero(peak >= -np.log1p(-alpha_min))
        for name, rows in [("every Gaussian", np.arange(len(peak))), ("those rendered", visible)]:
            ours = splat(gaussians, rows, lo, hi, truth.shape[0])
            error = np.linalg.norm(ours - truth) / np.linalg.norm(truth)
            correlation = np.corrcoef(ours.ravel(), truth.ravel())[0, 1]
            print(f"    splatting {name:14}: correlation {correlation:.4f}, relative error"
                  f" {error:.3f}, mass outside the true smoke {ours[outside].sum() / ours.sum():.2f}")


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    main(sys.argv[1], [int(f) for f in sys.argv[2].split(",")],
         sys.argv[3] if len(sys.argv) == 4 else None)
