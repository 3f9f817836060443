"""Hex-tiling (Mikkelsen 2022, JCGT 11(2); github mmikk/hextile-demo, hextiling.h
`hex2colTex`) on a C-channel feature plane.

Same triangle grid and per-vertex random offsets as HPB; each vertex's patch is also rotated
about the vertex centre. The blend is luminance-weighted and contrast-sharpened:
W_i = Dw_i w_i^7 normalised, Dw_i = lerp(1, luminance(c_i), 0.6), then `Gain3` with r = 0.7,
output sum W_i c_i. Deviations, both forced by the setting: (1) the per-tile angle comes from
the integer vertex hash instead of |vx vy| + |vx + vy| + pi (that product of two ~3e5
vertices is not representable in the shader's float32 at u = 1e5); (2) feature planes have no
colour, so `luminance(c)` is a linear function of the fetched features, clamped to [0, 1], as
the shader's Rec. 601 luminance is linear in the fetched colour: its C + 1 coefficients
(`lum_weights`) are the least-squares fit (`fit_luminance`) of the decoded BTF's luminance at
each texel, head-on light and view, scaled to [0, 1] (`luminance`). Linear in the features,
the luminance of a bilinear tap is the tap of the texels' luminances (before the clamp), and the
CPU kernel forms it from the features it fetches anyway: hex-tiling's texels are 16 bytes, as
HPB's, with no luminance taps (figures: struct hpb in neumat/btf/query_kernel.c). The fit's R^2
is kept in the state, logged by the btf_synthesize job and given in report section 61 (the tiny
run's synthetic wood: 0.681 for its Triple Plane, 0.993 for its NeuMIP).
The features are rounded to float16 (`_rounded`), as HPB's Gaussianised plane is: the CPU kernel
then reads half the bytes per tap, and the torch, Triton and C paths read the same values.
Settings and their ranges: neumat.btf.synthesis.settings (exponent at most 32: beyond ~93 all
three float32 weights w^exponent underflow to 0). With contrast 1, a point whose luminance
(after the clamp) is 0 at all three taps has blend weights 0 before Gain3; Gain3's power, floored
in every path (POW_FLOOR = 2^-126 here and in C, 2^-125 in Triton), then makes them 1/3 each, and
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
# luminance 0 at all three taps) both paths then give equal weights 1/3, not 0 / 0
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


def fit_luminance(plane: torch.Tensor, lum: torch.Tensor) -> tuple[torch.Tensor, float]:
    """The (C + 1,) float32 coefficients (a, b) of the least-squares fit a . f + b of the
    luminance (H, W) in [0, 1] from the features f (H, W, C), in float64, and its R^2 (1 where
    the luminance is constant and fitted exactly). ValueError on shapes that do not match or a
    luminance outside [0, 1] (NaN too)."""
    if plane.dim() != 3 or tuple(lum.shape) != tuple(plane.shape[:2]):
        raise ValueError(f"hex-tiling's luminance plane has shape {tuple(lum.shape)}, but the "
                         f"positional plane (H, W, C) = {tuple(plane.shape)} needs (H, W) = "
                         f"{tuple(plane.shape[:2])}")
    y = lum.detach().double().reshape(-1).cpu()
    if y.numel() and not bool(((y >= 0) & (y <= 1)).all()):  # NaN too
        raise ValueError("hex-tiling's luminance must lie in [0, 1] (hextile.luminance scales "
                         f"it so), got values in [{y.min().item():g}, {y.max().item():g}]")
    f = plane.detach().double().reshape(-1, plane.shape[-1]).cpu()
    A = torch.cat([f, torch.ones(len(f), 1, dtype=torch.float64)], 1)
    coef = torch.linalg.lstsq(A, y[:, None], driver="gelsd").solution[:, 0]
    ss = float(((y - y.mean()) ** 2).sum())
    r2 = 1.0 - float(((A @ coef - y) ** 2).sum()) / ss if ss > 0 else 1.0
    return coef.float(), r2


def _checked_weights(lum_weights: torch.Tensor, C: int) -> torch.Tensor:
    w = torch.as_tensor(lum_weights).detach().float().cpu()
    if tuple(w.shape) != (C + 1,):
        raise ValueError(f"hex-tiling's luminance weights have shape {tuple(w.shape)}, but a "
                         f"plane of {C} channels needs ({C + 1},): one per channel and the offset")
    if not bool(torch.isfinite(w).all()):
        raise ValueError("hex-tiling's luminance weights are not all finite")
    return w.contiguous()


def _rounded(plane: torch.Tensor) -> torch.Tensor:
    """(H, W, C) float32 rounded to float16 values (at most 2^-11 relative off; 2^-25 absolute
    below 2^-14): the C kernel stores the features exactly in float16, half the bytes of its
    random taps (its overhead before and after: struct hpb in neumat/btf/query_kernel.c)."""
    pl = plane.detach().float()
    big = pl.abs().max().item() if pl.numel() else 0.0
    if not big <= torch.finfo(torch.float16).max:  # NaN too
        raise ValueError(f"hex-tiling stores the positional plane in float16, but its features "
                         f"reach {big:g} (float16 ends at 65504): rescale f_U or use hpb")
    return pl.to(torch.float16).float().contiguous()


class HexTile:
    method, dynamic = "hextile", True

    def __init__(self, seed, plane, lum_weights, settings=None, lum_r2=None):
        self.s = _settings.check(self.method, settings)
        self.seed, self.plane = int(seed), _rounded(plane)
        self.lum_weights = _checked_weights(lum_weights, self.plane.shape[-1])
        self.lum_r2 = None if lum_r2 is None else float(lum_r2)  # of the fit, for the report

    @classmethod
    def build(cls, plane, seed, settings=None, luminance=None):
        if luminance is None:
            raise ValueError("hex-tiling needs the luminance plane of the decoded BTF")
        # the constructor checks the settings and rounds the plane (once), then the fit
        out = cls(seed, plane, torch.zeros(plane.shape[-1] + 1), settings)
        out.lum_weights, out.lum_r2 = fit_luminance(out.plane, luminance)
        return out

    def state(self) -> dict:
        """The luminance's coefficients, the shape of the plane they were fitted to, and the
        fit's R^2."""
        return {"lum_weights": self.lum_weights.clone(), "plane_shape": list(self.plane.shape),
                "lum_r2": self.lum_r2}

    @classmethod
    def from_state(cls, plane, seed, state, settings=None):
        """ValueError where the state lacks the luminance weights or was fitted to a plane of
        another shape."""
        missing = sorted({"lum_weights", "plane_shape"} - set(state))
        if missing:
            hint = (" (a state of an older neumat, which kept a luminance per texel: rerun "
                    "its jobs, e.g. snakemake report --cores 2 --forcerun btf_synthesize)"
                    if "luminance" in state else "")
            raise ValueError(f"hex-tiling state lacks {missing}{hint}")
        if list(state["plane_shape"]) != list(plane.shape):
            raise ValueError(f"hex-tiling state was fitted to a plane (H, W, C) = "
                             f"{tuple(state['plane_shape'])}, not {tuple(plane.shape)}")
        return cls(seed, plane, state["lum_weights"], settings, state.get("lum_r2"))

    def luminance_of(self, c: torch.Tensor) -> torch.Tensor:
        """luminance(c) of features c (..., C): a . c + b, clamped to [0, 1]."""
        a, b = self.lum_weights[:-1].to(c.device), self.lum_weights[-1].to(c.device)
        return ((c * a).sum(-1) + b).clamp(0.0, 1.0)

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        s = self.s
        C = self.plane.shape[-1]
        v, w = triangle_grid(u)
        r = vertex_hash(v, self.seed, 3)
        a = (2 * math.pi * r[..., 2] - math.pi) * s["rotation"]
        cen = vertex_uv(v)                                        # (N, 3, 2) float64
        d = u.double()[:, None, :] - cen                          # small: exact local offset
        cs, sn = torch.cos(a), torch.sin(a)
        rot = torch.stack([cs * d[..., 0] - sn * d[..., 1], sn * d[..., 0] + cs * d[..., 1]], -1)
        xy = torch.remainder(rot + torch.remainder(cen, 1.0) + r[..., :2], 1.0)
        xy = xy.float().clamp_(0.0, 1.0 - 2 ** -24)
        c = fetch(self.plane, xy.reshape(-1, 2), wrap=True).reshape(len(u), 3, C)
        dw = 1 + s["contrast"] * (self.luminance_of(c) - 1)
        W = dw * _power(w.float(), s["exponent"])
        W = W / W.sum(1, keepdim=True).clamp_min(1e-30)
        if s["gain"] != 0.5:
            W = gain3(W, s["gain"])
        return (W[..., None] * c).sum(1)
