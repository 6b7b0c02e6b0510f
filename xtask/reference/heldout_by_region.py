"""Where a run's held-out error sits: on the smoke, or on the static scene behind it (issue 20).

  python heldout_by_region.py DATA VIEW RUN FRAMES [RUN ...]   (numpy)

DATA is a PINF-layout synthetic set (`VIEW/TTT.png`, every frame), VIEW the held-out camera
(`view02` for the synthetic scenes), FRAMES a comma list of frames each RUN rendered
(`RUN/renders/VIEW/frame_TTT.png`). For each frame, splits the render's mean squared error
(over the colour channels and every pixel, x1e4) into the pixels where the reference frame
differs by more than 0.02 from the reference's minimum over time (smoke, which only adds
light), the other pixels where that minimum differs by more than 0.02 from the top-left
corner's colour (the static scene: a wall, a ball), and the rest (the background).

Why: on the blocks scene a longer fit of the static Gaussians makes the smoke's 3D density
far truer and the held-out picture worse; this says which pixels pay.
"""

import glob
import os
import sys

import numpy as np

from heldout_streaks import read_png


def split(reference, least, render):
    error = ((render - reference) ** 2).mean(axis=2)
    smoke = np.abs(reference - least).max(axis=2) > 0.02
    static = ~smoke & (np.abs(least - least[0, 0]).max(axis=2) > 0.02)
    background = ~smoke & ~static
    n = error.size
    return [1e4 * error[mask].sum() / n for mask in (smoke, static, background)]


if __name__ == "__main__":
    if len(sys.argv) < 5:
        sys.exit(__doc__)
    data, view, runs, frames = sys.argv[1], sys.argv[2], sys.argv[3:-1], sys.argv[-1]
    frames = [int(t) for t in frames.split(",")]
    paths = sorted(glob.glob(os.path.join(data, view, "[0-9][0-9][0-9].png")))
    if not paths:
        sys.exit(f"{data}/{view}: no frames")
    video = np.stack([read_png(p, rgb=True) for p in paths])
    least = video.min(axis=0)
    for run in runs:
        cells = []
        for t in frames:
            render = read_png(os.path.join(run, "renders", view, f"frame_{t:03}.png"), rgb=True)
            smoke, static, background = split(video[t], least, render)
            cells.append(f"{t}: smoke {smoke:.2f} static {static:.2f} background {background:.2f}")
        print(f"{run.rstrip('/').split('/')[-1]:34s} " + " | ".join(cells))
