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
Settings and their ranges: neumat.btf.synthesis.settings (exponent at most 32: beyond ~93 all
three float32 weights w^exponent underflow to 0). With contrast 1, a point whose three
luminance taps are all 0 has blend weights 0 before Gain3; Gain3's power, floored in every
path (POW_FLOOR = 2^-126 here and in C, 2^-125 in Triton), then makes them 1/3 each, and
without Gain3 (gain 0.5) the features there are 0, in the torch path and the kernels alike.

`__call__` is the torch path: the reference. `Synthesized` queries on the CPU run the same
synthesis inside the fused C query (`btf_triple_plane_hex` in neumat/btf/query_kernel.c,
tests/test_btf_query.py); there its angle is formed in float and its sin/cos are a float
polynomial (within 5.8e-7 of float64's; query_kernel.c sincos_polyf)."""

from __future__ import annotations

import math

import torch

from neumat.btf.neural import fetch
from neumat.btf.synthesis import settings as _settings
from neumat.btf.synthesis.grid import triangle_grid, vertex_hash, vertex_uv

DEFAULTS = _settings.defaults("hextile")
# Gain3's power b^k is floored here as the C kernel's powk floors it (query_kernel.c): no
# matter beside weights of order 1, but where all three blend weights are 0 (contrast 1 and
# three black luminance taps) both paths then give equal weights 1/3, not 0 / 0
POW_FLOOR = 2.0 ** -126


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
    """hextiling.h Gain3: contrast gain on each weight (r > 0.5 sharpens), renormalised. The
    power is floored at POW_FLOOR, as the C kernel's."""
    k = math.log(1 - r) / math.log(0.5)
    s = 2.0 * (x >= 0.5).to(x.dtype)
    m = 2.0 * (1 - s)
    p = torch.exp(k * torch.log(torch.clamp(s + x * m, min=1e-30))).clamp_min(POW_FLOOR)
    res = 0.5 * s + 0.25 * m * p
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
        self.s = _settings.check(self.method, settings)
        self.seed, self.plane_lum = int(seed), _rounded(plane_lum)

    @classmethod
    def build(cls, plane, seed, settings=None, luminance=None):
        if luminance is None:
            raise ValueError("hex-tiling needs the luminance plane of the decoded BTF")
        return cls(seed, _with_luminance(plane, luminance), settings)

    def state(self) -> dict:
        return {"luminance": self.plane_lum[..., -1].contiguous()}

    @classmethod
    def from_state(cls, plane, seed, state, settings=None):
        """ValueError where the stored luminance is not of the plane's (H, W)."""
        if "luminance" not in state:
            raise ValueError("hex-tiling state lacks 'luminance'")
        return cls(seed, _with_luminance(plane, state["luminance"]), settings)

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        s = self.s
        C = self.plane_lum.shape[-1]
        v, w = triangle_grid(u)
        r = vertex_hash(v, self.seed, 3)
        a = (2 * math.pi * r[..., 2] - math.pi) * s["rotation"]
        cen = vertex_uv(v)                                        # (N, 3, 2) float64
        d = u.double()[:, None, :] - cen                          # small: exact local offset
        cs, sn = torch.cos(a), torch.sin(a)
        rot = torch.stack([cs * d[..., 0] - sn * d[..., 1], sn * d[..., 0] + cs * d[..., 1]], -1)
        xy = torch.remainder(rot + torch.remainder(cen, 1.0) + r[..., :2], 1.0)
        xy = xy.float().clamp_(0.0, 1.0 - 2 ** -24)
        taps = fetch(self.plane_lum, xy.reshape(-1, 2), wrap=True).reshape(len(u), 3, C)
        c, lum = taps[..., :-1], taps[..., -1]
        dw = 1 + s["contrast"] * (lum - 1)
        W = dw * _power(w.float(), s["exponent"])
        W = W / W.sum(1, keepdim=True).clamp_min(1e-30)
        if s["gain"] != 0.5:
            W = gain3(W, s["gain"])
        return (W[..., None] * c).sum(1)


def _with_luminance(plane: torch.Tensor, lum: torch.Tensor) -> torch.Tensor:
    """(H, W, C) features and (H, W) luminance in [0, 1] -> (H, W, C + 1)."""
    if plane.dim() != 3 or tuple(lum.shape) != tuple(plane.shape[:2]):
        raise ValueError(f"hex-tiling's luminance plane has shape {tuple(lum.shape)}, but the "
                         f"positional plane (H, W, C) = {tuple(plane.shape)} needs (H, W) = "
                         f"{tuple(plane.shape[:2])}")
    lum = lum.detach().float().to(plane.device)
    if lum.numel() and not bool(((lum >= 0) & (lum <= 1)).all()):  # NaN too
        raise ValueError("hex-tiling's luminance must lie in [0, 1] (hextile.luminance scales "
                         f"it so), got values in [{lum.min().item():g}, {lum.max().item():g}]")
    return torch.cat([plane.detach().float(), lum[..., None]], -1)
