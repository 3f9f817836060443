"""Pairwise distances between two sets of materials, as whole matrices in one go.

* BRDF-L1 (M3ashy eq. 6): mean over a fixed sample of valid MERL bins and the 3 channels of
  |f - f'|, physical BRDF values at bin centres - neural fields are evaluated there, tables read
  there, so fields and tables are compared alike (`brdf_sample`, `field_values`, `table_values`).
* RMSE, NegPSNR (= -PSNR, peak 1), NegSSIM (= -SSIM) between metric renders, as sRGB-encoded
  float images in [0, 1] (`neumat.render.sphere.to_srgb`), over the whole image.

SSIM is a vectorised torch twin of `skimage.metrics.structural_similarity(a, b,
channel_axis=-1, data_range=1)` (7x7 uniform window, K1 = 0.01, K2 = 0.03, sample covariance,
mean over the window-valid region and the channels); tests check it against scikit-image.
"""

from __future__ import annotations

import ctypes
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from pathlib import Path

import numpy as np
import torch

from neumat import cbuild, nbrdf
from neumat.io import merl

PSNR_FLOOR_MSE = 1e-10  # identical images: NegPSNR = -100 dB instead of -inf
SSIM_WIN, SSIM_K1, SSIM_K2 = 7, 0.01, 0.03
_PAIR_FLOATS = 1 << 24  # bounds the per-chunk memory of the pairwise loops


# ----------------------------------------------------------------------------- BRDF-L1


def brdf_sample(n: int | str, seed: int) -> np.ndarray:
    """Flat MERL bin indices: all valid bins ("all") or a fixed random subset of n of them."""
    valid = np.flatnonzero(merl.valid_mask())
    if n == "all" or n >= len(valid):
        return valid
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"BRDF-L1 sample size must be a positive integer or 'all', got {n!r}")
    return np.sort(np.random.default_rng(seed).choice(valid, n, replace=False))


def field_values(weights, bins, activation: str = "relu", chunk: int | None = None) -> torch.Tensor:
    """Neural fields (B, 675) at the centres of `bins` -> (B, len(bins) * 3) float32, `chunk`
    materials a pass (default `nbrdf.materials_per_pass`: the same values as 64 a pass)."""
    th, td, pd = (a[bins] for a in merl.grid_angles())
    x = torch.as_tensor(merl.half_diff_cartesian(th, td, pd), dtype=torch.float32)
    w = torch.as_tensor(weights, dtype=torch.float32)
    chunk = chunk or nbrdf.materials_per_pass(len(x))
    out = torch.empty(len(w), 3 * len(x))
    with torch.no_grad():
        for s in range(0, len(w), chunk):
            out[s:s + chunk] = nbrdf.forward(w[s:s + chunk], x, activation).reshape(len(w[s:s + chunk]), -1)
    return out


def table_values(tables, bins) -> torch.Tensor:
    """MERL tables (B, 3, 90, 90, 180) at `bins` -> (B, len(bins) * 3) float32, same layout
    as `field_values` (bin-major, channel-minor); negative (invalid) entries count as 0."""
    t = torch.as_tensor(tables).reshape(len(tables), 3, merl.N_BINS)
    return t[:, :, torch.as_tensor(bins)].clamp_min(0).transpose(1, 2).reshape(len(t), -1).float()


_P, _L, _I, _F = ctypes.c_void_p, ctypes.c_long, ctypes.c_int, ctypes.c_float
# kernel source -> (what runs without it, its entry point, argtypes, restype)
_KERNELS = {
    "l1_kernel.c": ("BRDF-L1 uses torch.cdist", "l1_pairwise", [_L, _L, _L, _P, _P, _P], None),
    "ssim_kernel.c": ("pairwise SSIM uses torch", "ssim_pairs",
                      [_L, _L, _I, _I, _I, *[_P] * 10, _F, _F, _F, _I, _I, _I, _P], _I),
}


