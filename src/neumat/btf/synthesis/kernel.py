"""The CPU fast path of HPB's features: `hpb_features` of `neumat/btf/query_kernel.c`, the same
HPB tile code the fused query runs (`neumat.btf.query` with an HPB as `features_u`), compiled
on first use by `neumat.cbuild` (-march=native, cached in $NEUMAT_CACHE). Without a compiler,
or with NEUMAT_HPB_KERNEL=0, `hpb_features` returns None and HPB uses its torch path. Queries
are split over torch's thread count (ctypes releases the GIL)."""

from __future__ import annotations

import os

import torch

from neumat.btf import query
from neumat.btf.fold import check_lut


def _library():
    if os.environ.get("NEUMAT_HPB_KERNEL", "1") == "0":
        return None
    return query._library("native")


def available() -> bool:
    return _library() is not None


def hpb_features(u: torch.Tensor, hpb):
    """(N, C) float32 features of the HPB synthesis `hpb` at float64 u (N, 2) on the CPU, or
    None (no kernel)."""
    lib = _library()
    H, W, C = hpb.gauss.shape
    check_lut(hpb.lut, C)  # before C reads it: L < 2 would read outside the LUT
    if (lib is None or u.device.type != "cpu" or C > query.MAX_WIDTH
            or (H + 1) * (W + 1) * C >= 2 ** 31):  # int32 offsets into query.hpb_plane
        return None
    u = u.detach().double().contiguous()
    g = query.hpb_plane(hpb)
    mn, bs = (t.detach().float().contiguous() for t in (hpb.mean, hpb.basis))
    lt = query.lut_pairs(hpb.lut)
    out = torch.empty(len(u), C, dtype=torch.float32)
    threads = max(1, min(torch.get_num_threads(), len(u) // 65536))
    bounds = [len(u) * k // threads for k in range(threads + 1)]

    def part(k):
        a, b = bounds[k], bounds[k + 1]
        if b > a:
            lib.hpb_features(b - a, u.data_ptr() + 16 * a, g.data_ptr(), H, W, C, lt.data_ptr(),
                             lt.shape[1], hpb.seed & 0xFFFFFFFF, mn.data_ptr(), bs.data_ptr(),
                             out.data_ptr() + 4 * C * a)

    query.parallel(part, threads)
    return out
