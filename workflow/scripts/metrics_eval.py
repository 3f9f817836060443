"""Table-2 metrics of one model's sample draws against the reference set -> one CSV (a row per
draw x metric). `reference_halves` (sanity row): random halves of the reference set against
each other, one split per seed, read from the prepared reference alone. The reference set's
renders, distances and Inception features come prepared from rule metrics_reference."""
import numpy as np
import pandas as pd

from neumat.device import resolve_device
from neumat.diffusion import dataset
from neumat.logs import script_logging
from neumat.metrics import distances, evaluate, inception, materials


with script_logging(snakemake) as log:
    p, model = snakemake.params, snakemake.wildcards.model
    device = str(resolve_device(snakemake.config["device"]))
    ref = materials.load(snakemake.input.reference)
    net, reason = inception.fid_network(p.inception_weights, device, log)
    kw = dict(resolution=p.resolution, bins=distances.brdf_sample(p.brdf_samples, p.seed),
              activation=p.activation, fid_model=net, fid_unavailable=reason, device=device)
    prepared = evaluate.load_reference(snakemake.input.prepared)  # rule metrics_reference
    if model == "reference_halves":
        halves = [np.random.default_rng(s).permutation(len(ref)) for s in p.halves_seeds]
        h = len(ref) // 2
        log.info("sanity: %d random halves of %d references", len(halves), len(ref))
        table = evaluate.evaluate_halves(prepared, halves, ref=ref, resolution=p.resolution,
                                         bins=kw["bins"], activation=p.activation, fid_model=net,
                                         fid_unavailable=reason, device=device)
    else:
        smp = materials.load(snakemake.input.samples)
        log.info("%s: %d samples (%d draws) vs %d references", model, len(smp), p.draws, len(ref))
        draws = evaluate.split_draws(smp, p.draws, len(ref), snakemake.input.samples)
        table = evaluate.evaluate_draws(ref, draws, **kw,
                                        reference=prepared, source=snakemake.input.samples)
    # novelty: nearest NeuMERL training material at a subset of the BRDF-L1 bins (inside every
    # table set), as diffusion_nearest does for the diffusion sets; the subset from its own stream
    weights = np.load(snakemake.input.weights)
    train = dataset.training_rows(dataset.read_manifest(snakemake.input.manifest, len(weights)), "ours")
    nb = evaluate.novelty_bins(kw["bins"], p.novelty_bins, p.novelty_seed)
    f_train = materials.brdf_values(weights[train], nb, p.activation)
    materials.require_finite(f_train, f"{snakemake.input.weights} (training rows' BRDF values)",
                             "non-finite BRDF values")
    f_ref = materials.brdf_values(ref, nb, p.activation)
    sets = ([materials.rows(ref, o[h:2 * h]) for o in halves] if model == "reference_halves"
            else draws)
    nov = pd.concat([evaluate.novelty_rows(materials.brdf_values(s, nb, p.activation), f_train,
                                           f_ref).assign(draw=i) for i, s in enumerate(sets)])
    table = pd.concat([table, nov[table.columns]], ignore_index=True)
    table.to_csv(snakemake.output[0], index=False, float_format="%.8g")
    log.info("metrics:\n%s", table.to_string(index=False))
