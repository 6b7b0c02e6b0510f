"""How large a run's Gaussians are, frame by frame, next to frames fitted alone (issue 18).

  python gaussian_sizes.py RUN_DIR [FRAMES...]      (needs numpy)

For each frame, from the run's `frames/frame_TTT.safetensors`: the size of its Gaussians
weighted by their mass (the geometric mean of the three standard deviations, averaged in log
space with weights sigma * s_x * s_y * s_z, world units), and how many Gaussians hold 90% and
99% of the mass. Where `RUN_DIR-independent/frame_TTT` exists (`reproduce --independent`),
the same for that frame fitted alone. sigma = softplus(raw density), as the renderer.
"""

import os
import sys

import numpy as np

from safetensors_f32 import read_safetensors as read


def sizes(path):
    arrays = read(path)
    log_scales = arrays["log_scales"].astype(np.float64)
    sigma = np.logaddexp(0.0, arrays["raw_densities"].astype(np.float64))
    mass = sigma * np.exp(log_scales.sum(axis=1))
    weighted = np.exp((mass[:, None] * log_scales).sum() / mass.sum() / 3.0)
    share = np.cumsum(np.sort(mass)[::-1]) / mass.sum()
    return weighted, int(np.searchsorted(share, 0.9)) + 1, int(np.searchsorted(share, 0.99)) + 1


def main(run, frames):
    run = run.rstrip("/")
    if not frames:
        count = len([f for f in os.listdir(f"{run}/frames") if f.endswith(".safetensors")])
        frames = range(0, count, max(1, count // 12))
    print("frame  size (run)  90% / 99% of mass  |  size (alone)  90% / 99%")
    for t in frames:
        size, n90, n99 = sizes(f"{run}/frames/frame_{t:03}.safetensors")
        line = f"{t:5}  {size:10.4f}  {n90:6} / {n99:6}"
        alone = f"{run}-independent/frame_{t:03}/frames/frame_000.safetensors"
        if os.path.exists(alone):
            size, n90, n99 = sizes(alone)
            line += f"      |  {size:12.4f}  {n90:5} / {n99:5}"
        print(line)


if __name__ == "__main__":
    main(sys.argv[1], [int(f) for f in sys.argv[2:]])
