"""The CPU fast path of the batched fitter: `fit_step.c`, compiled on first use, via ctypes.

One call runs K Adam steps of M fits (minibatch gather, eq. 2 loss, hand-written backward,
Adam): the same maths as `fit.BatchFitter` with `fit.loss_and_grad` + `fit.adam_step`, material
by material with that material's activations in cache, where torch's batched matmuls spend most
of a step on per-matrix overhead at 21 x 21 (`benchmarks/fit_throughput.py` measures both).
Materials are split over `threads` Python threads; ctypes releases the GIL during the call,
so they run in parallel without touching torch's thread pool.

Why C and not a library: no maintained library trains thousands of tiny independent MLPs on a
CPU (tiny-cuda-nn is GPU-only).

The shared library is built and cached by `neumat.cbuild` for a target `-march` (default
`native`, or `$NEUMAT_FIT_MARCH`, e.g. `x86-64-v3` for an AVX2 build on any x86 host);
fit_step.c picks its vector width and register blocking from the target ISA. Without a
compiler, `available()` is False and the fitter uses the torch path.

`fit.kernel: auto` uses the C step only where it is the faster one here: `auto_choice` times
both steps on a small problem once per library (a few hundred ms) and caches the result next to
it (`<library>.choice.json`).
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from pathlib import Path

import torch

from neumat import cbuild, nbrdf

log = logging.getLogger(__name__)
SOURCE = Path(__file__).with_name("fit_step.c")
VECTOR = 16  # the widest vector of fit_step.c (AVX-512), floats: the minibatch must be a multiple
WORK_ROWS = 73  # scratch floats per sample per thread: inputs 7, 3 x 21 + 3 activations
# (+ 3 per material of the thread: its targets)


def default_march() -> str:
    """The -march the fitter's kernel is built for: `$NEUMAT_FIT_MARCH`, else native."""
    return os.environ.get("NEUMAT_FIT_MARCH", "native")


runs_here = cbuild.runs_here


@cache
def _library(march: str | None = None):
    """The loaded kernel library for `march`, or None (with the reason logged) where it cannot
    be built or cannot run on this CPU."""
    path = cbuild.build(SOURCE, march or default_march(), "the fitter uses the torch path")
    if path is None:
        return None
    lib = ctypes.CDLL(str(path))
    p, f, i = ctypes.c_void_p, ctypes.c_float, ctypes.c_int
    lib.nbrdf_fit_steps.argtypes = [i, i, i, i, p, p, i, p, p, p, p, p, p, p, p, p, f]
    lib.nbrdf_fit_steps.restype = None
    lib.nbrdf_loss_sums.argtypes = [i, i, i, i, p, p, i, p, p, p, p, f]
    lib.nbrdf_loss_sums.restype = None
    lib.path = path
    return lib


def available(march: str | None = None) -> bool:
    """True when the kernel is built (or can be) for this machine."""
    return _library(march) is not None


class Stepper:
    """Runs K steps of `fit_step.c` on M materials, the materials split over `threads` threads.

    Each thread runs all K steps of its materials in one C call, so threads meet once per call,
    not once per step (waking a thread costs a sizeable fraction of a step).
    xc_all (B, 7) inputs + cos and target (B, M * 3) of all bins are fixed at construction."""

    def __init__(self, xc_all: torch.Tensor, target: torch.Tensor, n: int, threads: int = 1,
                 slope: float = 0.0, march: str | None = None):
        if n % VECTOR:
            raise ValueError(f"the C fit kernel needs a minibatch that is a multiple of {VECTOR}, "
                             f"got {n}")
        self.lib = _library(march)
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


# ----------------------------------------------------------------------------- auto: C or torch

CALIBRATION = dict(materials=16, bins=4096, steps=8, rounds=3)  # ~0.1-0.5 s on one core
# make(kernel, batch, activation, materials, bins) -> a BatchFitter on random data; registered
# by neumat.fit, which imports this module (so this module never imports it back)
FITTER = None


def _time_steps(kernel: str, batch: int, activation: str, march: str | None) -> float:
    """CPU seconds per material-step of the batched fitter's `kernel` path ("c" or "torch") on a
    small random problem, one thread (this one: CPU time of the thread, not wall time, so that
    other processes on a shared machine do not decide): the best of a few rounds."""
    if FITTER is None:
        raise RuntimeError("fit_kernel.auto_choice needs neumat.fit imported (it registers the "
                           "fitter the calibration times)")
    c = CALIBRATION
    f = FITTER(kernel, batch, activation, c["materials"], max(c["bins"], 4 * batch))
    if kernel == "c" and march is not None:  # the variant being calibrated
        f._c.lib = _library(march)
    f._run(2)  # warm-up: first-touch of buffers, torch's kernel selection
    best = float("inf")
    for _ in range(c["rounds"]):
        t = time.thread_time()
        f._run(c["steps"])
        best = min(best, time.thread_time() - t)
    return best / (c["steps"] * c["materials"])


def _calibrate(batch: int, activation: str, march: str | None) -> dict:
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        t_torch = _time_steps("torch", batch, activation, march)
        t_c = _time_steps("c", batch, activation, march)
    finally:
        torch.set_num_threads(old)
    return dict(c_us=t_c * 1e6, torch_us=t_torch * 1e6, choice="c" if t_c <= t_torch else "torch")


@cache
def auto_choice(batch: int, activation: str = "relu", march: str | None = None) -> str:
    """"c" or "torch": the faster step for `fit.kernel: auto` on this CPU (the C kernel must be
    available). Timed once per library, minibatch size and activation (single-threaded, both
    paths, a small problem) and cached in `<library>.choice.json`; the choice is logged."""
    lib = _library(march)
    path = Path(str(lib.path) + ".choice.json")
    key = f"batch={batch} activation={activation}"
    try:
        table = json.loads(path.read_text())
    except (OSError, ValueError):
        table = {}
    how = "cached calibration"
    if key not in table:
        t0 = time.perf_counter()
        table[key] = _calibrate(batch, activation, march)
        how = f"calibrated in {time.perf_counter() - t0:.2f} s"
        try:
            fresh = json.loads(path.read_text())  # another job may have added other keys
        except (OSError, ValueError):
            fresh = {}
        fresh[key] = table[key]
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(fresh, indent=1, sort_keys=True))
        os.replace(tmp, path)
    e = table[key]
    log.info("fit kernel auto: %s (C step %.1f us, torch step %.1f us per material-step, %s, "
             "1 thread, %s; %s)", e["choice"], e["c_us"], e["torch_us"], key, path, how)
    return e["choice"]
