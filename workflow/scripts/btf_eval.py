"""Texture and tiling figures plus PSNR / DSSIM / FLIP of every representation of a material."""

from neumat.btf import fit
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p, o = snakemake.params, snakemake.output
    fit.evaluate(snakemake.wildcards.material, snakemake.input.data, dict(zip(p.methods, snakemake.input.models)),
                 p.roi, p.pairs, p.tiling, o.metrics, o.textures, o.tiling)
