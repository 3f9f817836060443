"""Reflectance statistics of the source MERL tables (full grid) and the category thresholds
derived from their per-type medians -> constrained/source_stats.tsv, constrained/rules.tsv."""
from neumat import constrained
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p, out = snakemake.params, snakemake.output
    stats = constrained.table_stats(snakemake.input.tables, p.names)
    stats["type"] = p.types
    d = p.derive
    th, how = constrained.derive_thresholds(stats, p.types, d["mirror_quantile"], d["plastic_quantile"],
                                            d["specular_quantiles"], p.e, p.metallic_exceptions)
    stats["category"] = constrained.classify(stats, th)
    stats.to_csv(out.stats, sep="\t", index=False, float_format="%.6g")
    th.to_frame(how).to_csv(out.rules, sep="\t", index=False, float_format="%.6g")
    log.info("thresholds: %s", th)
    log.info("source categories: %s", stats["category"].value_counts().to_dict())
