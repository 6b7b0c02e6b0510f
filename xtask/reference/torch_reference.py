"""Torch-CPU reference for the GauSmoke-rs renderer.

An independent, dense implementation of the Beer-Lambert volumetric Gaussian renderer
(paper Sec. 4.1 and Appendix B): it evaluates Eq. 25-27 with the inverse covariance directly
for every (pixel, Gaussian) pair in float64, composites front to back with cumulative
products, and takes gradients with torch autograd. The Rust tests compare every backend to
the golden files it writes.

    python torch_reference.py goldens OUT_DIR [--check]
    python torch_reference.py bench --gaussians 1000 10000 30000 --width 480 --height 270

Thresholds (alpha_min, alpha_max, transmittance_min, kernel_cutoff, near_plane) are those of
`RasterOptions::default()` and are stored in every golden file.
"""

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file

OPTIONS = {
    "alpha_min": 1.0 / 255.0,
    "alpha_max": 0.99,
    "transmittance_min": 1e-4,
    "kernel_cutoff": 9.0,
    "near_plane": 0.01,
}
OPTION_ORDER = ["alpha_min", "alpha_max", "transmittance_min", "kernel_cutoff", "near_plane"]


# ----------------------------------------------------------------------------- cameras

def look_at(eye, target, up=(0.0, 1.0, 0.0)):
    """Camera-to-world 4x4 in the OpenGL convention (camera looks down -Z, +Y up)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, back, eye
    return c2w


def camera(width, height, c2w, fov_x=None, fx=None, fy=None, cx=None, cy=None):
    if fov_x is not None:
        fx = fy = 0.5 * width / math.tan(0.5 * fov_x)
    cx = 0.5 * width if cx is None else cx
    cy = 0.5 * height if cy is None else cy
    # Round through f32 so Rust and torch see the very same camera.
    c2w32 = np.asarray(c2w, dtype=np.float32)
    return {
        "width": int(width),
        "height": int(height),
        "fx": float(np.float32(fx)),
        "fy": float(np.float32(fy)),
        "cx": float(np.float32(cx)),
        "cy": float(np.float32(cy)),
        "c2w": c2w32,
    }


def camera_vector(cam):
    """[width, height, fx, fy, cx, cy, c2w row-major (16)] as stored in the goldens."""
    head = [cam["width"], cam["height"], cam["fx"], cam["fy"], cam["cx"], cam["cy"]]
    return torch.tensor(head + list(cam["c2w"].reshape(-1)), dtype=torch.float32)


def camera_from_vector(v):
    v = v.double().numpy()
    return {
        "width": int(v[0]),
        "height": int(v[1]),
        "fx": v[2],
        "fy": v[3],
        "cx": v[4],
        "cy": v[5],
        "c2w": v[6:22].reshape(4, 4),
    }


# ----------------------------------------------------------------------------- renderer

def quat_to_rotation(q):
    n = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = n.unbind(-1)
    rows = [
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ]
    return torch.stack(rows, -2)


def pixel_rays(cam, dtype):
    """Ray origin (world) and unit world directions through every pixel centre, [P, 3]."""
    h, w = cam["height"], cam["width"]
    v, u = torch.meshgrid(
        torch.arange(h, dtype=dtype) + 0.5, torch.arange(w, dtype=dtype) + 0.5, indexing="ij"
    )
    x = (u - cam["cx"]) / cam["fx"]
    y = -(v - cam["cy"]) / cam["fy"]
    d_cam = torch.stack([x, y, -torch.ones_like(x)], -1).reshape(-1, 3)
    d_cam = d_cam / d_cam.norm(dim=-1, keepdim=True)
    c2w = torch.as_tensor(np.asarray(cam["c2w"], dtype=np.float64), dtype=dtype)
    return c2w[:3, 3], d_cam @ c2w[:3, :3].T


def gaussian_alphas(params, cam, origin, dirs, opts):
    """Opacity of every Gaussian on every ray, [P, N], and the view depth of each centre."""
    means, quats, log_scales, raw_densities = (
        params["means"], params["rotations"], params["log_scales"], params["raw_densities"]
    )
    rot = quat_to_rotation(quats)  # [N, 3, 3]
    inv_var = torch.exp(-2.0 * log_scales)  # [N, 3]
    inv_cov = rot @ torch.diag_embed(inv_var) @ rot.transpose(-1, -2)  # Sigma^-1, [N, 3, 3]
    om = origin[None, :] - means  # o - mu, [N, 3]
    a = torch.einsum("pi,nij,pj->pn", dirs, inv_cov, dirs)  # d^T Sigma^-1 d
    b = torch.einsum("ni,nij,pj->pn", om, inv_cov, dirs)  # (o - mu)^T Sigma^-1 d
    c = torch.einsum("ni,nij,nj->n", om, inv_cov, om)  # (o - mu)^T Sigma^-1 (o - mu)
    transverse = c[None, :] - b * b / a  # K, Eq. 26
    peak = -b / a  # gamma, Eq. 25
    beta = a.rsqrt()
    integral = math.sqrt(2.0 * math.pi) * beta * torch.exp(-0.5 * transverse)  # Eq. 27
    sigma = F.softplus(raw_densities)
    if opts.get("alpha_model", 0) == 0:
        raw_alpha = 1.0 - torch.exp(-sigma[None, :] * integral)  # Beer-Lambert
    else:
        # The 3DGS-style ablation: opacity 1 - exp(-sigma) times the projected kernel.
        raw_alpha = (1.0 - torch.exp(-sigma[None, :])) * torch.exp(-0.5 * transverse)

    c2w = torch.as_tensor(np.asarray(cam["c2w"], dtype=np.float64), dtype=means.dtype)
    depth = -((means - c2w[:3, 3]) @ c2w[:3, 2])  # view depth of the centre
    with torch.no_grad():
        valid = (
            (peak > 0)
            & (transverse <= opts["kernel_cutoff"])
            & (depth[None, :] > opts["near_plane"])
            & (raw_alpha >= opts["alpha_min"])
        )
    alpha = torch.where(valid, raw_alpha.clamp(max=opts["alpha_max"]), torch.zeros_like(raw_alpha))
    return alpha, depth


def composite(alpha, colors, background, opts):
    """Front-to-back compositing of depth-sorted alphas [P, N]; returns rgb [P, 3], T [P]."""
    with torch.no_grad():
        # A pixel stops before the Gaussian that would take T below transmittance_min; T only
        # decreases, so the composited Gaussians are the prefix where the running T stays above.
        keep = torch.cumprod(1.0 - alpha, dim=1) >= opts["transmittance_min"]
    alpha = alpha * keep
    one_minus = 1.0 - alpha
    t_incl = torch.cumprod(one_minus, dim=1)
    t_before = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=1)
    weights = t_before * alpha
    final_t = t_incl[:, -1] if alpha.shape[1] > 0 else torch.ones(alpha.shape[0], dtype=alpha.dtype)
    rgb = weights @ colors + final_t[:, None] * background[None, :]
    return rgb, final_t


def render(params, cam, opts, pixel_slice=None):
    origin, dirs = pixel_rays(cam, params["means"].dtype)
    if pixel_slice is not None:
        dirs = dirs[pixel_slice]
    alpha, depth = gaussian_alphas(params, cam, origin, dirs, opts)
    order = torch.argsort(depth.detach(), stable=True)
    rgb, final_t = composite(alpha[:, order], params["colors"][order], params["background"], opts)
    return rgb, final_t


# ----------------------------------------------------------------------------- cases

def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True) * rng.uniform(0.5, 2.0, size=(n, 1))


def case(name, description, cam, means, quats, log_scales, raw_densities, colors, background):
    return {
        "name": name,
        "description": description,
        "camera": cam,
        "params": {
            "means": np.asarray(means, dtype=np.float32).reshape(-1, 3),
            "rotations": np.asarray(quats, dtype=np.float32).reshape(-1, 4),
            "log_scales": np.asarray(log_scales, dtype=np.float32).reshape(-1, 3),
            "raw_densities": np.asarray(raw_densities, dtype=np.float32).reshape(-1),
            "colors": np.asarray(colors, dtype=np.float32).reshape(-1, 3),
            "background": np.asarray(background, dtype=np.float32).reshape(3),
        },
    }


def cases():
    rng = np.random.default_rng(20261122)
    front = look_at((0.0, 0.0, 4.0), (0.0, 0.0, 0.0))
    out = []
    out.append(case(
        "single", "one isotropic Gaussian at the image centre",
        camera(32, 24, front, fov_x=0.8),
        [[0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0, 0.0]], [[math.log(0.3)] * 3], [1.5],
        [[0.9, 0.6, 0.3]], [0.0, 0.0, 0.0],
    ))
    out.append(case(
        "overlap_depths", "four overlapping Gaussians at different depths and colours",
        camera(40, 32, look_at((0.5, 0.8, 4.0), (0.0, 0.0, 0.0)), fov_x=0.9),
        [[0.0, 0.0, 0.0], [0.2, 0.1, 0.8], [-0.15, -0.1, -0.7], [0.05, 0.25, 0.35]],
        [[1, 0, 0, 0], [0.9, 0.2, 0.1, 0.3], [0.7, -0.3, 0.5, 0.2], [0.5, 0.5, 0.5, 0.5]],
        np.log([[0.35, 0.3, 0.4], [0.25, 0.3, 0.2], [0.4, 0.35, 0.3], [0.2, 0.15, 0.25]]),
        [2.0, 1.0, 3.0, 0.5],
        [[0.9, 0.1, 0.1], [0.1, 0.9, 0.1], [0.1, 0.1, 0.9], [0.8, 0.8, 0.2]],
        [0.0, 0.0, 0.0],
    ))
    out.append(case(
        "behind_camera",
        "one Gaussian behind the camera, one in front, one whose centre is in front but close",
        camera(32, 32, front, fov_x=1.2),
        [[0.0, 0.0, 5.0], [0.1, -0.1, 0.0], [-0.3, 0.2, 3.5]],
        [[1, 0, 0, 0], [0.9, 0.1, 0.2, 0.0], [1, 0, 0, 0]],
        np.log([[0.8, 0.8, 0.8], [0.3, 0.4, 0.3], [0.2, 0.2, 0.2]]),
        [4.0, 1.0, 0.8],
        [[1.0, 0.0, 0.0], [0.2, 0.7, 0.9], [0.9, 0.9, 0.1]],
        [0.1, 0.1, 0.1],
    ))
    n = 6
    out.append(case(
        "elongated_rotated", "needle- and pancake-shaped Gaussians under random rotations",
        camera(48, 36, look_at((1.5, 1.0, 3.5), (0.0, 0.0, 0.0)), fov_x=0.9),
        rng.uniform(-0.6, 0.6, size=(n, 3)), random_quats(rng, n),
        np.log(np.array([[0.6, 0.05, 0.05], [0.04, 0.5, 0.5], [0.3, 0.03, 0.3],
                         [0.5, 0.08, 0.02], [0.02, 0.02, 0.7], [0.25, 0.25, 0.03]])),
        rng.uniform(0.5, 3.0, size=n), rng.uniform(0.1, 1.0, size=(n, 3)), [0.0, 0.0, 0.0],
    ))
    n = 300
    out.append(case(
        "random_300", "300 random Gaussians in a box, ScalarFlow-like grey smoke plus colour",
        camera(64, 48, look_at((0.3, 0.5, 3.0), (0.0, 0.1, 0.0)), fov_x=0.9),
        rng.uniform(-0.7, 0.7, size=(n, 3)), random_quats(rng, n),
        rng.uniform(np.log(0.03), np.log(0.2), size=(n, 3)),
        rng.uniform(-2.0, 2.5, size=n), rng.uniform(0.0, 1.0, size=(n, 3)), [0.05, 0.05, 0.08],
    ))
    n = 40
    out.append(case(
        "non_square_background",
        "portrait image, fx != fy, off-centre principal point, non-zero background",
        camera(30, 52, look_at((0.0, 0.3, 3.0), (0.0, 0.0, 0.0), up=(0.1, 1.0, 0.0)),
               fx=38.0, fy=44.0, cx=13.2, cy=27.9),
        rng.uniform(-0.5, 0.5, size=(n, 3)) * np.array([0.5, 1.2, 0.5]), random_quats(rng, n),
        rng.uniform(np.log(0.05), np.log(0.25), size=(n, 3)),
        rng.uniform(-1.0, 2.0, size=n), rng.uniform(0.0, 1.0, size=(n, 3)), [0.3, 0.5, 0.7],
    ))
    n = 60
    out.append(case(
        "dense_saturating",
        "very dense Gaussians: alpha hits the 0.99 clamp and pixels stop at transmittance_min",
        camera(40, 40, front, fov_x=0.7),
        rng.uniform(-0.4, 0.4, size=(n, 3)), random_quats(rng, n),
        rng.uniform(np.log(0.1), np.log(0.3), size=(n, 3)),
        rng.uniform(3.0, 6.0, size=n), rng.uniform(0.0, 1.0, size=(n, 3)), [0.0, 0.0, 0.0],
    ))
    # The "w/o volumetric rendering" ablation: splat-opacity alpha (alpha_model = 1).
    splat = dict(OPTIONS, alpha_model=1)
    n = 200
    out.append(dict(case(
        "splat_random_200", "splat-opacity alpha (3DGS ablation): 200 random Gaussians",
        camera(56, 44, look_at((0.2, 0.4, 3.0), (0.0, 0.1, 0.0)), fov_x=0.9),
        rng.uniform(-0.7, 0.7, size=(n, 3)), random_quats(rng, n),
        rng.uniform(np.log(0.03), np.log(0.2), size=(n, 3)),
        rng.uniform(-3.0, 1.0, size=n), rng.uniform(0.0, 1.0, size=(n, 3)), [0.05, 0.05, 0.08],
    ), options=splat))
    n = 50
    out.append(dict(case(
        "splat_dense", "splat-opacity alpha with opaque Gaussians: the 0.99 clamp and early stop",
        camera(36, 36, front, fov_x=0.7),
        rng.uniform(-0.4, 0.4, size=(n, 3)), random_quats(rng, n),
        rng.uniform(np.log(0.1), np.log(0.3), size=(n, 3)),
        rng.uniform(2.0, 8.0, size=n), rng.uniform(0.0, 1.0, size=(n, 3)), [0.0, 0.0, 0.0],
    ), options=splat))
    # Issue 20's mixed scene, composited as the trainer does: the smoke Gaussians first, the
    # static ones after them, one depth-sorted pass. Translucent grey smoke around and in
    # front of an opaque ball and a flat, opaque two-tone wall behind, over a grey-blue
    # background.
    smoke, ball, wall = 120, 40, 40
    ball_dirs = rng.normal(size=(ball, 3))
    ball_dirs /= np.linalg.norm(ball_dirs, axis=1, keepdims=True)
    wall_xy = np.stack([rng.uniform(-0.6, 0.6, wall), rng.uniform(-0.2, 0.8, wall)], 1)
    grey = rng.uniform(0.6, 1.0, size=(smoke, 1)) * np.ones((1, 3))
    tone = np.where((np.floor(wall_xy[:, 0] / 0.3) + np.floor(wall_xy[:, 1] / 0.3)) % 2 == 0,
                    0.2, 0.45)
    out.append(case(
        "mixed_static_smoke",
        f"{smoke} translucent smoke Gaussians, then {ball + wall} static ones: an opaque ball "
        "inside the smoke and a flat two-tone wall behind it (issue 20)",
        camera(48, 40, look_at((0.4, 0.6, 3.2), (0.0, 0.2, 0.0)), fov_x=0.9),
        np.concatenate([
            rng.uniform([-0.6, -0.2, -0.4], [0.6, 0.8, 0.6], size=(smoke, 3)),
            np.array([0.05, 0.3, 0.0]) + ball_dirs * rng.uniform(0.0, 0.2, size=(ball, 1)),
            np.concatenate([wall_xy, np.full((wall, 1), -0.5)], 1),
        ]),
        np.concatenate([
            random_quats(rng, smoke + ball),
            np.tile([[1.0, 0.0, 0.0, 0.0]], (wall, 1)),
        ]),
        np.concatenate([
            rng.uniform(np.log(0.05), np.log(0.2), size=(smoke, 3)),
            rng.uniform(np.log(0.04), np.log(0.09), size=(ball, 3)),
            np.log(np.concatenate([rng.uniform(0.1, 0.15, size=(wall, 2)),
                                   np.full((wall, 1), 0.01)], 1)),
        ]),
        np.concatenate([
            rng.uniform(-2.0, 1.0, size=smoke),
            rng.uniform(4.0, 7.0, size=ball),
            rng.uniform(3.0, 6.0, size=wall),
        ]),
        np.concatenate([
            grey,
            rng.uniform(0.2, 0.8, size=(ball, 3)),
            tone[:, None] * np.ones((1, 3)),
        ]),
        [0.12, 0.14, 0.18],
    ))
    return out


# ----------------------------------------------------------------------------- goldens

GRAD_NAMES = ["means", "rotations", "log_scales", "raw_densities", "colors", "background"]


def golden_tensors(c):
    """Inputs, loss weights, forward outputs and gradients of one case, as f32 tensors."""
    cam = c["camera"]
    params = {k: torch.tensor(v, dtype=torch.float64, requires_grad=True)
              for k, v in c["params"].items()}
    h, w = cam["height"], cam["width"]
    gen = torch.Generator().manual_seed(len(c["name"]) * 7919)
    weight_rgb = torch.randn(h, w, 3, generator=gen, dtype=torch.float64).float()
    weight_t = torch.randn(h, w, generator=gen, dtype=torch.float64).float()
    opts = c.get("options", OPTIONS)
    rgb, final_t = render(params, cam, opts)
    rgb, final_t = rgb.reshape(h, w, 3), final_t.reshape(h, w)
    # A fixed random linear loss exercises every output (and so every gradient term).
    loss = (rgb * weight_rgb.double()).sum() + (final_t * weight_t.double()).sum()
    loss.backward()
    out = {k: torch.tensor(v) for k, v in c["params"].items()}
    out["camera"] = camera_vector(cam)
    # A sixth entry only where the alpha model is not Beer-Lambert's (older files have five).
    extra = [opts["alpha_model"]] if "alpha_model" in opts else []
    out["options"] = torch.tensor([opts[k] for k in OPTION_ORDER] + extra, dtype=torch.float32)
    out["weight_rgb"] = weight_rgb
    out["weight_transmittance"] = weight_t
    out["rgb"] = rgb.detach().float()
    out["transmittance"] = final_t.detach().float()
    for k in GRAD_NAMES:
        out["grad_" + k] = params[k].grad.float()
    return out


def write_goldens(out_dir, check):
    out_dir.mkdir(parents=True, exist_ok=True)
    worst = 0.0
    for c in cases():
        tensors = golden_tensors(c)
        path = out_dir / f"render_{c['name']}.safetensors"
        meta = {"description": c["description"], "generator": "xtask/reference/torch_reference.py",
                "torch": torch.__version__}
        if check:
            old = load_file(str(path))
            for k, v in tensors.items():
                diff = (old[k] - v).abs().max().item() if v.numel() else 0.0
                scale = max(v.abs().max().item(), 1.0) if v.numel() else 1.0
                worst = max(worst, diff / scale)
                if diff > 1e-5 * scale:
                    print(f"{path.name}: {k} differs by {diff:.3e}", file=sys.stderr)
        else:
            save_file({k: v.contiguous() for k, v in tensors.items()}, str(path), metadata=meta)
        print(f"{path.name}: {c['description']} ({c['params']['raw_densities'].shape[0]} Gaussians, "
              f"{c['camera']['width']}x{c['camera']['height']})")
    worst = max(worst, model_goldens(out_dir, check))
    if check:
        print(f"largest relative difference to the committed goldens: {worst:.3e}")
        if worst > 1e-5:
            sys.exit(1)


# ----------------------------------------------------------------------------- model ops

def splat_density(params, lo, cell, res, cutoff):
    """sigma_grid [nx, ny, nz] = sum_i sigma_i k_i(x_c), k inside the cutoff support only."""
    axes = [torch.arange(n, dtype=torch.float64) * cell[a] + lo[a] + 0.5 * cell[a] for a, n in enumerate(res)]
    centres = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    rot = quat_to_rotation(params["rotations"])
    inv_var = torch.exp(-2.0 * params["log_scales"])
    inv_cov = rot @ torch.diag_embed(inv_var) @ rot.transpose(-1, -2)
    diff = centres[:, None, :] - params["means"][None, :, :]  # [C, N, 3]
    q = torch.einsum("cni,nij,cnj->cn", diff, inv_cov, diff)
    kernel = torch.where(q <= cutoff, torch.exp(-0.5 * q), torch.zeros_like(q))
    sigma = F.softplus(params["raw_densities"])
    return (kernel * sigma[None, :]).sum(1).reshape(*res)


def sample_velocity(velocity, points, lo, cell, res, stencil, std_cells):
    """Eq. 11 interpolation, Eq. 22 Jacobian: velocity [nx, ny, nz, 3], points [M, 3]."""
    lo_t = torch.tensor(lo, dtype=torch.float64)
    cell_t = torch.tensor(cell, dtype=torch.float64)
    coord = (points - lo_t) / cell_t - 0.5
    first = stencil // 2 - 1
    max_base = torch.tensor([n - stencil for n in res], dtype=torch.float64)
    base = torch.minimum(torch.clamp(torch.floor(coord.detach()) - first, min=0.0), max_base)
    r = torch.arange(stencil, dtype=torch.float64)
    offsets = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    node = base[:, None, :] + offsets[None, :, :]  # [M, S^3, 3]
    idx = node.long()
    node_u = velocity[idx[..., 0], idx[..., 1], idx[..., 2]]  # [M, S^3, 3]
    delta = node - coord[:, None, :]
    w = torch.exp(-0.5 * (delta ** 2).sum(-1) / std_cells ** 2)  # [M, S^3]
    total = w.sum(1, keepdim=True)
    u = (w[..., None] * node_u).sum(1) / total
    g = delta / (std_cells ** 2 * cell_t)
    jac = torch.einsum("ms,msa,msb->mab", w, node_u - u[:, None, :], g) / total[..., None]
    return u, jac


def unet_forward(w, velocity, density, t, frequencies):
    """Phi of gausmoke-model's unet.rs on one grid: velocity [nx, ny, nz, 3], density [nx, ny, nz]."""
    F = torch.nn.functional
    nx, ny, nz, _ = velocity.shape
    enc = []
    for k in range(frequencies):
        phase = (2 ** k) * math.pi * t
        enc += [math.sin(phase), math.cos(phase)]
    time = torch.tensor(enc, dtype=velocity.dtype).view(1, -1, 1, 1, 1).expand(1, 2 * frequencies, nx, ny, nz)
    x = torch.cat([velocity.permute(3, 0, 1, 2)[None], density[None, None], time], 1)

    def conv(name, x, padding):
        return F.conv3d(x, w[name + ".weight"], w[name + ".bias"], padding=padding)

    def double(name, x):
        return F.silu(conv(name + ".second", F.silu(conv(name + ".first", x, 1)), 1))

    def down(name, x):
        return F.conv3d(x, w[name + ".weight"], w[name + ".bias"], stride=2)

    def up(name, x):
        return F.conv_transpose3d(x, w[name + ".weight"], w[name + ".bias"], stride=2)

    skip1 = double("encode1", x)
    skip2 = double("encode2", F.silu(down("down1", skip1)))
    deep = double("bottleneck", F.silu(down("down2", skip2)))
    up2 = double("decode2", torch.cat([up("up2", deep), skip2], 1))
    up1 = double("decode1", torch.cat([up("up1", up2), skip1], 1))
    return conv("output", up1, 0)[0].permute(1, 2, 3, 0)


