"""Where a run's velocity goes wrong on a synthetic scene with ground truth (issue 18).

  python velocity_diagnosis.py RUN_DIR DATA_DIR [FRAMES...] [--estimate]
      (needs numpy and scipy)

For each frame, inside the true smoke (density above 1% of its maximum), prints the
relative error of the run's velocity (and the same in denser smoke, above 10% and 30%),
the mean cosine between it and the truth, the ratio of their mean speeds, its scale (the
least-squares factor that brings it nearest the truth) and the correlation of each
component; and two yardsticks computed from the truth alone: the best uniform velocity (the
smoke's mean flow) and the truth blurred by a Gaussian of 1, 2 and 4 cells (how well a field
that smooth could do; with their speed ratios and scales, since a smoothed field is slower
inside the smoke by its smoothness alone). Also the truth's rms displacement per frame in
cells. `--estimate` reads the run's `velocity_estimate/` (`gausmoke-train velocity`) instead
of its own velocity. A second line splits the error by height (bands of grid
rows, bottom to top): each band's relative error and its share of the error's energy. A
third takes the part of the flow that pictures can see, `grad rho . u` (transport along a
surface of equal density changes nothing): ours' and the blurred truth's relative error,
scale and correlation there, and how much of the truth's flow is of that kind. Arrays are
read from the safetensors files directly:
the run's `frames/frame_TTT.safetensors` (velocity [nx, ny, nz, 3], x slowest) and the
scene's `gt/frame_TTT.safetensors` (velocity [z, y, x, 3], x fastest), both in world units
per frame on the same box (the grids must have the same resolution).
"""

import sys

import numpy as np
from scipy.ndimage import gaussian_filter

from scene_truth import read_run_and_truth


def relative(x, truth):
    """RMS of `x - truth` over the RMS of `truth`."""
    return np.sqrt(((x - truth) ** 2).sum() / (truth ** 2).sum())


def by_height(ours, truth, smoke):
    """Relative error and share of the error energy inside `smoke`, per band of rows (the
    box's quarters, the top quarter split in two)."""
    n = smoke.shape[1]
    total = ((ours - truth)[smoke] ** 2).sum()
    bands = []
    for lo, hi in ((0, n // 4), (n // 4, n // 2), (n // 2, 3 * n // 4), (3 * n // 4, 7 * n // 8),
                   (7 * n // 8, n)):
        inside = np.zeros_like(smoke)
        inside[:, lo:hi, :] = smoke[:, lo:hi, :]
        if inside.sum() < 20:
            bands.append(f"rows {lo}-{hi - 1}: -")
            continue
        error = ((ours - truth)[inside] ** 2).sum()
        bands.append(f"rows {lo}-{hi - 1}: {np.sqrt(error / (truth[inside] ** 2).sum()):.2f} "
                     f"({error / total:.2f})")
    return ", ".join(bands)


def along_gradient(ours, truth, blurred, density, smoke):
    """`grad rho . u` inside `smoke`, for ours and for `blurred` (the truth blurred by 2 cells)
    against the truth's: each one's relative error, its scale (the least-squares factor on
    the truth's) and its correlation with it. Also how much of the truth's flow that is: the
    share of its energy along the unit gradient, and the share of smoke cells whose density
    is nearly flat (gradient under a tenth of its 95th percentile)."""
    gradient = np.stack(np.gradient(density.astype(np.float64)), axis=-1)
    seen = lambda v: (gradient * v).sum(axis=-1)[smoke]
    want = seen(truth)
    compare = lambda got: (relative(got, want), (got * want).sum() / (want**2).sum(),
                           np.corrcoef(got, want)[0, 1])
    size = np.linalg.norm(gradient, axis=-1)
    along = (truth * gradient).sum(axis=-1) / np.maximum(size, 1e-12)
    share = (along[smoke] ** 2).sum() / (truth[smoke] ** 2).sum()
    flat = (size[smoke] < 0.1 * np.percentile(size[smoke], 95)).mean()
    return compare(seen(ours)), compare(seen(blurred)), share, flat


def speed_and_scale(field, truth):
    """The ratio of `field`'s mean speed to `truth`'s, and the least-squares factor on `field`
    that brings it nearest `truth` (both [cells, 3])."""
    norm = lambda v: np.linalg.norm(v, axis=1)
    return norm(field).mean() / norm(truth).mean(), (field * truth).sum() / (field**2).sum()


def main(run, data, frames, folder):
    for t in frames:
        ours, density, velocity = read_run_and_truth(run, data, t, folder)
        smoke = density > 0.01 * density.max()
        a, b = ours[smoke], velocity[smoke]
        norm = lambda v: np.linalg.norm(v, axis=1)
        rel = relative(a, b)
        cosine = ((a * b).sum(1) / (norm(a) * norm(b) + 1e-12)).mean()
        uniform = relative(b.mean(0), b)
        smooth = {sigma: np.stack([gaussian_filter(velocity[..., c], sigma) for c in range(3)], -1)
                  for sigma in (1.0, 2.0, 4.0)}
        blurred = [relative(field[smoke], b) for field in smooth.values()]
        speeds = [speed_and_scale(field[smoke], b) for field in smooth.values()]
        components = [np.corrcoef(a[:, c], b[:, c])[0, 1] for c in range(3)]
        cells = np.sqrt((b ** 2).sum(1).mean()) * density.shape[0]
        # the same error in denser smoke only: how much of it sits in the thin edges
        dense = [relative(ours[m], velocity[m])
                 for m in (density > share * density.max() for share in (0.1, 0.3))]
        print(f"frame {t:3d}: rel. error {rel:.2f} (above 10/30% of the max density "
              + "/".join(f"{v:.2f}" for v in dense) + f"), mean cosine {cosine:.2f}, speed ratio "
              + "{:.2f}, scale {:.2f}".format(*speed_and_scale(a, b)) + ", component corr. "
              + " ".join(f"{c:.2f}" for c in components)
              + f" | truth: uniform mean flow {uniform:.2f}, blurred 1/2/4 cells "
              + "/".join(f"{v:.2f}" for v in blurred) + " (speed ratio "
              + "/".join(f"{v[0]:.2f}" for v in speeds) + ", scale "
              + "/".join(f"{v[1]:.2f}" for v in speeds) + ")"
              + f", rms displacement {cells:.2f} cells/frame")
        print("           by height " + by_height(ours, velocity, smoke))
        seen, seen_blurred, share, flat = along_gradient(ours, velocity, smooth[2.0], density,
                                                         smoke)
        print("           along the density's gradient: rel. error / scale / corr. "
              + "/".join(f"{v:.2f}" for v in seen) + " (truth blurred by 2 cells "
              + "/".join(f"{v:.2f}" for v in seen_blurred) + f"); the truth's energy there "
              f"{share:.2f}, flat smoke cells {flat:.2f}")


if __name__ == "__main__":
    arguments = [a for a in sys.argv[1:] if a != "--estimate"]
    if len(arguments) < 2:
        sys.exit(__doc__)
    frames = [int(f) for f in arguments[2:]] or [6, 12, 24, 36, 48, 60, 71]
    folder = "velocity_estimate" if "--estimate" in sys.argv else "frames"
    main(arguments[0], arguments[1], frames, folder)
