"""Write one analytic material (neumat.data.synthetic_merl) as a MERL .binary table."""
from neumat.data import synthetic_merl
from neumat.io.merl import write_merl
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p, name = snakemake.params, snakemake.wildcards.merl
    spec = {s.name: s for s in synthetic_merl.make_specs(p.n_materials, p.seed)}[name]
    log.info("%s", spec)
    write_merl(snakemake.output[0], synthetic_merl.make_table(spec))
