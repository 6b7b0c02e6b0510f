"""How long a sequential chain keeps the scene's own density once it is carried and refitted
(issue 18).

  python truth_chain.py TRAIN CONFIG DATA T0 T1 OUT [--velocity truth|RUN] [--scale S]
      [--integrator euler|midpoint|implicit] [--steps N] [--source truth|none] [--grow V]
      [--seed S]                                                                  (numpy)

A chain outside the trainer, so that its carrier and its fit can each be chosen freely. It
starts from the truth's density at frame T0, drawn by `gaussians_from_truth.py` with
`gaussians` from CONFIG, and fits it for N steps to frame T0's training views. Then, for
each frame t up to T1:

1. It carries the smoke Gaussians' centres one frame by S times a velocity (`truth_transport.py`'s
   particle step): the truth's velocity of frame t, or a run's (`RUN/frames/frame_TTT.safetensors`,
   saved at every frame). With `--grow V`, each smoke Gaussian's variance grows by V cells^2,
   a stand-in for the numerical diffusion of a solver that resamples its density on a grid.
2. With `--source truth` (the default), it renews the source. The smoke Gaussians below 0.2 of
   the box's height are dropped, and the truth's own there are put into free rows. The chain
   then measures what carrying loses, not what a missing emission loses.
3. It fits frame t for N steps with `TRAIN train --config CONFIG --set first_frame=t --set
   frames=1 --set init_iterations=N --set init_gaussians=...`: a frame-0 fit from the carried
   state. CONFIG is a frame fitted alone's, e.g. `RUN-independent/frame_018/config.toml` from
   `reproduce --independent`.
4. It scores the held-out view with `TRAIN eval`.

Prints one line per frame: the frame, the held-out PSNR and the density correlation. Each
frame's fit is kept in OUT/fit-TTT. TRAIN is the `gausmoke-train` binary.
"""

import argparse
import json
import os
import subprocess
import sys

import numpy as np

from safetensors_f32 import read_safetensors, write_safetensors
from scene_truth import read_truth, scene_box
from truth_transport import carried

GAUSSIAN_KEYS = ("means", "rotations", "log_scales", "raw_densities", "colors")
# gaussians_from_truth.py leaves its spare Gaussians at this raw density (negligible).
SPARE_RAW_DENSITY = -9.0
# Below this height (a fraction of the box's) the source renews the smoke every frame.
SOURCE_TOP = 0.2


def config_value(config, key):
    """A top-level integer setting of a run's config.toml."""
    for line in open(config):
        name, _, value = line.partition("=")
        if name.strip() == key:
            return int(value)
    sys.exit(f"{config}: no `{key}`")


def truth_gaussians(args, frame, out, count):
    here = os.path.dirname(os.path.abspath(__file__))
    subprocess.run(
        [sys.executable, os.path.join(here, "gaussians_from_truth.py"), args.data, str(frame),
         str(count), out],
        check=True, capture_output=True,
    )
    state = read_safetensors(out)
    return {k: np.array(state[k]) for k in GAUSSIAN_KEYS}


def fit(args, frame, start):
    out = os.path.join(args.out, f"fit-{frame:03}")
    command = [args.train, "train", "--data", args.data, "--out", out, "--config", args.config,
               "--set", f"first_frame={frame}", "--set", "frames=1", "--set", f"seed={args.seed}",
               "--set", f"init_iterations={args.steps}", "--set", f"init_gaussians={start}"]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"frame {frame}: {' '.join(command)}\n{done.stderr[-2000:]}")
    subprocess.run([args.train, "eval", "--run", out], check=True, capture_output=True)
    scores = json.load(open(os.path.join(out, "eval.json")))["frames"][0]
    state = read_safetensors(os.path.join(out, "frames", "frame_000.safetensors"))
    return {k: np.array(state[k]) for k in GAUSSIAN_KEYS}, scores


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("train")
    parser.add_argument("config")
    parser.add_argument("data")
    parser.add_argument("t0", type=int)
    parser.add_argument("t1", type=int)
    parser.add_argument("out")
    parser.add_argument("--velocity", default="truth", help="truth, or a run's folder")
    parser.add_argument("--scale", type=float, default=0.65)
    parser.add_argument("--integrator", default="euler",
                        choices=["euler", "midpoint", "implicit"])
    parser.add_argument("--steps", type=int, default=25)
    parser.add_argument("--source", default="truth", choices=["truth", "none"])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--grow", type=float, default=0.0,
                        help="variance (cells^2) added to each smoke Gaussian per frame carried")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    count = config_value(args.config, "gaussians")

    start = os.path.join(args.out, "start.safetensors")
    truth_gaussians(args, args.t0, start, count)
    state, scores = fit(args, args.t0, start)
    print(f"frame {args.t0}: {scores['test_psnr']:.2f} dB, density correlation "
          f"{scores['density_correlation']:.3f} (the truth, fitted)", flush=True)
    carried_path = os.path.join(args.out, "carried.safetensors")
    lo, extent = scene_box(args.data)
    for t in range(args.t0 + 1, args.t1 + 1):
        if args.velocity == "truth":
            velocity = read_truth(args.data, t)[1]
        else:
            frame = os.path.join(args.velocity, "frames", f"frame_{t:03}.safetensors")
            velocity = read_safetensors(frame)["velocity"].astype(np.float64)
        # In cell units with the centres of cells at whole numbers, as truth_transport.py's
        # particles; the velocity is in world units per frame.
        cell = extent / velocity.shape[0]
        smoke = state["raw_densities"] > SPARE_RAW_DENSITY + 1.0
        points = (state["means"][smoke].astype(np.float64) - lo) / cell - 0.5
        moved = carried(points, velocity / cell, args.scale, args.integrator)
        state["means"][smoke] = np.clip(lo + (moved + 0.5) * cell, lo, lo + extent)
        if args.grow > 0:
            variance = np.exp(2.0 * state["log_scales"][smoke].astype(np.float64))
            state["log_scales"][smoke] = 0.5 * np.log(variance + args.grow * cell.mean() ** 2)
        if args.source == "truth":
            source = truth_gaussians(args, t, os.path.join(args.out, "source.safetensors"), count)
            top = lo[1] + SOURCE_TOP * extent[1]
            new = np.flatnonzero((source["raw_densities"] > SPARE_RAW_DENSITY + 1.0)
                                 & (source["means"][:, 1] < top))
            old = (state["raw_densities"] > SPARE_RAW_DENSITY + 1.0) & (
                state["means"][:, 1] < top)
            state["raw_densities"][old] = SPARE_RAW_DENSITY
            free = np.flatnonzero(state["raw_densities"] <= SPARE_RAW_DENSITY + 1.0)[: len(new)]
            for key in GAUSSIAN_KEYS:
                state[key][free] = source[key][new[: len(free)]]
        write_safetensors(carried_path, state, {})
        state, scores = fit(args, t, carried_path)
        print(f"frame {t}: {scores['test_psnr']:.2f} dB, density correlation "
              f"{scores['density_correlation']:.3f}", flush=True)


if __name__ == "__main__":
    main()
