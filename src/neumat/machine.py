"""What machine a figure was measured on: CPU model, vector ISA, cores, sgemm peak.

Benchmarks print `describe()` before their figures (some on every figure line), so that a
speed-up is never quoted without the machine it came from (an AVX-512 figure says nothing about an AVX2 machine).
"""

from __future__ import annotations

import os
import platform
import shutil
import subprocess
import time
from functools import cache
from pathlib import Path


def _read_cpuinfo() -> str:
    try:
        return Path("/proc/cpuinfo").read_text()
    except OSError:
        return ""


def _cpuinfo(keys) -> str | None:
    """The value of the first /proc/cpuinfo line starting with `keys` (a prefix or a tuple of
    them), or None (no such line, no /proc/cpuinfo)."""
    for line in _read_cpuinfo().splitlines():
        if line.startswith(keys):
            return line.split(":", 1)[1].strip()
    return None


@cache
def cpu_family() -> str | None:
    """"family F model M" of an x86 CPU, or None. Under a hypervisor the model name may be just
    "AMD EPYC", which Zen 4 (family 25) and Zen 5 (family 26) hosts both show, and hosts of one
    ISA differ: the plain BTF query frame of one kernel took 257.2 CPU-ms on an Intel Xeon and
    117.3 on a family-26 AMD EPYC, both AVX-512 (benchmarks/btf_synthesis.py; docs/stages.md)."""
    fields = {}
    for line in _read_cpuinfo().splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    fam, mod = fields.get("cpu family", ""), fields.get("model", "")
    return f"family {fam} model {mod}" if fam.isdigit() and mod.isdigit() else None


@cache
def cpu_model() -> str:
    """The CPU's model name (lscpu's "Model name"), or the platform's processor string."""
    return _cpuinfo("model name") or platform.processor() or platform.machine()


@cache
def cpu_flags() -> frozenset[str]:
    return frozenset((_cpuinfo(("flags", "Features")) or "").split())


def _isa_name(has) -> str:
    """The widest float vector ISA among the names `has` accepts."""
    for name, keys in (("AVX-512", ("avx512f", "__AVX512F__")), ("AVX2", ("avx2", "__AVX2__")),
                       ("AVX", ("avx", "__AVX__")), ("SSE4.2", ("sse4_2", "__SSE4_2__")),
                       ("SSE2", ("sse2", "__SSE2__")), ("NEON", ("asimd", "__ARM_NEON"))):
        if any(has(k) for k in keys):
            return name
    return "scalar"


def host_isa() -> str:
    """The widest float vector ISA this CPU has, e.g. "AVX-512", "AVX2", "NEON"."""
    return _isa_name(cpu_flags().__contains__)


@cache
def compiler_isa(march: str = "native") -> str | None:
    """The vector ISA C code compiled with -march=`march` targets (the compiler's predefined
    macros), or None without a compiler or for a -march it rejects."""
    cc = os.environ.get("CC", "cc")
    if shutil.which(cc) is None:
        return None
    r = subprocess.run([cc, f"-march={march}", "-dM", "-E", "-"], input="", capture_output=True,
                       text=True)
    if r.returncode:
        return None
    macros = {line.split()[1] for line in r.stdout.splitlines() if line.startswith("#define")}
    return _isa_name(macros.__contains__)


def describe(march: str | None = None) -> str:
    """One line: CPU model (and x86 family), host ISA, CPUs, and the ISA of a C build for
    `march` if given."""
    fam = cpu_family()
    s = (f"CPU {cpu_model()} ({platform.machine()}{f' {fam}' if fam else ''}, {host_isa()}, "
         f"{os.cpu_count()} CPUs)")
    if march:
        s += f"; C kernel -march={march} -> {compiler_isa(march) or 'no compiler'}"
    return s


def gpu_matmul_rate(device, dtype=None, n: int = 8192, repeat: int = 5) -> float:
    """FLOP per wall second of an n^3 torch.mm on a CUDA `device` in fp32 (TF32 off, torch's
    default) or `dtype`, the best of `repeat` after a warm-up."""
    import torch
    a = torch.randn(n, n, device=device, dtype=dtype or torch.float32)
    c = a @ a  # warm-up
    best = float("inf")
    for _ in range(repeat):
        torch.cuda.synchronize()
        t = time.perf_counter()
        torch.mm(a, a, out=c)
        torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t)
    return 2 * n ** 3 / best


def sgemm_peak(threads: int | None = None, n: int = 2048, repeat: int = 5,
               dtype=None) -> tuple[float, float]:
    """fp32 (or `dtype`, e.g. torch.bfloat16) matmul rate of this machine from n^3 torch.mm
    (CPU) with `threads` torch threads (default: as set): (FLOP per wall second, FLOP per CPU
    second of the process), each the best of `repeat`. On a shared machine the second is the
    load-independent one."""
    import torch
    old = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        g = torch.Generator().manual_seed(0)
        a, b = torch.randn(n, n, generator=g), torch.randn(n, n, generator=g)
        if dtype is not None:
            a, b = a.to(dtype), b.to(dtype)
        c = torch.mm(a, b)  # warm-up
        wall = cpu = float("inf")
        for _ in range(repeat):
            t, p = time.perf_counter(), time.process_time()
            torch.mm(a, b, out=c)
            wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - p)
        return 2 * n ** 3 / wall, 2 * n ** 3 / cpu
    finally:
        torch.set_num_threads(old)
