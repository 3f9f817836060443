"""PCA-A (Nielsen-mapped AugMERL training tables) or PCA-N (NeuMERL training weights): fit,
then one draw per seed of as many samples as the reference set (see neumat.baselines.pca)."""
import time

import numpy as np
import pandas as pd

from neumat import augment
from neumat.baselines import pca
from neumat.diffusion import dataset
from neumat.io import merl
from neumat.logs import script_logging
from neumat.metrics import distances, materials

with script_logging(snakemake) as log:
    p, inp, out, model = snakemake.params, snakemake.input, snakemake.output, snakemake.wildcards.model
    weights = np.load(inp.weights) if model == "pca_n" else None
    man = dataset.read_manifest(inp.manifest, None if weights is None else len(weights))
    train, n_ref = dataset.training_rows(man, "ours"), len(dataset.reference_rows(man))
    t0 = time.perf_counter()
    if model == "pca_n":
        fitted = pca.WeightPCA(p.components).fit(weights[train])
        explained = fitted.pca.explained
        draws = [fitted.sample(n_ref, s) for s in p.seeds]
        materials.save(out.samples, np.concatenate(draws))
    else:
        # the table set holds the bins the metrics read; PCA over those in the common valid
        # region of the sources, 0 elsewhere (below the horizon)
        bins = materials.metric_bins(distances.brdf_sample(p.brdf_samples, p.brdf_seed), p.resolution)
        aug = augment.AugMERL(inp.recipe, inp.log_tables, inp.log_index)
        ok = np.isin(bins, aug.valid_bins) & merl.valid_mask()[bins]
        log.info("PCA-A: %d training tables at %d of %d metric bins", len(train), ok.sum(), len(bins))
        # the tables a block of bins at a time, each read twice (neumat.baselines.pca
        # fit_source): all of them at once are tens of GB at paper scale
        ids, fit_bins = man["id"].iloc[train], bins[ok]
        fitted = pca.NielsenPCA(p.components, fit_bins).fit_source(
            lambda sl: aug.values(ids, fit_bins[sl]), len(train))
        explained = fitted.pca.explained
        values = np.zeros((n_ref * len(p.seeds), 3, len(bins)), dtype=np.float32)
        for i, s in enumerate(p.seeds):  # each draw into its rows: no second copy of them all
            values[i * n_ref:(i + 1) * n_ref, :, ok] = fitted.sample(n_ref, s)
        materials.save(out.samples, materials.TableSet(bins, values))
    dt = time.perf_counter() - t0
    pd.DataFrame([{"model": model, "train_materials": len(train), "components": p.components,
                   "explained_variance": explained, "draws": len(p.seeds), "per_draw": n_ref,
                   "seconds": dt}]).to_csv(out.info, sep="\t", index=False, float_format="%.6g")
    log.info("%s: %d components explain %.3f of the variance; %d x %d samples in %.1f s",
             model, p.components, explained, len(p.seeds), n_ref, dt)
