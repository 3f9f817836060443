"""AugMERL log-table cache: log1p of every source table over their common valid bins, float32,
once for all consumers (they memory-map it; see neumat.augment.write_log_tables)."""
from neumat import augment
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    out = snakemake.output
    m, v = augment.write_log_tables(snakemake.input.tables, snakemake.params.names, out.logs,
                                    out.index)
    log.info("%d sources x 3 channels x %d valid bins: %.1f MB float32", m, v, m * 3 * v * 4 / 1e6)
