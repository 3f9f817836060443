"""Physical plausibility of synthesised neural BRDFs.

For each weight vector: non-finite weights or outputs, negative values hidden by the output
clamp max(exp(x) - 1, 0), exploding values, and energy passivity - the directional albedo
a(w_o) = integral of f(w_i, w_o) cos(theta_i) dw_i must not exceed 1 in any channel.

The albedo is integrated over the half vector h rather than w_i (w_i = reflect(w_o, h),
dw_i = 4 (w_o . h) dw_h) on a grid that is dense near the normal, like MERL's theta_h axis,
so narrow specular peaks (which sit at theta_h = 0 for every w_o) are resolved.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from neumat import nbrdf
from neumat.io import merl
from neumat.render.sphere import half_vector_nodes


def albedo_quadrature(n_theta_o: int = 8, n_theta_h: int = 64, n_phi_h: int = 64):
    """Directions and weights: x (n_o, M, 6) NBRDF inputs, w (n_o, M) quadrature weights
    (including cos(theta_i), the Jacobian and the below-horizon mask), theta_o (n_o,): the
    metric renderer's half-vector nodes (`sphere.half_vector_nodes`), phi_h over [0, 2 pi]."""
    theta_o = (np.arange(n_theta_o) + 0.5) / n_theta_o * (np.pi / 2)
    wi, wo, w = half_vector_nodes(theta_o, n_theta_h, n_phi_h, half=False)
    th_, td_, pd_ = merl.dirs_to_half_diff(wi.reshape(-1, 3), wo.reshape(-1, 3))
    x = merl.half_diff_cartesian(th_, td_, pd_).reshape(n_theta_o, -1, 6)
    return x, w, theta_o


@torch.no_grad()
def directional_albedo(weights: np.ndarray, n_theta_o: int = 8, n_theta_h: int = 64,
                       n_phi_h: int = 64, activation: str = "relu", chunk: int | None = None) -> np.ndarray:
    """(B, 675) weights -> (B, n_theta_o, 3) directional albedo per outgoing elevation;
    `chunk` materials per pass (default `nbrdf.materials_per_pass`)."""
    x, w, _ = albedo_quadrature(n_theta_o, n_theta_h, n_phi_h)
    n_o, m, _ = x.shape
    xt = torch.as_tensor(x.reshape(-1, 6), dtype=torch.float32)
    wt = torch.as_tensor(w, dtype=torch.float64)
    chunk = chunk or nbrdf.materials_per_pass(n_o * m)
    out = np.zeros((len(weights), n_o, 3))
    for s in range(0, len(weights), chunk):
        f = nbrdf.forward(torch.as_tensor(weights[s:s + chunk], dtype=torch.float32), xt, activation)
        f = f.double().reshape(-1, n_o, m, 3)
        out[s:s + chunk] = torch.einsum("bomc,om->boc", f, wt).numpy()
    return out


@torch.no_grad()
def plausibility(weights: np.ndarray, reference_max: float | None = None, n_angles: int = 20000,
                 explode_factor: float = 10.0, albedo_tol: float = 0.01, seed: int = 0,
                 activation: str = "relu", albedo_kw: dict | None = None,
                 block: int | None = None) -> pd.DataFrame:
    """Per-material checks -> DataFrame with columns
    nonfinite (weights or outputs NaN/inf), negative_share (share of valid MERL bins whose
    unclamped value exp(x) - 1 < 0, i.e. clamped to 0), max_value, exploding (max above
    explode_factor x `reference_max`, e.g. the training set's largest value),
    max_albedo (largest directional albedo over directions and channels), passivity_violation
    (max_albedo > 1 + albedo_tol; the tolerance absorbs quadrature error, ~1e-4 for a
    Lambertian BRDF on the default grid). `block` materials per NBRDF pass (default
    `nbrdf.materials_per_pass`, 1-2 materials: 64 materials' checks took 4.24x as long at 64 a
    pass, `OMP_NUM_THREADS=1 python benchmarks/plausibility.py`, AMD EPYC AVX-512, 2026-11-26,
    README "Benchmarks"); the values do not depend on it beyond float64
    rounding in the albedo sums (2.7e-15 there)."""
    weights = np.asarray(weights, dtype=np.float32)
    rng = np.random.default_rng(seed)
    valid = np.flatnonzero(merl.valid_mask())
    idx = np.sort(rng.choice(valid, size=min(n_angles, len(valid)), replace=False))
    th, td, pd_ = (a[idx] for a in merl.grid_angles())
    x = torch.as_tensor(merl.half_diff_cartesian(th, td, pd_), dtype=torch.float32)
    finite_o, neg, vmax = (np.zeros(len(weights), t) for t in (bool, float, float))
    step = block or nbrdf.materials_per_pass(len(x))
    for s in range(0, len(weights), step):
        vals = torch.expm1(nbrdf.forward_raw(torch.as_tensor(weights[s:s + step]), x, activation).double())
        finite_o[s:s + step] = torch.isfinite(vals).flatten(1).all(1).numpy()
        neg[s:s + step] = (vals < 0).flatten(1).double().mean(1).numpy()
        vmax[s:s + step] = torch.nan_to_num(vals, nan=np.inf).flatten(1).amax(1).numpy()
    finite_w = np.isfinite(weights).all(1)
    albedo = directional_albedo(np.nan_to_num(weights), activation=activation, chunk=block,
                                **(albedo_kw or {}))
    max_alb = np.nan_to_num(albedo.reshape(len(weights), -1).max(1), nan=np.inf) \
        if len(weights) else np.zeros(0)
    max_alb[~finite_w] = np.inf  # the albedo above was computed on zeroed NaNs: meaningless
    df = pd.DataFrame({
        "nonfinite": ~(finite_w & finite_o),
        "negative_share": neg,
        "max_value": vmax,
        "max_albedo": max_alb,
        "passivity_violation": max_alb > 1.0 + albedo_tol,
    })
    df["exploding"] = (vmax > explode_factor * reference_max) if reference_max else False
    return df


def summarize(df: pd.DataFrame) -> dict:
    """Shares over a set: the numbers the report prints."""
    return {
        "materials": len(df),
        "share_nonfinite": float(df["nonfinite"].mean()),
        "share_any_negative": float((df["negative_share"] > 0).mean()),
        "mean_negative_share": float(df["negative_share"].mean()),
        "share_exploding": float(df["exploding"].mean()),
        "share_passivity_violation": float(df["passivity_violation"].mean()),
        "median_max_albedo": float(df["max_albedo"].median()),
    }
