"""How well a run's velocity strains the smoke as the scene's does (issue 18).

  python strain_diagnosis.py RUN_DIR DATA_DIR [FRAMES...]     (needs numpy)

`shape_transport` deforms each Gaussian by the velocity's Jacobian at its centre, so what it
carries is only as good as the fitted velocity's gradient. For each frame, inside the true
smoke (density above 1% of its maximum), weighted by the true density, prints how the run's
strain rate (the symmetric part of the Jacobian, central differences on the grid) compares
with the truth's: their correlation over cells and the six components, the ratio of their
RMS magnitudes, and the same for the velocity itself for scale. Also the truth's own strain
next to the truth blurred by 2 cells (how well a field as smooth as ours could do). Arrays
as `velocity_diagnosis.py` reads them (same box and resolution).
"""

import sys

import numpy as np
from scipy.ndimage import gaussian_filter

from scene_truth import read_run_and_truth


def strain(velocity):
    """Symmetric part of the Jacobian, [nx, ny, nz, 6] (xx, yy, zz, xy, xz, yz), per cell."""
    grads = [np.stack(np.gradient(velocity[..., a]), axis=-1) for a in range(3)]  # d u_a / d x_b
    j = np.stack(grads, axis=-2)  # [..., a, b]
    s = 0.5 * (j + np.swapaxes(j, -1, -2))
    return np.stack([s[..., 0, 0], s[..., 1, 1], s[..., 2, 2], s[..., 0, 1], s[..., 0, 2],
                     s[..., 1, 2]], axis=-1)


def compare(ours, truth, weight):
    """Weighted correlation over the flattened components, and the RMS ratio."""
    w = np.repeat(weight[..., None], ours.shape[-1], axis=-1)
    a, b = ours * np.sqrt(w), truth * np.sqrt(w)
    correlation = (a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum())
    return correlation, np.sqrt((a * a).sum() / (b * b).sum())


def main():
    run, data = sys.argv[1], sys.argv[2]
    frames = [int(f) for f in sys.argv[3:]] or [9, 18, 36, 54, 71]
    print("frame  strain corr / rms ratio  |  velocity corr / rms ratio  |  2-cell-blurred truth's strain corr / ratio")
    for t in frames:
        ours, density, velocity = read_run_and_truth(run, data, t)
        smoke = density > 0.01 * density.max()
        weight = np.where(smoke, density, 0.0)
        blurred = np.stack([gaussian_filter(velocity[..., a], 2.0) for a in range(3)], axis=-1)
        s_true = strain(velocity)
        sc, sr = compare(strain(ours), s_true, weight)
        vc, vr = compare(ours, velocity, weight)
        bc, br = compare(strain(blurred), s_true, weight)
        print(f"{t:5d}  {sc:6.3f} / {sr:5.2f}           |  {vc:6.3f} / {vr:5.2f}               |  {bc:6.3f} / {br:5.2f}")


if __name__ == "__main__":
    main()
