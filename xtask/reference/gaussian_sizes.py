"""How large a run's Gaussians are, frame by frame, next to frames fitted alone (issue 18).

  python gaussian_sizes.py RUN_DIR [FRAMES...]      (needs numpy)

For each frame, from the run's `frames/frame_TTT.safetensors`: the size of its Gaussians
weighted by their mass (the geometric mean of the three standard deviations, averaged in log
space with weights sigma * s_x * s_y * s_z, world units), and how many Gaussians hold 90% and
99% of the mass. Where `RUN_DIR-independent/frame_TTT` exists (`reproduce --independent`),
the same for that frame fitted alone. sigma = softplus(raw density), as the renderer.

Also their shape: the mass-weighted mean of each Gaussian's longest over its shortest
standard deviation (1: a sphere), the share of the mass in Gaussians more than 3 times as
long as wide, and the mass-weighted mean |y| of the longest axis' direction (y is up;
directions spread evenly give 0.5, all vertical 1): whether the early plume's vertical
streaks are single stretched Gaussians or arrangements of round ones.
"""

import os
import sys

import numpy as np

from safetensors_f32 import read_safetensors as read


def rotation_matrices(quaternions):
    """[N, 3, 3] rotations of (w, x, y, z) quaternions (normalised here, as the renderer)."""
    q = quaternions / np.linalg.norm(quaternions, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def sizes(path):
    arrays = read(path)
    log_scales = arrays["log_scales"].astype(np.float64)
    sigma = np.logaddexp(0.0, arrays["raw_densities"].astype(np.float64))
    mass = sigma * np.exp(log_scales.sum(axis=1))
    weighted = np.exp((mass[:, None] * log_scales).sum() / mass.sum() / 3.0)
    share = np.cumsum(np.sort(mass)[::-1]) / mass.sum()
    return weighted, int(np.searchsorted(share, 0.9)) + 1, int(np.searchsorted(share, 0.99)) + 1


def shapes(path):
    """Mass-weighted mean elongation, mass share above 3, mass-weighted |y| of the long axis."""
    arrays = read(path)
    scales = np.exp(arrays["log_scales"].astype(np.float64))
    sigma = np.logaddexp(0.0, arrays["raw_densities"].astype(np.float64))
    weight = sigma * scales.prod(axis=1)
    weight /= weight.sum()
    ratio = scales.max(axis=1) / scales.min(axis=1)
    rotations = rotation_matrices(arrays["rotations"].astype(np.float64))
    longest = rotations[np.arange(len(scales)), :, scales.argmax(axis=1)]
    return (weight * ratio).sum(), weight[ratio > 3].sum(), (weight * np.abs(longest[:, 1])).sum()


def main(run, frames):
    run = run.rstrip("/")
    if not frames:
        count = len([f for f in os.listdir(f"{run}/frames") if f.endswith(".safetensors")])
        frames = range(0, count, max(1, count // 12))
    print("frame  size (run)  90% / 99% of mass  elongation  >3x  long axis |y|"
          "  |  size (alone)  90% / 99%  elongation  >3x  long axis |y|")
    for t in frames:
        path = f"{run}/frames/frame_{t:03}.safetensors"
        size, n90, n99 = sizes(path)
        line = f"{t:5}  {size:10.4f}  {n90:6} / {n99:6}  {shape_columns(path)}"
        alone = f"{run}-independent/frame_{t:03}/frames/frame_000.safetensors"
        if os.path.exists(alone):
            size, n90, n99 = sizes(alone)
            line += f"  |  {size:12.4f}  {n90:5} / {n99:5}  {shape_columns(alone)}"
        print(line)


def shape_columns(path):
    elongation, long_share, vertical = shapes(path)
    return f"{elongation:10.2f}  {long_share:4.2f}  {vertical:13.2f}"


if __name__ == "__main__":
    main(sys.argv[1], [int(f) for f in sys.argv[2:]])
