"""Evaluation of BTF representations: textures for fixed light/view pairs (paper Figs. 4, 8),
a tiled plane under two point lights (Fig. 5), and PSNR, DSSIM = (1 - SSIM) / 2 and FLIP.
Triple Plane queries on the CPU run fused in C (`neumat.btf.query`).

Images are compared as displayed: linear RGB times a per-material exposure (fixed from the
reference so the 99th percentile maps to 0.8), clipped to [0, 1], sRGB-encoded. The same
exposure is used for every method."""

from __future__ import annotations

import math

import numpy as np
import torch

from neumat.btf import query


def srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def exposure_for(reference: np.ndarray) -> float:
    p = float(np.percentile(reference, 99))
    return 0.8 / p if p > 0 else 1.0


def display(img: np.ndarray, exposure: float) -> np.ndarray:
    return srgb(img * exposure)


def image_metrics(ref_ldr: np.ndarray, img_ldr: np.ndarray) -> dict:
    """PSNR (dB), DSSIM and mean FLIP of two display-referred (sRGB, [0, 1]) images."""
    import flip_evaluator as flip
    from skimage.metrics import (  # lazily, like flip: the BTF jobs that score no image skip them
        peak_signal_noise_ratio, structural_similarity)

    ssim = structural_similarity(ref_ldr, img_ldr, channel_axis=-1, data_range=1.0,
                                 win_size=min(7, *[s - (s + 1) % 2 for s in ref_ldr.shape[:2]]))
    _, flip_mean, _ = flip.evaluate(np.ascontiguousarray(ref_ldr), np.ascontiguousarray(img_ldr),
                                    "LDR", applyMagma=False)
    return {"psnr": float(peak_signal_noise_ratio(ref_ldr, img_ldr, data_range=1.0)),
            "dssim": float((1 - ssim) / 2), "flip": float(flip_mean)}


@torch.no_grad()
def texture(model, width: int, height: int, wi, wo) -> np.ndarray:
    """(height, width, 3) RGB of a model at every texel centre for one light/view pair."""
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    u = torch.stack([(xs.reshape(-1) + 0.5) / width, (ys.reshape(-1) + 0.5) / height], -1)
    n = len(u)
    wi = torch.as_tensor(wi, dtype=torch.float32).reshape(1, 3).expand(n, 3)
    wo = torch.as_tensor(wo, dtype=torch.float32).reshape(1, 3).expand(n, 3)
    out = torch.cat([query.query(model, u[s:s + 16384], wi[s:s + 16384], wo[s:s + 16384])
                     for s in range(0, n, 16384)])
    return out.reshape(height, width, 3).numpy()


def plane_queries(width: int, height: int, tiles: float, light, fov_deg: float = 40.0,
                  wrap: bool = True):
    """Queries of a pinhole view of the plane z = 0, x, y in [-1, 1], with u = tiles * (x, y)
    / 2 wrapped (repetitive tiling), lit by a point light at `light` (3,). Returns u, wi, wo
    (N, .) of the pixels that hit the plane, their mask, and the 1 / r^2 light falloff (the
    cosine is already part of BTF values). wrap=False: u unwrapped, float64 (synthesis)."""
    cam = np.array([0.0, -2.4, 1.9])
    fwd = -cam / np.linalg.norm(cam)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    f = 1 / math.tan(math.radians(fov_deg) / 2)
    ys, xs = np.mgrid[0:height, 0:width]
    px = (2 * (xs + 0.5) / width - 1) * width / height
    py = 1 - 2 * (ys + 0.5) / height
    d = px[..., None] * right + py[..., None] * up + f * fwd
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    s = -cam[2] / np.minimum(d[..., 2], -1e-9)
    p = cam + s[..., None] * d
    mask = (np.abs(p[..., 0]) <= 1) & (np.abs(p[..., 1]) <= 1) & (d[..., 2] < 0)
    p = p[mask]
    wo = cam - p
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    li = np.asarray(light, np.float64) - p
    r2 = np.sum(li ** 2, -1)
    wi = li / np.sqrt(r2)[:, None]
    # directions in the texture's frame: v grows along world -y (image rows grow downwards)
    # and a BTF's y is its row direction (texel_uv; synthetic.normals_from_height), so its
    # frame is (x, -y, z): in world y the bumps were lit as if mirrored in v
    wo[:, 1] *= -1
    wi[:, 1] *= -1
    t = lambda a: torch.as_tensor(a, dtype=torch.float32)
    if not wrap:
        u = np.stack([tiles * (p[:, 0] + 1) / 2, tiles * (1 - p[:, 1]) / 2], -1)
        return torch.from_numpy(u), t(wi), t(wo), mask, (1 / r2).astype(np.float32)
    u = np.mod(tiles * (p[:, :2] + 1) / 2, 1.0)
    u[:, 1] = 1 - u[:, 1] - 1e-7 * (u[:, 1] == 0)     # image rows grow downwards in v
    return t(np.mod(u, 1.0)), t(wi), t(wo), mask, (1 / r2).astype(np.float32)


@torch.no_grad()
def render_plane(model, width, height, tiles, light, intensity) -> np.ndarray:
    u, wi, wo, mask, falloff = plane_queries(width, height, tiles, light)
    img = np.zeros((height, width, 3), np.float32)
    img[mask] = query.query(model, u, wi, wo).numpy() * (intensity * falloff)[:, None]
    return img


def evaluate_material(name, data, models: dict, pairs, tiling: dict):
    """All images and metrics of one material.

    data: `BTFData` (the reference); models: method -> model; pairs: [(light, view)] indices;
    tiling: dict(width, height, tiles, lights [[x, y, z], ...], intensity).
    Returns (rows of the metrics table, texture images {method: [P images]}, tiling images
    {method: [images per light]}, exposure values)."""
    refs = [texture(data, data.width, data.height, data.light_dirs[l], data.view_dirs[v])
            for l, v in pairs]
    exp_tex = exposure_for(np.stack(refs))
    tex = {"reference": [display(r, exp_tex) for r in refs]}
    rows = []
    for method, model in models.items():
        tex[method] = []
        for (l, v), ref in zip(pairs, tex["reference"]):
            img = display(texture(model, data.width, data.height, data.light_dirs[l],
                                  data.view_dirs[v]), exp_tex)
            tex[method].append(img)
            rows.append({"material": name, "method": method, "figure": "texture",
                         "light": int(l), "view": int(v), **image_metrics(ref, img),
                         "params": int(model.n_params())})
    plane = {}
    ref_planes = [render_plane(data, tiling["width"], tiling["height"], tiling["tiles"], li,
                               tiling["intensity"]) for li in tiling["lights"]]
    exp_plane = exposure_for(np.stack(ref_planes))
    plane["reference"] = [display(r, exp_plane) for r in ref_planes]
    for method in [m for m in ("triple_plane", "neumip") if m in models]:
        plane[method] = []
        for k, (li, ref) in enumerate(zip(tiling["lights"], plane["reference"])):
            img = display(render_plane(models[method], tiling["width"], tiling["height"],
                                       tiling["tiles"], li, tiling["intensity"]), exp_plane)
            plane[method].append(img)
            rows.append({"material": name, "method": method, "figure": "tiling", "light": k,
                         "view": -1, **image_metrics(ref, img),
                         "params": int(models[method].n_params())})
    return rows, tex, plane, (exp_tex, exp_plane)
