"""Analytic MERL-format materials: the offline stand-in for the MERL database (tiny config, tests).

Every material is an isotropic BRDF built from up to three reciprocal lobes:
    specular  GGX microfacet (height-correlated Smith G2) x Fresnel (exact dielectric or
              Schlick with a coloured F0 for conductors); tiny roughness gives near-mirrors
    sheen     Charlie distribution (Estevez & Kulla 2017) with Neubelt's visibility, fabric-like
    diffuse   Lambertian albedo coupled to the lobes above (Kelemen & Szirmay-Kalos 2001):
              rho (1 - E(mu_i)) (1 - E(mu_o)) / (pi (1 - E_avg))
where E(mu) is the directional albedo of specular + sheen. The coupling keeps the BRDF
symmetric in (wi, wo) and makes the total albedo E + rho (1 - E) <= 1, so each material is
reciprocal and energy-conserving by construction. Single-scattering GGX loses energy at high
roughness, which is physically plausible (no multiple-scattering compensation).

Every function is expressed in (mu_i, mu_o, cos theta_h, cos theta_d), which the MERL grid
gives directly, so a whole (3, 90, 90, 180) table is a handful of vectorised numpy passes.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from neumat.data.names import COLOUR_WORDS, material_type
from neumat.io import merl

RGB = tuple[float, float, float]

# Linear-RGB base colours for the colour words used in names (diffuse albedo before jitter).
COLOURS: dict[str, RGB] = {
    "white": (0.80, 0.80, 0.78), "black": (0.03, 0.03, 0.03), "gray": (0.25, 0.25, 0.25),
    "red": (0.55, 0.05, 0.04), "green": (0.06, 0.35, 0.08), "blue": (0.04, 0.09, 0.45),
    "yellow": (0.62, 0.50, 0.05), "orange": (0.68, 0.25, 0.03), "pink": (0.72, 0.30, 0.40),
    "purple": (0.25, 0.07, 0.35), "violet": (0.32, 0.10, 0.52), "maroon": (0.25, 0.03, 0.04),
    "brown": (0.20, 0.10, 0.05), "beige": (0.55, 0.45, 0.33), "gold": (0.55, 0.40, 0.10),
    "silver": (0.60, 0.60, 0.62),
}
assert set(COLOURS) <= COLOUR_WORDS
# Normal-incidence reflectance of bare metals (Schlick F0, linear RGB, approximate).
METAL_F0: dict[str, RGB] = {
    "gold": (1.00, 0.78, 0.34), "silver": (0.97, 0.96, 0.91), "brass": (0.91, 0.78, 0.42),
    "nickel": (0.66, 0.61, 0.53), "aluminium": (0.91, 0.92, 0.92), "steel": (0.56, 0.57, 0.58),
    "alum-bronze": (0.85, 0.68, 0.45), "chrome": (0.55, 0.56, 0.55),
}
HUES = [c for c in COLOURS if c not in ("gold", "silver")]

# Families in the order the first specs cycle through, so even 2-8 materials are diverse.
# Each template is a MERL-style name with an optional {c} colour slot (types from the catalogue).
FAMILIES: list[tuple[str, list[str]]] = [
    ("lambertian", ["{c}-paint", "{c}-rubber", "{c}-matte-plastic"]),
    ("conductor", ["{c}-metallic-paint", "brass", "nickel", "aluminium", "alum-bronze"]),
    ("plastic", ["{c}-plastic", "{c}-phenolic", "{c}-acrylic", "{c}-soft-plastic"]),
    ("fabric", ["{c}-fabric", "{c}-felt"]),
    ("mirror", ["chrome", "chrome-steel", "silver-metallic-paint"]),
    ("dielectric", ["{c}-specular-plastic", "specular-{c}-phenolic", "black-obsidian"]),
]
N_MU = 64  # directional-albedo table resolution (mu midpoints)
N_QUAD = 64  # per-axis stratified quadrature samples of the albedo integrals


@dataclass(frozen=True)
class Spec:
    """One analytic material. Zero `alpha` = no specular lobe, zero `sheen` = no sheen lobe."""
    name: str
    type: str
    family: str
    diffuse: RGB = (0.0, 0.0, 0.0)  # Lambertian albedo rho
    alpha: float = 0.0  # GGX roughness (alpha = perceptual roughness squared)
    ior: float = 0.0  # > 0: exact dielectric Fresnel (achromatic coat)
    f0: RGB = (0.0, 0.0, 0.0)  # ior == 0: Schlick Fresnel with this F0 (conductors)
    sheen: RGB = (0.0, 0.0, 0.0)  # sheen lobe colour
    sheen_alpha: float = 0.5  # Charlie roughness


# ----------------------------------------------------------------------------- specs


def _jitter(rng, rgb, lo=0.8, hi=1.1, cap=0.9):
    return tuple(float(v) for v in np.clip(np.asarray(rgb) * rng.uniform(lo, hi, 3), 0.005, cap))


def _spec_params(family: str, template: str, colour: str | None, rng) -> dict:
    """Random physical parameters of one family; colours follow the name's colour word."""
    base = COLOURS.get(colour, (0.5, 0.5, 0.5))
    if family == "lambertian":
        return dict(diffuse=_jitter(rng, base))
    if family == "plastic":
        return dict(diffuse=_jitter(rng, base), alpha=float(rng.uniform(0.05, 0.3)),
                    ior=float(rng.uniform(1.45, 1.6)))
    if family == "dielectric":
        return dict(diffuse=_jitter(rng, base, 0.5, 0.8), alpha=float(rng.uniform(0.01, 0.05)),
                    ior=float(rng.uniform(1.5, 1.7)))
    if family == "fabric":
        return dict(diffuse=_jitter(rng, base, 0.7, 1.0, 0.8),
                    sheen=_jitter(rng, np.sqrt(base), 0.3, 0.5, 0.5),
                    sheen_alpha=float(rng.uniform(0.3, 0.8)))
    if family in ("conductor", "mirror"):
        stem = template.replace("{c}-", "").replace("-metallic-paint", "")
        if stem in METAL_F0:
            f0 = METAL_F0[stem]
        elif colour in METAL_F0:
            f0 = METAL_F0[colour]
        else:  # tinted metallic paint: a coloured F0 derived from the hue
            f0 = tuple(0.25 + 0.7 * v / max(base) for v in base)
        lo, hi = (0.002, 0.012) if family == "mirror" else (0.06, 0.35)
        return dict(f0=_jitter(rng, f0, 0.95, 1.0, 0.99), alpha=float(rng.uniform(lo, hi)))
    raise ValueError(f"unknown family {family!r}")


