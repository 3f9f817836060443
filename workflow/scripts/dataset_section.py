"""Report section: AugMERL counts per operation, type and split; disk use; figures."""
from pathlib import Path

import numpy as np
import pandas as pd

from neumat import report
from neumat.io import merl
from neumat.logs import script_logging


def negative_bins_note(recipe, man):
    """A warning paragraph for source tables with more negative bins than real MERL tables."""
    if "negative_bins" not in recipe.files:
        return []
    counts = recipe["negative_bins"]
    n = int(merl.valid_mask().sum())
    sources = list(man.loc[man["operation"] == "original", "name"])
    bad = [(s, int(c)) for s, c in zip(sources, counts) if c > merl.WARN_NEGATIVE_SHARE * n]
    if not bad:
        return []
    listed = ", ".join(f"{s}: {c:,} ({c / n:.2%})" for s, c in bad)
    return [f"**Warning**: {len(bad)} source table(s) have many negative above-horizon bins, "
            f"left out of every material: {listed} (real MERL tables: 0.0041 %)."]


with script_logging(snakemake) as log:
    man = pd.read_csv(snakemake.input.manifest, sep="\t", keep_default_na=False)
    recipe = np.load(snakemake.input.recipe)
    shard_bytes = sum(Path(s).stat().st_size for s in snakemake.input.shards)
    ops = man.groupby(["operation", "split"]).size().unstack(fill_value=0)
    types = man[man["type"] != ""].groupby("type").size().sort_values(ascending=False)
    pca = pd.DataFrame({"split": recipe["pca_split"], "PCA dims": recipe["pca_k"],
                        "unexplained variance": 1 - recipe["pca_explained"]})
    md = [
        "## Dataset: AugMERL",
        f"Source: **{snakemake.params.source}** MERL-format tables, "
        f"{(man['operation'] == 'original').sum()} materials -> **{len(man)}** AugMERL materials "
        f"({len(recipe['valid_bins']):,} bins valid in every source; {len(recipe['bins']):,} "
        f"stored per material in {len(snakemake.input.shards)} shards, "
        f"{shard_bytes / 1e6:.1f} MB on disk).",
        "Splits are by source material; interpolation pairs never cross splits and each split "
        "has its own PCA.",
        *negative_bins_note(recipe, man),
        "### Materials per operation and split", report.md_table(ops.reset_index()),
        "### PCA", report.md_table(pca),
        f"### Materials per type ({len(types)} types; interpolations carry none)",
        report.md_table(types.rename("materials").reset_index()),
        "### Figures",
        "![RGB permutations](figures/augmerl_permutations.png)",
        "![PCA interpolation](figures/augmerl_interpolation.png)",
    ]
    Path(snakemake.output[0]).write_text("\n\n".join(md) + "\n")
    log.info("dataset section: %d materials, %.1f MB of shards", len(man), shard_bytes / 1e6)
