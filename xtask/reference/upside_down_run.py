"""A trained run of a synthetic scene and the scene's ground truth, both turned upside down: a
plume that rises becomes smoke that sinks, with everything else the same, to measure the
velocity estimate on sinking smoke (`gausmoke-train velocity --run OUT/run [--sinking]`, then
`velocity_diagnosis.py OUT/run OUT/data --estimate`).

    python xtask/reference/upside_down_run.py RUN DATA OUT

Writes OUT/data (DATA's info.json, and gt/ with each frame's density and velocity mirrored
in y and the velocity's y component negated; no pictures) and OUT/run (RUN's frame files
mirrored the same way, its run.json pointing at OUT/data, and its config.toml with the y
faces' open/solid roles and the inflow box (`[scene] inflow`) mirrored). The box must be
symmetric about its middle height in the grid's cells, as every box is: a mirror of the
grid's rows. Eval is not meant for OUT/run: its pictures are the upright scene's.
"""

import argparse
import json
import os
import re
import shutil
import sys
import tomllib

import numpy as np

from safetensors_f32 import read_safetensors, write_safetensors


def mirrored(tensors, y_axis):
    """`tensors`' density and velocity mirrored along `y_axis`, the velocity's y negated."""
    out = dict(tensors)
    if "density" in out:
        out["density"] = np.ascontiguousarray(np.flip(out["density"], axis=y_axis))
    if "velocity" in out:
        velocity = np.flip(out["velocity"], axis=y_axis).copy()
        velocity[..., 1] *= -1.0
        out["velocity"] = np.ascontiguousarray(velocity)
    return out


def mirrored_config(text):
    """config.toml's text with `[scene]`'s `open_faces` y faces swapped and its `inflow`
    mirrored in y (its `[x0, y0, z0, x1, y1, z1]` as fractions of the box)."""
    config = tomllib.loads(text).get("scene", {})
    swap = {"y-": "y+", "y+": "y-"}
    faces = [swap.get(face, face) for face in config.get("open_faces", [])]
    text, count = re.subn(r"(?m)^open_faces = \[.*\]$",
                          "open_faces = " + json.dumps(faces), text)
    if count != 1 and "open_faces" in config:
        sys.exit("config.toml: `open_faces` is not on one line; mirror it by hand")
    region = config.get("inflow")
    if region is not None:
        x0, y0, z0, x1, y1, z1 = region
        flipped = [x0, 1.0 - y1, z0, x1, 1.0 - y0, z1]
        text, count = re.subn(r"(?ms)^inflow = \[.*?\]$",
                              "inflow = " + json.dumps(flipped), text)
        if count != 1:
            sys.exit("config.toml: `[scene] inflow` not found as an array")
    check = tomllib.loads(text).get("scene", {})
    if check.get("open_faces", []) != faces or check.get("inflow") != (
            None if region is None else flipped):
        sys.exit("config.toml: the mirrored settings did not read back")
    return text


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a run folder written by `gausmoke-train train`")
    parser.add_argument("data", help="the synthetic scene it was trained on (with gt/)")
    parser.add_argument("out", help="the folder to write (must not exist)")
    args = parser.parse_args()
    if os.path.exists(args.out):
        sys.exit(f"{args.out} exists: give a new folder")
    data_out = os.path.join(args.out, "data")
    run_out = os.path.join(args.out, "run")
    os.makedirs(os.path.join(data_out, "gt"))
    os.makedirs(os.path.join(run_out, "frames"))
    shutil.copy(os.path.join(args.data, "info.json"), data_out)
    truths = sorted(os.listdir(os.path.join(args.data, "gt")))
    for name in truths:
        # The scene's files are [z, y, x]: y is axis 1 either way.
        tensors = read_safetensors(os.path.join(args.data, "gt", name))
        write_safetensors(os.path.join(data_out, "gt", name), mirrored(tensors, 1), {})
    frames = sorted(f for f in os.listdir(os.path.join(args.run, "frames"))
                    if f.startswith("frame_") and f.endswith(".safetensors"))
    if not frames:
        sys.exit(f"{args.run}/frames holds no frame files")
    for name in frames:
        # The run's grids are [x, y, z]. Its Gaussians are left as they are (the estimate
        # reads only the grids).
        tensors = read_safetensors(os.path.join(args.run, "frames", name))
        write_safetensors(os.path.join(run_out, "frames", name), mirrored(tensors, 1), {})
    info = json.load(open(os.path.join(args.run, "run.json")))
    info["data"] = os.path.abspath(data_out)
    info["data_fingerprint"] = None
    json.dump(info, open(os.path.join(run_out, "run.json"), "w"), indent=2)
    config = open(os.path.join(args.run, "config.toml")).read()
    open(os.path.join(run_out, "config.toml"), "w").write(mirrored_config(config))
    print(f"wrote {len(truths)} truth frames to {data_out} and {len(frames)} run frames to "
          f"{run_out}")


if __name__ == "__main__":
    main()
