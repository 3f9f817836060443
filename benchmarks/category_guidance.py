"""Category guidance (neumat.diffusion.constraints.CategoryConstraint) on a finished run: for
diffuse and metallic, the share of one batch of draws that paper eqs. 9-10 accept, by guidance
step and margin, against plain rejection sampling (step 0, the baseline, in the same run). Also
how far the accepted draws sit from the training set (median BRDF-L1 to the nearest training
material, the measure of rule diffusion_nearest) and the share of them that are passive
(directional albedo <= 1, `plausibility`) and how bright and glossy they are (median body and
peak, `neumat.constrained.features`) beside the real materials of that category, so a gain in acceptance that leaves the data is
visible, and the sampling time as a ratio to step 0. Prints the ISA and the CPU model.

    python benchmarks/category_guidance.py --run results/<run> [-n 64] [--steps 0 3 10 30]

Uses <run>/diffusion/ours/model.pt, <run>/neumerl/{weights.npy,manifest.tsv} and the run's
sampling settings (schema defaults: 100 DDIM steps, negative_step 30); one torch thread.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from neumat import constrained as C
from neumat import machine, nbrdf
from neumat.diffusion import Sampler, dataset
from neumat.diffusion import constraints as K
from neumat.diffusion.plausibility import plausibility
from neumat.diffusion.schedule import RowNoise, guided
from neumat.metrics import distances
from neumat.seeds import seed_for


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", required=True, type=Path)
    ap.add_argument("-n", type=int, default=64, help="draws per setting (one batch)")
    ap.add_argument("--steps", type=float, nargs="+", default=[0, 3, 10, 30])
    ap.add_argument("--margins", type=float, nargs="+", default=[0.0, K.MARGIN],
                    help="margins tried at --margin-step")
    ap.add_argument("--margin-step", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--bins", type=int, default=65536, help="statistics grid (constrained.bins)")
    ap.add_argument("--nn-bins", type=int, default=20000, help="BRDF-L1 bins (diffusion.nn_bins)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    print(f"machine: {machine.describe()}; torch threads 1")
    sampler = Sampler(a.run / "diffusion/ours/model.pt", "cpu")
    weights = np.load(a.run / "neumerl/weights.npy")
    man = dataset.read_manifest(a.run / "neumerl/manifest.tsv", len(weights))
    nn_bins = distances.brdf_sample(a.nn_bins, 0)
    f_train = distances.field_values(weights[dataset.training_rows(man, "ours")], nn_bins)
    # the yardstick: the real test-split materials' distance to the training set, per category
    # and how bright (body = max_c mean_c) and glossy (peak = max_c max_c) real ones are, 1/sr
    th = C.Thresholds()  # eqs. 9-10 are checked first: the derived thresholds do not matter here
    stat_bins = C.grid_bins(a.bins, 0)
    test = dataset.reference_rows(man)
    _, t_dist = dataset.nearest(distances.field_values(weights[test], nn_bins), f_train)
    for split, rows in (("test", test), ("train", dataset.training_rows(man, "ours"))):
        st = C.field_stats(weights[rows], bins=stat_bins)
        cat, feat = C.classify(st, th), C.features(st)
        for category in K.GUIDED_CATEGORIES + ("all",):
            m = cat == category if category != "all" else np.ones(len(rows), bool)
            near = f", median BRDF-L1 to the nearest training material {np.median(t_dist[m]):.3f}" \
                if split == "test" and m.any() else ""
            look = (f", median body {np.median(feat['body'][m]):.4f}, peak "
                    f"{np.median(feat['peak'][m]):.3f}") if m.any() else ""
            print(f"{split} split, {category}: {m.sum()} of {len(rows)} materials{near}{look}")

    def sample(category, step, margin):
        """Sampler.sample's draw (100 DDIM steps, no type guidance, negative_step 30), with the
        category guidance's margin open."""
        rows = RowNoise(seed_for(a.seed, "ddim"), nbrdf.N_PARAMS)  # Sampler.sample's noise
        hook = K.chain(K.NegativeConstraint(sampler.norm, 30.0, a.seed),
                       K.CategoryConstraint(sampler.norm, category, step, a.seed, margin=margin)
                       if step else None)
        z = sampler.diffusion.ddim_sample(guided(sampler.model, None, 1.0), (a.n, nbrdf.N_PARAMS),
                                          100, 0.0, None, "cpu", constrain=hook,
                                          noise=rows.batch(0, a.n))
        return sampler.norm.decode(z).float().numpy()

    def draw(category, step, margin):
        t0 = time.perf_counter()
        w = sample(category, step, margin)
        secs = time.perf_counter() - t0
        if margin == K.MARGIN:  # the library's path gives the same draws
            lib = sampler.sample(a.n, a.seed, None, 100, 0.0, 1.0, 256, None, 30.0, "relu",
                                 category if step else None, step)
            assert np.array_equal(lib, w), "benchmark and Sampler.sample disagree"
        st = C.field_stats(w, bins=stat_bins)
        ok, feat = C.classify(st, th) == category, C.features(st)
        _, dist = dataset.nearest(distances.field_values(np.nan_to_num(w), nn_bins), f_train)
        passive = ~plausibility(w[ok])["passivity_violation"].to_numpy(bool) if ok.any() else []
        return {"category": category, "step": step, "margin": margin if step else float("nan"),
                "drawn": a.n, "accepted": int(ok.sum()), "acceptance": ok.mean(),
                "nn_l1_accepted": float(np.median(dist[ok])) if ok.any() else float("nan"),
                "nn_l1_all": float(np.median(dist)),
                "passive_accepted": float(np.mean(passive)) if ok.any() else float("nan"),
                "body_accepted": float(np.median(feat["body"][ok])) if ok.any() else float("nan"),
                "peak_accepted": float(np.median(feat["peak"][ok])) if ok.any() else float("nan"),
                "seconds": secs}

    rows = []
    for category in K.GUIDED_CATEGORIES:
        settings = [(s, K.MARGIN) for s in a.steps]
        settings += [(a.margin_step, m) for m in a.margins if (a.margin_step, m) not in settings]
        for step, margin in settings:
            rows.append(draw(category, step, margin))
            print(rows[-1], flush=True)
    df = pd.DataFrame(rows)
    base = df[df["step"] == 0].set_index("category")["seconds"]
    df["time_vs_step0"] = df["seconds"] / df["category"].map(base)
    print(df.to_markdown(index=False, floatfmt=".3f"))


if __name__ == "__main__":
    main()
