"""Write one procedural BTF (wood / leather / stone) as a DFMF file."""
from neumat.btf import synthetic
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    log.info("synthetic %s BTF, %d^2 texels, %d components", p.kind, p.size, p.components)
    synthetic.synthesize(p.kind, p.size, p.seed, p.components, snakemake.output[0])
