"""Histogram-preserving blending (Heitz & Neyret 2018; GLSL form of Unity Labs'
procedural-stochastic-texturing) on a C-channel feature plane.

Up front (exemplar only, O(exemplar) storage): decorrelate the channels by a C x C PCA of the
channel covariance, Gaussianise each decorrelated channel by rank (T: rank i of N ->
0.5 + (1/6) sqrt(2) erfinv(2 (i + 0.5) / N - 1), i.e. N(0.5, (1/6)^2)), and tabulate the
inverse T^-1 as a LUT (entry k at G_k = (k + 0.5) / L: U = Phi((G_k - 0.5) / (1/6)),
value = sorted[floor(U N)]).

Per query (pure function of (u, seed)): triangle-grid weights w_i, per-vertex random offsets
h(v_i), three bilinear fetches of the Gaussianised plane, the variance-preserving blend
G = (sum w_i G_i - 0.5) / sqrt(sum w_i^2) + 0.5, the LUT back to the decorrelated values and
the inverse PCA rotation."""

from __future__ import annotations

import math

import torch

from neumat.btf.neural import fetch
from neumat.btf.synthesis import kernel
from neumat.btf.synthesis import settings as _settings
from neumat.btf.synthesis.grid import triangle_grid, vertex_hash, wrap_fetch_coords

SIGMA = 1.0 / 6.0


def decorrelate(x: torch.Tensor):
    """x (M, C) -> mean (C,), orthonormal basis (C, C) (columns = principal axes, by
    decreasing variance); q = (x - mean) @ basis has uncorrelated channels."""
    x = x.double()
    mean = x.mean(0)
    cov = torch.cov((x - mean).T).reshape(x.shape[1], x.shape[1])
    evals, evecs = torch.linalg.eigh(cov)
    order = torch.argsort(evals, descending=True)
    return mean.float(), evecs[:, order].float()


def gaussianise(q: torch.Tensor) -> torch.Tensor:
    """T: per channel, rank i of N -> 0.5 + SIGMA sqrt(2) erfinv(2 (i + 0.5) / N - 1), rounded
    to float16 precision (at most 2^-12 off for values below 1: 0.15 % of SIGMA, a thirty-second
    of the 128-entry LUT's step), so that the CPU kernel reads the plane as float16, half the
    bytes, with the very values of this path."""
    n = q.shape[0]
    ranks = torch.argsort(torch.argsort(q, dim=0, stable=True), dim=0, stable=True).double()
    g = 0.5 + SIGMA * math.sqrt(2) * torch.erfinv(2 * (ranks + 0.5) / n - 1)
    return g.to(torch.float16).float()


def build_lut(q: torch.Tensor, size: int) -> torch.Tensor:
    """T^-1 tabulated: (C, size), entry k = sorted[floor(Phi((G_k - 0.5) / SIGMA) N)]."""
    n = q.shape[0]
    g = (torch.arange(size, dtype=torch.float64) + 0.5) / size
    cdf = 0.5 * (1 + torch.erf((g - 0.5) / SIGMA / math.sqrt(2)))
    idx = torch.clamp((cdf * n).long(), 0, n - 1)
    return torch.sort(q, dim=0).values[idx].T.contiguous().float()


def inverse_lut(g: torch.Tensor, lut: torch.Tensor) -> torch.Tensor:
    """g (N, C) Gaussian values -> (N, C) through the per-channel LUT (C, L), linearly
    interpolated like a filtered 1-D texture fetch (clamped at both ends)."""
    C, L = lut.shape
    x = (g.clamp(0, 1) * L - 0.5).clamp(0, L - 1)
    i0 = x.floor().long().clamp(max=L - 2) if L > 1 else x.long()
    t = x - i0
    base = torch.arange(C, device=g.device) * L
    flat = lut.reshape(-1)
    a = flat[i0 + base]
    b = flat[(i0 + 1).clamp(max=L - 1) + base]
    return a + t * (b - a)


def blend(g: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Variance-preserving blend of Gaussian taps g (N, K, C) with weights w (N, K)."""
    num = torch.einsum("nkc,nk->nc", g - 0.5, w)
    return num / torch.sqrt((w * w).sum(1, keepdim=True)) + 0.5


class HPB:
    method, dynamic = "hpb", True

    def __init__(self, seed, mean, basis, gauss, lut):
        self.seed, self.mean, self.basis, self.gauss, self.lut = int(seed), mean, basis, gauss, lut

    @classmethod
    def build(cls, plane, seed, settings=None, luminance=None):
        s = _settings.check(cls.method, settings)
        H, W, C = plane.shape
        x = plane.detach().float().reshape(-1, C)
        mean, basis = decorrelate(x)
        q = (x - mean) @ basis
        lut = build_lut(q, s["lut_size"])
        return cls(seed, mean, basis, gaussianise(q).reshape(H, W, C).contiguous(), lut)

    def state(self) -> dict:
        return {"mean": self.mean, "basis": self.basis, "gauss": self.gauss, "lut": self.lut}

    @classmethod
    def from_state(cls, plane, seed, state, settings=None):
        """The synthesis of `state` (of `build` on a plane of plane's shape, with `settings`);
        ValueError where the state does not fit the plane or the settings."""
        s = _settings.check(cls.method, settings)
        missing = sorted({"mean", "basis", "gauss", "lut"} - set(state))
        if missing:
            raise ValueError(f"HPB state lacks {missing}")
        H, W, C = plane.shape
        want = {"gauss": (H, W, C), "mean": (C,), "basis": (C, C), "lut": (C, s["lut_size"])}
        for k, shape in want.items():
            if tuple(state[k].shape) != shape:
                raise ValueError(f"HPB state {k!r} has shape {tuple(state[k].shape)}, but the "
                                 f"model's plane (H, W, C) = {(H, W, C)} and lut_size "
                                 f"{s['lut_size']} need {shape}")
        return cls(seed, state["mean"], state["basis"], state["gauss"], state["lut"])

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        """Features (N, C) at u: the fused C kernel where it is built, else `torch_features`."""
        out = kernel.hpb_features(u, self)
        return self.torch_features(u) if out is None else out

    def torch_features(self, u: torch.Tensor) -> torch.Tensor:
        """The torch path: a pure function of (u, seed), to the bit, whatever the batch (no
        BLAS: its kernels, and so its rounding, depend on the number of rows)."""
        C = self.gauss.shape[-1]
        v, w = triangle_grid(u)
        xy = wrap_fetch_coords(u, vertex_hash(v, self.seed))
        taps = fetch(self.gauss, xy.reshape(-1, 2), wrap=True).reshape(len(u), 3, C)
        q = inverse_lut(blend(taps, w.float()), self.lut)
        # mean + basis q, summed over c in order, elementwise (as hpb_features in C)
        out = self.mean + q[:, :1] * self.basis[:, 0]
        for c in range(1, C):
            out = out + q[:, c:c + 1] * self.basis[:, c]
        return out
