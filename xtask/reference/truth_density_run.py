"""A copy of a trained run whose density grids are the synthetic scene's own, optionally
blurred: to ask how much of the velocity estimate's error the run's densities cause
(`gausmoke-train velocity --run OUT`, then `gausmoke-train eval --run OUT`).

    python xtask/reference/truth_density_run.py RUN DATA OUT [--blur CELLS]

OUT gets RUN's config.toml and run.json and, for every frame file of RUN, the same file with
its `density` replaced by the scene's true density at that frame (Gaussian-blurred by CELLS
cells when given). Everything else in the frame files is RUN's, so eval's other figures are
the run's own. A velocity estimate of OUT is read off the truth's density, not the run's.
"""

import argparse
import os
import shutil
import sys

import numpy as np
from scipy.ndimage import gaussian_filter

from safetensors_f32 import read_safetensors, write_safetensors
from scene_truth import read_truth


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a run folder written by `gausmoke-train train`")
    parser.add_argument("data", help="the synthetic scene it was trained on (with gt/)")
    parser.add_argument("out", help="the folder to write (must not exist)")
    parser.add_argument("--blur", type=float, default=0.0,
                        help="blur the true density by this many cells (standard deviation)")
    args = parser.parse_args()
    if os.path.exists(args.out):
        sys.exit(f"{args.out} exists: give a new folder")
    frames = sorted(f for f in os.listdir(os.path.join(args.run, "frames"))
                    if f.startswith("frame_") and f.endswith(".safetensors"))
    if not frames:
        sys.exit(f"{args.run}/frames holds no frame files")
    os.makedirs(os.path.join(args.out, "frames"))
    for name in ("config.toml", "run.json"):
        shutil.copy(os.path.join(args.run, name), args.out)
    for name in frames:
        t = int(name[len("frame_"):-len(".safetensors")])
        tensors = read_safetensors(os.path.join(args.run, "frames", name))
        density, _ = read_truth(args.data, t)
        if density.shape != tensors["density"].shape:
            sys.exit(f"frame {t}: the run's grid {tensors['density'].shape} is not the "
                     f"scene's {density.shape}")
        density = density.astype(np.float64)
        if args.blur > 0:
            density = gaussian_filter(density, args.blur)
        tensors["density"] = density.astype(np.float32)
        write_safetensors(os.path.join(args.out, "frames", name), tensors, {})
    print(f"wrote {len(frames)} frames to {args.out}")


if __name__ == "__main__":
    main()
