"""Triple Plane queries on a CUDA GPU in one Triton kernel: per block of 64 queries the
half/difference frame, the three bilinear plane fetches and the whole MLP (`tl.dot` at IEEE fp32,
no TF32), with the activations in registers. The torch path runs these as separate kernels, its
fetches as gathers and its layers as batched gemv; it stays the path everywhere else (CPU: the
fused C query, `neumat.btf.query`). Two more kernels synthesise f_U in place of its fetch:
histogram-preserving blending (neumat.btf.synthesis.hpb: the triangle grid in float64, the
integer hash, the fetch coordinates in 32-bit fixed point, the blend and the LUT at the
plane's 8 channels, not the dot's 16; the inverse PCA folded into layer 1)
and hex-tiling (neumat.btf.synthesis.hextile: the same grid and hash, the rotated patches and
the luminance-weighted blend, its features also at 8 channels).

    rgb = query(model, u, wi, wo)              # = model(u, wi, wo), all on the GPU
    rgb = query(model, u, wi, wo, synth=s)     # = Synthesized(model, s).torch_forward(u, wi, wo)

`neumat.btf.query.query` calls it (`try_query`) for CUDA tensors when `supported` says so.
Without Triton (CPU-only torch wheels do not ship it), or with NEUMAT_TRITON=0, `available()` is
False and the torch path runs. If a kernel fails on a GPU, `try_query` logs the error once,
names NEUMAT_TRITON=0, and the process keeps to the torch path, so a render does not die on it.

Tested on the CPU through Triton's interpreter (TRITON_INTERPRET=1; tests/test_btf_query_triton.py)
against the torch path to float tolerance, and compiled where a GPU is visible (all three
passed on an H200, the hex-tiling kernel first on 2026-11-28, all as shipped on 2026-11-29). The
interpreter checks the arithmetic, not the GPU compile or its speed: the ms per frame comes
from `benchmarks/btf_query.py` and `btf_synthesis.py --device cuda` on a GPU.
"""

from __future__ import annotations

import logging
import math
import os
from functools import cache

import torch

from neumat.btf.fold import check_lut, fold_pca

log = logging.getLogger(__name__)
_failed: list[str] = []  # the first kernel failure of this process, if any

# queries and warps per program, per kernel (None: the plain query): speed only, each query's
# arithmetic is the same. The fastest of 7 shapes for each kernel in two sweeps on an H200
# (benchmarks/btf_query.py --device cuda --sweep, 2026-11-28): plain 128 x 8 (level with 64 x 2,
# 0.890 and 0.969 ms/frame against 0.897 and 0.980). HPB and hex-tiling 64 x 2 since their taps
# sum into one 8-column accumulator (H200, 2026-11-28): HPB over the plain kernel at the same
# shape, one sweep of 7 shapes (a one-off script timing `query` as btf_query.py --sweep does),
# +6.3 % at 64 x 2 and at 128 x 4, +10.8 % at the 64 x 4 of its kernel before; hex-tiling (benchmarks/btf_triton_stages.py) 0.911 ms at 64 x 2, 0.910 at
# 128 x 4, 0.913 at 32 x 1, 1.32 at 64 x 4 and 1.53 at 128 x 8
LAUNCH = {None: {"BLOCK": 128, "num_warps": 8}, "hpb": {"BLOCK": 64, "num_warps": 2},
          "hextile": {"BLOCK": 64, "num_warps": 2}}
PACKS = 8  # packings kept per model (`packed`): a synthesis each


@cache
def _triton():
    """(triton, triton.language) or None."""
    try:
        import triton
        import triton.language as tl
    except ImportError:
        return None
    return triton, tl


def interpreting() -> bool:
    """Triton's CPU interpreter is on: kernels run on CPU tensors (tests only; slow)."""
    return os.environ.get("TRITON_INTERPRET") == "1"


def available(device: torch.device | str = "cuda") -> bool:
    """Whether the kernel can run on tensors of `device`."""
    dev = torch.device(device)
    if _triton() is None or os.environ.get("NEUMAT_TRITON") == "0" or _failed:
        return False
    return dev.type == "cuda" or (dev.type == "cpu" and interpreting())


