"""UBO2014 direction sets and the Rusinkiewicz (half, difference) change of variables.

UBO2014 samples light and view on the same 151 directions: rings of constant elevation
(theta in degrees: count) 0:1, 11:6, 23.5:12, 30:12, 37.5:12, 45:18, 52.5:18, 60:24, 67.5:24,
75:24, azimuths evenly spaced from 0 on each ring.
"""

from __future__ import annotations

import numpy as np
import torch

RINGS = [(0.0, 1), (11.0, 6), (23.5, 12), (30.0, 12), (37.5, 12), (45.0, 18), (52.5, 18),
         (60.0, 24), (67.5, 24), (75.0, 24)]


def ubo2014_angles() -> np.ndarray:
    """(151, 2) float32 (theta, phi) in radians, ring by ring, azimuth increasing."""
    out = [(np.radians(t), 2 * np.pi * k / n) for t, n in RINGS for k in range(n)]
    return np.array(out, np.float32)


def to_cartesian(tp) -> np.ndarray:
    tp = np.asarray(tp, np.float64)
    t, p = tp[..., 0], tp[..., 1]
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)


def half_diff(wi: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit (N, 3) light wi, view wo -> half vector h and difference vector d (both (N, 3)).

    d = R_b(-theta_h) R_n(-phi_h) wi. Anisotropic: phi_h is kept (h is the full half vector),
    so their xy (projected hemisphere, unit disc) are the 2-D plane coordinates."""
    h = torch.nn.functional.normalize(wi + wo, dim=-1)
    ct, st = h[..., 2].clamp(-1, 1), torch.linalg.norm(h[..., :2], dim=-1)
    # cos/sin(phi_h) from h directly (no atan2); phi_h = 0 at the pole
    cp = torch.where(st > 1e-8, h[..., 0] / st.clamp_min(1e-8), torch.ones_like(st))
    sp = torch.where(st > 1e-8, h[..., 1] / st.clamp_min(1e-8), torch.zeros_like(st))
    x = cp * wi[..., 0] + sp * wi[..., 1]          # R_n(-phi_h)
    y = -sp * wi[..., 0] + cp * wi[..., 1]
    z = wi[..., 2]
    d = torch.stack([ct * x - st * z, y, st * x + ct * z], -1)  # R_b(-theta_h)
    return h, d
