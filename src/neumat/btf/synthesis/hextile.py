"""Hex-tiling (Mikkelsen 2022, JCGT 11(2); github mmikk/hextile-demo, hextiling.h
`hex2colTex`) on a C-channel feature plane.

Same triangle grid and per-vertex random offsets as HPB; each vertex's patch is also rotated
about the vertex centre. The blend is luminance-weighted and contrast-sharpened:
W_i = Dw_i w_i^7 normalised, Dw_i = lerp(1, luminance(c_i), 0.6), then `Gain3` with r = 0.7,
output sum W_i c_i. Deviations, both forced by the setting: (1) the per-tile angle comes from
the integer vertex hash instead of |vx vy| + |vx + vy| + pi (that product of two ~3e5
vertices is not representable in the shader's float32 at u = 1e5); (2) feature planes have no
colour, so `luminance` is the decoded BTF's luminance at the texel, head-on light and view,
scaled to [0, 1] (`luminance` below), stored as one extra channel fetched with the taps.
The features are rounded to float16 (`_rounded`), as HPB's Gaussianised plane is: the CPU kernel
then reads half the bytes per tap, and the torch, Triton and C paths read the same values.

`__call__` is the torch path: the reference. `Synthesized` queries on the CPU run the same
synthesis inside the fused C query (`btf_triple_plane_hex` in neumat/btf/query_kernel.c,
tests/test_btf_query.py); there its angle is formed in float and its sin/cos are a float
polynomial (within 5.8e-7 of float64's; query_kernel.c sincos_polyf)."""

from __future__ import annotations

import math

import torch

from neumat.btf.neural import fetch
from neumat.btf.synthesis.grid import triangle_grid, vertex_hash, vertex_uv

DEFAULTS = {"rotation": 1.0, "contrast": 0.6, "exponent": 7.0, "gain": 0.7}


@torch.no_grad()
def luminance(model) -> torch.Tensor:
    """(H, W) Rec. 601 luminance of the model at its texel centres, wi = wo = normal, / max."""
    H, W, _ = model.f_u.shape
    dev = model.f_u.device  # a model on a GPU builds there
    n = torch.tensor([[0.0, 0.0, 1.0]], device=dev).expand(H * W, 3)
    rgb = torch.relu(torch.expm1(model.decode(model.f_u.reshape(-1, model.f_u.shape[-1]), n, n)))
    lum = rgb @ torch.tensor([0.299, 0.587, 0.114], device=dev)
    return (lum / lum.max().clamp_min(1e-12)).reshape(H, W)


def gain3(x: torch.Tensor, r: float) -> torch.Tensor:
    """hextiling.h Gain3: contrast gain on each weight (r > 0.5 sharpens), renormalised."""
    k = math.log(1 - r) / math.log(0.5)
    s = 2.0 * (x >= 0.5).to(x.dtype)
    m = 2.0 * (1 - s)
    res = 0.5 * s + 0.25 * m * torch.exp(k * torch.log(torch.clamp(s + x * m, min=1e-30)))
    return res / res.sum(-1, keepdim=True)


def _power(x: torch.Tensor, e: float) -> torch.Tensor:
    """x ** e; integer e by repeated multiplication (torch's SIMD and scalar pow differ in the
    last ulp, which would make a query's value depend on its position in the batch)."""
    if float(e).is_integer() and 0 <= e <= 16:
        out = torch.ones_like(x)
        for _ in range(int(e)):
            out = out * x
        return out
    return x ** e


def _rounded(plane_lum: torch.Tensor) -> torch.Tensor:
    """(H, W, C + 1) float32 with the C features rounded to float16 (at most 2^-11 relative
    off; 2^-25 absolute below 2^-14), the luminance kept: the C kernel stores the features
    exactly in float16, half the bytes of its random taps (its overhead before and after:
    struct hpb in neumat/btf/query_kernel.c)."""
    pl = plane_lum.detach().float().clone()
    big = pl[..., :-1].abs().max().item() if pl.numel() else 0.0
    if not big <= torch.finfo(torch.float16).max:  # NaN too
        raise ValueError(f"hex-tiling stores the positional plane in float16, but its features "
                         f"reach {big:g} (float16 ends at 65504): rescale f_U or use hpb")
    pl[..., :-1] = pl[..., :-1].to(torch.float16).float()
    return pl.contiguous()


class HexTile:
    method, dynamic = "hextile", True

    def __init__(self, seed, plane_lum, settings=None):
        self.seed, self.plane_lum = int(seed), _rounded(plane_lum)
        self.s = {**DEFAULTS, **(settings or {})}

    @classmethod
    def build(cls, plane, seed, settings=None, luminance=None):
        if luminance is None:
            raise ValueError("hex-tiling needs the luminance plane of the decoded BTF")
        return cls(seed, torch.cat([plane.detach().float(), luminance.float()[..., None]], -1),
                   settings)

    def state(self) -> dict:
        return {"luminance": self.plane_lum[..., -1].contiguous()}

    @classmethod
    def from_state(cls, plane, seed, state, settings=None):
        return cls(seed, torch.cat([plane, state["luminance"][..., None]], -1), settings)

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        s = self.s
        v, w = triangle_grid(u)
        r = vertex_hash(v, self.seed, 3)
        a = (2 * math.pi * r[..., 2] - math.pi) * s["rotation"]
        cen = vertex_uv(v)                                        # (N, 3, 2) float64
        d = u.double()[:, None, :] - cen                          # small: exact local offset
        cs, sn = torch.cos(a), torch.sin(a)
        rot = torch.stack([cs * d[..., 0] - sn * d[..., 1], sn * d[..., 0] + cs * d[..., 1]], -1)
        xy = torch.remainder(rot + torch.remainder(cen, 1.0) + r[..., :2], 1.0)
        xy = xy.float().clamp_(0.0, 1.0 - 2 ** -24)
        taps = fetch(self.plane_lum, xy.reshape(-1, 2), wrap=True).reshape(len(u), 3, -1)
        c, lum = taps[..., :-1], taps[..., -1]
        dw = 1 + s["contrast"] * (lum - 1)
        W = dw * _power(w.float(), s["exponent"])
        W = W / W.sum(1, keepdim=True).clamp_min(1e-30)
        if s["gain"] != 0.5:
            W = gain3(W, s["gain"])
        return (W[..., None] * c).sum(1)
