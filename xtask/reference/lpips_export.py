"""LPIPS weights for `gausmoke-train eval --lpips-weights`, and the golden file that checks our
implementation against the `lpips` package.

  python lpips_export.py export OUT.safetensors
      Writes `lpips.LPIPS(net="alex")`'s state dict (AlexNet v0.1, the weights HyFluid and the
      GauSmoke paper report with) as safetensors. Needs `pip install lpips torch torchvision`
      and network access once (torchvision downloads the AlexNet backbone).

  python lpips_export.py golden OUT_DIR
      Writes OUT_DIR/lpips_alexnet.safetensors: the package's real linear heads and scaling
      layer, two test images and the package's distance between them, with the AlexNet
      convolutions set to a deterministic formula (`formula_weights`, reproduced in the Rust
      test) so no backbone download is needed and the file stays small.
"""

import sys
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file

CONVOLUTIONS = [
    ("net.slice1.0", (64, 3, 11, 11)),
    ("net.slice2.3", (192, 64, 5, 5)),
    ("net.slice3.6", (384, 192, 3, 3)),
    ("net.slice4.8", (256, 384, 3, 3)),
    ("net.slice5.10", (256, 256, 3, 3)),
]


def formula_weights(shape, layer):
    """Deterministic pseudo-random conv weights (He-scaled) and biases, as the Rust test makes
    them: w[j] = sqrt(2 / fan_in) * sin(12.9898 * j + 1.7 * (layer + 1)), b[o] = 0.01 cos(o)."""
    fan_in = int(np.prod(shape[1:]))
    j = np.arange(int(np.prod(shape)), dtype=np.float64)
    w = np.sqrt(2.0 / fan_in) * np.sin(12.9898 * j + 1.7 * (layer + 1))
    b = 0.01 * np.cos(np.arange(shape[0], dtype=np.float64))
    return (torch.tensor(w.astype(np.float32).reshape(shape)),
            torch.tensor(b.astype(np.float32)))


def state_dict_without_aliases(model):
    # `lins.K` duplicates `linK` in the package's state dict.
    return {k: v.contiguous() for k, v in model.state_dict().items() if not k.startswith("lins.")}


def export(out):
    import lpips
    model = lpips.LPIPS(net="alex", verbose=False)
    save_file(state_dict_without_aliases(model), out, metadata={"generator": "xtask/reference/lpips_export.py"})
    print(f"wrote {out}")


def golden(out_dir):
    import lpips
    model = lpips.LPIPS(net="alex", pretrained=True, pnet_rand=True, verbose=False)
    sd = model.state_dict()
    for layer, (name, shape) in enumerate(CONVOLUTIONS):
        w, b = formula_weights(shape, layer)
        sd[name + ".weight"], sd[name + ".bias"] = w, b
    model.load_state_dict(sd)
    model.eval()
    h, w = 60, 84
    yy, xx = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    base = np.stack([0.5 + 0.4 * np.sin(6 * xx + 3 * yy), 0.5 + 0.3 * np.cos(5 * yy),
                     0.4 + 0.3 * xx * yy], axis=-1)
    rng = np.random.default_rng(5)
    other = np.clip(base + 0.08 * rng.normal(size=base.shape) + 0.1 * (xx > 0.5)[..., None], 0, 1)
    a = torch.tensor(base.astype(np.float32))
    b = torch.tensor(other.astype(np.float32))
    with torch.no_grad():
        d = model(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], normalize=True)
        same = model(a.permute(2, 0, 1)[None], a.permute(2, 0, 1)[None], normalize=True)
    keep = {k: v for k, v in state_dict_without_aliases(model).items()
            if k.startswith("lin") or k.startswith("scaling_layer")}
    keep.update({"image_a": a.contiguous(), "image_b": b.contiguous(),
                 "distance": d.reshape(1).float(), "distance_same": same.reshape(1).float()})
    path = Path(out_dir) / "lpips_alexnet.safetensors"
    save_file(keep, str(path), metadata={"generator": "xtask/reference/lpips_export.py",
                                         "description": "lpips package distance, formula conv weights"})
    print(f"{path}: distance {d.item():.6f}, same image {same.item():.2e}")


if __name__ == "__main__":
    if len(sys.argv) != 3 or sys.argv[1] not in ("export", "golden"):
        sys.exit(__doc__)
    {"export": export, "golden": golden}[sys.argv[1]](sys.argv[2])
