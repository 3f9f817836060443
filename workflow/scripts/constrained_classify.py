"""Classify every source material (from its table statistics) and every NeuMERL field into the
seven categories -> constrained/classes.tsv, and per type how cleanly it falls into one
category -> constrained/purity.tsv."""
import numpy as np
import pandas as pd

from neumat import constrained
from neumat.diffusion import dataset
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    inp, p, out = snakemake.input, snakemake.params, snakemake.output
    th = constrained.Thresholds.from_tsv(inp.rules, p.thresholds)
    src = pd.read_csv(inp.stats, sep="\t", keep_default_na=False)
    src = src.assign(set="source", id=np.arange(len(src)), category=constrained.classify(src, th))
    man = dataset.read_manifest(inp.manifest)
    weights = np.load(inp.weights)
    bins = constrained.grid_bins(p.bins, p.seed)
    neu = constrained.field_stats(weights, man["name"].tolist(), p.activation, bins)
    neu = neu.assign(set="neumerl", id=man["id"].to_numpy(), type=man["type"].to_numpy(),
                     category=constrained.classify(neu, th))
    cols = ["set", "id", "name", "type", "category", *constrained.STAT_COLUMNS]
    classes = pd.concat([src[cols], neu[cols]], ignore_index=True)
    classes = pd.concat([classes, constrained.features(classes).drop(columns="share_above")], axis=1)
    classes.to_csv(out.classes, sep="\t", index=False, float_format="%.6g")
    purity = pd.concat([constrained.type_purity(g["type"], g["category"]).assign(set=s)
                        for s, g in classes.groupby("set", sort=False)], ignore_index=True)
    purity.to_csv(out.purity, sep="\t", index=False, float_format="%.4g")
    for s, g in classes.groupby("set", sort=False):
        log.info("%s: %s", s, g["category"].value_counts().to_dict())