def make_specs(count: int, seed: int) -> list[Spec]:
    """`count` distinct materials with MERL-style names, deterministic given `seed`.

    Spec i cycles through FAMILIES (so the first few cover all families) and depends only on
    (seed, i) and the names before it, hence make_specs(n, s)[:k] == make_specs(k, s)."""
    if count < 1:
        raise ValueError(f"make_specs: count must be >= 1, got {count}")
    specs, seen = [], {}
    for i in range(count):
        rng = np.random.default_rng([seed, i])
        family, templates = FAMILIES[i % len(FAMILIES)]
        template = templates[rng.integers(len(templates))]
        colour = HUES[rng.integers(len(HUES))] if "{c}" in template else None
        if template.startswith("{c}-metallic-paint") and rng.random() < 0.4:
            colour = ("gold", "silver")[rng.integers(2)]  # MERL has gold/silver metallic paints
        name = template.format(c=colour)
        seen[name] = seen.get(name, 0) + 1
        if seen[name] > 1:  # MERL style: blue-metallic-paint2
            name = f"{name}{seen[name]}"
        colour = colour or next((w for w in name.split("-") if w in COLOURS), None)
        specs.append(Spec(name=name, type=material_type(name), family=family,
                          **_spec_params(family, template, colour, rng)))
    return specs


# ----------------------------------------------------------------------------- lobes


