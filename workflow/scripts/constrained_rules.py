"""Reflectance statistics of the source MERL tables (full grid) and the category thresholds in
use: the config's (constrained.thresholds), the rest derived from the tables' per-type medians
-> constrained/source_stats.tsv, constrained/rules.tsv (each value and where it came from)."""
from neumat import constrained
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p, out = snakemake.params, snakemake.output
    stats = constrained.table_stats(snakemake.input.tables, p.names)
    stats["type"] = p.types
    th, how = constrained.in_use(stats, p.types, p.derive, p.thresholds)
    stats["category"] = constrained.classify(stats, th)
    stats.to_csv(out.stats, sep="\t", index=False, float_format="%.6g")
    th.to_frame(how).to_csv(out.rules, sep="\t", index=False, float_format="%.6g")
    log.info("thresholds: %s", th)
    log.info("source categories: %s", stats["category"].value_counts().to_dict())
