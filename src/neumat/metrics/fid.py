"""Fréchet Inception Distance (Heusel et al. 2017) on renders.

FID = |mu1 - mu2|^2 + tr(S1 + S2 - 2 (S1 S2)^(1/2)), the Fréchet distance of two Gaussians
fitted to Inception pool3 features; the matrix square root as in pytorch-fid (scipy sqrtm,
with a small diagonal offset when the product is singular).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import linalg


def frechet_distance(mu1, sigma1, mu2, sigma2, eps: float = 1e-6) -> float:
    mu1, mu2 = np.atleast_1d(mu1).astype(np.float64), np.atleast_1d(mu2).astype(np.float64)
    s1, s2 = np.atleast_2d(sigma1).astype(np.float64), np.atleast_2d(sigma2).astype(np.float64)
    if mu1.shape != mu2.shape or s1.shape != s2.shape:
        raise ValueError(f"Gaussians differ in dimension: {mu1.shape} vs {mu2.shape}")
    covmean = linalg.sqrtm(s1 @ s2)
    if not np.isfinite(covmean).all():  # singular product: regularise
        off = np.eye(len(s1)) * eps
        covmean = linalg.sqrtm((s1 + off) @ (s2 + off))
    covmean = covmean.real
    diff = mu1 - mu2
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


def gaussian(features: np.ndarray):
    """Mean and (unbiased) covariance of (N, D) features."""
    f = np.asarray(features, dtype=np.float64)
    return f.mean(0), np.cov(f, rowvar=False)


@torch.no_grad()
def features(model, images, batch: int = 16, device="cpu") -> dict[int, np.ndarray]:
    """sRGB images (N, H, W, 3) in [0, 1] -> {64: (N, 64), 2048: (N, 2048)} features
    (`FIDInception.forward_dims`)."""
    x = torch.as_tensor(images, dtype=torch.float32).permute(0, 3, 1, 2)
    parts = [model.forward_dims(x[s:s + batch].to(device)) for s in range(0, len(x), batch)]
    return {d: torch.cat([p[d].cpu() for p in parts]).double().numpy() for d in parts[0]}


def fid_from_features(fa: np.ndarray, fb: np.ndarray) -> float:
    if min(len(fa), len(fb)) < 2:
        raise ValueError("FID needs at least 2 images per set")
    return frechet_distance(*gaussian(fa), *gaussian(fb))


def fid(model, images_a, images_b, dims: int = 2048, device="cpu") -> float:
    """FID between two sets of sRGB images on the `dims`-d features (2048 or 64)."""
    return fid_from_features(features(model, images_a, device=device)[dims],
                             features(model, images_b, device=device)[dims])
