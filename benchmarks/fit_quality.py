"""Fit quality and cost on realistic data with the default config's `fit:` settings.

Fits every MERL .binary table of --tables (e.g. the 100 real materials decoded from their
NBRDF networks) as one shard: template fit of the first (sorted) material, then all of them
from the template, `augmerl.bins` random valid bins each, exactly as `fit_template` and
`fit_shard` do. Prints median / 10th-percentile render PSNR (metric sphere view) and val loss,
wall time, time per material, the extrapolated time of the config's AugMERL size, and peak
memory (max RSS). Writes a per-material table with --out.

    OMP_NUM_THREADS=1 python benchmarks/fit_quality.py --tables /work/data/merl_decoded

--march builds the C kernel for another target (e.g. x86-64-v3: AVX2 on an AVX-512 host). The
CPU model, ISA and kernel are printed with the figures.
"""
import argparse
import os
import resource
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import yaml

from neumat import fit, fit_kernel, machine, nbrdf
from neumat.io import merl


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--tables", required=True, help="directory of MERL .binary tables")
    ap.add_argument("--config", default="config/config.yaml")
    ap.add_argument("--limit", type=int, default=None, help="fit only the first N tables")
    ap.add_argument("--out", default=None, help="write the per-material table (TSV) here")
    ap.add_argument("--march", default=None,
                    help="-march of the C kernel (default: native, or $NEUMAT_FIT_MARCH)")
    args = ap.parse_args()
    if args.march:  # before the first library load: the fitter builds for this target
        os.environ["NEUMAT_FIT_MARCH"] = args.march
    cfg = yaml.safe_load(open(args.config))
    fcfg, n_bins, seed = cfg["fit"], cfg["augmerl"]["bins"], cfg.get("seed", 0) + 3000
    torch.set_num_threads(fcfg.get("threads", 1))
    paths = sorted(Path(args.tables).glob("*.binary"))[:args.limit]
    if not paths:
        raise SystemExit(f"{args.tables}: no .binary files")
    tabs = np.stack([merl.read_merl(p) for p in paths])
    flat = tabs.reshape(len(tabs), 3, -1)
    ok = np.flatnonzero(merl.valid_mask() & (flat >= 0).all((0, 1)))
    bins = np.sort(np.random.default_rng(seed).choice(ok, n_bins, replace=False))
    values = flat[:, :, bins].astype(np.float32)
    ids = np.arange(len(paths))

    t0, c0 = time.perf_counter(), time.process_time()
    tmpl_s = fit.FitSettings.from_config(fcfg, "template_steps")
    init = nbrdf.init_weights(1, torch.Generator().manual_seed(seed)).numpy()
    tmpl = fit.fit_many(values[:1], bins, ids[:1], init, tmpl_s, seed)
    t_tmpl, c_tmpl = time.perf_counter() - t0, time.process_time() - c0
    s = fit.FitSettings.from_config(fcfg)
    t0, c0 = time.perf_counter(), time.process_time()
    res = fit.fit_many(values, bins, ids, tmpl["weights"][0], s, seed)
    t_fit, c_fit = time.perf_counter() - t0, time.process_time() - c0
    t0 = time.perf_counter()
    psnr = np.concatenate([fit.render_psnr(res["weights"][i:i + 8], tabs[i:i + 8],
                                           fcfg["render_resolution"], s.activation)
                           for i in range(0, len(ids), 8)])
    t_eval = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    df = pd.DataFrame({"name": [p.stem for p in paths], "train_loss": res["train_loss"],
                       "val_loss": res["val_loss"], "render_psnr": psnr})
    if args.out:
        df.to_csv(args.out, sep="\t", index=False, float_format="%.6g")
    n_aug, threads = cfg["augmerl"]["size"], fcfg.get("threads", 1)
    per, cper = t_fit / len(ids), c_fit / len(ids)
    print(df.sort_values("render_psnr").to_string(index=False))
    kernel = fit.resolve_kernel(s, "cpu")
    where = machine.describe(fit_kernel.default_march() if kernel == "c" else None)
    print(f"\nmachine: {where}; fit kernel {kernel}")
    print(f"{len(ids)} materials, {n_bins} bins, steps {s.steps}, batch {s.batch}, lr {s.lr}->"
          f"{s.lr_final}, {s.materials_per_batch} per batched model, {threads} thread(s)")
    print(f"render PSNR: median {np.median(psnr):.2f} dB, 10th percentile "
          f"{np.percentile(psnr, 10):.2f} dB, min {psnr.min():.2f} dB")
    print(f"val loss: median {np.median(res['val_loss']):.5f}, 90th percentile "
          f"{np.percentile(res['val_loss'], 90):.5f}; template val loss {tmpl['val_loss'][0]:.5f}")
    print(f"wall: template {t_tmpl:.1f} s, fits {t_fit:.1f} s ({per:.2f} s/material), "
          f"render PSNR {t_eval:.1f} s; peak RSS {rss:.0f} MB")
    print(f"CPU time: template {c_tmpl:.1f} s, fits {c_fit:.1f} s ({cper:.2f} CPU-s/material)"
          f"  [{where}; kernel {kernel}]")
    print(f"extrapolated {n_aug} fits: wall {n_aug * per / 3600:.2f} h on {threads} thread(s) at "
          f"this run's load; from CPU time {n_aug * cper / 3600:.2f} CPU-h = "
          f"{n_aug * cper / 3600 / 2:.2f} h with 2 such jobs on 2 free cores")


if __name__ == "__main__":
    main()
