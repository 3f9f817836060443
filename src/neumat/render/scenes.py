"""Mitsuba 3 figure scenes (paper Fig. 5 style) for `neumat_brdf` materials, plus EXR / PNG I/O.

* `sphere_scene`: a sphere under a generated HDR sky (`sky_envmap`, no downloads).
* `mixed_plane_scene`: a tilted plane whose material is a spatially varying mix of two
  materials, weighted by a mask texture (`blend_mask`), through Mitsuba's `blendbsdf`.
* `normal_mapped_scene`: a sphere with a procedural tangent-space normal map (`normalmap` BSDF).
All scenes use the `path` integrator (BSDF sampling + environment sampling with MIS).
Call `mitsuba_bsdf.select_variant()` first.
"""

from __future__ import annotations

import os

import numpy as np

from neumat.render import mitsuba_bsdf as mb
from neumat.render.sphere import tonemap

SUN_ELEVATION, SUN_AZIMUTH, SUN_RADIUS = np.radians(40), 0.35, np.radians(4)


def sky_envmap(height: int) -> np.ndarray:
    """Equirectangular HDR sky (height, 2 height, 3) float32: blue-to-white gradient above the
    horizon, a warm grey ground, and a small bright sun (radiance 200) at 40 deg elevation."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(2 * height) + 0.5) / (2 * height)
    elev = (0.5 - v)[:, None] * np.pi * np.ones_like(u)[None]
    az = 2 * np.pi * u[None] * np.ones_like(v)[:, None]
    t = np.clip(np.sin(elev), 0, 1)[..., None]
    sky = (1 - t) * np.array([1.0, 1.0, 1.0]) + t * np.array([0.35, 0.55, 1.0])
    ground = np.array([0.25, 0.22, 0.18]) * np.ones_like(sky)
    img = np.where(elev[..., None] > 0, sky, ground)
    # angular distance to the sun on the sphere
    cos_g = (np.sin(elev) * np.sin(SUN_ELEVATION) + np.cos(elev) * np.cos(SUN_ELEVATION)
             * np.cos(az - 2 * np.pi * SUN_AZIMUTH))
    img[np.arccos(np.clip(cos_g, -1, 1)) < SUN_RADIUS] = 200.0
    return img.astype(np.float32)


def blend_mask(size: int) -> np.ndarray:
    """(size, size, 1) float32 mask in [0, 1]: soft-edged discs on a grid (material B inside)."""
    c = (np.arange(size) + 0.5) / size * 4
    x, y = np.meshgrid(c, c)
    r = np.hypot(x % 1 - 0.5, y % 1 - 0.5)
    return np.clip((0.33 - r) * 20 + 0.5, 0, 1)[..., None].astype(np.float32)


def ripple_normals(size: int, frequency: float = 12.0, amplitude: float = 0.35) -> np.ndarray:
    """(size, size, 3) tangent-space normal map (encoded (n + 1) / 2) of concentric ripples."""
    c = (np.arange(size) + 0.5) / size
    x, y = np.meshgrid(c, c)
    r = np.hypot(x - 0.5, y - 0.25) * 2 * np.pi * frequency
    g = amplitude * np.cos(r)  # slope along the radial direction
    ang = np.arctan2(y - 0.25, x - 0.5)
    n = np.stack([-g * np.cos(ang), -g * np.sin(ang), np.ones_like(g)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return ((n + 1) / 2).astype(np.float32)


def _bitmap(mi, array, raw=True):
    return {"type": "bitmap", "bitmap": mi.Bitmap(array), "raw": raw, "filter_type": "bilinear"}


def _base(mi, resolution, spp, env, origin, target, fov=30):
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "sensor": {"type": "perspective", "fov": fov,
                   "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=target,
                                                              up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": resolution, "height": resolution,
                            "rfilter": {"type": "gaussian"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(env)},
    }


def sphere_scene(material: mb.Material, resolution: int, spp: int, env: np.ndarray) -> dict:
    import mitsuba as mi
    s = _base(mi, resolution, spp, env, [0, 0.6, 4.2], [0, 0, 0])
    s["object"] = {"type": "sphere", "bsdf": mb.bsdf_dict(material, resolution ** 2 * spp)}
    return s


def mixed_plane_scene(a: mb.Material, b: mb.Material, resolution: int, spp: int,
                      env: np.ndarray, mask: np.ndarray) -> dict:
    import mitsuba as mi
    s = _base(mi, resolution, spp, env, [0, 2.6, 3.0], [0, 0, 0], fov=35)
    s["object"] = {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(1.3),
        "bsdf": {"type": "blendbsdf", "weight": _bitmap(mi, mask),
                 "a": mb.bsdf_dict(a, resolution ** 2 * spp),
                 "b": mb.bsdf_dict(b, resolution ** 2 * spp)},
    }
    return s


def normal_mapped_scene(material: mb.Material, resolution: int, spp: int, env: np.ndarray,
                        normals: np.ndarray) -> dict:
    import mitsuba as mi
    s = _base(mi, resolution, spp, env, [0, 0.6, 4.2], [0, 0, 0])
    s["object"] = {"type": "sphere",
                   "bsdf": {"type": "normalmap", "normalmap": _bitmap(mi, normals),
                            "bsdf": mb.bsdf_dict(material, resolution ** 2 * spp)}}
    return s


def render(scene: dict, seed: int = 0) -> np.ndarray:
    """Render a scene dictionary -> (H, W, 3) float32 linear RGB (deterministic per seed)."""
    import mitsuba as mi
    return np.asarray(mi.render(mi.load_dict(scene), seed=seed), dtype=np.float32)[..., :3]


def write_png(path: str | os.PathLike, img: np.ndarray, exposure: float = 0.0) -> None:
    """Linear RGB -> 8-bit sRGB PNG preview (`sphere.tonemap`)."""
    from PIL import Image
    Image.fromarray(tonemap(img, exposure)).save(path)


def render_spheres(weights, names, cfg: dict, activation: str = "relu", seed: int = 0,
                   progress=None) -> list[np.ndarray]:
    """Neural fields (N, 675) as spheres under the generated sky, one linear-RGB image each.
    `cfg` holds resolution, spp and envmap_size (config render.mitsuba); the caller picks the
    variant first (`mitsuba_bsdf.select_variant`)."""
    env = sky_envmap(cfg["envmap_size"])
    images = []
    for k, (n, w) in enumerate(zip(names, weights)):
        m = mb.Material(str(n), weights=np.nan_to_num(np.asarray(w, np.float32)), activation=activation)
        images.append(render(sphere_scene(m, cfg["resolution"], cfg["spp"], env), seed=seed))
        if progress:
            progress(k + 1, len(weights))
    return images