def _fresnel(spec: Spec, cos_d: np.ndarray) -> np.ndarray:
    """Fresnel reflectance at the microfacet angle cos theta_d = wi . h: (1, N) for the
    achromatic dielectric, (3, N) for a coloured conductor."""
    c = np.clip(cos_d, 0.0, 1.0)[None]
    if spec.ior > 0:  # exact unpolarised dielectric Fresnel
        g = np.sqrt(spec.ior ** 2 - 1 + c ** 2)
        return 0.5 * ((g - c) / (g + c)) ** 2 * (1 + ((c * (g + c) - 1) / (c * (g - c) + 1)) ** 2)
    f0 = np.asarray(spec.f0)[:, None]
    return f0 + (1 - f0) * (1 - c) ** 5


def _smith_g2(mu_i, mu_o, alpha):
    """Height-correlated Smith masking-shadowing 1 / (1 + Lambda(mu_i) + Lambda(mu_o))."""
    a2 = alpha ** 2

    def lam2(mu):  # 2 Lambda(mu)
        mu2 = np.clip(mu, 1e-9, 1.0) ** 2
        return np.sqrt(1 + a2 * (1 - mu2) / mu2) - 1

    return 2 / (2 + lam2(mu_i) + lam2(mu_o))


def _specular(spec: Spec, mu_i, mu_o, cos_h, cos_d) -> np.ndarray:
    """GGX microfacet lobe D G2 F / (4 mu_i mu_o), (3, N) or (1, N)."""
    a2 = spec.alpha ** 2
    d = a2 / (np.pi * (cos_h ** 2 * (a2 - 1) + 1) ** 2)
    return d * _smith_g2(mu_i, mu_o, spec.alpha) / (4 * mu_i * mu_o) * _fresnel(spec, cos_d)


def _sheen(spec: Spec, mu_i, mu_o, cos_h, cos_d) -> np.ndarray:
    """Charlie sheen D / (4 (mu_i + mu_o - mu_i mu_o)) x colour, (3, N)."""
    inv = 1 / spec.sheen_alpha
    sin_h = np.sqrt(np.clip(1 - cos_h ** 2, 0, 1))
    d = (2 + inv) * sin_h ** inv / (2 * np.pi)
    return d / (4 * (mu_i + mu_o - mu_i * mu_o)) * np.asarray(spec.sheen)[:, None]


def _frames(mu: np.ndarray, wi: np.ndarray):
    """(mu_i, mu_o, cos_h, cos_d), each flat (M*K,), for wo = (sqrt(1-mu^2), 0, mu) per row of
    mu (M,) and incident directions wi (M, K, 3)."""
    wo = np.stack([np.sqrt(1 - mu ** 2), np.zeros_like(mu), mu], -1)[:, None]
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    mu_o = np.broadcast_to(wo[..., 2], wi.shape[:2])
    return (wi[..., 2].ravel(), mu_o.ravel(), h[..., 2].ravel(), np.sum(wi * h, -1).ravel())


@functools.lru_cache(maxsize=256)
def albedo_table(spec: Spec) -> tuple[np.ndarray, np.ndarray]:
    """Directional albedo E(mu) (3, N_MU) of the specular + sheen lobes at mu midpoints.

    Deterministic stratified quadrature: the specular lobe is integrated by sampling h from
    D(h) cos theta_h (accurate for any roughness, near-mirrors included), the sheen lobe by
    cosine-weighted sampling of wi."""
    mu = (np.arange(N_MU) + 0.5) / N_MU
    u = (np.arange(N_QUAD) + 0.5) / N_QUAD
    u1, u2 = (a.ravel() for a in np.meshgrid(u, u))
    phi = 2 * np.pi * u2
    e = np.zeros((3, N_MU))
    if spec.alpha > 0:
        th = np.arctan(spec.alpha * np.sqrt(u1 / (1 - u1)))
        h = np.stack([np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)], -1)
        wo = np.stack([np.sqrt(1 - mu ** 2), np.zeros_like(mu), mu], -1)
        odh = wo @ h.T  # (N_MU, K)
        mi, mo, ch, cd = _frames(mu, 2 * odh[..., None] * h[None] - wo[:, None])
        # f mu_i / pdf with pdf(wi) = D cos_h / (4 wo.h): D cancels -> F G2 (wo.h) / (mu_o cos_h)
        w = np.where((mi > 0) & (odh.ravel() > 0),
                     _smith_g2(mi, mo, spec.alpha) * odh.ravel() / (mo * ch), 0.0)
        e += (w * _fresnel(spec, cd)).reshape(-1, N_MU, N_QUAD ** 2).mean(-1)
    if max(spec.sheen) > 0:
        r = np.sqrt(u1)
        wi = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], -1)
        mi, mo, ch, cd = _frames(mu, np.broadcast_to(wi, (N_MU, *wi.shape)))
        e += np.pi * _sheen(spec, mi, mo, ch, cd).reshape(3, N_MU, -1).mean(-1)
    return mu, e


