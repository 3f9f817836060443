"""The CPU fast path of the batched fitter: `fit_step.c`, compiled on first use, via ctypes.

One call runs K Adam steps of M fits (minibatch gather, eq. 2 loss, hand-written backward,
Adam): the same maths as `fit.BatchFitter` with `fit.loss_and_grad` + `fit.adam_step`, material
by material with that material's activations in cache. It is ~3.5x faster per material-step than torch's batched matmuls,
whose per-matrix overhead dominates at 21 x 21 (measured: `benchmarks/fit_throughput.py`).
Materials are split over `threads` Python threads; ctypes releases the GIL during the call,
so they run in parallel without touching torch's thread pool.

Why C and not a library: no maintained library trains thousands of tiny independent MLPs on a
CPU (tiny-cuda-nn is GPU-only), and torch.compile of the step gained <= 10 %.

The shared library is built with the system C compiler (`$CC`, default `cc`) for this CPU
(-march=native) into `$NEUMAT_CACHE` (default `~/.cache/neumat`), keyed by a hash of the
source, the compiler and the CPU, so a cluster with mixed nodes builds one per CPU type.
Without a compiler, `available()` is False and the fitter uses the torch path.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from pathlib import Path

import torch

from neumat import nbrdf

log = logging.getLogger(__name__)
SOURCE = Path(__file__).with_name("fit_step.c")
VECTOR = 16  # floats per vector in fit_step.c: the minibatch must be a multiple
WORK_ROWS = 73  # scratch floats per sample per thread: inputs 7, 3 x 21 + 3 activations
# (+ 3 per material of the thread: its targets)


def _cpu_id() -> str:
    """What -march=native depends on: the CPU model and its feature flags."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        return "\n".join(sorted({l for l in lines if l.startswith(("model name", "flags"))}))
    except OSError:
        return platform.processor() + platform.machine()


def _flags() -> list[str]:
    flags = ["-O3", "-ffast-math", "-march=native", "-fPIC"]
    if platform.machine().lower() in ("x86_64", "amd64"):
        flags.append("-mprefer-vector-width=512")  # 16-float vectors: one zmm where there is one
    return flags


