"""Fit every material of one AugMERL shard, batched, from the template's weights."""
from pathlib import Path

import numpy as np

from neumat import augment, fit
from neumat.device import resolve_device
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    shard = augment.load_shard(snakemake.input.shard)
    template = fit.load_fits(snakemake.input.template)["weights"][0]
    # params hold what changes the result; speed-only keys come from the config (speed_keys.yaml)
    speed = {k: snakemake.config["fit"][k] for k in ("materials_per_batch", "checkpoint_every")}
    settings = fit.FitSettings.from_config({**p.cfg, **speed})
    Path(p.checkpoint).parent.mkdir(parents=True, exist_ok=True)
    res = fit.fit_many(shard["values"], shard["bins"], shard["ids"], template, settings, p.seed,
                       resolve_device(snakemake.config["device"]), checkpoint=p.checkpoint)
    fit.save_fits(snakemake.output[0], res)
    Path(p.checkpoint).unlink(missing_ok=True)
    log.info("shard %s: %d materials, median val loss %.4g (max %.4g), %.1f s",
             snakemake.wildcards.shard, len(res["ids"]), np.median(res["val_loss"]),
             res["val_loss"].max(), res["seconds"])
