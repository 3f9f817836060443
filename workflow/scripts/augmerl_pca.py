"""AugMERL plan: manifest (one row per material) + exact reconstruction recipe."""
import numpy as np
import pandas as pd

from neumat import augment
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    cfg, seed = snakemake.params.cfg, snakemake.params.seed
    catalog = pd.DataFrame(snakemake.params.catalog)
    names = list(catalog["name"])
    split = augment.split_sources(names, cfg["test_fraction"], seed)
    rows = augment.plan_rows(catalog, cfg["permutations"], split)
    n_interp = max(cfg["size"] - len(rows), 0)
    if cfg["size"] < len(rows):
        log.warning("augmerl.size = %d < %d originals+permutations: no interpolations",
                    cfg["size"], len(rows))
    pairs = augment.plan_pairs(rows, n_interp, seed)
    manifest = augment.build_manifest(rows, pairs, cfg["shard_size"])
    log.info("%d sources -> %d rows + %d interpolations", len(names), len(rows), len(pairs))

    # negative-bin counts per table: warned in the cache's log, shown in the report
    logs, valid, cached, negative = augment.open_log_tables(snakemake.input.log_tables,
                                                            snakemake.input.log_index)
    if cached != names:
        raise ValueError(f"{snakemake.input.log_index}: holds {len(cached)} sources, not this "
                         f"run's {len(names)} (merl.subset); rerun the workflow")
    log.info("%d bins valid in every source table", len(valid))
    recipe = augment.build_recipe(manifest, rows, pairs, logs, names, cfg["pca_dims"])
    bins = augment.choose_bins(valid, cfg["bins"], seed)
    stats = recipe.pop("pca_stats")
    np.savez(snakemake.output.recipe, bins=bins, valid_bins=valid,
             pca_split=np.array(sorted(stats)), pca_k=np.array([stats[s][0] for s in sorted(stats)]),
             pca_explained=np.array([stats[s][1] for s in sorted(stats)]),
             negative_bins=np.asarray(negative), **recipe)
    manifest.to_csv(snakemake.output.manifest, sep="\t", index=False)