def supported(model, *tensors) -> bool:
    """A Triple Plane model and tensors on one device the kernel runs on, and no autograd."""
    from neumat.btf.neural import TriplePlane
    if not isinstance(model, TriplePlane):
        return False
    devices = {t.device for t in (model.f_u, *tensors)}
    if len(devices) != 1 or not available(next(iter(devices))):
        return False
    if model.f_h.shape != model.f_d.shape or model.f_h.shape[0] != model.f_h.shape[1]:
        return False
    if max(model.f_u.numel(), model.f_h.numel()) >= 2 ** 31:  # int32 texel offsets
        return False
    if torch.is_grad_enabled() and any(p.requires_grad for p in model.parameters()):
        return False
    return True


def _pow2(n: int, least: int = 16) -> int:
    """tl.arange and tl.dot want power-of-two extents of at least 16."""
    return max(least, 1 << (int(n) - 1).bit_length())


def pack(model, first: tuple | None = None) -> dict:
    """The MLP as the kernel reads it: transposed, zero-padded to power-of-two widths; layer 1
    split into its f_U, f_H and f_D rows (three dots, no concatenated input). `first`: (W1, b1)
    in place of layer 1's (HPB's, with its inverse PCA folded in)."""
    lin = [m for m in model.net if isinstance(m, torch.nn.Linear)]
    cu, cd = model.kwargs["u_channels"], model.kwargs["dir_channels"]
    hidden = lin[0].out_features
    pu, pd, hp = _pow2(cu), _pow2(cd), _pow2(hidden)
    dev = model.f_u.device
    z = lambda *s: torch.zeros(*s, device=dev, dtype=torch.float32)

    def block(w, rows, cols):  # w (out, in) -> (rows, cols) holding w.T
        out = z(rows, cols)
        out[: w.shape[1], : w.shape[0]] = w.detach().float().T
        return out.contiguous()

    w1, b1_src = first if first is not None else (lin[0].weight, lin[0].bias)
    w1 = w1.to(dev)
    hid = lin[1:-1]
    wh = torch.stack([block(l.weight, hp, hp) for l in hid]) if hid else z(1, hp, hp)
    bh = z(max(len(hid), 1), hp)
    for i, l in enumerate(hid):
        bh[i, : l.out_features] = l.bias.detach().float()
    b1, bl = z(hp), z(16)
    b1[:hidden] = b1_src.detach().float().to(dev)
    bl[:3] = lin[-1].bias.detach().float()
    return dict(w1u=block(w1[:, :cu], pu, hp), w1h=block(w1[:, cu:cu + cd], pd, hp),
                w1d=block(w1[:, cu + cd:], pd, hp), b1=b1, wh=wh.contiguous(), bh=bh,
                wl=block(lin[-1].weight, hp, 16), bl=bl, cu=cu, cd=cd, pu=pu, pd=pd, hp=hp,
                n_hidden=len(hid))


METHODS = ("hpb", "hextile")  # the syntheses with a kernel of their own


def _kernel(method: str | None = None):
    from neumat.btf import triton_kernels  # imports triton: only where it is installed
    return {None: triton_kernels.triple_plane, "hpb": triton_kernels.triple_plane_hpb,
            "hextile": triton_kernels.triple_plane_hex}[method]


def packed(model, synth=None) -> dict:
    """`pack(model)` (with a synthesis: its tables on the model's device, and for HPB its
    folded layer 1), kept on the model until a parameter or the synthesis changes (a frame's
    queries come in chunks: repacking would launch a dozen small kernels per chunk). One packing
    per synthesis object (up to PACKS), so queries that alternate between syntheses, or between
    plain and synthesised (paper Fig. 9), do not repack on every call: with one slot,
    alternating plain, HPB and hex-tiling queries cost 0.5 to 1.2 ms more per 1920 x 1080
    frame than the kernels, with one per synthesis 0.1 to 0.5 ms (H200,
    benchmarks/btf_synthesis.py --device cuda, 2026-11-28)."""
    key = (tuple((p.data_ptr(), p._version) for p in model.parameters()),
           None if synth is None else (synth.seed, repr(getattr(synth, "s", None)),
                                       tuple((t.data_ptr(), t._version)
                                             for t in _synth_tensors(synth))))
    packs = model.__dict__.setdefault("_triton_packs", {})
    slot = None if synth is None else id(synth)
    cached = packs.get(slot)
    if cached is None or cached[0] != key:
        if len(packs) >= PACKS:
            packs.clear()
        cached = packs[slot] = (key, _pack(model, synth))
    return cached[1]


