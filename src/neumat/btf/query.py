"""Fast Triple Plane queries on the CPU: `query_kernel.c` (half/difference frame, three bilinear
fetches and the MLP fused per tile of 64 queries), the same function of (u, wi, wo) as
`TriplePlane.forward` to float32 rounding (tests/test_btf_query.py); `benchmarks/btf_query.py`
measures both against the FLOP bound.

    rgb = query(model, u, wi, wo)                       # = model(u, wi, wo)
    rgb = query(model, u, wi, wo, features_u=f)         # = relu(expm1(model.decode(f, wi, wo)))

The f_U hook, for texture synthesis: `features_u` replaces the positional fetch of f_U at u by
the caller's features, either a tensor (N, C_U) or a callable u -> (N, C_U) (e.g. a fetch from a
synthesised plane); u is then only passed to that callable. Everything else (directions,
f_H, f_D, MLP) is unchanged. An `HPB` synthesis (neumat.btf.synthesis.hpb) as `features_u`
runs inside the kernel instead (`btf_triple_plane_hpb`: grid, hash, three fetches of its
Gaussianised plane, blend and LUT per tile, at float64 u, no (N, C_U) buffer); its inverse PCA
is folded into the first layer (`neumat.btf.fold.fold_pca`). A `HexTile` (neumat.btf.synthesis.hextile) runs
inside it the same way (`btf_triple_plane_hex`: the same grid, hash and taps, rotated, of its
plane (`hex_plane`), its luminance linear in the fetched features, and hex-tiling's
blend).

On a CUDA GPU the plain query of a Triple Plane, and its query with an HPB or hex-tiling
synthesis as `features_u`, run as one Triton kernel each (`neumat.btf.query_triton`) where
Triton is installed (CUDA builds of torch bring it).

Falls back to the model's torch path (same results) for other models (NeuMIP, the classical
ones), other devices, autograd, or where the kernel cannot be built (no compiler; see
neumat.cbuild).
"""

from __future__ import annotations

import ctypes
import os
import time
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from pathlib import Path
from typing import Callable

import torch

from neumat import cbuild
from neumat.btf.fold import check_lut, fold_pca
from neumat.btf import query_triton

SOURCE = Path(__file__).with_name("query_kernel.c")
MAX_WIDTH = 128  # MAXW in query_kernel.c: the widest layer its scratch holds


@cache
def _library(march: str = "native"):
    # generic tuning: GCC 12 tunes -march=native on a Zen 4 for Zen 3 (no AVX-512), and there
    # the query took 9 % more CPU time (benchmarks/btf_query.py: 233.0 against 213.6 CPU-ms per
    # frame) and HPB 7-9 % (btf_synthesis.py: 274-280 against 257); AMD EPYC AVX-512, 2 cores.
    # The fit kernel was slower with generic tuning and keeps -march's. x86-64-vN imply it.
    path = cbuild.build(SOURCE, march, "BTF queries use the torch path", tune="generic")
    if path is None:
        return None
    lib = ctypes.CDLL(str(path))
    p, i, l = ctypes.c_void_p, ctypes.c_int, ctypes.c_long
    lib.btf_triple_plane.argtypes = [l, p, p, p, p, p, i, i, i, p, p, i, i, i, p, p, p, i]
    lib.btf_triple_plane.restype = None
    u32 = ctypes.c_uint32
    lib.btf_triple_plane_hpb.argtypes = [l, p, p, p, p, i, i, i, p, i, u32, p, p, i, i, i, p, p,
                                         p, i, i]
    lib.btf_triple_plane_hpb.restype = None
    d, f = ctypes.c_double, ctypes.c_float
    lib.btf_triple_plane_hex.argtypes = [l, p, p, p, p, p, i, i, i, u32, d, f, f, f, p, p, i, i,
                                         i, p, p, p, i, i]
    lib.btf_triple_plane_hex.restype = None
    lib.hpb_features.argtypes = [l, p, p, i, i, i, p, i, u32, p, p, p]
    lib.hpb_features.restype = None
    if hasattr(lib, "fma_peak"):  # kernels before 2026-12-03 (btf_kernel_ab.py --rev) lack it
        lib.fma_peak.argtypes = [l, f, f]
        lib.fma_peak.restype = f
        lib.vector_lanes.argtypes = []
        lib.vector_lanes.restype = i
    return lib


