"""What the refinement's moves are, against a synthetic scene's truth (issue 18).

  python refine_move_diagnosis.py RUN_DIR DATA_DIR [FIRST LAST]     (needs numpy and scipy)

Reads the run's `exports/grid_TTT.npz` (a run with `output_every = 1`: `refine_move`, the
refinement's grid-scale move field, and `refine_move_flow`, its divergence-free part, both
in cells per frame; `velocity` in world units per frame) and the scene's truth. For frames
FIRST..LAST (default 2..70; LAST + 1 must exist), averaged over blocks of frames, prints:

- where the move field sits: the share of its sum of squares (whole, flow part, gathering
  part = the rest) in the source's rows (the bottom 10% of the box), in the top eighth, and
  between (these three add up to 1; beside them the true density's shares of the same
  rows), and outside the true smoke (density under 1% of its maximum); and the mean upward
  move inside the smoke;
- whether the moves point where the velocity errs: inside the true smoke, the correlation
  of the move field (and its flow part) with the truth's velocity less ours, in cells per
  frame; and the horizontal flow's error relative to the truth's, beside the same for the
  previous frame's velocity carried along itself (before the frame's increment: what the
  increment fitted to the frame's pictures changes) and for the truth blurred by a
  Gaussian of 2 cells (what a field as smooth as ours could reach);
- whether the next frame's velocity takes the flow part over or undoes it: the regression
  coefficient of the change of velocity from frame t to t+1 on frame t's flow part,
  `<u(t+1) - u(t), f(t)> / <f(t), f(t)>` over the whole grid (0: left as it was; with
  `refine_velocity_share = s`, -s: what the share added is taken back);
- the same frames' persistence of the flow and gathering parts (correlation with the frame
  before's over the whole grid), which the run's metrics report too.
"""

import sys

import numpy as np
from scipy.ndimage import gaussian_filter

from scene_truth import read_truth
from velocity_persistence import transported


def load(run, t):
    with np.load(f"{run}/exports/grid_{t:03}.npz") as z:
        arrays = {k: z[k].astype(np.float64) for k in z.files}
    if "refine_move" not in arrays:
        sys.exit(f"frame {t}: no refine_move in the export (a run with refinement and "
                 "output_every = 1 writes it)")
    cells = np.array(arrays["velocity"].shape[:3]) / (arrays["hi"] - arrays["lo"])
    return {
        "move": arrays["refine_move"],
        "flow": arrays["refine_move_flow"],
        "velocity": arrays["velocity"] * cells,
        "cells": cells,
    }


def dot(a, b):
    return float((a * b).sum())


def correlation(a, b):
    norms = np.sqrt(dot(a, a) * dot(b, b))
    return dot(a, b) / norms if norms > 0 else 0.0


def frame_figures(run, data, t):
    now, before, after = load(run, t), load(run, t - 1), load(run, t + 1)
    move, flow = now["move"], now["flow"]
    gathering = move - flow
    density, truth = read_truth(data, t)
    truth = truth * now["cells"]
    n = move.shape[1]
    smoke = density > 0.01 * density.max()
    rows = np.arange(n)[None, :, None]
    source, top = max(1, round(0.1 * n)), n - max(1, n // 8)
    regions = {
        "source": np.broadcast_to(rows < source, smoke.shape),
        "between": np.broadcast_to((rows >= source) & (rows < top), smoke.shape),
        "top": np.broadcast_to(rows >= top, smoke.shape),
        "outside": ~smoke,
    }
    figures = {}
    for region in ("source", "between", "top"):
        figures[f"true density {region}"] = density[regions[region]].sum() / density.sum()
    for name, field in (("whole", move), ("flow", flow), ("gathering", gathering)):
        total = dot(field, field)
        for region, mask in regions.items():
            figures[f"{name} {region}"] = dot(field[mask], field[mask]) / total if total else 0.0
    figures["upward move"] = move[smoke][:, 1].mean()
    error = truth - now["velocity"]
    # The horizontal flow's error, relative to the truth's (1: as bad as none at all), and
    # the same for the truth blurred by 2 cells (what a field as smooth as ours could reach).
    horizontal = truth[smoke][:, [0, 2]]
    figures["horizontal error"] = np.sqrt(
        (error[smoke][:, [0, 2]] ** 2).sum() / (horizontal ** 2).sum()
    )
    # The previous frame's velocity carried along itself, before this frame's increment:
    # how much the increment (fitted to this frame's pictures) changes that error.
    carried = transported(before["velocity"])[smoke][:, [0, 2]]
    figures["horizontal error carried"] = np.sqrt(
        ((carried - horizontal) ** 2).sum() / (horizontal ** 2).sum()
    )
    blurred = np.stack([gaussian_filter(truth[..., c], 2.0) for c in (0, 2)], -1)[smoke]
    figures["horizontal, truth blurred"] = np.sqrt(
        ((blurred - horizontal) ** 2).sum() / (horizontal ** 2).sum()
    )
    figures["corr(move, error)"] = correlation(move[smoke], error[smoke])
    figures["corr(flow, error)"] = correlation(flow[smoke], error[smoke])
    change = after["velocity"] - now["velocity"]
    figures["take-over"] = dot(change, flow) / dot(flow, flow) if dot(flow, flow) else 0.0
    figures["flow persistence"] = correlation(flow, before["flow"])
    figures["gathering persistence"] = correlation(gathering, before["move"] - before["flow"])
    return figures


def main(run, data, first, last):
    block = []
    blocks = []
    for t in range(first, last + 1):
        block.append((t, frame_figures(run, data, t)))
        if len(block) == 12 or t == last:
            blocks.append(block)
            block = []
    names = list(blocks[0][0][1])
    print("frames".ljust(24) + "".join(f"{b[0][0]:>3}-{b[-1][0]:<3}".rjust(9) for b in blocks))
    for name in names:
        means = [np.mean([f[name] for _, f in b]) for b in blocks]
        print(name.ljust(24) + "".join(f"{m:9.3f}" for m in means))


if __name__ == "__main__":
    if len(sys.argv) not in (3, 5):
        sys.exit(__doc__)
    first, last = (int(sys.argv[3]), int(sys.argv[4])) if len(sys.argv) == 5 else (2, 70)
    main(sys.argv[1], sys.argv[2], max(first, 2), last)
