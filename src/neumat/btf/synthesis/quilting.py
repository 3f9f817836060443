"""Image quilting (Efros & Freeman 2001) of a C-channel feature plane: non-dynamic, the
output is generated up front to `scale` x the exemplar and then fetched (and repeats beyond).

Blocks of B texels overlap by B / 6; each new block is chosen at random among the exemplar
positions whose SSD over the already-filled overlap is within `tolerance` x the best, then
pasted along a minimum-error boundary cut (dynamic programming over the overlap's squared
difference). Candidates are all W x H positions of the exemplar treated as a torus (the plane
tiles), so the SSD of every candidate is three FFT correlations. On a torus the verbatim
continuation of the left / upper neighbour's source always matches with zero error, and
quilting would reproduce plain tiling; candidates within B / 2 texels of those continuations
are therefore excluded (Efros & Freeman's exemplars have borders, which break such runs)."""

from __future__ import annotations

import numpy as np
import torch

from neumat.btf.neural import fetch
from neumat.btf.synthesis import settings as _settings

DEFAULTS = _settings.defaults("quilting")


def block_size(exemplar_size: int, block) -> int:
    """`block` <= 1: a fraction of the exemplar's smaller side; > 1: texels. At least 6."""
    b = int(round(block * exemplar_size)) if block <= 1 else int(block)
    return max(6, min(b, exemplar_size))


def _corr(F_E, k, H, W):
    """Circular correlation sum_ij k[i, j] E[(y + i) % H, (x + j) % W] for all (y, x), summed
    over channels; F_E = rfft2 of E (C, H, W), k (C, b, b)."""
    kp = np.zeros((k.shape[0], H, W))
    kp[:, :k.shape[1], :k.shape[2]] = k
    return np.fft.irfft2(F_E * np.conj(np.fft.rfft2(kp)), s=(H, W)).sum(0)


def _min_cut(err: np.ndarray) -> np.ndarray:
    """Minimum-cost top-to-bottom path through err (rows, ov): per row, the column where the
    new block starts (texels left of it keep the old content)."""
    rows, ov = err.shape
    cost = err.copy()
    for i in range(1, rows):
        prev = cost[i - 1]
        left = np.concatenate([[np.inf], prev[:-1]])
        right = np.concatenate([prev[1:], [np.inf]])
        cost[i] += np.minimum(np.minimum(left, prev), right)
    path = np.empty(rows, np.int64)
    path[-1] = int(np.argmin(cost[-1]))
    for i in range(rows - 2, -1, -1):
        j = path[i + 1]
        lo, hi = max(j - 1, 0), min(j + 2, ov)
        path[i] = lo + int(np.argmin(cost[i, lo:hi]))
    return path


