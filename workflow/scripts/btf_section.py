"""Report section 60: quality table of the BTF representations and their figures."""
from neumat.btf import fit
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    fit.write_section(snakemake.input.metrics, snakemake.output.md, snakemake.output.table,
                      snakemake.params.source, snakemake.params.crop)