def unet_golden(rng, gen):
    """One forward of Phi on fixed random weights (output layer not zero), with gradients."""
    c, frequencies, res, t = 4, 2, (8, 8, 4), 0.3
    inputs = 4 + 2 * frequencies
    # (name, out, in, kernel, transposed): burn's and torch's weight layouts agree
    # (conv [out, in, k, k, k]; transposed conv [in, out, k, k, k]).
    layers = []
    for name, i, o in [("encode1", inputs, c), ("encode2", 2 * c, 2 * c), ("bottleneck", 4 * c, 4 * c),
                       ("decode2", 4 * c, 2 * c), ("decode1", 2 * c, c)]:
        layers += [(name + ".first", o, i, 3, False), (name + ".second", o, o, 3, False)]
    layers += [("down1", 2 * c, c, 2, False), ("down2", 4 * c, 2 * c, 2, False),
               ("up2", 2 * c, 4 * c, 2, True), ("up1", c, 2 * c, 2, True), ("output", 3, c, 1, False)]
    w = {}
    for name, o, i, k, transposed in layers:
        shape = (i, o, k, k, k) if transposed else (o, i, k, k, k)
        scale = 1.0 / math.sqrt(i * k ** 3)
        w[name + ".weight"] = rng.normal(0.0, 1.5 * scale, size=shape)
        w[name + ".bias"] = rng.normal(0.0, 0.1, size=o)
    w = {k: torch.tensor(v.astype(np.float32), dtype=torch.float64, requires_grad=True) for k, v in w.items()}
    velocity = torch.tensor(rng.uniform(-1, 1, size=(*res, 3)).astype(np.float32), dtype=torch.float64,
                            requires_grad=True)
    density = torch.tensor(rng.uniform(0, 2, size=res).astype(np.float32), dtype=torch.float64,
                           requires_grad=True)
    delta = unet_forward(w, velocity, density, t, frequencies)
    weight = torch.randn(*res, 3, generator=gen, dtype=torch.float64).float()
    (delta * weight.double()).sum().backward()
    out = {"param." + k: v.detach().float() for k, v in w.items()}
    out.update({"velocity": velocity.detach().float(), "density": density.detach().float(),
                "config": torch.tensor([c, frequencies, t], dtype=torch.float32),
                "weight": weight, "delta": delta.detach().float(),
                "grad_velocity": velocity.grad.float(), "grad_density": density.grad.float(),
                "grad_encode1.first.weight": w["encode1.first.weight"].grad.float(),
                "grad_output.weight": w["output.weight"].grad.float()})
    return out, "U-Net Phi (4 base channels, L = 2, t = 0.3) on an 8x8x4 grid, fixed random weights"


