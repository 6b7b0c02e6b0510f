"""Does a run's cell-centred velocity carry checkerboard modes (issue 18, hypothesis 4)?

  python checkerboard_diagnosis.py RUN_DIR DATA_DIR [FRAMES...]     (needs numpy)

DATA_DIR `-` for a scene without ground truth (the run's own density grid marks the smoke).

On a collocated grid the exact projection zeroes the divergence measured by central
differences, (u[i+1] - u[i-1]) / 2, which cannot see a field alternating from cell to cell:
such modes survive every projection. A staggered (MAC) grid would remove them, so this
measures whether there is anything for it to remove. For each frame, for the run's velocity
and the ground truth's (a staggered solver's field sampled at cell centres):

- `central`: rms of the central-difference divergence, relative to the rms of all nine
  velocity derivatives (the run's is ~0 by construction);
- `compact`: the same with the divergence of one-sided differences averaged over the
  cell's eight corners, which does see alternating modes;
- `nyquist`: the share of the field's energy (mean removed, per component) at wavenumbers
  whose central-difference symbol is below half its peak on some axis, i.e. |k| > 5N/12 of
  the grid's N cells, where the projection is nearly blind.

Inside the true smoke (density above 1% of its maximum, the box's outer cells left out) for
the derivative measures; the whole grid for the spectrum. Cell sizes from the run's `run.json`; arrays as in
velocity_diagnosis.py.
"""

import json
import sys

import numpy as np

from safetensors_f32 import read_safetensors as read
from scene_truth import read_run_and_truth


def derivatives(v, h):
    """Central differences of each component along each axis, [3 comp, 3 axis, ...]."""
    return np.stack([np.stack(np.gradient(v[..., c], *h), 0) for c in range(3)], 0)


def compact_divergence(v, h):
    """Divergence at the cells' corners from one-sided differences, averaged back to cells."""
    div = np.zeros(tuple(s - 1 for s in v.shape[:3]))
    for axis in range(3):
        d = np.diff(v[..., axis], axis=axis) / h[axis]
        # average the difference over the other two axes' neighbouring pairs: corner values
        for other in range(3):
            if other != axis:
                d = 0.5 * (np.take(d, range(d.shape[other] - 1), axis=other)
                           + np.take(d, range(1, d.shape[other]), axis=other))
        div = div + d[tuple(slice(0, s) for s in div.shape)]
    return div


def nyquist_share(v):
    n = v.shape[0]
    k = np.abs(np.fft.fftfreq(n) * n)
    high = k > 5 * n / 12
    mask = high[:, None, None] | high[None, :, None] | high[None, None, :]
    total, band = 0.0, 0.0
    for c in range(3):
        spectrum = np.abs(np.fft.fftn(v[..., c] - v[..., c].mean())) ** 2
        total += spectrum.sum()
        band += spectrum[mask].sum()
    return band / max(total, 1e-30)


def measures(v, smoke, h):
    # np.gradient is one-sided at the box's faces, where central differences do not apply
    smoke = smoke.copy()
    for axis in range(3):
        edge = [slice(None)] * 3
        for i in (0, -1):
            edge[axis] = i
            smoke[tuple(edge)] = False
    grads = derivatives(v, h)
    scale = np.sqrt((grads[..., smoke] ** 2).sum(axis=(0, 1)).mean())
    central = grads[0, 0] + grads[1, 1] + grads[2, 2]
    compact = compact_divergence(v, h)
    corner_smoke = smoke[:-1, :-1, :-1]
    rel = lambda d, m: np.sqrt((d[m] ** 2).mean()) / max(scale, 1e-30)
    return rel(central, smoke), rel(compact, corner_smoke), nyquist_share(v)


def main(run, data, frames):
    with open(f"{run}/run.json") as f:
        box = json.load(f)
    h = [(hi - lo) / n for lo, hi, n in zip(box["box_lo"], box["box_hi"], box["grid_resolution"])]
    for t in frames:
        line = f"frame {t:3d}: run "
        if data == "-":
            frame = read(f"{run}/frames/frame_{t:03}.safetensors")
            ours, own = frame["velocity"].astype(np.float64), frame["density"]
            a = measures(ours, own > 0.01 * own.max(), h)
        else:
            ours, density, velocity = read_run_and_truth(run, data, t)
            smoke = density > 0.01 * density.max()
            a = measures(ours, smoke, h)
            b = measures(velocity, smoke, h)
            line = f"frame {t:3d}: truth central {b[0]:.3f} compact {b[1]:.3f} nyquist {b[2]:.4f} | run "
        print(line + f"central {a[0]:.3f} compact {a[1]:.3f} nyquist {a[2]:.4f}")


if __name__ == "__main__":
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    frames = [int(f) for f in sys.argv[3:]] or [6, 12, 24, 36, 48, 60, 71]
    main(sys.argv[1], sys.argv[2], frames)
