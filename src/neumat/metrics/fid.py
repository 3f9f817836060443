"""Fréchet Inception Distance (Heusel et al. 2017) on renders.

FID = |mu1 - mu2|^2 + tr(S1 + S2 - 2 (S1 S2)^(1/2)), the Fréchet distance of two Gaussians
fitted to Inception pool3 features. `frechet_distance` takes the Gaussians and uses the matrix
square root as pytorch-fid does (scipy sqrtm, with a small diagonal offset when the product is
singular, and an error when the root has a sizeable imaginary part). `fid_from_features` gets
the same value from the features without any D x D matrix function: with centred features
A1 (n1 x D), A2 (n2 x D), S_i = A_i^T A_i / (n_i - 1), the non-zero eigenvalues of S1 S2 are
those of M M^T / ((n1 - 1)(n2 - 1)) with M = A1 A2^T (n1 x n2), so tr (S1 S2)^(1/2) = sum of
the singular values of M / sqrt((n1 - 1)(n2 - 1)), for any n1, n2 and D. Where a set has more
images than dimensions (n > D, the 64-d features), A_i is first replaced by R_i of its QR
decomposition (D x D, A_i = Q_i R_i, Q_i with orthonormal columns): A1 A2^T = Q1 R1 R2^T Q2^T
has the singular values of R1 R2^T. Real and exact throughout (no imaginary part to drop),
and cheap: sqrtm of a 2048 x 2048 matrix costs minutes on a loaded 2-core machine, the SVD
of a 120 x 120 one milliseconds.
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
    if np.iscomplexobj(covmean):  # as pytorch-fid: a sizeable imaginary part is an error
        if not np.allclose(np.diagonal(covmean).imag, 0, atol=1e-3):
            raise ValueError(f"Fréchet distance: the square root of S1 S2 has an imaginary "
                             f"component up to {np.abs(covmean.imag).max():.3g} (a covariance "
                             f"not positive semi-definite, or too few samples); use "
                             f"fid_from_features on the features instead")
        covmean = covmean.real
    diff = mu1 - mu2
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


def gaussian(features: np.ndarray):
    """Mean and (unbiased) covariance of (N, D) features."""
    f = np.asarray(features, dtype=np.float64)
    return f.mean(0), np.cov(f, rowvar=False)


@torch.no_grad()
def features(model, images, batch: int | None = None, device="cpu") -> dict[int, np.ndarray]:
    """sRGB images (N, H, W, 3) in [0, 1] -> {64: (N, 64), 2048: (N, 2048)} features
    (`FIDInception.forward_dims`), `batch` images at a time (default: 4 on the CPU, 16
    elsewhere).

    4 on the CPU: a batch's largest activation (32 x 149 x 149 floats an image) then stays
    below glibc's 32 MB mmap ceiling, so freed activations are reused from the heap rather than
    mapped afresh and page-faulted in for every layer. The tiny run's `metrics` jobs for `ours`
    and `pca_a` against batches of 16: 2.9 -> 1.7 s of system time, 10.4 -> 9.7 s wall,
    830 -> 600 MB peak RSS, the same bytes out on 2 threads (AMD EPYC AVX-512, 2 cores; with
    torch and oneDNN held to AVX2, CPU time level and RSS 830 -> 630 MB; issue #20's note). On one thread the 2048-d features move by up to 5e-6 (convolutions summed in
    another order), as they do between thread counts."""
    if batch is None:
        batch = 4 if torch.device(device).type == "cpu" else 16
    # (N, H, W, 3) permuted is channels-last in memory, the layout for_inference's weights take
    x = torch.as_tensor(images, dtype=torch.float32).permute(0, 3, 1, 2)
    parts = [model.forward_dims(x[s:s + batch].to(device)) for s in range(0, len(x), batch)]
    return {d: torch.cat([p[d].cpu() for p in parts]).double().numpy() for d in parts[0]}


def fid_from_features(fa: np.ndarray, fb: np.ndarray) -> float:
    """FID of two feature sets (N, D) (see the module docstring for the trace identity)."""
    fa, fb = np.asarray(fa, dtype=np.float64), np.asarray(fb, dtype=np.float64)
    if min(len(fa), len(fb)) < 2:
        raise ValueError("FID needs at least 2 images per set")
    if fa.shape[1] != fb.shape[1]:
        raise ValueError(f"feature sets differ in dimension: {fa.shape[1]} vs {fb.shape[1]}")
    a, b = fa - fa.mean(0), fb - fb.mean(0)
    ca, cb = len(fa) - 1, len(fb) - 1
    diff = fa.mean(0) - fb.mean(0)
    ra, rb = (np.linalg.qr(x, mode="r") if len(x) > x.shape[1] else x for x in (a, b))
    tr_sqrt = np.linalg.svd(ra @ rb.T, compute_uv=False).sum() / np.sqrt(ca * cb)
    return float(diff @ diff + (a * a).sum() / ca + (b * b).sum() / cb - 2 * tr_sqrt)


def fid(model, images_a, images_b, dims: int = 2048, device="cpu") -> float:
    """FID between two sets of sRGB images on the `dims`-d features (2048 or 64)."""
    return fid_from_features(features(model, images_a, device=device)[dims],
                             features(model, images_b, device=device)[dims])