def _compile(cc: str, out: Path) -> None:
    """Compile to a temporary name and rename: concurrent jobs never load a half-written file.

    -ffast-math only when compiling: linking a shared library with it would add crtfastmath,
    which sets flush-to-zero for the whole process (torch included) when loaded."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        obj, lib = Path(tmp) / "fit_step.o", Path(tmp) / out.name
        for cmd in ([cc, *_flags(), "-c", str(SOURCE), "-o", str(obj)],
                    [cc, "-shared", str(obj), "-o", str(lib), "-lm"]):
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode:
                raise RuntimeError(f"compiling {SOURCE.name} failed: {' '.join(cmd)}\n{r.stderr}")
        os.replace(lib, out)


@cache
def _library():
    """The loaded kernel library, or None (with the reason logged) where it cannot be built."""
    cc = os.environ.get("CC", "cc")
    if shutil.which(cc) is None:
        log.warning("no C compiler (%s): the fitter uses the slower torch path", cc)
        return None
    version = subprocess.run([cc, "--version"], capture_output=True, text=True).stdout
    key = hashlib.sha256("\0".join([SOURCE.read_text(), version, " ".join(_flags()),
                                    _cpu_id()]).encode()).hexdigest()[:16]
    cache_dir = Path(os.environ.get("NEUMAT_CACHE", Path.home() / ".cache" / "neumat"))
    path = cache_dir / f"fit_step-{key}.so"
    if not path.exists():
        log.info("compiling %s -> %s", SOURCE.name, path)
        try:
            _compile(cc, path)
        except (RuntimeError, OSError) as e:
            log.warning("%s; the fitter uses the slower torch path", e)
            return None
    lib = ctypes.CDLL(str(path))
    p, f, i = ctypes.c_void_p, ctypes.c_float, ctypes.c_int
    lib.nbrdf_fit_steps.argtypes = [i, i, i, i, p, p, i, p, p, p, p, p, p, p, p, p, f]
    lib.nbrdf_fit_steps.restype = None
    lib.nbrdf_loss_sums.argtypes = [i, i, i, i, p, p, i, p, p, p, p, f]
    lib.nbrdf_loss_sums.restype = None
    return lib


def available() -> bool:
    """True when the kernel is built (or can be) for this machine."""
    return _library() is not None


class Stepper:
    """Runs K steps of `fit_step.c` on M materials, the materials split over `threads` threads.

    Each thread runs all K steps of its materials in one C call, so threads meet once per call,
    not once per step (waking a thread costs ~100 us on these VMs, a step of 25 materials ~600).
    xc_all (B, 7) inputs + cos and target (B, M * 3) of all bins are fixed at construction."""

    def __init__(self, xc_all: torch.Tensor, target: torch.Tensor, n: int, threads: int = 1,
                 slope: float = 0.0):
        if n % VECTOR:
            raise ValueError(f"the C fit kernel needs a minibatch that is a multiple of {VECTOR}, "
                             f"got {n}")
        self.lib = _library()
        if self.lib is None:
            raise RuntimeError("the C fit kernel could not be built (see the log)")
        B, self.M = xc_all.shape[0], target.shape[1] // 3
        _check(xc_all, (B, 7))
        _check(target, (B, 3 * self.M))
        self.xc_all, self.target, self.n = xc_all, target, n
        self.slope = slope  # of the hidden activation: 0 relu, fit.LEAKY_SLOPE leaky relu
        threads = max(1, min(threads, self.M))
        bounds = [self.M * k // threads for k in range(threads + 1)]
        self.parts = list(zip(bounds, bounds[1:]))
        self.work = [torch.empty((WORK_ROWS + 3 * (b - a)) * (n + VECTOR)) for a, b in self.parts]
        self.loss, self.grad = torch.zeros(self.M), torch.zeros(self.M, nbrdf.N_PARAMS)
        self.pool = _pool(threads - 1) if threads > 1 else None

    def run(self, w, m, v, idx, sign, lr, step0: int):
        """Steps step0 + 1 ... step0 + K in place on w, m, v (M, 675); returns the last step's
        loss (M,) and gradient (M, 675). idx (K, n) int64 bin positions, sign (K, n) float32
        (-1: mirror phi_d), lr (K,) float32 (<= 0: gradient only, no Adam update)."""
        K = idx.shape[0]
        for t, shape in ((w, (self.M, nbrdf.N_PARAMS)), (m, w.shape), (v, w.shape),
                         (sign, (K, self.n)), (lr, (K,))):
            _check(t, shape)
        if idx.shape != (K, self.n) or idx.dtype != torch.int64 or not idx.is_contiguous():
            raise ValueError(f"fit kernel: idx must be contiguous int64 {(K, self.n)}")
        if K and (idx.min() < 0 or idx.max() >= self.xc_all.shape[0]):
            raise ValueError("fit kernel: minibatch bin positions out of range")
        f4, row = 4, 4 * nbrdf.N_PARAMS  # bytes per float, per weight vector

        def part(k):
            a, b = self.parts[k]
            self.lib.nbrdf_fit_steps(
                b - a, self.n, K, step0, self.xc_all.data_ptr(),
                self.target.data_ptr() + 3 * f4 * a, 3 * self.M, idx.data_ptr(),
                sign.data_ptr(), lr.data_ptr(), w.data_ptr() + row * a, m.data_ptr() + row * a,
                v.data_ptr() + row * a, self.grad.data_ptr() + row * a,
                self.loss.data_ptr() + f4 * a, self.work[k].data_ptr(), self.slope)

        self._parallel(part)
        return self.loss, self.grad

    def losses(self, w, idx) -> torch.Tensor:
        """Eq. 2 loss (M,) float64 of the fields w (M, 675) over the bin positions idx (N,), as
        evaluated (f = max(exp(y) - 1, 0)) and not mirrored: `fit.field_loss`, in C."""
        _check(w, (self.M, nbrdf.N_PARAMS))
        nv = len(idx)
        if nv == 0 or idx.min() < 0 or idx.max() >= self.xc_all.shape[0]:
            raise ValueError("fit kernel: evaluation bin positions empty or out of range")
        pad = -nv % VECTOR  # repeat the last bin up to whole vectors; they are not summed
        idx = torch.cat([idx, idx[-1:].expand(pad)]).to(torch.int64).contiguous()
        out = torch.zeros(self.M, dtype=torch.float64)
        f4, row = 4, 4 * nbrdf.N_PARAMS

        def part(k):
            a, b = self.parts[k]
            self.lib.nbrdf_loss_sums(b - a, self.n, len(idx), nv, self.xc_all.data_ptr(),
                                     self.target.data_ptr() + 3 * f4 * a, 3 * self.M,
                                     idx.data_ptr(), w.data_ptr() + row * a,
                                     out.data_ptr() + 8 * a, self.work[k].data_ptr(), self.slope)

        self._parallel(part)
        return out / (3 * nv)

    def _parallel(self, part):
        """part(k) for every thread's share k, share 0 in this thread while the others run."""
        others = [self.pool.submit(part, k) for k in range(1, len(self.parts))] if self.pool else []
        part(0)
        for f in others:
            f.result()


def _check(t: torch.Tensor, shape):
    if tuple(t.shape) != tuple(shape) or t.dtype != torch.float32 or not t.is_contiguous() \
            or t.device.type != "cpu":
        raise ValueError(f"fit kernel: expected a contiguous CPU float32 tensor of shape "
                         f"{tuple(shape)}, got {tuple(t.shape)} {t.dtype} on {t.device}")


@cache
def _pool(threads: int) -> ThreadPoolExecutor:
    """One pool per thread count for the process: fitters come and go, threads stay idle."""
    return ThreadPoolExecutor(threads, thread_name_prefix="fit_kernel")
