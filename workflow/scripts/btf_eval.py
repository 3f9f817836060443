"""Texture and tiling figures plus PSNR / DSSIM / FLIP of every representation of a material."""
import torch

from neumat.btf import fit
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    torch.set_num_threads(snakemake.threads)
    p, o = snakemake.params, snakemake.output
    fit.evaluate(snakemake.wildcards.name, snakemake.input.data, dict(zip(p.methods, snakemake.input.models)),
                 p.roi, p.pairs, p.tiling, o.metrics, o.textures, o.tiling)
