"""Where HPB's GPU overhead goes: the Triton HPB query (`neumat.btf.triton_kernels`) against the
plain query, and variants of HPB that leave one stage out, do it another way, or are the kernel
before its taps summed into one accumulator, timed in interleaved rounds on one 1920 x 1080
frame (random 400 x 400 Triple Plane, u float64 over a x2000 area, random directions). A GPU
has no hardware counters here (gVisor), so a stage's time is the difference between the full
kernel and the kernel without it (the device library's H200.md).

Variants (each the shipped kernel's arithmetic except where named):
  plain          the shipped plain query (query_triton.LAUNCH's shape)
  mlp only       the plain query with no plane fetch (features zero): frame, MLP, store
  hpb            the shipped HPB query: taps at the plane's 8 channels, the blend and the LUT's
                 scale on the bilinear weights, one accumulator, widened for tl.dot
  hpb -lut       without the inverse LUT (diagnostic: wrong values)
  hpb 1 tap      one triangle vertex fetched, not three (diagnostic)
  hpb grid f32   the triangle grid in float32 (diagnostic: wrong at large u)
  hpb nodiv      the grid without float64 divisions, s = (2 sqrt3 u.x - 2 u.y, 4 u.y) (the
                 skew's exact form; moves the grid by an ulp)
  hpb 64x4       the shipped kernel at the launch shape of the kernel before
  hpb before     the kernel before (2026-11-28, b62f565): each tap's 16 padded columns fetched
                 into its own rows, then the blend and the LUT, at its 64 x 4
  hex            the shipped hex-tiling query: the luminance taps first (each a 16-byte load of
                 the texel's 2 x 2 neighbourhood), then the blend weights, then the feature
                 taps at 8 channels folded into one accumulator, widened
  hex BxW        the same at other launch shapes
  hex lum1       the shipped kernel on the (H, W) luminance plane: four 4-byte loads per tap
                 (the layout before, 2026-11-28)
  hex -gain      the shipped kernel without Gain3 (diagnostic: other weights), on that plane
  hex before     the hex-tiling kernel before that (2445d8a): per-tap feature rows of 16
                 padded columns, blended after, at its 128 x 8
Candidates are checked against the shipped kernel (max |difference| of the RGB). Tried on an
H200 on 2026-11-28 and dropped: the LUT's (value, slope) pair as one 64-bit load (level), the
plain query's fetches at 8 columns (level), hex-tiling's taps at 8 columns with the blend after
them (+28 % at 128 x 8).

    python benchmarks/btf_triton_stages.py [--rounds 20] [--calls 5]

Without a GPU (under TRITON_INTERPRET=1) it only runs the checks, on --n queries.
"""

from __future__ import annotations

import argparse

import torch
import triton
import triton.language as tl

from btf_query import flops_per_query
from neumat import machine
from neumat.btf import models, query_triton, triton_kernels
from neumat.btf import synthesis as syn
from neumat.btf.triton_kernels import (bilinear, columns, decode, frame, hex_tap, hex_weights,
                                       hpb_frac32, hpb_tap, interp, mix, mlp, queries_grid,
                                       triangle_grid, triangle_split, widen)

FRAME = 1920 * 1080
HEX_SHAPES = ((32, 1), (64, 4), (128, 4), (128, 8))  # besides query_triton.LAUNCH's


@triton.jit
def mlp_only(u_ptr, wi_ptr, wo_ptr, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr, bh_ptr, wl_ptr,
             bl_ptr, out_ptr, N, PU: tl.constexpr, PD: tl.constexpr, HP: tl.constexpr,
             NH: tl.constexpr, BLOCK: tl.constexpr):
    """The plain query without its three plane fetches (zero features that depend on the
    loads, so none is dropped)."""
    q = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = q < N
    ux = tl.load(u_ptr + 2 * q, mask=m, other=0.0)
    uy = tl.load(u_ptr + 2 * q + 1, mask=m, other=0.0)
    hu, hv, du, dv = frame(wi_ptr, wo_ptr, q, m)
    fu = tl.full((BLOCK, PU), 0.0, tl.float32) + (ux + uy + hu + hv + du + dv)[:, None] * 0.0
    fh = tl.full((BLOCK, PD), 0.0, tl.float32)
    mlp(fu, fh, fh, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr,
        q, m, PU, PD, HP, NH, False)


