"""How long a sequential chain keeps the scene's own density once it is carried and refitted
(issue 18).

  python truth_chain.py TRAIN CONFIG DATA T0 T1 OUT [--carrier particles|grid]
      [--velocity truth|RUN] [--estimate] [--scale S] [--integrator euler|midpoint|implicit]
      [--substeps K] [--steps N] [--refit every|last] [--source truth|none] [--grow V]
      [--dense-first] [--velocity-blur CELLS] [--seed S] [--start-from RUN]
      (numpy; scipy for --velocity-blur)

A chain outside the trainer, so that its carrier and its fit can each be chosen freely. It
starts from the truth's density at frame T0, drawn as `gaussians_from_truth.py` draws it
(`--dense-first` as there) with `gaussians` from CONFIG, and fits it for N steps to frame
T0's training views; with `--start-from RUN`, it starts from that run's own Gaussians at
frame T0 (`RUN/frames/frame_T0.safetensors`) instead, so that the chain is one a second pass
over a trained run could make. Then, for each frame t up to T1:

1. It carries the state one frame by S times a velocity (S is 0.65 for particles and 1 on
   the grid unless `--scale` says otherwise): the truth's velocity of frame t, or
   a run's (`RUN/frames/frame_TTT.safetensors`, saved at every frame; with `--estimate`
   the run's `gausmoke-train velocity` estimate, `RUN/velocity_estimate/`). `--velocity-blur`
   blurs each of its components by a Gaussian of that many cells first, for a velocity
   with the truth's direction but a field's smoothness.
   - `--carrier particles` (the default) moves the smoke Gaussians' centres
     (`truth_transport.py`'s particle step, by `--integrator`). With `--grow V`, each smoke
     Gaussian's variance also grows by V cells^2, a stand-in for the numerical diffusion of
     a solver that resamples its density on a grid.
   - `--carrier grid` carries the fitted state's density, splatted on the grid (its frame
     file's `density`), by K semi-Lagrangian steps (`--substeps`, 2 by default): each
     cell takes the trilinear sample where the velocity traced it back from. This is the
     synthetic scene's own kind of step. It then draws the carried density afresh.
2. With `--source truth` (the default), it renews the source below 0.2 of the box's height
   from the truth: the particles' smoke Gaussians there are replaced by the truth's own, in
   free rows, and the grid's rows there by the truth's density. The chain then measures what
   carrying loses, not what a missing emission loses. With `--source run` (the grid carrier
   and `--start-from` only) the grid's rows there come from that run's own density grid of
   frame t instead, as a second pass over the run could take them.
3. With `--refit every` (the default) it fits frame t for N steps with `TRAIN train --config
   CONFIG --set first_frame=t --set frames=1 --set init_iterations=N --set
   init_gaussians=...`: a frame-0 fit from the carried state. CONFIG is a frame fitted
   alone's, e.g. `RUN-independent/frame_018/config.toml` from `reproduce --independent`.
4. It scores the held-out view with `TRAIN eval`.

With `--refit last`, nothing is fitted before T1: the truth as drawn at T0 is carried to T1
(its density itself on the grid), and only frame T1 is fitted and scored.

Prints one line per frame: the frame, the held-out PSNR and the density correlation. Each
frame's fit is kept in OUT/fit-TTT. TRAIN is the `gausmoke-train` binary.
"""

import argparse
import json
import os
import subprocess
import sys

import numpy as np

from gaussians_from_truth import draw, options
from safetensors_f32 import read_safetensors, write_safetensors
from scene_truth import read_truth, scene_box
from truth_transport import carried, trilinear

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


def drawer(args, count, scale, lo, extent):
    """The frame-file arrays of `count` Gaussians drawing a density (the scene's units), as
    gaussians_from_truth.py draws the truth, as a function of the density."""
    parser = argparse.ArgumentParser()
    options(parser)
    drawing = parser.parse_args(["--dense-first"] if args.dense_first else [])
    return lambda density: draw(density.astype(np.float64), count, scale, lo, extent, drawing)[0]


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
    return {k: np.array(state[k]) for k in (*GAUSSIAN_KEYS, "density")}, scores


def report(frame, scores, note=""):
    print(f"frame {frame}: {scores['test_psnr']:.2f} dB, density correlation "
          f"{scores['density_correlation']:.3f}{note}", flush=True)


