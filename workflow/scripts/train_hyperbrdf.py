"""Train one HyperBRDF model (`merl`: train-split source materials; `augmerl`: the whole
AugMERL train split) on a fixed random subset of each material's stored bins; resumes from the
checkpoint beside the output after a kill."""
from pathlib import Path

import numpy as np
import pandas as pd

from neumat import augment
from neumat.baselines import hyperbrdf as hb
from neumat.device import resolve_device
from neumat.logs import script_logging
from neumat.seeds import seed_for

with script_logging(snakemake) as log:
    # config device first: `cuda` without a GPU fails here, not after reading every shard
    dev = str(resolve_device(snakemake.config["device"]))
    inp, p, trainset = snakemake.input, snakemake.params, snakemake.wildcards.trainset
    man = pd.read_csv(inp.manifest, sep="\t", keep_default_na=False)
    train = man["split"] == "train"
    if trainset == "merl":
        train &= man["operation"] == "original"
    ids = set(man.loc[train, "id"].tolist())
    if not ids:
        raise ValueError(f"{inp.manifest}: no training materials for training set {trainset!r}")
    values, keep, bins, bins_key = [], None, None, "hyperbrdf.train_bins"
    for path in inp.shards:
        sh = augment.load_shard(path)
        if keep is None:
            n = min(p.cfg["train_bins"], len(sh["bins"]))
            if len(sh["bins"]) < p.cfg["train_bins"]:
                bins_key = "augmerl.bins"  # the shards store fewer bins than train_bins
            rng = np.random.default_rng(seed_for(p.seed, "bins"))  # p.seed seeds the model
            keep = np.sort(rng.choice(len(sh["bins"]), n, replace=False))
            bins = sh["bins"][keep]
        elif not np.array_equal(sh["bins"][keep], bins):
            raise ValueError(f"{path}: stores other bins than the first shard")
        rows = np.flatnonzero(np.isin(sh["ids"], list(ids)))
        values.append(sh["values"][rows][:, :, keep])
    values = np.concatenate(values)
    median = np.load(inp.median)[bins]
    log.info("training set %s: %d training materials x %d bins", trainset, len(values), len(bins))
    Path(p.checkpoint).parent.mkdir(parents=True, exist_ok=True)
    ckpt = snakemake.config["hyperbrdf"]["train"]["checkpoint_every"]  # speed-only: not a param
    bundle = hb.train(values, bins, median, hb.HyperConfig(**p.cfg["model"]),
                      hb.HyperTrainConfig(**p.cfg["train"], checkpoint_every=ckpt), snakemake.output.model,
                      p.checkpoint, p.seed, dev, bins_key=bins_key)
    pd.DataFrame(bundle["history"], columns=hb.HISTORY_COLUMNS).to_csv(
        snakemake.output.history, sep="\t", index=False, float_format="%.6g")
    Path(p.checkpoint).unlink(missing_ok=True)
    log.info("trained %s in %.1f s (final loss %.4g)", trainset, bundle["train_seconds"],
             bundle["history"][-1][1])