@triton.jit
def grid_nodiv(ux, uy):
    """triangle_grid with s = (2 sqrt3 ux - 2 uy, 4 uy): no float64 division."""
    K = tl.full(ux.shape, 3.4641016151377544, tl.float64)
    return triangle_split(ux * K - 2 * uy, 4 * uy)


@triton.jit
def grid_f32(ux, uy):
    """The triangle grid in float32 (diagnostic only: it loses the grid at large u)."""
    x = ux.to(tl.float32)
    y = uy.to(tl.float32)
    return triangle_split(x * 3.4641016 - 2 * y, 4 * y)


@triton.jit
def hpb_variant(u_ptr, wi_ptr, wo_ptr, gauss_ptr, lut_ptr, fh_ptr, fd_ptr, w1u_ptr,
                w1h_ptr, w1d_ptr, b1_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr, N,
                HG, WG, L, R, hs_bits, CU: tl.constexpr, CD: tl.constexpr,
                PU: tl.constexpr, PD: tl.constexpr, QU: tl.constexpr, HP: tl.constexpr,
                NH: tl.constexpr, GRID: tl.constexpr, TAPS: tl.constexpr, LUT: tl.constexpr,
                BLOCK: tl.constexpr):
    """triple_plane_hpb with GRID 0 (float64, shipped), 1 (no division) or 2 (float32); TAPS
    3 or 1; LUT False: the accumulator is the feature."""
    q = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = q < N
    ux = tl.load(u_ptr + 2 * q, mask=m, other=0.0)
    uy = tl.load(u_ptr + 2 * q + 1, mask=m, other=0.0)
    if GRID == 0:
        i0, i1, up, w0, w1, w2, _, _ = triangle_grid(ux, uy)
    elif GRID == 1:
        i0, i1, up, w0, w1, w2, _, _ = grid_nodiv(ux, uy)
    else:
        i0, i1, up, w0, w1, w2, _, _ = grid_f32(ux, uy)
    fx = hpb_frac32(ux)
    fy = hpb_frac32(uy)
    hs = hs_bits.to(tl.uint32, bitcast=True)
    dn = tl.where(up, 0, 1).to(tl.int64)
    inv = 1.0 / tl.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    s = L * inv
    bias = L * 0.5 * (1 - inv * (w0 + w1 + w2)) - 0.5
    x = tl.full((BLOCK, QU), 0.0, tl.float32) + bias[:, None]
    x = hpb_tap(x, gauss_ptr, fx, fy, i0 + dn, i1 + dn, hs, w0 * s, HG, WG, CU, QU, m)
    if TAPS == 3:
        x = hpb_tap(x, gauss_ptr, fx, fy, i0 + dn, i1 + 1 - dn, hs, w1 * s, HG, WG, CU, QU, m)
        x = hpb_tap(x, gauss_ptr, fx, fy, i0 + 1 - dn, i1 + dn, hs, w2 * s, HG, WG, CU, QU, m)
    mc = columns(m, CU, QU)
    if LUT:
        x = tl.minimum(tl.maximum(x, 0.0), L - 1.0)
        k0 = tl.minimum(tl.floor(x).to(tl.int32), L - 2)
        base = lut_ptr + tl.arange(0, QU)[None, :] * L + k0
        a = tl.load(base, mask=mc, other=0.0)
        b = tl.load(base + 1, mask=mc, other=0.0)
        x = a + (x - k0.to(tl.float32)) * (b - a)
    qf = widen(tl.where(mc, x, 0.0), BLOCK, QU, PU)
    hu, hv, du, dv = frame(wi_ptr, wo_ptr, q, m)
    decode(qf, hu, hv, du, dv, fh_ptr, fd_ptr, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr,
           bh_ptr, wl_ptr, bl_ptr, out_ptr, q, m, R, CD, PU, PD, HP, NH, False)


