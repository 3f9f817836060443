"""The HyperBRDF value mapping's median: per MERL bin, over the train-split source materials
and their channels (neumat.baselines.hyperbrdf.bin_median); 0 at invalid bins."""
import numpy as np
import pandas as pd

from neumat import augment
from neumat.baselines import hyperbrdf as hb
from neumat.io.atomic import save_npy
from neumat.io import merl
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    inp = snakemake.input
    man = pd.read_csv(inp.manifest, sep="\t", keep_default_na=False)
    ids = man.loc[(man["operation"] == "original") & (man["split"] == "train"), "id"].to_numpy()
    if len(ids) == 0:
        raise ValueError(f"{inp.manifest}: no train-split source materials")
    aug = augment.AugMERL(inp.recipe, inp.log_tables, inp.log_index)
    median = np.zeros(merl.N_BINS, np.float32)
    valid = aug.valid_bins
    for s in range(0, len(valid), 1 << 16):
        b = valid[s:s + (1 << 16)]
        median[b] = hb.bin_median(aug.values(ids, b))
    save_npy(snakemake.output[0], median)
    log.info("median over %d train sources x 3 channels at %d valid bins (mean %.4g)",
             len(ids), len(valid), float(median[valid].mean()))
