"""Do several runs' held-out errors agree? (issue 18)

  python heldout_agreement.py RUN_DIR,RUN_DIR[,...] FRAMES   (numpy and scipy)

RUN_DIRs are runs of one data set (typically one preset's seeds; a frame fitted alone,
`RUN-independent/frame_TTT`, is read at `comparison/frame_000.png` when FRAMES names one
frame). FRAMES is a comma list of frames every run wrote comparisons for. For each frame it
prints each run's held-out PSNR over the whole image (to 8-bit rounding), the pairwise
correlation of the runs' errors (render minus reference), and the PSNR of the runs' mean
render.

Why: if the errors are each run's own noise (what an initialisation leaves in the views'
null space), they are uncorrelated and the mean of n renders gains up to 10 log10(n) dB;
if they agree, the error is the data's and the method's, and no averaging of seeds, nor a
prior that only removes noise, takes it away.
"""

import os
import sys

import numpy as np

from heldout_streaks import read_png


def halves(path):
    pair = read_png(path)
    width = (pair.shape[1] - 4) // 2
    return pair[:, :width], pair[:, width + 4 :]


def comparison(run, frame):
    own = os.path.join(run, "comparison", f"frame_{frame:03d}.png")
    return own if os.path.exists(own) else os.path.join(run, "comparison", "frame_000.png")


def psnr(image, reference):
    return -10.0 * np.log10(((image - reference) ** 2).mean())


def main(runs, frames):
    for t in frames:
        pairs = [halves(comparison(run, t)) for run in runs]
        reference = pairs[0][0]
        for other, _ in pairs[1:]:
            assert np.abs(other - reference).max() < 1.5 / 255, f"frame {t}: references differ"
        renders = [render for _, render in pairs]
        errors = [(render - reference).ravel() for render in renders]
        correlations = [
            np.dot(a, b) / np.sqrt(np.dot(a, a) * np.dot(b, b))
            for i, a in enumerate(errors)
            for b in errors[i + 1 :]
        ]
        alone = [psnr(render, reference) for render in renders]
        mean = psnr(np.mean(renders, axis=0), reference)
        print(
            f"frame {t:3d}: PSNR {' '.join(f'{p:.2f}' for p in alone)} (mean {np.mean(alone):.2f});"
            f" errors correlate {' '.join(f'{c:.2f}' for c in correlations)};"
            f" mean render {mean:.2f} dB ({mean - np.mean(alone):+.2f})"
        )


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1].split(","), [int(f) for f in sys.argv[2].split(",")])