@triton.jit
def old_tap(gauss_ptr, fx, fy, bx, by, hs, H, W, C: tl.constexpr, P: tl.constexpr, m):
    """The kernel before's hpb_tap: one vertex's bilinear fetch, (BLOCK, P)."""
    h = mix(by.to(tl.uint32) ^ mix(bx.to(tl.uint32) ^ hs))
    h = mix(h ^ tl.full(h.shape, 0x9E3779B1, tl.uint32))
    x = (h + fx).to(tl.float32) * 2.3283064365386963e-10
    h = mix(h ^ tl.full(h.shape, 0x9E3779B2, tl.uint32))
    y = (h + fy).to(tl.float32) * 2.3283064365386963e-10
    top = 1.0 - 5.9604644775390625e-08
    return bilinear(gauss_ptr, tl.minimum(x, top), tl.minimum(y, top), H, W, C, P, True, m)


@triton.jit
def hpb_before(u_ptr, wi_ptr, wo_ptr, gauss_ptr, lut_ptr, fh_ptr, fd_ptr, w1u_ptr,
               w1h_ptr, w1d_ptr, b1_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr, N,
               HG, WG, L, R, hs_bits, CU: tl.constexpr, CD: tl.constexpr,
               PU: tl.constexpr, PD: tl.constexpr, HP: tl.constexpr, NH: tl.constexpr,
               BLOCK: tl.constexpr):
    """triple_plane_hpb as of b62f565 (the baseline of its one-accumulator form)."""
    q, m, i0, i1, dn, w0, w1, w2, _, _, fx, fy, hs = queries_grid(u_ptr, hs_bits, N, BLOCK)
    g0 = old_tap(gauss_ptr, fx, fy, i0 + dn, i1 + dn, hs, HG, WG, CU, PU, m)
    g1 = old_tap(gauss_ptr, fx, fy, i0 + dn, i1 + 1 - dn, hs, HG, WG, CU, PU, m)
    g2 = old_tap(gauss_ptr, fx, fy, i0 + 1 - dn, i1 + dn, hs, HG, WG, CU, PU, m)
    num = (g0 - 0.5) * w0[:, None] + (g1 - 0.5) * w1[:, None] + (g2 - 0.5) * w2[:, None]
    g = num / tl.sqrt(w0 * w0 + w1 * w1 + w2 * w2)[:, None] + 0.5
    x = tl.minimum(tl.maximum(tl.minimum(tl.maximum(g, 0.0), 1.0) * L - 0.5, 0.0), L - 1.0)
    k0 = tl.minimum(tl.floor(x).to(tl.int32), L - 2)
    c = tl.arange(0, PU)
    mc = m[:, None] & (c < CU)[None, :]
    base = lut_ptr + c[None, :] * L + k0
    a = tl.load(base, mask=mc, other=0.0)
    b = tl.load(base + 1, mask=mc, other=0.0)
    qf = tl.where(mc, a + (x - k0.to(tl.float32)) * (b - a), 0.0)
    hu, hv, du, dv = frame(wi_ptr, wo_ptr, q, m)
    decode(qf, hu, hv, du, dv, fh_ptr, fd_ptr, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr,
           bh_ptr, wl_ptr, bl_ptr, out_ptr, q, m, R, CD, PU, PD, HP, NH, False)