def _synth_tensors(synth):
    if synth.method == "hextile":
        return synth.plane, synth.lum_weights
    return synth.mean, synth.basis, synth.gauss, synth.lut


def _pack(model, synth, half: bool = True) -> dict:
    """`half`: the synthesised planes as float16 (the default; the same values as float32,
    which only `benchmarks/btf_synthesis.py --device cuda` asks for, as its baseline)."""
    if synth is None:
        return pack(model)
    pack_synth = _pack_hpb if synth.method == "hpb" else _pack_hex
    return pack_synth(model, synth, torch.float16 if half else torch.float32)


def _seed_hash(seed: int) -> int:
    """The seed's hash (grid.vertex_hash's first step), as a signed 32-bit kernel argument
    the kernel bitcasts back to uint32."""
    from neumat.btf.synthesis.grid import _mix  # lazily: the synthesis package imports `query`
    hs = int(_mix(torch.tensor(int(seed) & 0xFFFFFFFF)))
    return hs - (1 << 32) if hs >= 1 << 31 else hs


def _narrow(p: dict) -> None:
    """A synthesis kernel forms f_U at qu columns (the channels' power of two, not the pu >= 16
    that tl.dot wants) and widens them, channel i landing in column i pu / qu
    (triton_kernels.widen): layer 1's f_U rows moved to match."""
    cu, pu = p["cu"], p["pu"]
    p["qu"] = qu = max(_pow2(cu, 1), pu // 4)
    w1u = torch.zeros_like(p["w1u"])
    w1u[0:cu * (pu // qu):pu // qu] = p["w1u"][:cu]
    p["w1u"] = w1u


def _pack_hpb(model, hpb, dtype) -> dict:
    """pack(model) with HPB's folded layer 1, its LUT and its Gaussianised plane as `dtype`:
    float16 holds it exactly (hpb.gaussianise rounds it so), at half the bytes per tap."""
    check_lut(hpb.lut, hpb.gauss.shape[-1])  # the kernel interpolates entries k and k + 1
    lin = [m for m in model.net if isinstance(m, torch.nn.Linear)]
    w1, b1 = fold_pca(lin[0].weight, lin[0].bias, model.kwargs["u_channels"], hpb.mean, hpb.basis)
    dev = model.f_u.device
    p = pack(model, (w1, b1))
    _narrow(p)
    p["gauss"] = hpb.gauss.detach().to(dev, dtype).contiguous()
    p["lut"] = hpb.lut.detach().float().to(dev).contiguous()
    p["hs"] = _seed_hash(hpb.seed)
    return p


def _pack_hex(model, hexs, dtype) -> dict:
    """pack(model) with the feature plane (H, W, C) as `dtype` (float16 holds it exactly:
    hextile rounds the features so), the luminance a . f + b of each texel's features (linear:
    the bilinear tap of these is the luminance of the bilinear features, which the kernel then
    clamps to [0, 1] as hextile.HexTile.luminance_of) in float32 as each texel's wrapped 2 x 2
    neighbourhood (H, W, 4) (texels (x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1): a tap's
    four values in one 16-byte load; triton_kernels.hex_tap), and hex-tiling's settings as the
    kernel takes them."""
    dev = model.f_u.device
    p, s = pack(model), hexs.s
    _narrow(p)
    pl = hexs.plane.detach().to(dev)
    a = hexs.lum_weights.to(dev, torch.float64)
    lum = (pl.double() @ a[:-1] + a[-1]).float()
    lum4 = torch.stack([lum, lum.roll(-1, 1), lum.roll(-1, 0), lum.roll((-1, -1), (0, 1))], -1)
    p.update(plane=pl.to(dtype).contiguous(), lum4=lum4.contiguous(),
             hs=_seed_hash(hexs.seed),
             rotation=float(s["rotation"]),  # float32 in the kernel, as the C kernel's
             contrast=float(s["contrast"]), exponent=float(s["exponent"]),
             gain_k=math.log(1 - s["gain"]) / math.log(0.5), gain=s["gain"] != 0.5)
    e = float(s["exponent"])
    p["ie"] = int(e) if e.is_integer() and 0 <= e <= 16 else -1  # hextile._power
    return p


def query(model, u, wi, wo, raw: bool = False, packed: dict | None = None,
          synth=None, launch: dict | None = None) -> torch.Tensor:
    """RGB (N, 3) of a Triple Plane `model` at u (N, 2), wi, wo (N, 3), all on the GPU (or on
    the CPU under TRITON_INTERPRET=1); raw=True: log(1 + RGB). `synth`: an HPB or hex-tiling
    synthesis (neumat.btf.synthesis.hpb, .hextile; `method` in METHODS) in place of the f_U
    fetch, u then float64 and unbounded. `packed`: `packed(model, synth)`, to reuse across
    calls. `launch`: BLOCK and num_warps in place of LAUNCH's for this kernel (the benchmark's
    sweep). Callers check `supported` first."""
    p = packed or _pack(model, synth)
    f32 = lambda t: t.detach().to(torch.float32).contiguous()
    wi, wo = f32(wi), f32(wo)
    fh, fd = f32(model.f_h), f32(model.f_d)
    n = wi.shape[0]
    out = torch.empty(n, 3, device=wi.device, dtype=torch.float32)
    if n == 0:
        return out
    triton, _ = _triton()
    method = None if synth is None else synth.method
    launch = launch or LAUNCH[method]
    grid = (triton.cdiv(n, launch["BLOCK"]),)
    mlp = (p["w1u"], p["w1h"], p["w1d"], p["b1"], p["wh"], p["bh"], p["wl"], p["bl"], out, n)
    shapes = dict(CU=p["cu"], CD=p["cd"], PU=p["pu"], PD=p["pd"], HP=p["hp"], NH=p["n_hidden"],
                  RAW=bool(raw), **launch)
    if method is None:
        fu = f32(model.f_u)
        _kernel()[grid](f32(u), wi, wo, fu, fh, fd, *mlp, fu.shape[0], fu.shape[1],
                        fh.shape[0], **shapes)
    elif method == "hpb":
        g = p["gauss"]
        _kernel("hpb")[grid](u.detach().double().contiguous(), wi, wo, g, p["lut"], fh, fd,
                             *mlp, g.shape[0], g.shape[1], p["lut"].shape[1], fh.shape[0],
                             p["hs"], QU=p["qu"], **shapes)
    else:
        pl, u64 = p["plane"], u.detach().double().contiguous()
        _kernel("hextile")[grid](u64, wi, wo, pl, p["lum4"], fh, fd, *mlp, pl.shape[0],
                                 pl.shape[1], fh.shape[0], p["hs"], p["rotation"],
                                 p["contrast"], p["exponent"], p["gain_k"],
                                 IE=p["ie"], GAIN=p["gain"], QU=p["qu"], **shapes)
    return out


def try_query(model, u, wi, wo, raw: bool = False, synth=None) -> torch.Tensor | None:
    """`query` with the model's cached packing, or None after logging why if the kernel fails
    (then `available()` is False for the rest of the process: the caller's torch path runs)."""
    try:
        return query(model, u, wi, wo, raw=raw, packed=packed(model, synth), synth=synth)
    except Exception as e:  # compile or launch errors of an untested GPU (Triton raises its own types)
        _failed.append(f"{type(e).__name__}: {e}")
        log.warning("Triton Triple Plane query failed on %s, using the torch path from now on "
                    "(set NEUMAT_TRITON=0 to skip it): %s", wi.device, _failed[0])
        return None
