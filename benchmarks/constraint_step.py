"""The clamp-aware constraint's cost per DDIM step (neumat.diffusion.constraints.NegativeConstraint:
an NBRDF forward and backward pass at 4096 valid MERL bins for every sample), against the same
gradient taken over the whole batch at once (the baseline, in the same run), for batch sizes
a user meets: 16 (the `neumat sample` default scale), 128 and 256 (diffusion.sample.batch_size).
Prints ms per call, the ratio, the largest gradient difference (the split is exact up to float
rounding), and the achieved rate as a fraction of this machine's fp32 sgemm rate (2048^3,
measured in the same run), with the ISA and the CPU model.

    OMP_NUM_THREADS=2 python benchmarks/constraint_step.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import time

import torch

from neumat import machine, nbrdf
from neumat.diffusion import constraints


class _Identity:  # the constraint's de-standardisation, left out: the cost is the NBRDF's
    @staticmethod
    def decode(z):
        return z


def best_ms(fn, repeat):
    fn()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--batches", type=int, nargs="+", default=[16, 128, 256])
    ap.add_argument("--block", type=int, default=constraints.CPU_BLOCK,
                    help="samples per pass (default: the library's CPU_BLOCK)")
    a = ap.parse_args()
    constraints.CPU_BLOCK = a.block
    peak = machine.sgemm_peak()[0]  # per wall second, as the times below
    print(f"machine: {machine.describe()}; torch threads {torch.get_num_threads()}, "
          f"fp32 sgemm {peak / 1e9:.0f} GFLOP/s")
    con = constraints.NegativeConstraint(_Identity(), 1.0, seed=0)
    n = len(con.x)
    flop_per_sample = 3 * 2 * n * sum(i * o for i, o in nbrdf.LAYERS)  # forward + backward
    print(f"{n} bins, {flop_per_sample / 1e6:.1f} MFLOP per sample (forward + backward); "
          f"blocks of {constraints.CPU_BLOCK} samples")
    print(f"{'batch':>6s} {'whole batch ms':>15s} {'blocked ms':>11s} {'speed-up':>9s} "
          f"{'of sgemm peak':>14s} {'max |diff|':>11s}")
    for b in a.batches:
        w = nbrdf.init_weights(b, torch.Generator().manual_seed(b)) * 3
        whole = lambda: con._grad(w.clone(), con.x)
        blocked = lambda: w - con(w)  # step 1: x0 - x0' is the gradient
        t_whole, t_blocked = best_ms(whole, a.repeat), best_ms(blocked, a.repeat)
        diff = float((whole() - blocked()).abs().max())
        frac = b * flop_per_sample / (t_blocked / 1e3) / peak
        print(f"{b:6d} {t_whole:15.1f} {t_blocked:11.1f} {t_whole / t_blocked:8.2f}x "
              f"{frac * 100:13.1f}% {diff:11.2e}")


if __name__ == "__main__":
    main()
