"""Golden values of the image metrics, computed by scikit-image, for
`gausmoke-train/tests/metrics_golden.rs`:

  python metrics_golden.py OUT.safetensors     (needs numpy and scikit-image==0.25.2)

SSIM is `skimage.metrics.structural_similarity(a, b, channel_axis=2, data_range=1.0,
gaussian_weights=True, sigma=1.5, use_sample_covariance=False)`, the settings of the 3DGS /
HyFluid evaluation scripts and the ones `gausmoke_train::metrics::ssim` claims; PSNR is
`skimage.metrics.peak_signal_noise_ratio(a, b, data_range=1.0)`. Images are float64 in
[0, 1], stored as float32 (the Rust side reads them back exactly and computes from those).
"""

import sys

import numpy as np
import skimage
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from safetensors_f32 import write_safetensors


def pairs():
    rng = np.random.default_rng(2026)
    y, x = np.mgrid[0:48, 0:64] / 48.0
    plume = np.exp(-((x - 0.6) ** 2 + (y - 0.5) ** 2) / 0.05)
    smooth = np.stack([plume, 0.9 * plume, 0.8 * plume], axis=-1)
    yield "smoke_vs_shifted", smooth, np.roll(smooth, 2, axis=1) * 0.9
    yield "smoke_vs_noisy", smooth, np.clip(smooth + 0.05 * rng.standard_normal(smooth.shape), 0, 1)
    a = rng.random((37, 53, 3))
    yield "random_odd_size", a, np.clip(a + 0.1 * rng.standard_normal(a.shape), 0, 1)
    flat = np.full((20, 30, 3), 0.3)
    yield "flat_vs_gradient", flat, flat + 0.2 * np.linspace(0, 1, 30)[None, :, None]


def main(out):
    tensors, meta = {}, {"generator": "xtask/reference/metrics_golden.py",
                         "scikit-image": skimage.__version__}
    names = []
    for name, a, b in pairs():
        a = a.astype(np.float32)
        b = b.astype(np.float32)
        a64, b64 = a.astype(np.float64), b.astype(np.float64)
        ssim = structural_similarity(a64, b64, channel_axis=2, data_range=1.0,
                                     gaussian_weights=True, sigma=1.5,
                                     use_sample_covariance=False)
        psnr = peak_signal_noise_ratio(a64, b64, data_range=1.0)
        tensors[f"{name}.a"] = a
        tensors[f"{name}.b"] = b
        meta[f"{name}.ssim"] = repr(float(ssim))
        meta[f"{name}.psnr"] = repr(float(psnr))
        names.append(name)
        print(f"{name}: {a.shape} SSIM {ssim:.10f} PSNR {psnr:.10f}")
    meta["pairs"] = ",".join(names)
    write_safetensors(out, tensors, meta)
    print(f"wrote {out}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
