"""Exporting NBRDF fields to MERL .binary tables (`neumat sample`, rules `export_samples` and
`neumerl_export`): `nbrdf.evaluate_grid` at the library's chunk size (on the CPU 2^15 / B bins,
a power of two) against 2^18 bins per chunk (the default before 2026-11-26: the baseline, in
the same run), for one table and a batch of 8; and `merl.write_merl` against writing the same
bytes with one `ndarray.tofile` (the bound). Prints the best wall time, CPU seconds split
user/system, the minor page faults, the ratios, and the evaluation's rate as a fraction of this
machine's fp32 sgemm rate, with the ISA and the CPU model. The chunk sizes give identical tables
(checked here).

    OMP_NUM_THREADS=1 python benchmarks/merl_export.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time

import numpy as np
import torch

from neumat import machine, nbrdf
from neumat.io import merl


def measure(fn, repeat):
    """Best of `repeat` (after one warm-up): wall s, user s, sys s, minor faults; and fn()."""
    out = fn()
    best = None
    for _ in range(repeat):
        r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        out = fn()
        t1, r1 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
        m = (t1 - t0, r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime,
             r1.ru_minflt - r0.ru_minflt)
        best = m if best is None or m[0] < best[0] else best
    return best, out


def row(name, m, base=None, rate=None):
    ratio = f"{base[0] / m[0]:8.2f}x" if base else f"{'':9s}"
    frac = f"{rate:7.1%}" if rate is not None else f"{'':7s}"
    print(f"{name:34s} {m[0] * 1e3:8.1f} {m[1]:7.3f} {m[2]:7.3f} {m[3]:9d} {ratio} {frac}")


def machine_line() -> float:
    """Print the machine, torch's threads and the fp32 sgemm rate; return that rate (FLOP/s)."""
    peak = machine.sgemm_peak()[0]
    print(f"machine: {machine.describe()}; torch threads {torch.get_num_threads()}, "
          f"fp32 sgemm {peak / 1e9:.0f} GFLOP/s")
    return peak


def header():
    print(f"{'':34s} {'wall ms':>8s} {'user s':>7s} {'sys s':>7s} {'faults':>9s} "
          f"{'speed-up':>9s} {'of sgemm':>7s}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--batch", type=int, default=8)
    a = ap.parse_args()
    peak = machine_line()
    flop = 2 * merl.N_BINS * sum(i * o for i, o in nbrdf.LAYERS)  # per table, matmuls only
    print(f"{merl.N_BINS} bins, {flop / 1e9:.2f} GFLOP per table")
    header()
    for b in (1, a.batch):
        w = nbrdf.init_weights(b, torch.Generator().manual_seed(b)) * 2
        base, t_base = measure(lambda: nbrdf.evaluate_grid(w, chunk=1 << 18), a.repeat)
        new, t_new = measure(lambda: nbrdf.evaluate_grid(w), a.repeat)
        assert np.array_equal(t_base, t_new), "the chunk size changed the values"
        row(f"evaluate_grid B={b}, chunk 2^18", base, rate=b * flop / base[0] / peak)
        row(f"evaluate_grid B={b}, library chunk", new, base,
            rate=b * flop / new[0] / peak)
    table = t_new[0]
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "t.binary")

        def tofile():  # the bound: the stored bytes, already scaled, written in one call
            with open(path, "wb") as f:
                merl.HEADER.tofile(f)
                stored.tofile(f)
        stored = (table / merl.SCALE[:, None, None, None]).astype("<f8")
        bound, _ = measure(tofile, a.repeat)
        wm, _ = measure(lambda: merl.write_merl(path, table), a.repeat)
        row("tofile of the scaled table (bound)", bound)
        print(f"{'write_merl':34s} {wm[0] * 1e3:8.1f} {wm[1]:7.3f} {wm[2]:7.3f} {wm[3]:9d} "
              f"{bound[0] / wm[0]:8.0%} of the bound")


if __name__ == "__main__":
    main()
