"""Metric renderer: a sphere in one fixed view, evaluated analytically per pixel.

Setup (fixed forever, so renders of different runs are comparable):
  * unit sphere at the origin, orthographic camera looking down -z; pixel (row, col) covers
    x, y in [-1, 1] (row 0 = top, y = +1); the view direction is wo = +z for every pixel;
  * one point light at LIGHT_POS = (-2, 2, 3) (upper left, in front), intensity
    pi (|LIGHT_POS| - 1)^2, so the irradiance at the sphere point nearest the light is pi
    (a white Lambertian surface facing the light has radiance 1);
  * a dim uniform white environment of radiance AMBIENT = 0.1. On a convex sphere under a
    uniform environment the reflected radiance is AMBIENT * a(theta_o), with a the directional
    albedo of the material (isotropic BRDFs: a depends on theta_o alone). a is integrated on a
    fixed grid of N_THETA_O view angles by a fixed product quadrature of AMB_TH x AMB_PHI half
    vectors (`albedo_quadrature`: theta_h dense near the specular peak, as MERL's bins), and
    linearly interpolated per pixel in theta_o.
  L(pixel) = f(wi, wo) I cos(theta_i) / dist^2  +  AMBIENT * a(theta_o(pixel)).
No random sampling anywhere: the renders are deterministic and carry no Monte Carlo noise.

The geometry is precomputed once per (resolution, device) in `SphereView`: every row of `wi`,
`wo` (local shading frame, normal = +z) is one BRDF evaluation - a lit pixel under the point
light, or one albedo quadrature node - with its `weight`. A render evaluates f on all rows for a batch
of materials at once, weights them and writes them into the image. Output: float32 linear HDR (B, H, W, 3),
background 0.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from neumat import nbrdf
from neumat.io import merl

LIGHT_POS = np.array([-2.0, 2.0, 3.0])
LIGHT_INTENSITY = float(np.pi * (np.linalg.norm(LIGHT_POS) - 1.0) ** 2)
AMBIENT = 0.1
N_THETA_O, AMB_TH, AMB_PHI = 24, 32, 16
EXPOSURE = 0.0  # stops applied by `tonemap`
# Floats of hidden activations a pass on a GPU (two hidden layers of 21 plus output): bounds
# the chunk so thousands of materials fit in memory. The CPU takes nbrdf.materials_per_pass.
_CHUNK_FLOATS = 1 << 24


def half_vector_nodes(theta_o, n_h: int, n_phi: int, half: bool):
    """Quadrature of int g(wi) cos(theta_i) dwi over the hemisphere at each view angle theta_o,
    in half-vector space: h on a product grid of theta_h = (pi/2) t^2 (t at n_h midpoints: dense
    near the specular peak, as MERL's theta_h bins) by n_phi midpoints of phi_h, wi = the
    reflection of wo = (sin theta_o, 0, cos theta_o) about h, dwi = 4 (wo . h) dwh. `half`:
    phi_h over [0, pi] counted twice, exact for isotropic BRDFs (wo lies in the xz-plane, so h
    and its mirror image give the same value); else over [0, 2 pi].

    Returns wi, wo (n_o, n_h * n_phi, 3) and weights (n_o, n_h * n_phi): cos(theta_i) times the
    Jacobian and the cell's solid angle, 0 where wi is below the horizon (such a node's wi is
    the normal, a valid direction that weighs nothing).

    In the cosine-weighted (sin^2 theta_i, phi_i) grid the metric renderer used before, 16 x 16
    nodes missed a GGX lobe of roughness 0.1 by up to 0.52 in albedo (0.05: 0.83); the metric
    renderer's 32 x 16 of these (`albedo_quadrature`) is within 0.0019 of a 400 x 400 grid for
    roughness 0.02 to 0.1 (0.3: 0.0039, 0.5: 0.0066) at all 24 view angles, and exact for a
    Lambertian BRDF
    (benchmarks/metric_renderer_ab.py --albedo-only, AMD EPYC AVX-512, 2026-11-29;
    tests/test_render_sphere.py holds it to 0.5 %)."""
    theta_o = np.asarray(theta_o, np.float64)
    t = (np.arange(n_h) + 0.5) / n_h
    th, dth = t ** 2 * (np.pi / 2), 2 * t * (np.pi / 2) / n_h
    span = np.pi if half else 2 * np.pi
    ph = (np.arange(n_phi) + 0.5) / n_phi * span
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    h = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], -1).reshape(-1, 3)
    dwh = (np.sin(TH) * dth[:, None] * (span / n_phi)).reshape(-1) * (2 if half else 1)
    wo = np.stack([np.sin(theta_o), np.zeros_like(theta_o), np.cos(theta_o)], -1)
    wo = np.broadcast_to(wo[:, None], (len(theta_o), len(h), 3))
    oh = np.sum(wo * h, -1)
    wi = 2 * oh[..., None] * h - wo
    valid = (wi[..., 2] > 0) & (oh > 0)
    weight = np.where(valid, np.clip(wi[..., 2], 0, None) * 4 * oh * dwh, 0.0)
    wi = np.where(valid[..., None], wi, [0.0, 0.0, 1.0])
    return wi, np.ascontiguousarray(wo), weight


def albedo_quadrature(n_theta: int = N_THETA_O, n_h: int = AMB_TH, n_phi: int = AMB_PHI):
    """Nodes for the directional albedo a(theta_o) = int f cos dwi over the hemisphere at
    n_theta view angles (`half_vector_nodes`, phi_h over [0, pi] by symmetry).

    Returns theta_o (n_theta,), wi, wo (n_theta * n_h * n_phi, 3) local directions, and the
    quadrature weight per node (n_theta * n_h * n_phi,), scaled at each view angle so that the
    weights integrate cos(theta_i) to pi exactly: a Lambertian albedo is exact."""
    theta_o = (np.arange(n_theta) + 0.5) / n_theta * np.pi / 2
    wi, wo, weight = half_vector_nodes(theta_o, n_h, n_phi, half=True)
    weight = weight * (np.pi / weight.sum(1, keepdims=True))
    return theta_o, wi.reshape(-1, 3), wo.reshape(-1, 3), weight.reshape(-1)


class SphereView:
    """Per-pixel geometry of the metric view (see module docstring).

    Attributes (torch, on `device`):
      mask   (H, W) bool - pixels on the sphere
      wi, wo (N, 3) float32 - unit incident / outgoing directions in the local frame
             (normal = +z); the first `n_lit` rows are lit pixels under the point light,
             the rest the albedo quadrature nodes of the environment term
      weight (N,) float32 - irradiance (point light) or AMBIENT * quadrature weight
      pixel  (n_lit,) int64 - flat pixel index (row * W + col) of each point-light row
      x6     (N, 6) float32 - neural-field input [h, d] of each row
      bins   (N,) int64 - flat MERL bin index of each row (nearest bin)
    """

    def __init__(self, resolution: int, device: str | torch.device = "cpu", light=LIGHT_POS,
                 quadrature: tuple[int, int, int] = (N_THETA_O, AMB_TH, AMB_PHI)):
        """`light`: point-light position (default the metric view's LIGHT_POS; other positions
        give extra views of the same sphere, e.g. Table 3's grazing light), intensity as for
        LIGHT_POS: pi (|light| - 1)^2, irradiance pi at the sphere point nearest the light.
        `quadrature`: (n_theta, n_h, n_phi) of the albedo term (`albedo_quadrature`); coarser
        than the metric's for a cheap approximate render (particle guidance,
        neumat.diffusion.constraints)."""
        if resolution < 2:
            raise ValueError(f"sphere resolution must be >= 2, got {resolution}")
        self.resolution, self.device = resolution, torch.device(device)
        r = resolution
        c = (np.arange(r) + 0.5) / r * 2 - 1
        x, y = np.meshgrid(c, -c)  # row 0 is the top of the image
        rho2 = x ** 2 + y ** 2
        mask = rho2 < 1
        n = np.stack([x[mask], y[mask], np.sqrt(1 - rho2[mask])], -1)  # normal = surface point
        # Local frame: tangent = world x projected onto the tangent plane (only degenerate on
        # the silhouette, which the open mask excludes); isotropic BRDFs need nothing more.
        t = np.array([1.0, 0, 0]) - n[:, :1] * n
        t /= np.linalg.norm(t, axis=-1, keepdims=True)
        frame = np.stack([t, np.cross(n, t), n], 1)  # (P, 3, 3): rows = local axes

        light = np.asarray(light, dtype=np.float64)
        if light.shape != (3,) or np.linalg.norm(light) <= 1:
            raise ValueError(f"light position must be a 3-vector outside the unit sphere, got {light}")
        to_light = light - n
        dist2 = np.sum(to_light ** 2, -1)
        wi = np.einsum("pij,pj->pi", frame, to_light / np.sqrt(dist2)[:, None])
        wo = frame[:, :, 2].copy()  # the camera direction (world +z) in the local frame
        lit = wi[:, 2] > 0
        pixels = np.flatnonzero(mask.ravel())
        intensity = np.pi * (np.linalg.norm(light) - 1.0) ** 2
        weight = (intensity / dist2 * wi[:, 2])[lit]

        theta_o, awi, awo, aw = albedo_quadrature(*quadrature)
        wi = np.concatenate([wi[lit], awi])
        wo = np.concatenate([wo[lit], awo])
        weight = np.concatenate([weight, AMBIENT * aw])
        # linear interpolation of the albedo table at each sphere pixel's view angle
        k = np.interp(np.arccos(n[:, 2]), theta_o, np.arange(len(theta_o)))
        k0 = np.minimum(np.floor(k).astype(np.int64), len(theta_o) - 2)
        th, td, pd = merl.dirs_to_half_diff(wi, wo)

        as_t = functools.partial(torch.as_tensor, device=self.device)
        self.n_lit, self.n_theta = int(lit.sum()), len(theta_o)
        self.mask = as_t(mask)
        self.wi = as_t(wi, dtype=torch.float32)
        self.wo = as_t(wo, dtype=torch.float32)
        self.weight = as_t(weight, dtype=torch.float32)
        self.pixel = as_t(pixels[lit], dtype=torch.int64)
        self.x6 = as_t(merl.half_diff_cartesian(th, td, pd), dtype=torch.float32)
        self.bins = as_t(merl.angles_to_index(th, td, pd), dtype=torch.int64)
        self._pixels = as_t(pixels, dtype=torch.int64)
        self._k0 = as_t(k0, dtype=torch.int64)
        self._t = as_t(k - k0, dtype=torch.float32)[:, None]

    def __len__(self):
        return len(self.weight)

    def composite(self, values: torch.Tensor) -> torch.Tensor:
        """BRDF values (B, N, 3) at the view's rows -> linear HDR images (B, H, W, 3)."""
        b, r, n = values.shape[0], self.resolution, self.n_lit
        values = values.float() * self.weight[:, None]
        img = torch.zeros(b, r * r, 3, dtype=torch.float32, device=values.device)
        img[:, self.pixel] = values[:, :n]  # at most one point-light row per pixel
        albedo = values[:, n:].reshape(b, self.n_theta, -1, 3).sum(2)
        img[:, self._pixels] += torch.lerp(albedo[:, self._k0], albedo[:, self._k0 + 1], self._t)
        return img.reshape(b, r, r, 3)


