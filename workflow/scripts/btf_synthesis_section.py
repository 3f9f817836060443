"""Report fragment 61: synthesis measurements of every material and the figures."""

from neumat.btf.synthesis import stage
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    stage.write_section(snakemake.input.metrics, snakemake.output.md, snakemake.output.table,
                        p.measure, p.render, p.quilt_scale, p.channels)
