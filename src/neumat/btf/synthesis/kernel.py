"""The CPU fast path of HPB: `hpb_kernel.c`, compiled on first use by `neumat.cbuild` like the
fitter's kernel (-march=native, cached in $NEUMAT_CACHE), but without -ffast-math. Without a compiler `hpb_features` returns None and HPB uses its
torch path. Queries are split over torch's thread count (ctypes releases the GIL)."""

from __future__ import annotations

import ctypes
import logging
import os
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from pathlib import Path

import torch

from neumat import cbuild

log = logging.getLogger(__name__)
SOURCE = Path(__file__).with_name("hpb_kernel.c")


@cache
def _library():
    if os.environ.get("NEUMAT_HPB_KERNEL", "1") == "0":
        return None
    # no -ffast-math: the same arithmetic as the torch path (and the float64 reference)
    path = cbuild.build(SOURCE, "native", "HPB uses its torch path", fast_math=False)
    if path is None:
        return None
    lib = ctypes.CDLL(str(path))
    p, i = ctypes.c_void_p, ctypes.c_int
    lib.hpb_features.argtypes = [ctypes.c_int64, p, p, i, i, i, p, i, p, p, ctypes.c_uint32, p]
    lib.hpb_features.restype = i
    return lib


def available() -> bool:
    return _library() is not None


def _ptr(t: torch.Tensor):
    return ctypes.c_void_p(t.data_ptr())


def hpb_features(u: torch.Tensor, gauss, lut, mean, basis, seed: int):
    """(N, C) float32 HPB features of float64 u (N, 2) on the CPU, or None (no kernel)."""
    lib = _library()
    if lib is None or u.device.type != "cpu" or gauss.shape[-1] > 64:
        return None
    u = u.double().contiguous()
    H, W, C = gauss.shape
    g, lt, mn, bs = (t.float().contiguous() for t in (gauss, lut, mean, basis))
    out = torch.empty(len(u), C, dtype=torch.float32)
    threads = max(1, min(torch.get_num_threads(), len(u) // 65536))
    bounds = [len(u) * k // threads for k in range(threads + 1)]

    def part(k):
        a, b = bounds[k], bounds[k + 1]
        if b > a:
            lib.hpb_features(b - a, _ptr(u[a:b]), _ptr(g), H, W, C, _ptr(lt), lt.shape[1],
                             _ptr(mn), _ptr(bs), int(seed) & 0xFFFFFFFF, _ptr(out[a:b]))

    if threads == 1:
        part(0)
    else:
        with ThreadPoolExecutor(threads) as ex:
            list(ex.map(part, range(threads)))
    return out