def _interp_mu(e: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Linear interpolation of a (3, N_MU) table at midpoint nodes -> (3, N), clamped ends."""
    t = np.clip(mu * N_MU - 0.5, 0, N_MU - 1)
    i = np.minimum(t.astype(np.int64), N_MU - 2)
    w = t - i
    return e[:, i] * (1 - w) + e[:, i + 1] * w


def _brdf(spec: Spec, mu_i, mu_o, cos_h, cos_d) -> np.ndarray:
    """Physical BRDF (3, N) for directions above the horizon (mu_i, mu_o > 0)."""
    f = np.zeros((3, mu_i.size))
    if spec.alpha > 0:
        f += _specular(spec, mu_i, mu_o, cos_h, cos_d)
    if max(spec.sheen) > 0:
        f += _sheen(spec, mu_i, mu_o, cos_h, cos_d)
    rho = np.asarray(spec.diffuse)[:, None]
    if spec.alpha > 0 or max(spec.sheen) > 0:
        mu, e = albedo_table(spec)
        e_avg = np.mean(2 * mu * e, 1, keepdims=True)  # 2 int E(mu) mu dmu, per channel
        f += rho / (np.pi * (1 - e_avg)) * (1 - _interp_mu(e, mu_i)) * (1 - _interp_mu(e, mu_o))
    else:  # plain Lambertian
        f += rho / np.pi
    return f


def evaluate(spec: Spec, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """BRDF (N, 3) of direction pairs (N, 3) in the local frame; 0 below the horizon."""
    wi, wo = np.asarray(wi, dtype=np.float64), np.asarray(wo, dtype=np.float64)
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    ok = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    f = np.zeros((len(wi), 3))
    f[ok] = _brdf(spec, wi[ok, 2], wo[ok, 2], h[ok, 2], np.sum(wi[ok] * h[ok], -1)).T
    return f


@functools.lru_cache(maxsize=1)
def _grid_terms():
    """(mu_i, mu_o, cos_h, cos_d) of the valid MERL bin centres and the valid mask (flat, file
    order). In the half-vector frame wo is wi mirrored about h, i.e. phi_d + pi; the mask
    equals merl.valid_mask() (tested)."""
    th, td, pd = merl.grid_angles()
    a, b = np.cos(td) * np.cos(th), np.sin(td) * np.cos(pd) * np.sin(th)
    mu_i, mu_o = a - b, a + b
    valid = (mu_i > 0) & (mu_o > 0)
    return mu_i[valid], mu_o[valid], np.cos(th[valid]), np.cos(td[valid]), valid


def make_table(spec: Spec) -> np.ndarray:
    """Physical BRDF (3, 90, 90, 180) float64 at MERL bin centres; below-horizon bins hold
    -1 * SCALE per channel, like measured MERL files."""
    mu_i, mu_o, cos_h, cos_d, valid = _grid_terms()
    table = np.empty((3, merl.N_BINS))
    table[:] = -merl.SCALE[:, None]
    table[:, valid] = _brdf(spec, mu_i, mu_o, cos_h, cos_d)
    return table.reshape(merl.SHAPE)
