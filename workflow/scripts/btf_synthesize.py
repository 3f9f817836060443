"""Synthesis state of one method (wildcards.method) for each plane model of one material."""

from neumat.btf.synthesis import stage
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    stage.synthesize(dict(zip(p.planes, snakemake.input)), snakemake.wildcards.method, p.seed,
                     p.settings, snakemake.output[0])
