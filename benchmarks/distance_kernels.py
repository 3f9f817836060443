"""The Table 2 metrics' distance matrices, C kernels against their torch paths in the same run.

BRDF-L1: `neumat/metrics/l1_kernel.c` (`distances.l1_sums`) against torch.cdist(p=1) in float64
(what `pairwise_l1` ran before) and in float32, at the default config's width (65536 bins x 3
channels). Rate in G pair-dims/s (one |a_d - b_d| term of one pair); bound = the machine's fp32
add rate, taken as half the FLOP/s of a 2048^3 sgemm measured here (one FMA lane = 2 FLOP, and
a term needs a subtract and an add; the abs is a bitwise AND on other ports).

SSIM: `neumat/metrics/ssim_kernel.c` against `pairwise_ssim`'s torch loop (band-matrix box
filters), on 128 x 128 RGB renders (the default `report.sphere_resolution`). Fraction of the
sgemm FLOP/s, counting the kernel's arithmetic: per channel 3 H W (centred product)
+ 6 H (W - 6) (row sums) + 22 (H - 6)(W - 6) (column sums and the formula, one division).

    OMP_NUM_THREADS=2 python benchmarks/distance_kernels.py [--rows 128] [--dim 196608]
                      [--images 48] [--repeat 3] [--march x86-64-v3]
"""

from __future__ import annotations

import argparse
import time

import torch

from neumat import machine
from neumat.metrics import distances as D


def best(fn, repeat):
    wall = cpu = float("inf")
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
    return wall, cpu


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", type=int, default=128, help="materials per side")
    ap.add_argument("--dim", type=int, default=65536 * 3)
    ap.add_argument("--images", type=int, default=48, help="renders per side for SSIM")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--march", default="native", help="kernel build target, e.g. x86-64-v3 (AVX2)")
    a = ap.parse_args()
    g = torch.Generator().manual_seed(0)
    x, y = torch.rand(a.rows, a.dim, generator=g), torch.rand(a.rows, a.dim, generator=g)
    threads = torch.get_num_threads()
    print(f"machine: {machine.describe(a.march)}; torch threads {threads}, torch {torch.__version__}")
    peak_wall, peak_cpu = machine.sgemm_peak()
    terms = a.rows * a.rows * a.dim
    runs = {"C kernel (l1_sums)": lambda: D.l1_sums(x, y, march=a.march),
            "torch.cdist float64": lambda: torch.cdist(x.double(), y.double(), p=1),
            "torch.cdist float32": lambda: torch.cdist(x, y, p=1)}
    ref = torch.cdist(x.double(), y.double(), p=1)
    err = float(((D.l1_sums(x, y, march=a.march) - ref).abs() / ref).max())
    times = {k: best(fn, a.repeat) for k, fn in runs.items()}
    print(f"{a.rows} x {a.rows} pairs x {a.dim} dims; max relative difference C vs float64 cdist "
          f"{err:.1e}; add bound {peak_wall / 2e9:.1f} G/s wall ({peak_cpu / 2e9:.1f} per CPU-s)")
    base = times["torch.cdist float64"][0]
    for k, (wall, cpu) in times.items():
        print(f"{k:22s} {wall:8.3f} s  {terms / wall / 1e9:7.2f} G pair-dims/s  "
              f"{base / wall:6.1f}x vs float64 cdist  {terms / wall / (peak_wall / 2):6.1%} of "
              f"add bound (per CPU-s: {terms / cpu / (peak_cpu / 2):6.1%})")


    ssim(a, peak_wall, peak_cpu)


def ssim(a, peak_wall, peak_cpu):
    g = torch.Generator().manual_seed(1)
    n, res = a.images, 128
    x, y = torch.rand(n, res, res, 3, generator=g), torch.rand(n, res, res, 3, generator=g)
    kernel = D._ssim_kernel
    runs = {"C kernel (ssim_kernel)": lambda: D.pairwise_ssim(x, y),
            "torch (band matrices)": lambda: D.pairwise_ssim(x, y)}
    D._ssim_kernel = lambda *args, **kw: kernel(*args, march=a.march, **kw)
    got = D.pairwise_ssim(x, y)
    times = {"C kernel (ssim_kernel)": best(runs["C kernel (ssim_kernel)"], a.repeat)}
    D._ssim_kernel = lambda *args, **kw: None
    err = float((got - D.pairwise_ssim(x, y)).abs().max())
    times["torch (band matrices)"] = best(runs["torch (band matrices)"], a.repeat)
    D._ssim_kernel = kernel
    v = res - 6
    flop = n * n * 3 * (3 * res * res + 6 * res * v + 22 * v * v)
    print(f"SSIM: {n} x {n} pairs of {res} x {res} RGB; max difference C vs torch {err:.1e}")
    base = times["torch (band matrices)"][0]
    for k, (wall, cpu) in times.items():
        print(f"{k:24s} {wall:8.3f} s  {wall / n / n * 1e6:7.1f} us/pair  {base / wall:6.1f}x vs "
              f"torch  {flop / wall / peak_wall:6.1%} of sgemm FLOP/s (per CPU-s: "
              f"{flop / cpu / peak_cpu:6.1%})")


if __name__ == "__main__":
    main()
