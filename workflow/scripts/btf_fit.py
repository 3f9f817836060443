"""Fit or train one BTF representation (params.method) on one material."""

from neumat.btf import fit
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    fit.fit_method(p.method, snakemake.input[0], snakemake.output[0], p.settings, p.seed,
                   roi=p.roi)
