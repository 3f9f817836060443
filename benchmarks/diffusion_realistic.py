"""Hyperdiffusion on realistic weights without the fitting stage: the 100 published NBRDF fits of
MERL (Sztrajman et al. 2021, ../shared/data/merl_nbrdf.zip; same 6-21-21-3 architecture) and
their 6 RGB permutations, which for a neural field are exact (permute the rows of W3 and b3).

  ours    : the 95 train-split sources x 6 permutations (570 fields)
  merl100 : the 95 train-split originals
  reference: the 5 test sources x 6 permutations (30 fields); 'training': 30 random train fields

Differences from the workflow (say so when quoting numbers): no PCA interpolations, and the
fits were not initialised from a common template (no weight-symmetry alignment).

Usage (each model in its own process, then the evaluation):
  python benchmarks/diffusion_realistic.py train ours --steps 800 --batch 64
  python benchmarks/diffusion_realistic.py train merl100 --steps 800 --batch 64
  python benchmarks/diffusion_realistic.py evaluate
Outputs under benchmarks/out/diffusion_realistic/.
"""

import argparse
import glob
import itertools
import json
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import yaml

from neumat import machine
from neumat.diffusion import (DenoiserConfig, Sampler, ScheduleConfig, TrainConfig, dataset,
                              plausibility, train)
from neumat.metrics import distances
from neumat.io import modelfile
from neumat.metrics.evaluate import evaluate_fields, table2

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks/out/diffusion_realistic"
ZIP_DIR = Path(os.environ.get("NBRDF_DIR", "/tmp/nbrdfzip/merl_nbrdf"))  # unzipped merl_nbrdf.zip


def load_fits():
    import h5py

    files = sorted(glob.glob(str(ZIP_DIR / "*.h5")))
    if len(files) != 100:
        raise FileNotFoundError(f"{ZIP_DIR}: expected 100 .h5 NBRDF files, found {len(files)} "
                                "(unzip ../shared/data/merl_nbrdf.zip, or set NBRDF_DIR)")
    names, ws = [], []
    for f in files:
        with h5py.File(f, "r") as h:
            parts = []
            for n in ("dense_1", "dense_2", "dense_3"):
                g = h[n][n]
                parts += [g["kernel:0"][()].T.ravel(), g["bias:0"][()].ravel()]  # Keras (in,out)
        names.append(Path(f).stem)
        ws.append(np.concatenate(parts).astype(np.float32))
    return names, np.stack(ws)


def permute_channels(w, perm):
    """The field of the RGB-permuted material: output channel c <- channel perm[c]."""
    w = w.copy()
    W3, b3 = w[..., -66:-3].reshape(*w.shape[:-1], 3, 21), w[..., -3:]
    w[..., -66:-3] = W3[..., list(perm), :].reshape(*w.shape[:-1], 63)
    w[..., -3:] = b3[..., list(perm)]
    return w


def build(seed=0):
    names, w = load_fits()
    cat = pd.read_csv(ROOT / "config/merl_materials.tsv", sep="\t", keep_default_na=False)
    types = cat.set_index("name").loc[names, "type"].to_numpy()
    test = set(np.random.default_rng(seed).choice(len(names), 5, replace=False).tolist())
    rows = []
    for k, perm in enumerate(itertools.permutations(range(3))):
        for i, n in enumerate(names):
            rows.append({"name": n if k == 0 else f"{n}@{''.join('rgb'[j] for j in perm)}",
                         "operation": "original" if k == 0 else "permutation", "type": types[i],
                         "split": "test" if i in test else "train", "src": i, "perm": k})
    man = pd.DataFrame(rows)
    man.insert(0, "id", np.arange(len(man)))
    perms = list(itertools.permutations(range(3)))
    weights = np.stack([permute_channels(w[r.src], perms[r.perm]) for r in man.itertuples()])
    return man, weights