@functools.lru_cache(maxsize=8)
def sphere_view(resolution: int, device: str = "cpu", light: tuple | None = None,
                quadrature: tuple[int, int, int] = (N_THETA_O, AMB_TH, AMB_PHI)) -> SphereView:
    """Cached `SphereView` (the geometry is the same for every call); `light` a position tuple,
    None = the metric view's LIGHT_POS; `quadrature` as SphereView's."""
    return SphereView(resolution, device, LIGHT_POS if light is None else light, quadrature)


def _chunks(n: int, size: int):
    for s in range(0, n, size):
        yield slice(s, min(s + size, n))


def render_fn(fn, B: int, resolution: int = 128, device: str = "cpu") -> torch.Tensor:
    """Render any BRDF callable `fn(wi, wo) -> (B, N, 3)` (torch, local frame) -> (B, H, W, 3)."""
    view = sphere_view(resolution, str(device))
    with torch.no_grad():
        values = fn(view.wi, view.wo)
    if values.shape != (B, len(view), 3):
        raise ValueError(f"BRDF callable returned shape {tuple(values.shape)}, "
                         f"expected {(B, len(view), 3)}")
    return view.composite(values).cpu()


def render_fields(weights, resolution: int = 128, activation: str = "relu",
                  device: str = "cpu", chunk: int | None = None,
                  light: tuple | None = None) -> torch.Tensor:
    """Neural fields (B, 675) -> linear HDR renders (B, H, W, 3) float32 (CPU tensor)."""
    w = torch.as_tensor(np.asarray(weights) if not torch.is_tensor(weights) else weights,
                        dtype=torch.float32)
    if w.dim() != 2 or w.shape[1] != nbrdf.N_PARAMS:
        raise ValueError(f"weights must have shape (B, {nbrdf.N_PARAMS}), got {tuple(w.shape)}")
    view = sphere_view(resolution, str(device), None if light is None else tuple(light))
    if chunk is None:  # on the CPU in cache-sized passes: 2^24 floats (51 materials at 128^2)
        # mapped fresh pages for every pass (benchmarks/plausibility.py)
        chunk = (nbrdf.materials_per_pass(len(view)) if torch.device(device).type == "cpu"
                 else max(1, _CHUNK_FLOATS // (len(view) * 21)))
    out = torch.empty(len(w), resolution, resolution, 3)
    with torch.no_grad():
        for s in _chunks(len(w), chunk):
            f = nbrdf.forward(w[s].to(view.device), view.x6, activation)
            out[s] = view.composite(f).cpu()
    return out


def render_tables(tables, resolution: int = 128, device: str = "cpu",
                  chunk: int = 64) -> torch.Tensor:
    """MERL tables (B, 3, 90, 90, 180) physical BRDF -> linear HDR renders (B, H, W, 3).

    Nearest-bin lookup (as `neumat.io.merl.lookup`), one gather per chunk of materials;
    negative (below-horizon) table entries count as 0."""
    t = torch.as_tensor(tables)
    if t.dim() != 5 or tuple(t.shape[1:]) != merl.SHAPE:
        raise ValueError(f"tables must have shape (B, {', '.join(map(str, merl.SHAPE))}), "
                         f"got {tuple(t.shape)}")
    view = sphere_view(resolution, str(device))
    out = torch.empty(len(t), resolution, resolution, 3)
    for s in _chunks(len(t), chunk):
        flat = t[s].reshape(-1, 3, merl.N_BINS).to(view.device, torch.float32)
        out[s] = render_view_values(flat[:, :, view.bins], resolution, device)
    return out


def render_view_values(values, resolution: int = 128, device: str = "cpu") -> torch.Tensor:
    """Physical BRDF at the view's bins, (B, 3, N) for `sphere_view(resolution).bins`, ->
    linear HDR renders (B, H, W, 3); negative values count as 0. A table render needs only
    these ~10^4 bins, not the 4.4 M of a full table."""
    view = sphere_view(resolution, str(device))
    f = torch.as_tensor(values, device=view.device, dtype=torch.float32)
    return view.composite(f.clamp_min(0).transpose(1, 2)).cpu()


def srgb_encode(x):
    """Linear [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1 curve); clips first."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def to_srgb(img, exposure: float = EXPOSURE) -> torch.Tensor:
    """Linear HDR (..., 3) -> float32 sRGB in [0, 1]: scale by 2**exposure, clip, sRGB curve.
    The images the render distances (RMSE, PSNR, SSIM) and FID see."""
    x = torch.as_tensor(img, dtype=torch.float32) * 2.0 ** exposure
    x = x.clamp(0, 1)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)


def srgb_decode(x) -> torch.Tensor:
    """sRGB-encoded [0, 1] -> linear [0, 1], the inverse of `to_srgb`'s curve: the light the
    metric renders hold, after their exposure and clip (benchmarks/diffusion_diagnose.py kinds
    --linear compares errors there)."""
    x = torch.as_tensor(x, dtype=torch.float32)
    return torch.where(x <= 0.04045, x / 12.92, ((x.clamp_min(0) + 0.055) / 1.055) ** 2.4)


def tonemap(img, exposure: float = EXPOSURE) -> np.ndarray:
    """Linear HDR (..., 3) -> uint8 sRGB: `to_srgb` rounded to 8 bits. With exposure 0 a
    white Lambertian (albedo 1) facing the light is 1.0 linear plus the ambient (clipped: 255)."""
    x = img.numpy() if torch.is_tensor(img) else np.asarray(img)
    return np.round(srgb_encode(x * 2.0 ** exposure) * 255).astype(np.uint8)
