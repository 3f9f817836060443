"""Train one hyperdiffusion model (`ours` or `merl100`) on its NeuMERL rows; resumes from the
checkpoint beside the output after a kill."""
from pathlib import Path

import numpy as np
import pandas as pd

from neumat.diffusion import DenoiserConfig, ScheduleConfig, TrainConfig, dataset, train
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p, model = snakemake.params, snakemake.wildcards.model
    weights = np.load(snakemake.input.weights)
    man = dataset.read_manifest(snakemake.input.manifest, len(weights))
    rows = dataset.training_rows(man, model)
    labels = dataset.labels(man["type"].iloc[rows], p.class_names)
    log.info("model %s: %d training materials (%d typed), %d classes", model, len(rows),
             int((labels >= 0).sum()), len(p.class_names))
    cfg, c = p.cfg, snakemake.config["diffusion"]  # c: speed-only keys (checkpoint_every)
    Path(p.checkpoint).parent.mkdir(parents=True, exist_ok=True)
    bundle = train(weights[rows], labels, p.class_names,
                   DenoiserConfig(**cfg["model"], n_classes=len(p.class_names)),
                   ScheduleConfig(**cfg["schedule"]),
                   TrainConfig(**cfg["train"], checkpoint_every=c["train"]["checkpoint_every"],
                               compile=c["train"]["compile"]),
                   snakemake.output.model, p.checkpoint, p.seed, snakemake.config["device"],
                   activation=getattr(p, "activation", "relu"))
    pd.DataFrame(bundle["history"], columns=["step", "loss"]).to_csv(
        snakemake.output.history, sep="\t", index=False, float_format="%.6g")
    Path(p.checkpoint).unlink(missing_ok=True)
    log.info("trained %s in %.1f s (final loss %.4g)", model, bundle["train_seconds"],
             bundle["history"][-1][1])
