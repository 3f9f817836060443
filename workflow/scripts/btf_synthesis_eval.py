"""Renders, figures and measurements of every synthesis method on one material."""

from neumat.btf.synthesis import stage
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p, i, o = snakemake.params, snakemake.input, snakemake.output
    stage.evaluate(snakemake.wildcards.material, dict(zip(p.planes, i.models)),
                   dict(zip(p.methods, i.synth)), p.render, p.measure, p.lights, p.intensity,
                   p.seed, p.patch_seed, o.metrics, o.methods, o.planes, o.models)