def model_goldens(out_dir, check):
    rng = np.random.default_rng(7)
    files = {}
    # Density splatting: 12 Gaussians in a non-cubic grid, support cut at 3 sigma.
    n = 12
    lo, res = (0.1, -0.2, 0.0), (10, 14, 8)
    cell = (0.06, 0.05, 0.07)
    params = {
        "means": rng.uniform([0.2, 0.0, 0.1], [0.6, 0.5, 0.5], size=(n, 3)),
        "rotations": random_quats(rng, n),
        "log_scales": rng.uniform(np.log(0.04), np.log(0.12), size=(n, 3)),
        "raw_densities": rng.uniform(-1.0, 2.0, size=n),
    }
    params = {k: torch.tensor(np.asarray(v, dtype=np.float32), dtype=torch.float64, requires_grad=True)
              for k, v in params.items()}
    sigma = splat_density(params, lo, cell, res, 9.0)
    gen = torch.Generator().manual_seed(11)
    weight = torch.randn(*res, generator=gen, dtype=torch.float64).float()
    (sigma * weight.double()).sum().backward()
    t = {k: v.detach().float() for k, v in params.items()}
    t.update({"grid": torch.tensor(list(lo) + list(cell) + list(res) + [9.0], dtype=torch.float32),
              "weight": weight, "sigma": sigma.detach().float()})
    t.update({"grad_" + k: v.grad.float() for k, v in params.items()})
    files["model_density_splat"] = (t, "density of 12 Gaussians at the cell centres of a 10x14x8 grid, 3-sigma support")

    # Interpolation (Eq. 11) and closed-form divergence (Eq. 12) of a random grid.
    lo, res, cell = (-0.3, 0.0, 0.1), (7, 9, 6), (0.8 / 7, 0.1, 0.1)
    velocity = torch.tensor(rng.uniform(-1, 1, size=(*res, 3)).astype(np.float32), dtype=torch.float64, requires_grad=True)
    # Points away from cell-centre crossings (where the stencil moves) so gradients are defined.
    pts = []
    while len(pts) < 40:
        p = rng.uniform([-0.25, 0.05, 0.15], [0.45, 0.85, 0.65])
        c = (p - np.array(lo)) / np.array(cell) - 0.5
        if np.all(np.abs(c - np.round(c)) > 0.05):
            pts.append(p)
    points = torch.tensor(np.asarray(pts, dtype=np.float32), dtype=torch.float64, requires_grad=True)
    u, jac = sample_velocity(velocity, points, lo, cell, res, 4, 0.6)
    div = jac.diagonal(dim1=1, dim2=2).sum(-1)
    wu = torch.randn(40, 3, generator=gen, dtype=torch.float64).float()
    wd = torch.randn(40, generator=gen, dtype=torch.float64).float()
    ((u * wu.double()).sum() + (div * wd.double()).sum()).backward()
    t = {"velocity": velocity.detach().float(), "points": points.detach().float(),
         "grid": torch.tensor(list(lo) + list(cell) + list(res) + [4.0, 0.6], dtype=torch.float32),
         "weight_velocity": wu, "weight_divergence": wd, "u": u.detach().float(),
         "jacobian": jac.detach().float(), "divergence": div.detach().float(),
         "grad_velocity": velocity.grad.float(), "grad_points": points.grad.float()}
    files["model_interp_gaussian"] = (t, "Eq. 11 interpolation (4x4x4, std 0.6 cells) and Eq. 12 divergence at 40 points")

    files["model_unet"] = unet_golden(rng, gen)

    worst = 0.0
    for name, (tensors, description) in files.items():
        path = out_dir / f"{name}.safetensors"
        if check:
            old = load_file(str(path))
            for k, v in tensors.items():
                diff = (old[k] - v).abs().max().item()
                scale = max(v.abs().max().item(), 1.0)
                worst = max(worst, diff / scale)
        else:
            save_file({k: v.contiguous() for k, v in tensors.items()}, str(path),
                      metadata={"description": description, "torch": torch.__version__})
        print(f"{path.name}: {description}")
    return worst


