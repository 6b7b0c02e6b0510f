"""A synthetic scene's ground truth and a run's velocity, in the run's layout, for the
reference diagnostics (numpy alone).

The scene's `gt/frame_TTT.safetensors` holds density [z, y, x] and velocity [z, y, x, 3]
(x fastest); a run's `frames/frame_TTT.safetensors` holds velocity [x, y, z, 3] (x slowest);
both in world units per frame on the same box.
"""

import json
import os
import sys

import numpy as np

from safetensors_f32 import read_safetensors as read


def read_truth(data, t):
    """Frame `t`'s true density [x, y, z] and velocity [x, y, z, 3] (float64)."""
    truth = read(f"{data}/gt/frame_{t:03}.safetensors")
    density = np.transpose(truth["density"], (2, 1, 0))
    velocity = np.transpose(truth["velocity"], (2, 1, 0, 3)).astype(np.float64)
    return density, velocity


def read_run_and_truth(run, data, t, folder="frames"):
    """The run's velocity at frame `t` (from `RUN/folder`: `velocity_estimate` for the
    estimate of `gausmoke-train velocity`, in the same layout) with the truth's density and
    velocity; exits when the grids differ."""
    ours = read(f"{run}/{folder}/frame_{t:03}.safetensors")["velocity"].astype(np.float64)
    density, velocity = read_truth(data, t)
    if ours.shape != velocity.shape:
        sys.exit(f"frame {t}: run grid {ours.shape[:3]} vs truth {velocity.shape[:3]}")
    return ours, density, velocity


def scene_box(data):
    """The scene's box from its `info.json`: the voxel cube [0, voxel_scale] carried into the
    world by voxel_matrix, as its lowest corner and its extent (numpy arrays)."""
    info = json.load(open(os.path.join(data, "info.json")))
    matrix = np.array(info["voxel_matrix"], dtype=np.float64)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.float64)
    world = (corners * np.array(info["voxel_scale"])) @ matrix[:3, :3].T + matrix[:3, 3]
    return world.min(axis=0), world.max(axis=0) - world.min(axis=0)
