"""Export the first samples of a set as MERL .binary tables (any MERL tool can read them)."""
import re

import numpy as np
import torch

from neumat import nbrdf
from neumat.io import merl
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    w = np.load(snakemake.input[0])
    for path in snakemake.output:
        i = int(re.search(r"sample_(\d+)\.binary$", path).group(1))
        if i >= len(w):
            raise ValueError(f"{snakemake.input[0]}: sample {i} requested, the file holds {len(w)}")
        table = nbrdf.evaluate_grid(torch.as_tensor(w[i:i + 1]), snakemake.params.activation)[0]
        merl.write_merl(path, table)
        log.info("sample %d -> %s", i, path)
