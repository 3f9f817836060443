"""Train the multimodal diffusion model (type + text + image, each dropped independently) on the
NeuMERL train split; resumes from the checkpoint beside the output after a kill."""
from pathlib import Path

import numpy as np
import pandas as pd

from neumat.diffusion import DenoiserConfig, ScheduleConfig, TrainConfig, dataset, train
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p, inp = snakemake.params, snakemake.input
    weights = np.load(inp.weights)
    man = dataset.read_manifest(inp.manifest, len(weights))
    rows = dataset.training_rows(man, "ours")
    labels = dataset.labels(man["type"].iloc[rows], p.class_names)
    text, img = np.load(inp.text)[rows], np.load(inp.image)[rows]
    cfg = p.cfg
    mcfg = DenoiserConfig(**cfg["model"], n_classes=len(p.class_names),
                          vector_conditions={"text": text.shape[-1], "image": img.shape[-1]})
    speed = snakemake.config["diffusion"]["train"]  # speed-only keys: not in params
    tcfg = TrainConfig(**{**cfg["train"],  # cond_drop: conditions.cond_drop (the rule's params)
                          "checkpoint_every": speed["checkpoint_every"], "compile": speed["compile"]})
    log.info("multimodal: %d training materials (%d typed), text %s, image %s", len(rows),
             int((labels >= 0).sum()), text.shape, img.shape)
    Path(p.checkpoint).parent.mkdir(parents=True, exist_ok=True)
    bundle = train(weights[rows], labels, p.class_names, mcfg, ScheduleConfig(**cfg["schedule"]),
                   tcfg, snakemake.output.model, p.checkpoint, p.seed, snakemake.config["device"],
                   vectors={"text": text, "image": img}, activation=getattr(p, "activation", "relu"))
    pd.DataFrame(bundle["history"], columns=["step", "loss"]).to_csv(
        snakemake.output.history, sep="\t", index=False, float_format="%.6g")
    Path(p.checkpoint).unlink(missing_ok=True)
    log.info("trained in %.1f s (final loss %.4g)", bundle["train_seconds"], bundle["history"][-1][1])