def quilt(ex: np.ndarray, out_h: int, out_w: int, block: int, rng: np.random.Generator,
          tolerance: float = 1.1, random_placement: bool = False) -> tuple[np.ndarray, float]:
    """Quilt exemplar ex (H, W, C) into (out_h, out_w, C). random_placement=True picks blocks
    uniformly and pastes them without a cut (the baseline quilting must beat). Returns the
    output and the mean squared difference over all overlaps of the chosen blocks (before
    the cut), per texel and channel."""
    H, W, C = ex.shape
    ov = max(1, block // 6)
    step = block - ov
    ny, nx = -(-max(out_h - ov, 1) // step), -(-max(out_w - ov, 1) // step)
    out = np.zeros((ny * step + ov, nx * step + ov, C), np.float64)
    E = np.transpose(ex, (2, 0, 1)).astype(np.float64)
    F_E, F_E2 = np.fft.rfft2(E), np.fft.rfft2(E * E)
    exw = np.concatenate([ex, ex[:block]], 0)
    exw = np.concatenate([exw, exw[:, :block]], 1).astype(np.float64)   # torus windows
    err_sum, err_n = 0.0, 0
    src = {}
    r = block // 2
    for by in range(ny):
        for bx in range(nx):
            y0, x0 = by * step, bx * step
            mask = np.zeros((block, block), bool)
            if bx:
                mask[:, :ov] = True
            if by:
                mask[:ov, :] = True
            tgt = out[y0:y0 + block, x0:x0 + block]
            if not mask.any():
                py, px = rng.integers(H), rng.integers(W)
            elif random_placement:
                py, px = rng.integers(H), rng.integers(W)
            else:
                m = mask[None].astype(np.float64)
                T = np.transpose(tgt, (2, 0, 1)) * m
                ssd = (_corr(F_E2, np.broadcast_to(m, T.shape), H, W)
                       - 2 * _corr(F_E, T, H, W) + (T * T).sum())
                ssd = np.maximum(ssd, 0)
                for (sy, sx) in ([(src[by, bx - 1][0], src[by, bx - 1][1] + step)] if bx else []) + \
                        ([(src[by - 1, bx][0] + step, src[by - 1, bx][1])] if by else []):
                    ys = np.arange(sy - r + 1, sy + r) % H
                    xs = np.arange(sx - r + 1, sx + r) % W
                    ssd[np.ix_(ys, xs)] = np.inf
                best = ssd.min()
                cand = np.flatnonzero(ssd.reshape(-1) <= best * tolerance + 1e-12 * (1 + best))
                py, px = divmod(int(cand[rng.integers(len(cand))]), W)
            src[by, bx] = (py, px)
            patch = exw[py:py + block, px:px + block]
            if mask.any():
                d = ((patch - tgt) ** 2).sum(-1)
                err_sum += float(d[mask].sum()) / C
                err_n += int(mask.sum())
            keep = np.zeros((block, block), bool)                     # True: old content
            if not random_placement:
                d = ((patch - tgt) ** 2).sum(-1)
                if bx:
                    cut = _min_cut(d[:, :ov])
                    keep[:, :ov] |= np.arange(ov)[None, :] < cut[:, None]
                if by:
                    cut = _min_cut(d[:ov, :].T)
                    keep[:ov, :] |= (np.arange(ov)[:, None] < cut[None, :])
            out[y0:y0 + block, x0:x0 + block] = np.where(keep[..., None], tgt, patch)
    return out[:out_h, :out_w].astype(np.float32), err_sum / max(err_n, 1)


def excess_gradient(img: np.ndarray, ex: np.ndarray) -> float:
    """Mean squared neighbour difference of img over that of the (tiled) exemplar, minus 1:
    seams add energy at block borders; 0 means no more discontinuity than the exemplar has."""
    def g(a, wrap):
        dx = (np.roll(a, -1, 1) - a) if wrap else np.diff(a, axis=1)
        dy = (np.roll(a, -1, 0) - a) if wrap else np.diff(a, axis=0)
        return (np.mean(dx ** 2) + np.mean(dy ** 2)) / 2
    return float(g(img, False) / g(ex, True) - 1)


class Quilting:
    method, dynamic = "quilting", False

    def __init__(self, seed, quilted, settings=None, seam_ssd=float("nan")):
        self.s = _settings.check(self.method, settings)
        self.seed, self.quilted = int(seed), quilted
        self.seam_ssd = seam_ssd

    @classmethod
    def build(cls, plane, seed, settings=None, luminance=None):
        s = _settings.check(cls.method, settings)
        ex = plane.detach().float().numpy()
        H, W, _ = ex.shape
        b = block_size(min(H, W), s["block"])
        q, err = quilt(ex, s["scale"] * H, s["scale"] * W, b, np.random.default_rng(seed),
                       s["tolerance"])
        return cls(seed, torch.from_numpy(q).contiguous(), s, err)

    def state(self) -> dict:
        return {"quilted": self.quilted, "seam_ssd": float(self.seam_ssd)}

    @classmethod
    def from_state(cls, plane, seed, state, settings=None):
        """ValueError where the quilt is not `scale` x the plane (H, W, C) of its settings."""
        s = _settings.check(cls.method, settings)
        if "quilted" not in state:
            raise ValueError("quilting state lacks 'quilted'")
        H, W, C = plane.shape
        want = (s["scale"] * H, s["scale"] * W, C)
        if tuple(state["quilted"].shape) != want:
            raise ValueError(f"quilting state 'quilted' has shape {tuple(state['quilted'].shape)}, "
                             f"but the model's plane (H, W, C) = {(H, W, C)} at scale "
                             f"{s['scale']} needs {want}")
        return cls(seed, state["quilted"], s, state.get("seam_ssd", float("nan")))

    def storage_bytes(self) -> int:
        return self.quilted.numel() * self.quilted.element_size()

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        """The quilt covers u in [0, scale)^2 and tiles beyond."""
        xy = torch.remainder(u.double() / self.s["scale"], 1.0).float().clamp_(0, 1 - 2 ** -24)
        return fetch(self.quilted, xy, wrap=True)
