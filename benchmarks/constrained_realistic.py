"""Constrained synthesis on realistic weights: acceptance rate per category of a diffusion model
trained on the published NBRDF fits of the 100 MERL materials (see diffusion_realistic.py, which
trains it), with thresholds derived from those 100 materials.

Also lays the results out as a run directory (diffusion/ours/model.pt, constrained/rules.tsv,
constrained/classes.tsv, constrained/acceptance.tsv) so `neumat info/sample` work on it.

Usage:
  python benchmarks/diffusion_realistic.py train ours --steps 1500 --batch 64
  python benchmarks/constrained_realistic.py --budget 256 --batch 64
Outputs under benchmarks/out/constrained_realistic/run/.
"""

import argparse
import shutil
import sys
import time
from pathlib import Path

import pandas as pd
import torch
import yaml

sys.path.insert(0, str(Path(__file__).parent))
import diffusion_realistic as dr  # noqa: E402

from neumat import constrained as C  # noqa: E402
from neumat import machine  # noqa: E402
from neumat.diffusion import Sampler  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "benchmarks/out/constrained_realistic/run"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--budget", type=int, default=256)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--per-category", type=int, default=8)
    ap.add_argument("--bins", type=int, default=65536)
    ap.add_argument("--source-bins", type=int, default=None, help="bins for the 100 sources (default: all)")
    ap.add_argument("--seed", type=int, default=7000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = dr.OUT / "ours.pt"
    if not model.exists():
        sys.exit(f"{model} missing: run `python benchmarks/diffusion_realistic.py train ours` first")
    (RUN / "diffusion/ours").mkdir(parents=True, exist_ok=True)
    (RUN / "constrained").mkdir(parents=True, exist_ok=True)
    shutil.copy(model, RUN / "diffusion/ours/model.pt")

    names, w = dr.load_fits()
    types = pd.read_csv(ROOT / "config/merl_materials.tsv", sep="\t").set_index("name").loc[names, "type"].tolist()
    t0 = time.perf_counter()
    stats = C.field_stats(w, names, bins=C.grid_bins(args.source_bins, 0))
    th, how = C.derive_thresholds(stats, types)
    th.to_frame(how).to_csv(RUN / "constrained/rules.tsv", sep="\t", index=False, float_format="%.6g")
    src = stats.assign(set="source", id=range(len(names)), type=types, category=C.classify(stats, th))
    src.to_csv(RUN / "constrained/classes.tsv", sep="\t", index=False, float_format="%.6g")
    print(f"source statistics + thresholds: {time.perf_counter() - t0:.0f} s; {th}")
    print(src["category"].value_counts().to_string())

    sampler = Sampler(RUN / "diffusion/ours/model.pt", "cpu")
    guides = C.category_types(src["type"], src["category"])
    sample_cfg = yaml.safe_load(open(ROOT / "config/schema.yaml"))["properties"]["diffusion"][
        "properties"]["sample"]["properties"]
    sample_cfg = {k: v["default"] for k, v in sample_cfg.items()}
    bins = C.grid_bins(args.bins, args.seed)
    rows = []
    for k, cat in enumerate(C.CATEGORIES):
        t0 = time.perf_counter()
        r = C.sample_category(sampler, cat, th, args.per_category, args.budget, args.batch,
                              args.seed + 10_000_000 * k, sample_cfg,
                              [t for t in guides[cat] if t in sampler.class_names], bins)
        row = C.acceptance_row(r, args.per_category) | {"seconds": round(time.perf_counter() - t0, 1)}
        rows.append(row)
        print(row, flush=True)
    acc = pd.DataFrame(rows)
    acc.to_csv(RUN / "constrained/acceptance.tsv", sep="\t", index=False, float_format="%.4g")
    print(acc.drop(columns=["seconds"]).to_markdown(index=False, floatfmt=".3f"))
    print(f"machine: {machine.describe()}, torch threads {torch.get_num_threads()}")


if __name__ == "__main__":
    main()
