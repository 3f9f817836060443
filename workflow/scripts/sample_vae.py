"""Sample a VAE baseline from its prior: one draw per seed, each as large as the reference set."""
import time

import numpy as np

from neumat.baselines import vae
from neumat.diffusion import dataset
from neumat.logs import script_logging
from neumat.metrics import materials

with script_logging(snakemake) as log:
    p, out = snakemake.params, snakemake.output
    n_ref = len(dataset.reference_rows(dataset.read_manifest(snakemake.input.manifest)))
    net = vae.load(snakemake.input.model)
    t0 = time.perf_counter()
    w = np.concatenate([vae.prior_samples(net, n_ref, s) for s in p.seeds])
    materials.save(out.samples, w)
    log.info("%d x %d samples in %.2f s", len(p.seeds), n_ref, time.perf_counter() - t0)