# ----------------------------------------------------------------------------- bench

def bench(args):
    """Time the dense torch reference on scenes written by `cargo xtask bench render`."""
    torch.set_num_threads(args.threads)
    results = []
    for path in args.scenes:
        t = load_file(path)
        cam = camera_from_vector(t["camera"])
        params = {k: t[k].float().clone().requires_grad_(True) for k in GRAD_NAMES}
        n = params["raw_densities"].shape[0]
        pixels = cam["width"] * cam["height"]
        # Chunk pixels so the [P, N] intermediates fit in memory; the loss is a sum over
        # pixels, so per-chunk backward passes accumulate the exact gradient.
        chunk = max(1, int(args.chunk_elements // max(n, 1)))
        def run(backward, limit=None):
            for start in range(0, pixels if limit is None else min(pixels, limit), chunk):
                sl = slice(start, min(start + chunk, pixels))
                if backward:
                    rgb, ft = render(params, cam, OPTIONS, pixel_slice=sl)
                    (rgb.sum() + ft.sum()).backward()
                else:
                    with torch.no_grad():
                        render(params, cam, OPTIONS, pixel_slice=sl)
        timings = {}
        for mode, backward in (("forward", False), ("forward_backward", True)):
            run(backward, limit=chunk)  # warm-up on one chunk: a full dense run can take minutes
            reps = []
            deadline = time.perf_counter() + args.budget_s
            while len(reps) < args.reps and (not reps or time.perf_counter() < deadline):
                t0 = time.perf_counter()
                run(backward)
                reps.append(time.perf_counter() - t0)
            timings[mode] = {"median_ms": 1000 * float(np.median(reps)), "reps": len(reps)}
        results.append({"scene": path, "gaussians": n, "width": cam["width"],
                        "height": cam["height"], "threads": args.threads, **timings})
        print(json.dumps(results[-1]), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("goldens", help="write (or --check) the golden files")
    g.add_argument("out_dir", type=Path)
    g.add_argument("--check", action="store_true", help="compare with the files in OUT_DIR instead")
    b = sub.add_parser("bench", help="time the dense reference on scene files")
    b.add_argument("scenes", nargs="+")
    b.add_argument("--threads", type=int, default=2)
    b.add_argument("--reps", type=int, default=5)
    b.add_argument("--budget-s", type=float, default=60.0)
    b.add_argument("--chunk-elements", type=float, default=3e7)
    b.add_argument("--json")
    args = p.parse_args()
    torch.set_num_threads(1 if args.cmd == "goldens" else args.threads)
    if args.cmd == "goldens":
        write_goldens(args.out_dir, args.check)
    else:
        bench(args)


if __name__ == "__main__":
    main()
