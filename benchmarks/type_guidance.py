"""Type-conditioned samples of `ours` (rule sample_type) against the guidance scale, on a
finished run: per scale and draw, the type hits (the nearest typed training material has the
asked type) and the distance to the nearest training material, absolute (median BRDF-L1, rule
diffusion_nearest's measure) and relative to that material's mean value over the same bins
(`relative_l1`; a specular material's values run tens of times a diffuse one's, so the absolute
median of a set depends on its mix of materials). The test split's own figures are the
yardstick row; the time of each scale is given as a ratio to scale 1 (the baseline, one pass of
the model per step; other scales take two). Prints the ISA and the CPU model.

    python benchmarks/type_guidance.py --run results/<run> [--scales 1 2] [--draws 2]

Draw 1 is the run's own (seed stream `sample_type`): at the scale its samples/ours_type/timing.tsv
records, it must equal the run's samples/ours_type/weights.npy (checked). Draw k > 1 comes from
stream `sample_type`/check<k>. Settings (the types, per_type, DDIM steps, eta, clamp step and
refit, nn_bins) are the run's recorded config (report/index.md), else the schema's defaults; on
the CPU, one torch thread (the check assumes the run sampled on the CPU too).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from neumat import cli, machine
from neumat.diffusion import Sampler, dataset
from neumat.metrics import distances
from neumat.seeds import seed_for


def nearest(f, f_train, train_mean):
    """(index, BRDF-L1, BRDF-L1 over the nearest's mean value) of each row's nearest row."""
    idx, dist = dataset.nearest(f, f_train)
    return idx, dist, dataset.relative(dist, idx, train_mean)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", required=True, type=Path)
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--draws", type=int, default=2, help="draws per scale (the run's own first)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    print(f"machine: {machine.describe()}; torch threads 1")
    setting = cli.Run(a.run).setting
    s = {k: setting("diffusion", "sample", k) for k in ("steps", "eta", "batch_size", "clip",
                                                        "negative_step", "refit_steps")}
    activation = setting("fit", "activation")
    weights = np.load(a.run / "neumerl/weights.npy")
    man = dataset.read_manifest(a.run / "neumerl/manifest.tsv", len(weights))
    train = dataset.training_rows(man, "ours")
    typed = train[man["type"].iloc[train].to_numpy() != ""]
    bins = distances.brdf_sample(setting("diffusion", "nn_bins"),
                                 seed_for(setting("seed"), "diffusion_nearest"))
    fv = lambda w: distances.field_values(np.nan_to_num(w), bins, activation)  # noqa: E731
    f_train = fv(weights[train])
    train_mean = f_train.abs().mean(1).numpy()
    f_typed = f_train[np.searchsorted(train, typed)]
    types = setting("diffusion", "types") or sorted(dataset.training_types(man))  # as sample_type
    asked = np.array([t for t in types for _ in range(setting("diffusion", "per_type"))])

    ref = dataset.reference_rows(man)
    _, d, rel = nearest(fv(weights[ref]), f_train, train_mean)
    rows = [{"set": "test split", "scale": "", "draw": "", "type hits %": "",
             "median BRDF-L1": np.median(d), "median relative": np.median(rel),
             "relative p90": np.percentile(rel, 90), "time ratio": ""}]
    run_w = np.load(a.run / "samples/ours_type/weights.npy")
    run_scale = float(pd.read_csv(a.run / "samples/ours_type/timing.tsv", sep="\t")["guidance"][0])
    base = setting("seed")
    sampler = Sampler(a.run / "diffusion/ours/model.pt", "cpu")  # loaded once, outside the timer
    times, checked = {}, False
    for g in a.scales:
        for k in range(1, a.draws + 1):
            seed = seed_for(base, "sample_type") if k == 1 else seed_for(base, "sample_type",
                                                                         f"check{k}")
            t = time.perf_counter()
            w = sampler.sample(len(asked), seed, list(asked), s["steps"], s["eta"], g,
                               s["batch_size"], s["clip"], s["negative_step"], activation,
                               refit_steps=s["refit_steps"])
            times.setdefault(g, []).append(time.perf_counter() - t)
            if k == 1 and g == run_scale:
                assert np.array_equal(w, run_w), "draw 1 differs from the run's ours_type"
                checked = True
            f = fv(w)
            _, d, rel = nearest(f, f_train, train_mean)
            tidx, _ = dataset.nearest(f, f_typed)
            hits = asked == man["type"].iloc[typed[tidx]].to_numpy()
            rows.append({"set": "ours_type", "scale": g, "draw": k,
                         "type hits %": 100 * hits.mean(), "median BRDF-L1": np.median(d),
                         "median relative": np.median(rel),
                         "relative p90": np.percentile(rel, 90), "time ratio": None})
    base_scale = 1.0 if 1.0 in times else a.scales[0]  # the baseline: scale 1, one pass a step
    for r in rows[1:]:
        r["time ratio"] = np.mean(times[r["scale"]]) / np.mean(times[base_scale])
    print(f"{len(asked)} samples per draw ({len(types)} types x "
          f"{setting('diffusion', 'per_type')}), {s['steps']} DDIM steps, clamp step "
          f"{s['negative_step']:g}; run {a.run} (its ours_type at scale {run_scale:g}: "
          f"{'draw 1 equal to it' if checked else 'not among --scales, unchecked'}); "
          f"time ratio to scale {base_scale:g}")
    print(pd.DataFrame(rows).to_string(index=False, float_format=lambda v: f"{v:.3f}"))


if __name__ == "__main__":
    main()
