"""Materialise one AugMERL shard: physical BRDF of its materials at the stored bins."""
import pandas as pd

from neumat import augment
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    shard = snakemake.wildcards.shard
    manifest = pd.read_csv(snakemake.input.manifest, sep="\t", dtype={"shard": str},
                           keep_default_na=False)
    ids = manifest.loc[manifest["shard"] == shard, "id"].to_numpy()
    inp = snakemake.input
    aug = augment.AugMERL(inp.recipe, inp.log_tables, inp.log_index)
    values = aug.values(ids)
    log.info("shard %s: %d materials x %d bins, %.1f MB", shard, len(ids), values.shape[-1],
             values.nbytes / 1e6)
    augment.save_shard(snakemake.output[0], ids, aug.shard_bins, values)
