"""Export one fitted field as a MERL .binary table (any MERL tool can read it)."""
import numpy as np
import pandas as pd

from neumat import fit
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    name = snakemake.wildcards.augmerl
    man = pd.read_csv(snakemake.input.manifest, sep="\t", keep_default_na=False)
    hit = np.flatnonzero(man["name"].to_numpy() == name)
    if not len(hit):
        raise ValueError(f"config fit.export: {name!r} is not a material of "
                         f"{snakemake.input.manifest}")
    w = np.load(snakemake.input.weights, mmap_mode="r")[man["id"].iat[hit[0]]]
    fit.export_merl(w, snakemake.output[0], snakemake.params.activation)
    log.info("exported %s (id %d) -> %s", name, man["id"].iat[hit[0]], snakemake.output[0])