@triton.jit
def old_hex_tap(plane_ptr, lum_ptr, fx, fy, e0, e1, bx, by, hs, rotation, H, W, C: tl.constexpr,
                P: tl.constexpr, m):
    """The kernel before's hex_tap: one vertex's features (BLOCK, P) and luminance."""
    i00, i01, i10, i11, tx, ty, lum = hex_tap(lum_ptr, fx, fy, e0, e1, bx, by, hs, rotation, H,
                                              W, m, False)
    return interp(plane_ptr, i00, i01, i10, i11, tx, ty, C, C, P, m), lum


@triton.jit
def hex_before(u_ptr, wi_ptr, wo_ptr, plane_ptr, lum_ptr, fh_ptr, fd_ptr, w1u_ptr, w1h_ptr,
               w1d_ptr, b1_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr, N, HP_, WP_, R,
               hs_bits, rotation, contrast, exponent, gain_k,
               CU: tl.constexpr, CD: tl.constexpr, PU: tl.constexpr, PD: tl.constexpr,
               HP: tl.constexpr, NH: tl.constexpr, IE: tl.constexpr, GAIN: tl.constexpr,
               RAW: tl.constexpr, BLOCK: tl.constexpr):
    """triple_plane_hex as of 2445d8a (the baseline of its one-accumulator form)."""
    q, m, i0, i1, dn, w0, w1, w2, f0, f1, fx, fy, hs = queries_grid(u_ptr, hs_bits, N, BLOCK)
    dnf = dn.to(tl.float32)
    c0, l0 = old_hex_tap(plane_ptr, lum_ptr, fx, fy, f0 - dnf, f1 - dnf, i0 + dn, i1 + dn, hs,
                         rotation, HP_, WP_, CU, PU, m)
    c1, l1 = old_hex_tap(plane_ptr, lum_ptr, fx, fy, f0 - dnf, f1 - (1 - dnf), i0 + dn,
                         i1 + 1 - dn, hs, rotation, HP_, WP_, CU, PU, m)
    c2, l2 = old_hex_tap(plane_ptr, lum_ptr, fx, fy, f0 - (1 - dnf), f1 - dnf, i0 + 1 - dn,
                         i1 + dn, hs, rotation, HP_, WP_, CU, PU, m)
    v0, v1, v2 = hex_weights(w0, w1, w2, l0, l1, l2, contrast, exponent, gain_k, IE, GAIN)
    fu = v0[:, None] * c0 + v1[:, None] * c1 + v2[:, None] * c2
    hu, hv, du, dv = frame(wi_ptr, wo_ptr, q, m)
    decode(fu, hu, hv, du, dv, fh_ptr, fd_ptr, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr,
           bh_ptr, wl_ptr, bl_ptr, out_ptr, q, m, R, CD, PU, PD, HP, NH, RAW)


