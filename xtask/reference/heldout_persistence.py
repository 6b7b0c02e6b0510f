"""Whether a run's held-out error moves with the smoke (issue 18).

  python heldout_persistence.py RUN_DIR FRAMES [ALONE_DIR]     (numpy and scipy)

FRAMES is a comma list of frames t for which the run wrote `comparison/frame_TTT.png` at t
and t + STEP (STEP = 4, the quick presets' `output_every`). For each pair, inside the smoke
of either frame, prints how many image rows the held-out reference moved (the shift that
best carries frame t's picture onto frame t + STEP's, the smoke rising) and how the run's
held-out error at t + STEP correlates with its error at t moved by that shift, and unmoved.
Error that the chain carries along the flow correlates at the smoke's shift; error each
frame's fit makes anew does not. With ALONE_DIR (holding `frame_TTT/` folders of frames
fitted alone, `gausmoke-train train --config RUN/config.toml --set first_frame=T --set
frames=1`, then `eval`), the same for the frames fitted alone, and how the two errors
correlate at the same frame.

Why: a prior that tells streaks from smoke by their persistence along the flow can only work
if the streaks do not move with the smoke.
"""

import os
import sys

import numpy as np

from heldout_streaks import read_png

STEP = 4


def load(path):
    """Reference, error (render minus reference) and background of a comparison PNG."""
    pair = read_png(path)
    width = (pair.shape[1] - 4) // 2
    reference, render = pair[:, :width], pair[:, width + 4 :]
    border = np.concatenate(
        [reference[:5].ravel(), reference[-5:].ravel(), reference[:, :5].ravel(),
         reference[:, -5:].ravel()]
    )
    return reference, render - reference, np.median(border)


def correlation(a, b, mask):
    a, b = a[mask] - a[mask].mean(), b[mask] - b[mask].mean()
    return (a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum())


def raised(image, rows):
    """`image` with its content moved up by `rows` rows (down for negative)."""
    out = np.zeros_like(image)
    if rows >= 0:
        out[: image.shape[0] - rows] = image[rows:]
    else:
        out[-rows:] = image[:rows]
    return out


def persistence(before, after, smoke, shift):
    """Correlation of `after` with `before` raised by `shift`, and unmoved."""
    return correlation(after, raised(before, shift), smoke), correlation(after, before, smoke)


def main(run, frames, alone):
    for t in frames:
        r0, e0, b0 = load(os.path.join(run, "comparison", f"frame_{t:03d}.png"))
        r1, e1, b1 = load(os.path.join(run, "comparison", f"frame_{t + STEP:03d}.png"))
        smoke = (np.abs(r0 - b0) > 0.02) | (np.abs(r1 - b1) > 0.02)
        shift = max(range(-2, 16), key=lambda d: correlation(r1 - b1, raised(r0 - b0, d), smoke))
        moved, still = persistence(e0, e1, smoke, shift)
        line = (f"frames {t} -> {t + STEP}: smoke raised {shift} rows; the run's error "
                f"correlates {moved:.2f} at that shift ({still:.2f} unmoved)")
        if alone:
            fitted = [os.path.join(alone, f"frame_{f:03d}", "comparison", "frame_000.png")
                      for f in (t, t + STEP)]
            _, a0, _ = load(fitted[0])
            _, a1, _ = load(fitted[1])
            moved, still = persistence(a0, a1, smoke, shift)
            line += (f"; alone {moved:.2f} ({still:.2f} unmoved); run against alone at the "
                     f"same frame {correlation(e0, a0, smoke):.2f} / {correlation(e1, a1, smoke):.2f}")
        print(line)


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    main(sys.argv[1], [int(f) for f in sys.argv[2].split(",")],
         sys.argv[3] if len(sys.argv) == 4 else None)