def fma_peak(march: str = "native", seconds: float = 0.2, repeat: int = 3) -> float | None:
    """This kernel build's fp32 vector FMA rate, FLOP per CPU-second of one thread: the best of
    `repeat` runs of query_kernel.c's `fma_peak` (12 independent FMA chains), each of a round
    count that took between a quarter of `seconds` and `seconds` when calibrated. The bound the
    benchmarks measure the query against, in place of a matmul library's rate, which the
    query's MLP can beat (MKL's sgemm on an AMD Zen 5: about 100 GFLOP/CPU-s, the MLP about
    200, docs/stages.md). None without the kernel."""
    lib = _library(march)
    if lib is None:
        return None
    flop = 24 * lib.vector_lanes()  # per round: 12 chains of a multiply and an add per lane
    n = 1 << 16
    while True:  # 4x the rounds until they take over a quarter of `seconds`
        t = time.process_time()
        lib.fma_peak(n, 0.999, 0.001)
        dt = time.process_time() - t
        if dt > seconds / 4 or n > 1 << 40:
            break
        n *= 4
    best = float("inf")
    for _ in range(repeat):
        t = time.process_time()
        lib.fma_peak(n, 0.999, 0.001)
        best = min(best, time.process_time() - t)
    return n * flop / best


def lut_pairs(lut: torch.Tensor) -> torch.Tensor:
    """HPB's inverse LUT (C, L) as the kernel reads it: (C, L, 2) float32 (value, slope) pairs,
    slope = next value - value (0 for the last entry, which the kernel never reads)."""
    lut = lut.detach().float().contiguous()
    slope = torch.cat([lut[:, 1:] - lut[:, :-1], torch.zeros_like(lut[:, :1])], 1)
    return torch.stack([lut, slope], -1).contiguous()


def _wrapped(t: torch.Tensor) -> torch.Tensor:
    """(H, W, ...) -> (H + 1, W + 1, ...): the first row and column repeated at the end."""
    t = torch.cat([t, t[:, :1]], 1)
    return torch.cat([t, t[:1]], 0).contiguous()


def plane16(synth, plane: torch.Tensor) -> torch.Tensor:
    """A synthesis's plane (H, W, C) as the kernel reads it: (H + 1, W + 1, C) float16, wrapped
    by one row and column, so a bilinear footprint is one offset (struct hpb). float16 holds
    the values exactly: HPB's Gaussianised plane (hpb.gaussianise rounds it) and hex-tiling's
    features (hextile._rounded). Cached on the synthesis object: a frame is queried in chunks,
    and the copy is a pass over the plane."""
    cached = getattr(synth, "_kernel_plane", None)
    if cached is not None and cached[0] is plane:
        return cached[1]
    p = _wrapped(plane.detach().to(torch.float16))
    synth._kernel_plane = (plane, p)
    return p


def hpb_plane(hpb) -> torch.Tensor:
    """HPB's Gaussianised plane as the kernel reads it (`plane16`)."""
    return plane16(hpb, hpb.gauss)


def hex_plane(hexs) -> torch.Tensor:
    """Hex-tiling's features as the kernel reads it (`plane16`): texels of C float16 features
    and no luminance, which the kernel forms from the fetched features (hextile.HexTile.
    luminance_of)."""
    return plane16(hexs, hexs.plane)


