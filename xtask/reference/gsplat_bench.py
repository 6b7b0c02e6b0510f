"""Times gsplat's standard 3DGS rasterizer on the scenes `cargo xtask bench render` writes.

Usage (on a CUDA machine with torch and gsplat): python gsplat_bench.py SCENE.safetensors...
    [--reps 50]

Each scene holds our Gaussians (means, quaternions wxyz, log-scales, raw densities, colours)
and the camera `[width, height, fx, fy, cx, cy, camera-to-world row-major (OpenGL)]`. gsplat
uses OpenCV cameras, so the camera's y and z axes are flipped. Opacity for 3DGS is the
Beer-Lambert alpha of the ray through each centre, `1 - exp(-sigma sqrt(2 pi) s_mean)`, as our
PLY export writes it, so both renderers see comparable footprints. Colours are passed as
3-channel features (no spherical harmonics). Prints one JSON line per scene: median ms of
forward and of forward+backward (backward of `sum(rgb) + sum(alpha)`), CUDA-synchronised.
"""

import argparse
import json
import math
import time

import torch
from safetensors.torch import load_file


def load(path, device):
    t = load_file(path)
    cam = t["camera"].tolist()
    width, height = int(cam[0]), int(cam[1])
    fx, fy, cx, cy = cam[2:6]
    c2w_gl = torch.tensor(cam[6:22], dtype=torch.float64).reshape(4, 4)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    viewmat = torch.linalg.inv(c2w_gl @ flip).float()
    K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float32)
    scales = t["log_scales"].exp()
    sigma = torch.nn.functional.softplus(t["raw_densities"])
    opacity = 1 - torch.exp(-sigma * math.sqrt(2 * math.pi) * scales.mean(dim=1))
    return dict(
        means=t["means"].to(device),
        quats=t["rotations"].to(device),
        scales=scales.to(device),
        opacities=opacity.clamp(0, 0.99).to(device),
        colors=t["colors"].to(device),
        viewmats=viewmat[None].to(device),
        Ks=K[None].to(device),
        width=width,
        height=height,
    )


def median_ms(fn, reps):
    fn()
    torch.cuda.synchronize()
    samples = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        samples.append(time.perf_counter() - t0)
    samples.sort()
    return samples[len(samples) // 2] * 1e3


def main():
    from gsplat import rasterization

    parser = argparse.ArgumentParser()
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--reps", type=int, default=50)
    args = parser.parse_args()
    device = torch.device("cuda")
    for path in args.scenes:
        s = load(path, device)

        def forward():
            with torch.no_grad():
                rasterization(
                    s["means"], s["quats"], s["scales"], s["opacities"], s["colors"],
                    s["viewmats"], s["Ks"], s["width"], s["height"], packed=False,
                )

        leaves = {k: s[k].clone().requires_grad_(True)
                  for k in ("means", "quats", "scales", "opacities", "colors")}

        def forward_backward():
            rgb, alpha, _ = rasterization(
                leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                leaves["colors"], s["viewmats"], s["Ks"], s["width"], s["height"],
                packed=False,
            )
            (rgb.sum() + alpha.sum()).backward()

        print(json.dumps({
            "scene": path,
            "gaussians": int(s["means"].shape[0]),
            "width": s["width"],
            "height": s["height"],
            "forward_ms": median_ms(forward, args.reps),
            "forward_backward_ms": median_ms(forward_backward, args.reps),
            "device": torch.cuda.get_device_name(),
        }), flush=True)


if __name__ == "__main__":
    main()
