"""Fit or train one BTF representation (params.method) on one material."""

from neumat.btf import fit
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    # checkpoint_every is speed-only (config/speed_keys.yaml): from the config, not params
    ck = snakemake.config["btf"].get(p.method, {}).get("checkpoint_every")
    settings = {**p.settings, **({"checkpoint_every": ck} if ck is not None else {})}
    fit.fit_method(p.method, snakemake.input[0], snakemake.output[0], settings, p.seed,
                   roi=p.roi)
