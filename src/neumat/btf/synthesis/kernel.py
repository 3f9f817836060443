"""The CPU fast path of HPB: `hpb_kernel.c`, compiled on first use like the fitter's kernel
(`neumat.fit_kernel`: system C compiler, -O3 -march=native, cached in $NEUMAT_CACHE by a hash
of source, compiler and CPU). Without a compiler `hpb_features` returns None and HPB uses its
torch path. Queries are split over torch's thread count (ctypes releases the GIL)."""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from pathlib import Path

import torch

from neumat.cbuild import cpu_id as _cpu_id

log = logging.getLogger(__name__)
SOURCE = Path(__file__).with_name("hpb_kernel.c")
FLAGS = ["-O3", "-march=native", "-fPIC"]   # no -ffast-math: same arithmetic as torch


@cache
def _library():
    if os.environ.get("NEUMAT_HPB_KERNEL", "1") == "0":
        return None
    cc = os.environ.get("CC", "cc")
    if shutil.which(cc) is None:
        log.warning("no C compiler (%s): HPB uses its torch path", cc)
        return None
    version = subprocess.run([cc, "--version"], capture_output=True, text=True).stdout
    key = hashlib.sha256("\0".join([SOURCE.read_text(), version, " ".join(FLAGS),
                                    _cpu_id()]).encode()).hexdigest()[:16]
    cache_dir = Path(os.environ.get("NEUMAT_CACHE", Path.home() / ".cache" / "neumat"))
    path = cache_dir / f"hpb_kernel-{key}.so"
    if not path.exists():
        cache_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=cache_dir) as tmp:
            lib = Path(tmp) / path.name
            r = subprocess.run([cc, *FLAGS, "-shared", str(SOURCE), "-o", str(lib), "-lm"],
                               capture_output=True, text=True)
            if r.returncode:
                log.warning("compiling %s failed (%s); HPB uses its torch path", SOURCE.name,
                            r.stderr.strip()[-500:])
                return None
            os.replace(lib, path)
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
