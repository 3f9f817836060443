"""Image embeddings of every NeuMERL material under each training light: (N, n_lights, D)."""
import numpy as np

from neumat.conditions import image
from neumat.io.atomic import save_npy
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    enc = image.load(snakemake.input.model)
    weights = np.load(snakemake.input.weights)
    e = image.embed_fields(enc, weights, snakemake.params.activation)
    save_npy(snakemake.output[0], e.astype(np.float32))
    log.info("image embeddings %s", e.shape)