def tap_prefetch() -> bool:
    """Whether the HPB and hex-tiling queries prefetch the next tile's taps (struct hpb's
    `prefetch` in query_kernel.c: one query's footprints at a time, spread over the tile
    before, `prefetch_taps`). Outputs are the same either way; NEUMAT_TAP_PREFETCH=0 or 1
    overrides the default, on (read on every query). Per 1920 x 1080 frame on an Intel Xeon,
    against no prefetch, HPB took 9.4 and 12.8 CPU-ms less on the AVX-512 and AVX2 builds,
    hex-tiling 13.5 and 10.4 less (`OMP_NUM_THREADS=1 python benchmarks/btf_kernel_ab.py --rev
    beb9859 --control --processes 5 --repeat 5 --tap-prefetch both`, and with `--march
    x86-64-v3`; medians of 5 processes, idle, 2026-11-30). Not measured on AMD, where the
    earlier burst of a tile's prefetches (on there, off on Intel, where it cost more than it
    hid) was designed."""
    env = os.environ.get("NEUMAT_TAP_PREFETCH")
    if env is None:
        return True
    if env not in ("0", "1"):
        raise ValueError(f"NEUMAT_TAP_PREFETCH must be 0 or 1, got {env!r}")
    return env == "1"


def available(march: str = "native") -> bool:
    return _library(march) is not None


