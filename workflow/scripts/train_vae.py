"""Train a VAE baseline: VAE-N on NeuMERL training weights, VAE-A (set encoder -> latent ->
hypernetwork -> NBRDF) on AugMERL training tables (see neumat.baselines.vae); resumes from its
checkpoint beside the output after a kill."""
import time
from pathlib import Path

import numpy as np
import pandas as pd

from neumat import augment
from neumat.baselines import vae
from neumat.diffusion import dataset
from neumat.io import merl
from neumat.logs import script_logging
from neumat.seeds import seed_for

with script_logging(snakemake) as log:
    p, inp, out, model = snakemake.params, snakemake.input, snakemake.output, snakemake.wildcards.model
    weights = np.load(inp.weights) if model == "vae_n" else None
    man = dataset.read_manifest(inp.manifest, None if weights is None else len(weights))
    train = dataset.training_rows(man, "ours")
    c = dict(p.cfg)
    t0 = time.perf_counter()
    if model == "vae_n":
        arch = {"latent": c.pop("latent"), "hidden": c.pop("hidden")}
        net, history = vae.train_weight_vae(weights[train], **arch, **c,
                                            seed=p.seed, log=log, checkpoint=p.checkpoint)
    else:
        # a fixed random subset of the stored bins of every training material, shard by shard
        ids = set(man["id"].iloc[train])
        rng = np.random.default_rng(seed_for(p.seed, "bins"))  # p.seed seeds the model
        values, pick = [], None
        for f in inp.shards:
            s = augment.load_shard(f)
            if pick is not None and not np.array_equal(s["bins"], first):
                raise ValueError(f"{f}: stores other MERL bins than {inp.shards[0]}; rebuild the "
                                 f"AugMERL shards with one augmerl.bins")
            if pick is None:
                first = s["bins"]
                pick = np.sort(rng.choice(len(s["bins"]), min(c["bins"], len(s["bins"])), replace=False))
                bins = s["bins"][pick]
            keep = np.isin(s["ids"], list(ids))
            values.append(s["values"][keep][:, :, pick])
        values = np.concatenate(values)
        if len(values) != len(ids):
            raise ValueError(f"VAE-A: the AugMERL shards hold {len(values)} of the {len(ids)} "
                             f"training materials of {inp.manifest}; rebuild the AugMERL shards "
                             f"and NeuMERL of this run together")
        th, td, pd_ = (a[bins] for a in merl.grid_angles())
        log.info("VAE-A: %d training tables x %d bins", len(values), len(bins))
        arch = {"latent": c.pop("latent"), "hidden": c.pop("hidden")}
        c.pop("bins")
        net, history = vae.train_set_vae(values, merl.half_diff_cartesian(th, td, pd_),
                                         merl.cos_theta_i(th, td, pd_), **arch, **c,
                                         seed=p.seed, activation=p.activation, log=log,
                                         checkpoint=p.checkpoint)
    vae.save(out.model, net, model, arch)
    Path(p.checkpoint).unlink(missing_ok=True)  # trained: the model file holds the result
    pd.DataFrame(history).to_csv(out.history, sep="\t", index=False, float_format="%.6g")
    log.info("%s trained in %.1f s (%d parameters)", model, time.perf_counter() - t0,
             sum(q.numel() for q in net.parameters()))
