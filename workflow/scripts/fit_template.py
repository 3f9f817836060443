"""Fit the template material (the first train-split original: augment.template_id) from a
random init; its weights initialise every other fit (weight-symmetry alignment, paper §3.2)."""
from pathlib import Path

import numpy as np
import torch

from neumat import augment, fit, nbrdf
from neumat.device import resolve_device
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    shard = augment.load_shard(snakemake.input.shard)
    hit = np.flatnonzero(shard["ids"] == p.template)
    if not len(hit):
        raise ValueError(f"{snakemake.input.shard}: holds no material with manifest id "
                         f"{p.template}; rerun the workflow (augmerl_pca, augmerl_shard)")
    k = slice(hit[0], hit[0] + 1)
    # params hold what changes the result; speed-only keys come from the config (speed_keys.yaml)
    speed = {k: snakemake.config["fit"][k] for k in ("materials_per_batch", "checkpoint_every")}
    settings = fit.FitSettings.from_config({**p.cfg, **speed}, "template_steps")
    init = nbrdf.init_weights(1, torch.Generator().manual_seed(p.seed)).numpy()
    Path(p.checkpoint).parent.mkdir(parents=True, exist_ok=True)
    res = fit.fit_many(shard["values"][k], shard["bins"], shard["ids"][k], init, settings,
                       p.seed, resolve_device(snakemake.config["device"]), checkpoint=p.checkpoint)
    fit.save_fits(snakemake.output[0], res)
    Path(p.checkpoint).unlink(missing_ok=True)
    log.info("template (id %d): train loss %.4g, val loss %.4g, %d steps in %.1f s", p.template,
             res["train_loss"][0], res["val_loss"][0], settings.steps, res["seconds"])
