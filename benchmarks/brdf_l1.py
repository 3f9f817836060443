"""BRDF-L1 distance matrix (the Table 2 metrics' largest cost): the C kernel
(`neumat/metrics/l1_kernel.c`, via `distances.l1_sums`) against torch.cdist(p=1) in float64
(what `pairwise_l1` ran before) and in float32, in the same run, on the default config's width
(65536 bins x 3 channels).

Rate in G pair-dims/s (one |a_d - b_d| term of one pair); bound = the machine's fp32 add rate,
taken as half the FLOP/s of a 2048^3 sgemm measured here (one FMA lane = 2 FLOP, and a term
needs a subtract and an add; the abs is a bitwise AND on other ports).

    OMP_NUM_THREADS=2 python benchmarks/brdf_l1.py [--rows 128] [--dim 196608] [--repeat 3]
                                                  [--march x86-64-v3]
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


if __name__ == "__main__":
    main()
