"""Fit or train one BTF representation (params.method) on one material."""
import torch

from neumat.btf import fit
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    torch.set_num_threads(snakemake.threads)
    p = snakemake.params
    fit.fit_method(p.method, snakemake.input[0], snakemake.output[0], p.settings, p.seed,
                   roi=p.roi)
