"""Train a finished run's `ours` again with another training seed, for Table 2's spread over
trainings.

Rule train_diffusion's training as it ran: the run's NeuMERL weights and manifest, `ours`'
training rows and type labels, and the configs, class names and seed recorded in the run's
diffusion/ours/model.pt; the seed + K, so each K is one more training of the same config on
the same data, on the CPU. Writes OUT (a model.pt; its checkpoint beside it, OUT's stem +
.checkpoint.pt, so a killed run resumes) and prints the wall time and final loss. Score it as
rule metrics scores the run's own:

    OMP_NUM_THREADS=2 python benchmarks/retrain_seed.py --results results/<run> --offset 1 --out M
    OMP_NUM_THREADS=2 python benchmarks/clamp_step_table2.py --results results/<run> --steps 0 --model M

`--activation`: the NBRDF's (fit.activation), for the field term; default the run's recorded one.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from neumat import cli, machine
from neumat.diffusion import DenoiserConfig, ScheduleConfig, TrainConfig, dataset, train
from neumat.io import modelfile


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", required=True, help="a finished run: results/<run>")
    ap.add_argument("--offset", type=int, required=True, help="K: train with the run's seed + K")
    ap.add_argument("--out", required=True, help="the model.pt to write")
    ap.add_argument("--activation", help="the NBRDF's activation (default: the run's)")
    a = ap.parse_args()
    if a.offset == 0:
        ap.error("--offset 0 retrains the run's own model: give K != 0")
    run = Path(a.results)
    src = run / "diffusion/ours/model.pt"
    bundle = modelfile.require(modelfile.load(src), ("model_cfg", "sched_cfg", "train_cfg",
                                                     "class_names", "seed"), src, "train_diffusion")
    weights = np.load(run / "neumerl/weights.npy")
    man = dataset.read_manifest(run / "neumerl/manifest.tsv", len(weights))
    rows = dataset.training_rows(man, "ours")
    labels = dataset.labels(man["type"].iloc[rows], bundle["class_names"])
    seed = int(bundle["seed"]) + a.offset
    activation = a.activation or cli.Run(run).activation()
    out = Path(a.out)
    checkpoint = out.with_name(out.stem + ".checkpoint.pt")
    out.parent.mkdir(parents=True, exist_ok=True)
    print(f"machine: {machine.describe()}; {run}: {len(rows)} training rows, seed {seed} "
          f"(the run's {bundle['seed']} + {a.offset}), activation {activation}")
    t0 = time.perf_counter()
    result = train(weights[rows], labels, bundle["class_names"],
                   DenoiserConfig.from_dict(bundle["model_cfg"]),
                   ScheduleConfig(**bundle["sched_cfg"]), TrainConfig(**bundle["train_cfg"]),
                   out, checkpoint, seed, "cpu",
                   activation=activation)
    print(f"{out}: {time.perf_counter() - t0:.0f} s wall this process, "
          f"{result['train_seconds']:.0f} s training in all, "
          f"final loss {result['history'][-1][1]:.4g}")


if __name__ == "__main__":
    main()
