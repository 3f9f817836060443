"""Exporting NBRDF fields to MERL .binary tables (`neumat sample`, rules `export_samples` and
`neumerl_export`): `nbrdf.evaluate_grid` (channel-major layers, valid bins only, since
2026-11-26) against the version before it in the same run (`row_major_grid`: row-major
layers, `nbrdf_layout.row_major`, at every bin, the invalid ones then overwritten), for one
table and a batch of 8; and `merl.write_merl` against writing the same bytes with one
`ndarray.tofile` (the bound). Prints the best wall time, CPU seconds split user/system, the
minor page faults, the ratios, and the evaluation's rate (the matmuls of the bins it
evaluates) as a fraction of this machine's fp32 sgemm rate, with the ISA and the CPU model.
The two give the same tables to float32 rounding (checked here).

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
from nbrdf_layout import row_major  # this directory: the row-major layers of the baseline


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


def row_major_grid(w: torch.Tensor) -> np.ndarray:
    """The baseline: evaluate_grid before 2026-11-26, every bin through row-major layers
    (nbrdf.forward then), 2^15 / B bins a chunk, the invalid bins overwritten with -1/scale."""
    grid = merl.grid_inputs()
    chunk = 1 << max(10, ((1 << 15) // max(1, w.shape[0])).bit_length() - 1)
    out = np.empty((w.shape[0], 3, merl.N_BINS), dtype=np.float64)
    with torch.no_grad():
        for s in range(0, merl.N_BINS, chunk):
            x = torch.from_numpy(grid[s:s + chunk].copy())
            f = torch.relu(torch.expm1(row_major(w, x)))
            out[:, :, s:s + chunk] = f.numpy().transpose(0, 2, 1)
    out[:, :, ~merl.valid_mask()] = -1.0 * merl.SCALE[None, :, None]
    return out.reshape(w.shape[0], *merl.SHAPE)


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
    per_bin = 2 * sum(i * o for i, o in nbrdf.LAYERS)  # matmul FLOPs per bin
    valid = int(merl.valid_mask().sum())
    print(f"{merl.N_BINS} bins ({valid} valid), {per_bin * merl.N_BINS / 1e9:.2f} GFLOP per "
          f"table at every bin")
    header()
    for b in (1, a.batch):
        w = nbrdf.init_weights(b, torch.Generator().manual_seed(b)) * 2
        base, t_base = measure(lambda: row_major_grid(w), a.repeat)
        new, t_new = measure(lambda: nbrdf.evaluate_grid(w), a.repeat)
        np.testing.assert_allclose(t_new, t_base, rtol=1e-5, atol=1e-6)
        row(f"B={b}, every bin, row-major (before)", base,
            rate=b * per_bin * merl.N_BINS / base[0] / peak)
        row(f"B={b}, evaluate_grid", new, base, rate=b * per_bin * valid / new[0] / peak)
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