def _f32(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to(torch.float32).contiguous()


def supported(model, *tensors, march: str = "native") -> bool:
    """Whether `query` runs this model and these inputs in C (else it uses the torch path):
    a Triple Plane model on the CPU, and no autograd wanted (grad mode off, or no parameter
    that requires grad)."""
    from neumat.btf.neural import TriplePlane
    if not isinstance(model, TriplePlane) or not available(march):
        return False
    lin = [m for m in model.net if isinstance(m, torch.nn.Linear)]
    if max(max(l.in_features, l.out_features) for l in lin) > MAX_WIDTH:
        return False
    if model.f_h.shape != model.f_d.shape or model.f_h.shape[0] != model.f_h.shape[1]:
        return False
    if model.f_u.numel() >= 2 ** 31:  # the kernel's plane offsets are int32
        return False
    if torch.is_grad_enabled() and any(p.requires_grad for p in model.parameters()):
        return False
    return all(t.device.type == "cpu" for t in (model.f_u, *tensors))


def _hpb(features_u):
    """features_u if it is an HPB or hex-tiling synthesis (neumat.btf.synthesis.hpb.HPB,
    .hextile.HexTile, known by their `method`: this module does not import the synthesis
    package, which imports it) the kernel can run, else None."""
    method = getattr(features_u, "method", None)
    if method not in ("hpb", "hextile"):
        return None
    H, W, C = (features_u.gauss if method == "hpb" else features_u.plane).shape
    if method == "hpb":
        check_lut(features_u.lut, C)
    # int32 offsets in elements of plane16's (H + 1, W + 1, C)
    return features_u if (H + 1) * (W + 1) * C < 2 ** 31 else None


def query(model, u, wi, wo, features_u: torch.Tensor | Callable | None = None,
          raw: bool = False, threads: int | None = None, march: str = "native") -> torch.Tensor:
    """RGB (N, 3) of `model` at texture coordinates u (N, 2) and unit directions wi, wo (N, 3);
    raw=True: the MLP output log(1 + RGB) instead. `features_u`: see the module docstring.
    Queries are split over `threads` (default: torch's) threads; `march`: the kernel build
    (e.g. x86-64-v3 for the AVX2 one, in tests)."""
    synth = features_u if getattr(features_u, "method", None) in query_triton.METHODS else None
    if ((features_u is None or synth is not None) and wi.device.type == "cuda"
            and query_triton.supported(model, u, wi, wo)):
        out = query_triton.try_query(model, u, wi, wo, raw=raw, synth=synth)
        if out is not None:
            return out
    hpb = _hpb(features_u) if supported(model, u, wi, wo, march=march) else None
    if callable(features_u) and hpb is None:
        features_u = features_u(u)
    if hpb is None and not supported(model, u, wi, wo,
                                     *([] if features_u is None else [features_u]), march=march):
        if features_u is None:  # any model answering model(u, wi, wo) (neumat.btf.models)
            return model.raw(u, wi, wo) if raw else model(u, wi, wo)
        y = model.decode(features_u, wi, wo)
        return y if raw else torch.relu(torch.expm1(y))
    N = wi.shape[0]
    cu = model.kwargs["u_channels"]
    if hpb is None and features_u is not None and tuple(features_u.shape) != (N, cu):
        raise ValueError(f"features_u must be ({N}, {cu}), got {tuple(features_u.shape)}")
    wi, wo = _f32(wi), _f32(wo)
    fh, fd = _f32(model.f_h), _f32(model.f_d)
    lin = [m for m in model.net if isinstance(m, torch.nn.Linear)]
    dims = torch.tensor([lin[0].in_features] + [l.out_features for l in lin], dtype=torch.int32)
    weights = [t.detach() for l in lin for t in (l.weight, l.bias)]
    lib = _library(march)
    f4 = 4
    if hpb is None:
        u = _f32(u)
        feat = None if features_u is None else _f32(features_u)
        fu = _f32(model.f_u)

        def call(a, n, out_ptr):
            lib.btf_triple_plane(
                n, u.data_ptr() + 2 * f4 * a, wi.data_ptr() + 3 * f4 * a,
                wo.data_ptr() + 3 * f4 * a, None if feat is None else feat.data_ptr() + cu * f4 * a,
                fu.data_ptr(), fu.shape[0], fu.shape[1], cu, fh.data_ptr(), fd.data_ptr(),
                fh.shape[0], fh.shape[2], len(lin), dims.data_ptr(), params.data_ptr(),
                out_ptr, int(raw))
    elif hpb.method == "hextile":
        u = u.detach().double().contiguous()
        st = hpb.s
        if hpb.plane.shape[-1] != cu:
            raise ValueError(f"hex-tiling plane has {hpb.plane.shape[-1]} channels, "
                             f"the model {cu}")
        plane, lumw = hex_plane(hpb), hpb.lum_weights.float().contiguous()
        H, W = hpb.plane.shape[:2]
        pf = int(tap_prefetch())

        def call(a, n, out_ptr):
            lib.btf_triple_plane_hex(
                n, u.data_ptr() + 2 * 8 * a, wi.data_ptr() + 3 * f4 * a,
                wo.data_ptr() + 3 * f4 * a, plane.data_ptr(), lumw.data_ptr(), H, W, cu,
                hpb.seed & 0xFFFFFFFF,
                float(st["rotation"]), float(st["contrast"]),
                float(st["exponent"]), float(st["gain"]), fh.data_ptr(), fd.data_ptr(),
                fh.shape[0], fh.shape[2], len(lin), dims.data_ptr(), params.data_ptr(),
                out_ptr, int(raw), pf)
    else:
        u = u.detach().double().contiguous()
        weights[:2] = fold_pca(weights[0], weights[1], cu, hpb.mean, hpb.basis)
        gauss, lut = hpb_plane(hpb), lut_pairs(hpb.lut)
        H, W = hpb.gauss.shape[:2]
        pf = int(tap_prefetch())

        def call(a, n, out_ptr):
            lib.btf_triple_plane_hpb(
                n, u.data_ptr() + 2 * 8 * a, wi.data_ptr() + 3 * f4 * a,
                wo.data_ptr() + 3 * f4 * a, gauss.data_ptr(), H, W, cu, lut.data_ptr(),
                lut.shape[1], hpb.seed & 0xFFFFFFFF, fh.data_ptr(), fd.data_ptr(), fh.shape[0],
                fh.shape[2], len(lin), dims.data_ptr(),
                params.data_ptr(), out_ptr, int(raw), pf)
    params = torch.cat([t.reshape(-1) for t in weights]).float()
    out = torch.empty(N, 3)
    threads = max(1, min(threads or torch.get_num_threads(), N // 4096 + 1))
    bounds = [N * k // threads for k in range(threads + 1)]

    def part(k):
        a, b = bounds[k], bounds[k + 1]
        call(a, b - a, out.data_ptr() + 3 * f4 * a)

    parallel(part, threads)
    return out


def parallel(part, threads: int) -> None:
    """part(0) ... part(threads - 1), in parallel (ctypes releases the GIL)."""
    if threads == 1:
        part(0)
    else:
        futures = [_pool(threads - 1).submit(part, k) for k in range(1, threads)]
        part(0)
        for f in futures:
            f.result()


@cache
def _pool(threads: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(threads, thread_name_prefix="btf_query")