@cache
def _library(source: str, march: str = "native"):
    """The C kernel `source` (beside this file) built for `march` and typed, or None."""
    fallback, name, argtypes, restype = _KERNELS[source]
    path = cbuild.build(Path(__file__).with_name(source), march, fallback)
    if path is None:
        return None
    lib = ctypes.CDLL(str(path))
    getattr(lib, name).argtypes, getattr(lib, name).restype = argtypes, restype
    return lib


def _l1_library(march: str = "native"):
    return _library("l1_kernel.c", march)


def _ssim_library(march: str = "native"):
    return _library("ssim_kernel.c", march)


def _in_threads(part, workers: int) -> list:
    """part(0) ... part(workers - 1) on a thread each: the kernels' ctypes calls drop the GIL,
    so the threads run in parallel."""
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(part, range(workers)))


def l1_sums(a: torch.Tensor, b: torch.Tensor, threads: int | None = None,
            march: str = "native"):
    """sum_d |a_i - b_j| (n, m) float64 by the C kernel (`l1_kernel.c` built for `march`, rows
    of a split over `threads`, default torch's), or None where it is not built."""
    lib = _l1_library(march)
    if lib is None:
        return None
    a, b = a.flatten(1).float().contiguous(), b.flatten(1).float().contiguous()
    n, m, d = a.shape[0], b.shape[0], a.shape[1]
    out = torch.empty(n, m, dtype=torch.float64)
    threads = max(1, min(threads or torch.get_num_threads(), n))
    edges = [n * k // threads for k in range(threads + 1)]

    def part(k):
        s, e = edges[k], edges[k + 1]
        lib.l1_pairwise(e - s, m, d, a.data_ptr() + 4 * s * d, b.data_ptr(),
                        out.data_ptr() + 8 * s * m)

    _in_threads(part, threads)
    return out


def pairwise_l1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference between every row of a (n, D) and of b (m, D) -> (n, m),
    float64: the C kernel (float32 differences, float64 sums), else torch.cdist in float64."""
    out = l1_sums(a, b)
    if out is None:
        out = torch.cdist(a.flatten(1).double(), b.flatten(1).double(), p=1)
    return out / a.flatten(1).shape[1]


# ----------------------------------------------------------------------------- image distances


def _images(x) -> torch.Tensor:
    x = torch.as_tensor(x)
    if x.dim() != 4 or x.shape[-1] not in (1, 3):
        raise ValueError(f"images must have shape (N, H, W, C), got {tuple(x.shape)}")
    return x.double()


def pairwise_mse(x, y=None) -> torch.Tensor:
    """Mean squared error between every image of x (n, H, W, C) and y (m, H, W, C) -> (n, m),
    as |x|^2 + |y|^2 - 2 x.y in float64 (one matrix product). y=None: x against itself."""
    x = _images(x).flatten(1)
    y = x if y is None else _images(y).flatten(1)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"image sets differ in size: {x.shape[1]} vs {y.shape[1]} values")
    d = (x * x).sum(1)[:, None] + (y * y).sum(1)[None] - 2 * x @ y.T
    return d.clamp_min(0) / x.shape[1]


def pairwise_rmse(x, y=None) -> torch.Tensor:
    return pairwise_mse(x, y).sqrt()


def pairwise_negpsnr(x, y=None) -> torch.Tensor:
    """-PSNR with peak 1: 10 log10(MSE), MSE floored at PSNR_FLOOR_MSE."""
    return 10 * torch.log10(pairwise_mse(x, y).clamp_min(PSNR_FLOOR_MSE))


def _band(n: int, dtype) -> torch.Tensor:
    """(n - 6, n) matrix averaging every run of SSIM_WIN consecutive entries."""
    i = torch.arange(n - SSIM_WIN + 1)[:, None]
    j = torch.arange(n)[None]
    return ((j >= i) & (j < i + SSIM_WIN)).to(dtype) / SSIM_WIN


def _box(x: torch.Tensor) -> torch.Tensor:
    """Mean over every valid 7x7 window of (..., H, W) -> (..., H-6, W-6), as two matrix
    products with band matrices (several times faster than avg_pool2d on CPU)."""
    return _band(x.shape[-2], x.dtype) @ x @ _band(x.shape[-1], x.dtype).T


def pairwise_ssim(x, y=None) -> torch.Tensor:
    """SSIM of every pair (scikit-image defaults, data range 1) -> (n, m); float32 inside,
    within 1e-5 of scikit-image's float64. y=None: x against itself, computing each
    unordered pair once."""
    sym = y is None
    x = _images(x).float().permute(0, 3, 1, 2).contiguous()
    y = x if sym else _images(y).float().permute(0, 3, 1, 2).contiguous()
    if x.shape[1:] != y.shape[1:]:
        raise ValueError(f"image sets differ in shape: {tuple(x.shape[1:])} vs {tuple(y.shape[1:])}")
    if min(x.shape[2:]) < SSIM_WIN:
        raise ValueError(f"SSIM needs images of at least {SSIM_WIN}x{SSIM_WIN} pixels")
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2
    k = SSIM_WIN ** 2 / (SSIM_WIN ** 2 - 1)  # sample covariance, as scikit-image
    # per-image terms: SSIM = (2 ux uy + c1)(2 vxy + c2) / ((ux^2 + uy^2 + c1)(vx + vy + c2))
    ux, uy = _box(x), _box(y)
    qx, qy = ux * ux, uy * uy + c1
    rx, ry = k * (_box(x * x) - qx), k * (_box(y * y) - uy * uy) + c2
    out = _ssim_kernel(x, y, ux, qx, rx, uy, qy, ry, c1, c2, k, sym)
    if out is not None:
        return out
    out = torch.empty(len(x), len(y), dtype=torch.float64)
    step = max(1, _PAIR_FLOATS // (len(y) * x[0].numel()))
    for s in range(0, len(x), step):
        rows = slice(s, s + step)
        cols = slice(s if sym else 0, len(y))  # symmetric: upper triangle incl. diagonal
        p = _box(x[rows, None] * y[None, cols])
        uu = ux[rows, None] * uy[None, cols]
        p.sub_(uu).mul_(2 * k).add_(c2).mul_(uu.mul_(2).add_(c1))
        den = (qx[rows, None] + qy[None, cols]).mul_(rx[rows, None] + ry[None, cols])
        out[rows, cols] = p.div_(den).mean((2, 3, 4)).double()
    if sym:
        out = torch.triu(out) + torch.triu(out, 1).T
    return out


def _ssim_kernel(x, y, ux, qx, rx, uy, qy, ry, c1, c2, k, sym, threads=None,
                 march: str = "native"):
    """pairwise_ssim's pairs by `ssim_kernel.c` (rows split over `threads`, default torch's),
    or None where it is not built or the images are wider than it holds."""
    lib = _ssim_library(march)
    if lib is None or x.shape[-1] > 1024:
        return None
    shifts = x.mean((2, 3)), y.mean((2, 3))  # centred products: small covariances keep digits
    t = [a.float().contiguous() for a in (x, y, *shifts, ux, qx, rx, uy, qy, ry)]
    n, m, (C, H, W) = len(x), len(y), x.shape[1:]
    out = torch.zeros(n, m, dtype=torch.float64)
    workers = max(1, min(threads or torch.get_num_threads(), n))

    def part(w):
        return lib.ssim_pairs(n, m, C, H, W, *(a.data_ptr() for a in t), c1, c2, k, int(sym),
                              w, workers, out.data_ptr())

    if any(_in_threads(part, workers)):
        return None
    return torch.triu(out) + torch.triu(out, 1).T if sym else out


def pairwise_negssim(x, y=None) -> torch.Tensor:
    return -pairwise_ssim(x, y)


IMAGE_DISTANCES = {"RMSE": pairwise_rmse, "NegPSNR": pairwise_negpsnr, "NegSSIM": pairwise_negssim}
DISTANCES = ("BRDF-L1", *IMAGE_DISTANCES)