def settings(steps, batch=None):
    cfg = yaml.safe_load(open(ROOT / "config/schema.yaml"))["properties"]["diffusion"]["properties"]
    d = lambda sec: {k: v["default"] for k, v in cfg[sec]["properties"].items()}  # noqa: E731
    tr = d("train")
    tr.update(steps=steps, warmup_steps=min(tr["warmup_steps"], steps // 10),
              batch_size=batch or tr["batch_size"])
    return d("model"), d("schedule"), tr, d("sample")


def cmd_train(model, steps, seed, batch):
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    man, weights = build()
    names = dataset.class_names(man["type"])
    rows = dataset.training_rows(man, model)
    m, s, t, _ = settings(steps, batch)
    OUT.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    train(weights[rows], dataset.labels(man["type"].iloc[rows], names), names,
          DenoiserConfig(**m, n_classes=len(names)), ScheduleConfig(**s), TrainConfig(**t),
          OUT / f"{model}.pt", OUT / f"{model}.ckpt.pt", seed, "cpu")
    print(f"{model}: {len(rows)} training fields, {steps} steps, {time.perf_counter() - t0:.0f} s")


def cmd_evaluate(seed, resolution, bins):
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    man, weights = build()
    ref = weights[dataset.reference_rows(man)]
    _, _, _, smp = settings(1)
    sets, info = {"training_set": weights[dataset.training_subset(man, seed)]}, {}
    for model in ("merl100", "ours"):
        b = modelfile.load(OUT / f"{model}.pt")
        sampler = Sampler(b, "cpu")
        t0 = time.perf_counter()
        sets[model] = sampler.sample(len(ref), seed + 1, None, smp["steps"], smp["eta"])
        dt = time.perf_counter() - t0
        np.save(OUT / f"{model}_samples.npy", sets[model])
        info[model] = {"train_s": b["train_seconds"], "steps": b["train_cfg"]["steps"],
                       "n_train": b["n_train"], "samples_per_s": len(ref) / dt}
    # type conditioning: 8 samples for each of 6 types, nearest typed training field
    b = Sampler(modelfile.load(OUT / "ours.pt"), "cpu")
    tr = dataset.training_rows(man, "ours")
    asked = [t for t in sorted(set(man["type"].iloc[tr]))[:48:8] for _ in range(8)]
    wt = b.sample(len(asked), seed + 2, asked, smp["steps"], smp["eta"], smp["guidance"])
    bsel = distances.brdf_sample(bins, seed)
    idx, _ = dataset.nearest(distances.field_values(np.nan_to_num(wt), bsel),
                             distances.field_values(weights[tr], bsel))
    match = float(np.mean(man["type"].iloc[tr[idx]].to_numpy() == np.array(asked)))
    bins_sel = distances.brdf_sample(bins, seed)
    res = {k: evaluate_fields(ref, np.nan_to_num(v), resolution=resolution, bins=bins_sel)
           for k, v in sets.items()}
    tab = table2(res)
    OUT.mkdir(parents=True, exist_ok=True)
    tab.to_csv(OUT / "table2.csv")
    print(tab.reset_index().to_markdown(index=False))
    ref_max = float(plausibility.plausibility(weights[tr])["max_value"].max())
    plaus = pd.DataFrame([{"set": k, **plausibility.summarize(plausibility.plausibility(
        v, reference_max=ref_max))} for k, v in {"reference": ref, **sets, "ours_type": wt}.items()])
    print(plaus.to_markdown(index=False))
    print(json.dumps({"models": info, "type_match": match, "types": sorted(set(asked))}, indent=1))


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd", choices=["train", "evaluate"])
    ap.add_argument("model", nargs="?", choices=["ours", "merl100"])
    ap.add_argument("--steps", type=int, default=5000)
    ap.add_argument("--batch", type=int, default=None, help="default: the config default")
    ap.add_argument("--seed", type=int, default=5000)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--bins", type=int, default=20000)
    a = ap.parse_args()
    print(f"machine: {machine.describe()}", flush=True)
    if a.cmd == "train":
        cmd_train(a.model, a.steps, a.seed, a.batch)
    else:
        cmd_evaluate(a.seed, a.resolution, a.bins)