def variants(m, h, x, u32, u64, wi, wo):
    """name -> (launch(), the variant it is checked against, its output buffer)."""
    n = u32.shape[0]
    p, ph, px = query_triton.packed(m), query_triton._pack(m, h), query_triton._pack(m, x)
    fh = m.f_h.detach().float().contiguous()
    fd = m.f_d.detach().float().contiguous()
    g, lut = ph["gauss"], ph["lut"]
    shapes = dict(CU=p["cu"], CD=p["cd"], PU=p["pu"], PD=p["pd"], HP=p["hp"], NH=p["n_hidden"])
    outs = []

    def mlp_args(pk, w1u=None):  # a new output buffer per variant
        outs.append(torch.empty(n, 3, device=u32.device))
        return (pk["w1u"] if w1u is None else w1u, pk["w1h"], pk["w1d"], pk["b1"], pk["wh"],
                pk["bh"], pk["wl"], pk["bl"], outs[-1], n)

    launch = lambda L: dict(grid=(triton.cdiv(n, L["BLOCK"]),), shape=L)
    hpb_tables = lambda: (g, lut, fh, fd)
    hpb_sizes = (g.shape[0], g.shape[1], lut.shape[1], fh.shape[0], ph["hs"])

    def run(kernel, args, L=None, **kw):  # args end with the buffer mlp_args just made
        at = launch(L)
        return lambda: kernel[at["grid"]](*args, **kw, **at["shape"]), len(outs) - 1

    def shipped(method, shape=None):  # through query_triton.query, packed once, as a renderer's
        s = {None: None, "hpb": h, "hextile": x}[method]
        uu = u32 if s is None else u64
        pk = {None: p, "hpb": ph, "hextile": px}[method]
        outs.append(None)
        i = len(outs) - 1

        def f():
            outs[i] = query_triton.query(m, uu, wi, wo, packed=pk, synth=s, launch=shape)
        return f, i

    def variant(L=query_triton.LAUNCH["hpb"], **flags):
        return run(hpb_variant, (u64, wi, wo, *hpb_tables(), *mlp_args(ph), *hpb_sizes), L,
                   QU=ph["qu"], **shapes, **flags)

    # the kernel before reads layer 1's rows in order: undo the shipped interleave
    def in_order(pk):
        w = torch.zeros_like(pk["w1u"])
        w[:p["cu"]] = pk["w1u"][0:p["cu"] * (p["pu"] // pk["qu"]):p["pu"] // pk["qu"]]
        return w
    w1u_before, w1u_hex_before = in_order(ph), in_order(px)
    lum1 = px["lum4"][..., 0].contiguous()  # the (H, W) luminance plane of the layout before
    hex_args = lambda pk, w1u=None: (u64, wi, wo, px["plane"], lum1, fh, fd, *mlp_args(pk, w1u),
                                     *hex_sizes)
    hex_flags = dict(IE=px["ie"], QU=px["qu"], RAW=False, **shapes)
    hex_sizes = (px["plane"].shape[0], px["plane"].shape[1], fh.shape[0], px["hs"],
                 px["rotation"], px["contrast"], px["exponent"], px["gain_k"])
    made = {}
    for name, ref, make in (
            ("plain", None, lambda: shipped(None)),
            ("mlp only", None, lambda: run(mlp_only, (u32, wi, wo, *mlp_args(p)),
                                           query_triton.LAUNCH[None], PU=p["pu"], PD=p["pd"],
                                           HP=p["hp"], NH=p["n_hidden"])),
            ("hpb", None, lambda: shipped("hpb")),
            ("hpb -lut", None, lambda: variant(GRID=0, TAPS=3, LUT=False)),
            ("hpb 1 tap", None, lambda: variant(GRID=0, TAPS=1, LUT=True)),
            ("hpb grid f32", None, lambda: variant(GRID=2, TAPS=3, LUT=True)),
            ("hpb nodiv", "hpb", lambda: variant(GRID=1, TAPS=3, LUT=True)),
            ("hpb 64x4", "hpb", lambda: variant({"BLOCK": 64, "num_warps": 4}, GRID=0, TAPS=3,
                                                LUT=True)),
            ("hpb before", "hpb", lambda: run(hpb_before, (u64, wi, wo, *hpb_tables(),
                                                           *mlp_args(ph, w1u_before), *hpb_sizes),
                                              {"BLOCK": 64, "num_warps": 4}, **shapes)),
            ("hex", None, lambda: shipped("hextile")),
            *[(f"hex {b}x{w}", "hex",
               lambda b=b, w=w: shipped("hextile", dict(BLOCK=b, num_warps=w)))
              for b, w in HEX_SHAPES],
            ("hex lum1", "hex", lambda: run(triton_kernels.triple_plane_hex, hex_args(px),
                                            query_triton.LAUNCH["hextile"], GAIN=px["gain"],
                                            LUM4=False, **hex_flags)),
            ("hex -gain", None, lambda: run(triton_kernels.triple_plane_hex, hex_args(px),
                                            query_triton.LAUNCH["hextile"], GAIN=False,
                                            LUM4=False, **hex_flags)),
            ("hex before", "hex", lambda: run(hex_before, hex_args(px, w1u_hex_before),
                                              {"BLOCK": 128, "num_warps": 8}, IE=px["ie"],
                                              GAIN=px["gain"], RAW=False, **shapes))):
        f, i = make()
        made[name] = (f, ref, i)
    return made, outs


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=20, help="interleaved rounds (best kept)")
    ap.add_argument("--calls", type=int, default=5, help="launches per timing (their mean)")
    ap.add_argument("--n", type=int, default=FRAME, help="queries per launch")
    a = ap.parse_args()
    dev = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    torch.manual_seed(0)
    m = models.TriplePlane(400, 400).to(dev).eval().requires_grad_(False)
    h, x = syn.build(m, "hpb", 1, {}), syn.build(m, "hextile", 1, {})
    gen = torch.Generator().manual_seed(0)
    u = torch.rand(a.n, 2, generator=gen)

    def hemi():
        w = torch.randn(a.n, 3, generator=gen)
        w[:, 2] = w[:, 2].abs() + 0.05
        return torch.nn.functional.normalize(w, dim=-1).to(dev).contiguous()
    wi, wo = hemi(), hemi()
    u32 = u.to(dev).contiguous()
    u64 = ((u.double() - 0.5) * 2e3).to(dev).contiguous()
    runs, outs = variants(m, h, x, u32, u64, wi, wo)
    for f, _, _ in runs.values():
        f()  # compile and warm
    where = machine.describe()
    if dev.type == "cuda":
        where += (f"; GPU {torch.cuda.get_device_name(dev)}, torch {torch.__version__}, "
                  f"triton {triton.__version__}")
    print(f"machine: {where}")
    print(f"launch shapes (queries x warps per program): {query_triton.LAUNCH}")
    for name, (_, ref, i) in runs.items():
        if ref:
            want = outs[runs[ref][2]]
            d = (outs[i] - want).abs().max().item()
            print(f"check: {name} vs {ref}: max |RGB difference| {d:.3g} "
                  f"(mean |RGB| {want.abs().mean().item():.3g})")
    if dev.type != "cuda":
        return
    best = {k: float("inf") for k in runs}
    for _ in range(a.rounds):
        for k, (f, _, _) in runs.items():
            s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            s.record()
            for _ in range(a.calls):
                f()
            e.record()
            e.synchronize()
            best[k] = min(best[k], s.elapsed_time(e) / a.calls)
    print(f"ms per frame of {a.n} queries, best of {a.rounds} interleaved rounds of {a.calls} "
          f"launches (CUDA events):")
    for k, v in best.items():
        own = "hpb" if k.startswith("hpb ") else "hex" if k.startswith("hex ") else None
        extra = f"; vs {own} {100 * (v / best[own] - 1):+.1f} %" if own else ""
        print(f"  {k:13s} {v:.4f} ms  vs plain {100 * (v / best['plain'] - 1):+.1f} %{extra}")
    print(f"HPB overhead over the plain query: {100 * (best['hpb'] / best['plain'] - 1):+.1f} % "
          f"(goal <= 10 %); the kernel before: "
          f"{100 * (best['hpb before'] / best['plain'] - 1):+.1f} %")
    print(f"hex-tiling overhead: {100 * (best['hex'] / best['plain'] - 1):+.1f} %; the kernel "
          f"before: {100 * (best['hex before'] / best['plain'] - 1):+.1f} %")
    fq, peak = flops_per_query(m), machine.gpu_matmul_rate(dev)
    bound = a.n * fq / peak * 1e3
    print(f"FLOP bound of the plain query: {bound:.3f} ms per frame ({fq} FLOP/query at the fp32 "
          f"torch.mm rate, {peak / 1e12:.1f} TFLOP/s in this run); the plain kernel "
          f"{bound / best['plain']:.3f} of it, HPB {bound / best['hpb']:.3f}, hex-tiling "
          f"{bound / best['hex']:.3f}")


if __name__ == "__main__":
    main()
