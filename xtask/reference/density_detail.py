"""How a run's 3D density compares with a synthetic scene's truth beyond correlation (issue 18).

  python density_detail.py RUN_DIR DATA_DIR FRAMES [--alone RUN-independent]
                                                              (needs numpy)

FRAMES is a comma list. For each frame, from the run's `frames/frame_TTT.safetensors`
(`density` [nx, ny, nz] splatted at the cell centres, and the Gaussians) and the scene's
`gt/frame_TTT.safetensors`, prints:
- the density's total variation per unit mass (sum of |grad| over the sum, central cells)
  over the truth's, all of it and its horizontal part: below 1, smoother than the truth;
- the Gaussians whose centre lies in the true smoke (above 1% of its maximum) and their
  median density;
- the colour of those Gaussians (median and 10th percentile of the channels' mean; the
  synthetic scenes render grey smoke of albedo 1).
With `--alone`, the same for the frames fitted alone (`ALONE/frame_TTT/frames/frame_000`).
The box is the synthetic scenes' [-0.5, 0.5] x [0, 1] x [-0.5, 0.5].
"""

import argparse

import numpy as np

from safetensors_f32 import read_safetensors as read
from scene_truth import read_truth

BOX_LO = np.array([-0.5, 0.0, -0.5])


def variation(d):
    """Total variation per unit mass: all of it and its horizontal (x, z) part."""
    gx = np.diff(d, axis=0)[:, :-1, :-1]
    gy = np.diff(d, axis=1)[:-1, :, :-1]
    gz = np.diff(d, axis=2)[:-1, :-1, :]
    mass = d.sum()
    return np.sqrt(gx**2 + gy**2 + gz**2).sum() / mass, np.sqrt(gx**2 + gz**2).sum() / mass


def describe(path, truth):
    state = read(path)
    n = truth.shape[0]
    all_tv, horizontal_tv = variation(state["density"])
    truth_all, truth_horizontal = variation(truth)
    cells = np.clip(((state["means"] - BOX_LO) * n).astype(int), 0, n - 1)
    inside = truth[cells[:, 0], cells[:, 1], cells[:, 2]] > 0.01 * truth.max()
    density = np.logaddexp(0.0, state["raw_densities"])
    colour = state["colors"][inside].mean(axis=1)
    return (
        f"TV / truth's {all_tv / truth_all:.2f} (horizontal {horizontal_tv / truth_horizontal:.2f}); "
        f"{inside.sum()} Gaussians in the smoke, median density {np.median(density[inside]):.2f}, "
        f"colour median {np.median(colour):.2f} (10th percentile {np.percentile(colour, 10):.2f})"
    )


def main(run, data, frames, alone):
    for t in frames:
        truth, _ = read_truth(data, t)
        print(f"frame {t:3d}: ours  {describe(f'{run}/frames/frame_{t:03d}.safetensors', truth)}")
        if alone:
            path = f"{alone}/frame_{t:03d}/frames/frame_000.safetensors"
            print(f"           alone {describe(path, truth)}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(usage=__doc__)
    parser.add_argument("run")
    parser.add_argument("data")
    parser.add_argument("frames")
    parser.add_argument("--alone")
    args = parser.parse_args()
    main(args.run, args.data, [int(t) for t in args.frames.split(",")], args.alone)
