"""Rule metrics_reference: the reference set prepared once for all Table-2 columns, against each
metrics job preparing it itself (the baseline), in the same run, on a finished run's files.

Times one column's metrics (`--model`, its first `--draws` draws) both ways: `evaluate_draws`
rendering and featurising the references itself, and `prepare_reference` once plus
`evaluate_draws(..., reference=)`. Checks that the two tables are equal, and prints the cost of
the metrics stage for the run's columns both ways (every column but the halves sanity row uses
the shared file), the timed part's wall time against its bound here, CPU-s / cores used (torch's
threads, at most the CPUs; near it: CPU-bound, only less CPU work shortens it), with the CPU
model and ISA.

    OMP_NUM_THREADS=2 python benchmarks/metrics_reference.py --results results/default [--model ours]
        [--config C]   # settings: the run's recorded config (report/index.md), else the schema
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import pandas as pd
import torch
import yaml

from neumat import cli, machine, seeds
from neumat.metrics import distances, evaluate, inception, materials


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", required=True, help="a finished run: results/<run>")
    ap.add_argument("--model", default="ours", help="the column timed (samples/<model>/)")
    ap.add_argument("--draws", type=int, default=1, help="draws of that column timed")
    ap.add_argument("--config", help="a config whose keys override the run's recorded config "
                                     "(default: that, or the schema's defaults)")
    a = ap.parse_args()
    run = Path(a.results)
    # the run's config as `report` recorded it, else the schema defaults; --config's keys first
    setting = cli.Run(run, yaml.safe_load(Path(a.config).read_text()) if a.config else None).setting

    seed = seeds.seed_for(setting("seed"), "metrics")
    draws = setting("metrics", "draws")
    kw = dict(resolution=setting("render", "resolution"),
              bins=distances.brdf_sample(setting("metrics", "brdf_samples"), seed),
              activation=setting("fit", "activation"),
              fid_model=inception.fid_network(setting("metrics", "inception_weights"))[0])
    ref = materials.load(run / "samples/reference/weights.npy")
    smp_dir = run / "samples" / a.model
    smp = materials.load(next(p for p in (smp_dir / "weights.npy", smp_dir / "tables.npz") if p.exists()))
    n = len(smp) // draws
    sets = [materials.rows(smp, slice(i * n, (i + 1) * n)) for i in range(a.draws)]
    print(f"machine: {machine.describe()}; {len(ref)} references, {a.model}: {a.draws} of "
          f"{draws} draws of {n}, renders {kw['resolution']} px")
    c_start, w_start = time.process_time(), time.perf_counter()  # the CPU bound of what is timed
    t0 = time.perf_counter()
    own = evaluate.evaluate_draws(ref, sets, **kw)
    t_own = time.perf_counter() - t0
    t0 = time.perf_counter()
    prepared = evaluate.prepare_reference(ref, **kw)
    t_prep = time.perf_counter() - t0
    t0 = time.perf_counter()
    shared = evaluate.evaluate_draws(None, sets, **kw, reference=prepared)
    t_shared = time.perf_counter() - t0
    cpu, wall = time.process_time() - c_start, time.perf_counter() - w_start
    n_thr = min(torch.get_num_threads(), os.cpu_count() or 1)  # the cores it can use
    pd.testing.assert_frame_equal(own, shared, check_exact=True)
    models = setting("metrics", "models")
    per_draw = t_shared / a.draws
    before = len(models) * (t_own + (draws - a.draws) * per_draw)
    after = t_prep + len(models) * draws * per_draw
    print(f"one job, {a.draws} draw(s): preparing the references itself {t_own:.1f} s; "
          f"with the prepared file {t_shared:.1f} s; preparing it once {t_prep:.1f} s; "
          f"tables equal")
    print(f"timed: {wall:.1f} s wall, {cpu:.1f} CPU-s; bound on {n_thr} cores {cpu / n_thr:.1f} s: "
          f"wall is {wall / (cpu / n_thr):.2f}x the bound, the cores {cpu / (n_thr * wall):.0%} "
          "busy")
    print(f"metrics stage, {len(models)} columns x {draws} draws (the halves row aside): "
          f"{before:.0f} s -> {after:.0f} s ({before / after:.2f}x)  [{machine.describe()}]")


if __name__ == "__main__":
    main()