def carried_on_grid(density, velocity, substeps):
    """`density` ([x, y, z]) carried one frame by `velocity` (cells per frame, [x, y, z, 3]) in
    `substeps` semi-Lagrangian steps with trilinear samples."""
    n = density.shape[0]
    cells = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    cells = cells.astype(np.float64)
    step = velocity / substeps
    for _ in range(substeps):
        density = trilinear(density, cells - trilinear(step, cells)).reshape(density.shape)
    return density


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("train")
    parser.add_argument("config")
    parser.add_argument("data")
    parser.add_argument("t0", type=int)
    parser.add_argument("t1", type=int)
    parser.add_argument("out")
    parser.add_argument("--velocity", default="truth", help="truth, or a run's folder")
    parser.add_argument("--estimate", action="store_true",
                        help="the run's velocity_estimate/ instead of its own velocity")
    parser.add_argument("--scale", type=float, help="0.65 for particles, 1 on the grid")
    parser.add_argument("--integrator", default="euler",
                        choices=["euler", "midpoint", "implicit"])
    parser.add_argument("--steps", type=int, default=25)
    parser.add_argument("--source", default="truth", choices=["truth", "none", "run"])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--grow", type=float, default=0.0,
                        help="variance (cells^2) added to each smoke Gaussian per frame carried")
    parser.add_argument("--carrier", default="particles", choices=["particles", "grid"])
    parser.add_argument("--substeps", type=int, default=2)
    parser.add_argument("--dense-first", action="store_true")
    parser.add_argument("--refit", default="every", choices=["every", "last"])
    parser.add_argument("--velocity-blur", type=float, default=0.0, help="cells")
    parser.add_argument("--start-from", metavar="RUN",
                        help="start from the run's Gaussians at T0 instead of the truth")
    args = parser.parse_args()
    if args.source == "run" and (not args.start_from or args.carrier != "grid"):
        sys.exit("--source run renews the grid's source rows from the run of --start-from")
    if args.estimate and args.velocity == "truth":
        sys.exit("--estimate reads a run's estimate: pass the run with --velocity RUN")
    if args.carrier == "grid" and (args.grow > 0 or args.integrator != "euler"):
        sys.exit("--grow and --integrator move particles; the grid carrier has neither")
    if args.scale is None:
        # One explicit Euler step carries the scene's smoke best at about 0.65 of its velocity
        # (truth_transport.py --scales); the scene's own kind of step at all of it.
        args.scale = 0.65 if args.carrier == "particles" else 1.0
    if os.path.isdir(args.out) and os.listdir(args.out):
        sys.exit(f"{args.out} is not empty: choose another OUT")
    os.makedirs(args.out, exist_ok=True)
    count = config_value(args.config, "gaussians")
    scale = json.load(open(os.path.join(args.data, "info.json")))["synth"]["density_scale"]
    lo, extent = scene_box(args.data)
    drawn = drawer(args, count, scale, lo, extent)

    start = os.path.join(args.out, "start.safetensors")
    truth = read_truth(args.data, args.t0)[0]
    if args.start_from:
        if args.refit != "every":
            sys.exit("--start-from starts a fitted chain: it needs --refit every")
        own = read_safetensors(os.path.join(args.start_from, "frames",
                                            f"frame_{args.t0:03}.safetensors"))
        write_safetensors(start, {k: own[k] for k in GAUSSIAN_KEYS}, {})
    else:
        write_safetensors(start, drawn(truth), {})
    if args.refit == "every":
        state, scores = fit(args, args.t0, start)
        report(args.t0, scores, " (the run's state, fitted)" if args.start_from
               else " (the truth, fitted)")
    else:
        state = {k: np.array(v) for k, v in read_safetensors(start).items()}
        state["density"] = scale * truth.astype(np.float64)
    carried_path = os.path.join(args.out, "carried.safetensors")
    for t in range(args.t0 + 1, args.t1 + 1):
        if args.velocity == "truth":
            velocity = read_truth(args.data, t)[1]
        else:
            folder = "velocity_estimate" if args.estimate else "frames"
            frame = os.path.join(args.velocity, folder, f"frame_{t:03}.safetensors")
            velocity = read_safetensors(frame)["velocity"].astype(np.float64)
        if args.velocity_blur > 0:
            from scipy.ndimage import gaussian_filter

            velocity = np.stack([gaussian_filter(velocity[..., a], args.velocity_blur)
                                 for a in range(3)], axis=-1)
        # In cell units with the centres of cells at whole numbers, as truth_transport.py's
        # particles; the velocity is in world units per frame.
        cell = extent / velocity.shape[0]
        if args.carrier == "grid":
            density = state["density"].astype(np.float64) / scale
            if density.shape != velocity.shape[:3]:
                sys.exit(f"the fit's density grid {density.shape} is not the velocity's")
            density = carried_on_grid(density, args.scale * velocity / cell, args.substeps)
            rows = int(SOURCE_TOP * density.shape[1])
            if args.source == "truth":
                density[:, :rows, :] = read_truth(args.data, t)[0][:, :rows, :]
            elif args.source == "run":
                own = read_safetensors(os.path.join(args.start_from, "frames",
                                                    f"frame_{t:03}.safetensors"))["density"]
                density[:, :rows, :] = own[:, :rows, :].astype(np.float64) / scale
            arrays = drawn(density)
        else:
            smoke = state["raw_densities"] > SPARE_RAW_DENSITY + 1.0
            points = (state["means"][smoke].astype(np.float64) - lo) / cell - 0.5
            moved = carried(points, velocity / cell, args.scale, args.integrator)
            state["means"][smoke] = np.clip(lo + (moved + 0.5) * cell, lo, lo + extent)
            if args.grow > 0:
                variance = np.exp(2.0 * state["log_scales"][smoke].astype(np.float64))
                state["log_scales"][smoke] = 0.5 * np.log(variance + args.grow * cell.mean()**2)
            if args.source == "truth":
                source = drawn(read_truth(args.data, t)[0])
                top = lo[1] + SOURCE_TOP * extent[1]
                live = SPARE_RAW_DENSITY + 1.0
                new = np.flatnonzero((source["raw_densities"] > live)
                                     & (source["means"][:, 1] < top))
                old = (state["raw_densities"] > live) & (state["means"][:, 1] < top)
                state["raw_densities"][old] = SPARE_RAW_DENSITY
                free = np.flatnonzero(state["raw_densities"] <= live)[: len(new)]
                for key in GAUSSIAN_KEYS:
                    state[key][free] = source[key][new[: len(free)]]
            arrays = {k: state[k] for k in GAUSSIAN_KEYS}
        write_safetensors(carried_path, arrays, {})
        if args.refit == "every" or t == args.t1:
            state, scores = fit(args, t, carried_path)
            report(t, scores)
        elif args.carrier == "grid":
            # Carried on unfitted: the next frame starts from this density.
            state = {"density": scale * density}


if __name__ == "__main__":
    main()
