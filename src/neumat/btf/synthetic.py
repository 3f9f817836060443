"""Synthetic BTFs: procedural wood-, leather- and stone-like surfaces (spatially varying albedo,
roughness and normal maps) shaded with a Lambert + GGX microfacet BRDF, sampled at the UBO2014
151 x 151 directions and written as DFMF (colour model 11, truncated SVD) like the real files.

Value stored per (texel, light, view): f_r(wi, wo; texel) * max(n . wi, 0), i.e. outgoing
radiance under unit directional light, which is what the UBO2014 images measure. All maps tile
(wrap-around filtering), so repetitive tiling shows no seams.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from neumat.btf.directions import to_cartesian, ubo2014_angles
from neumat.io import dfmf

KINDS = ("wood", "leather", "stone")


def _noise(rng, size, sigma):
    """Tileable smooth noise in [0, 1]."""
    n = ndimage.gaussian_filter(rng.standard_normal((size, size)), sigma, mode="wrap")
    return (n - n.min()) / (np.ptp(n) + 1e-12)


def _fbm(rng, size, octaves=4):
    return sum(0.5 ** o * _noise(rng, size, size / 8 / 2 ** o) for o in range(octaves)) / 1.9


def _cells(rng, size, n):
    """Periodic Worley noise: F2 - F1 distance (creases at cell borders), normalised."""
    pts = rng.random((n, 2)) * size
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    d, _ = cKDTree(pts, boxsize=size).query(np.stack([xs.ravel(), ys.ravel()], -1), k=2)
    f = (d[:, 1] - d[:, 0]).reshape(size, size)
    return f / f.max()


def material_maps(kind: str, size: int, seed: int):
    """albedo (S, S, 3), specular (S, S), roughness (S, S), height (S, S) for one material."""
    rng = np.random.default_rng(seed)
    if kind == "wood":
        ys, xs = np.mgrid[0:size, 0:size] / size
        warp = _fbm(rng, size)
        rings = 0.5 + 0.5 * np.sin(2 * np.pi * (3 * ys + 2 * np.sin(2 * np.pi * xs) / 8 + 1.5 * warp))
        dark, light = np.array([0.20, 0.09, 0.03]), np.array([0.55, 0.32, 0.14])
        albedo = light + (dark - light) * rings[..., None] ** 2
        rough = 0.18 + 0.25 * rings
        spec = np.full((size, size), 0.04)
        height = 0.6 * rings + 0.4 * _noise(rng, size, 1.0)
    elif kind == "leather":
        cells = _cells(rng, size, max(12, size ** 2 // 48))
        crease = np.exp(-cells / 0.08)
        albedo = np.array([0.30, 0.12, 0.06]) * (1 - 0.6 * crease)[..., None] \
            * (0.85 + 0.3 * _noise(rng, size, 2.0))[..., None]
        rough = 0.30 + 0.35 * crease
        spec = 0.05 * (1 - 0.7 * crease)
        height = -crease + 0.2 * _noise(rng, size, 1.0)
    elif kind == "stone":
        grain = _fbm(rng, size)
        speck = (_noise(rng, size, 0.7) > 0.75).astype(float)
        albedo = (0.25 + 0.35 * grain)[..., None] * np.array([1.0, 0.97, 0.92]) \
            + 0.3 * speck[..., None]
        rough = 0.5 + 0.3 * (1 - grain) - 0.35 * speck
        spec = 0.03 + 0.15 * speck
        height = 1.5 * grain
    else:
        raise ValueError(f"unknown synthetic BTF kind {kind!r}; choose from {KINDS}")
    return albedo, spec, np.clip(rough, 0.05, 1.0), height


def normals_from_height(height: np.ndarray, strength: float) -> np.ndarray:
    """(S, S, 3) unit normals of z = strength * height (in texel units, wrap-around)."""
    gy, gx = np.gradient(np.pad(height, 1, mode="wrap"))
    gx, gy = gx[1:-1, 1:-1], gy[1:-1, 1:-1]
    n = np.stack([-strength * gx, -strength * gy, np.ones_like(gx)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def shade(albedo, spec, rough, normal, wi, wo):
    """Lambert + GGX (Smith G, Schlick F) times n.wi. Texel arrays (T, ...), dirs (R, 3)
    -> (R, T, 3) float32."""
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    ni = np.clip(wi @ normal.T, 0, None)              # (R, T)
    no = np.clip(wo @ normal.T, 1e-4, None)
    nh = np.clip(h @ normal.T, 0, None)
    a2 = rough[None] ** 4                             # alpha = roughness^2
    D = a2 / (np.pi * (nh ** 2 * (a2 - 1) + 1) ** 2)
    k = rough[None] ** 2 / 2
    G = ni / (ni * (1 - k) + k) * no / (no * (1 - k) + k)
    F = spec[None] + (1 - spec[None]) * (1 - np.sum(wi * h, -1, keepdims=True)) ** 5
    f = albedo[None] / np.pi + (D * G * F / (4 * no * np.maximum(ni, 1e-4)))[..., None]
    return (f * ni[..., None]).astype(np.float32)


RANK_TOL = 1e-10  # eigenvalues of the Gram matrix below this share of the largest count as 0


def synthesize(kind: str, size: int, seed: int, components: int, path, scalar: int = 2,
               chunk: int = 1024, normal_strength: float = 2.0,
               max_bytes: int = 1 << 29) -> None:
    """Write a synthetic BTF as DFMF. Truncated SVD of the colour-model-11 channels, computed
    from the texel Gram matrix so the (22801 x texels) matrix is generated twice in row chunks
    and never held whole."""
    albedo, spec, rough, height = material_maps(kind, size, seed)
    normal = normals_from_height(height, normal_strength * size / 64)
    tex = [a.reshape(size * size, *a.shape[2:]).astype(np.float32)
           for a in (albedo, spec, rough, normal)]
    ang = ubo2014_angles()
    dirs = to_cartesian(ang).astype(np.float32)
    n = len(dirs)
    rows = np.arange(n * n)

    def channels(r):  # rows r = view * L + light -> (len(r), T, 3) decorrelated channels
        rgb = shade(*tex, dirs[r % n], dirs[r // n])
        return dfmf.from_rgb(rgb, 11)

    T = size * size
    k = min(components, T)
    # Keep the decorrelated matrix in memory when it is small (one generation pass), else
    # generate it twice in row chunks (Gram pass, then projection pass).
    keep = len(rows) * T * 3 * 4 <= max_bytes
    held = np.zeros((len(rows), T, 3), np.float32) if keep else None
    gram = np.zeros((3, T, T))
    for s in range(0, len(rows), chunk):
        m = channels(rows[s:s + chunk])
        if keep:
            held[s:s + chunk] = m
        for c in range(3):
            gram[c] += (m[..., c].T @ m[..., c]).astype(np.float64)
    V, sig = [], []
    for c in range(3):
        w, v = np.linalg.eigh(gram[c])
        idx = np.argsort(w)[::-1][:k]
        # a component past the texture's rank has sigma ~ 0: U = m V / sigma is then rounding
        # noise blown up past float16 (inf in the file, which every BTF job reads as damaged)
        rank = int((w > RANK_TOL * w.max()).sum())
        if rank < k:
            raise ValueError(f"ubo2014.synthetic.components {components}: the {size} x {size} "
                             f"procedural {kind!r} texture has rank {rank} in colour channel {c}; "
                             f"give at most {rank} (or a larger ubo2014.synthetic.size)")
        sig.append(np.sqrt(np.maximum(w[idx], 1e-20)))
        V.append(v[:, idx])
    U = [np.zeros((len(rows), k)) for _ in range(3)]
    for s in range(0, len(rows), chunk):
        m = held[s:s + chunk] if keep else channels(rows[s:s + chunk])
        for c in range(3):
            U[c][s:s + chunk] = m[..., c] @ (V[c] / sig[c])
    SV = [V[c] * sig[c] for c in range(3)]
    dfmf.write_dfmf(path, U, SV, ang, ang, size, size, color_model=11, scalar=scalar, S=sig)
