"""Table 3 scores: the test-split source materials reconstructed by each HyperBRDF model
(sparse, compression), by their NeuMERL fits (upper bound) and as the mean train-split source
material (floor), rendered in every view of neumat.metrics.reconstruction against the
ground truth (the source tables)."""
import numpy as np
import pandas as pd
import torch

from neumat import augment, nbrdf
from neumat.baselines import hyperbrdf as hb
from neumat.device import resolve_device
from neumat.logs import script_logging
from neumat.metrics import reconstruction as rec
from neumat.render import sphere

with script_logging(snakemake) as log:
    inp, out, p = snakemake.input, snakemake.output, snakemake.params
    dev = str(resolve_device(snakemake.config["device"]))
    man = pd.read_csv(inp.manifest, sep="\t", keep_default_na=False)
    orig = man["operation"] == "original"
    test = man[orig & (man["split"] == "test")]
    train_ids = man.loc[orig & (man["split"] == "train"), "id"].to_numpy()
    if test.empty:
        raise ValueError(f"{inp.manifest}: no test-split source materials (augmerl.test_fraction)")
    ids, names = test["id"].to_numpy(), list(test["name"])
    # stored samples of the test materials
    stored, bins = {}, None
    for path in inp.shards:
        sh = augment.load_shard(path)
        bins = sh["bins"]
        for r in np.flatnonzero(np.isin(sh["ids"], ids)):
            stored[int(sh["ids"][r])] = sh["values"][r].copy()  # a view kept the whole shard
    absent = [n for i, n in zip(ids, names) if i not in stored]
    if absent:
        raise ValueError(f"test material(s) {absent[:5]} in none of the AugMERL shards "
                         f"{', '.join(map(str, inp.shards))[:200]}: rebuild them (rule augmerl_shard)")
    values = np.stack([stored[i] for i in ids])
    median = np.load(inp.median)
    aug = augment.AugMERL(inp.recipe, inp.log_tables, inp.log_index)
    weights = np.load(inp.weights)
    views = {v: rec.view(v, p.resolution, dev) for v in rec.VIEWS}

    def composite(v, f):  # f (n, 3, N) physical BRDF at the view's rows
        return views[v].composite(torch.as_tensor(f, device=dev).clamp_min(0).transpose(1, 2)).cpu()

    hdr = {("truth", "-"): {v: composite(v, aug.values_or_zero(ids, vw.bins.cpu().numpy()))
                            for v, vw in views.items()}}
    floor = {v: aug.values_or_zero(train_ids, vw.bins.cpu().numpy()).mean(0, keepdims=True)
             for v, vw in views.items()}
    hdr["mean training material", "any"] = {v: composite(v, np.repeat(floor[v], len(ids), 0))
                                            for v in views}
    w = torch.as_tensor(weights[ids])
    hdr["NeuMERL fit", "any"] = {
        v: vw.composite(nbrdf.forward(w.to(dev), vw.x6, p.activation)).cpu()
        for v, vw in views.items()}
    for m, path in zip(p.models, inp.models):
        model = hb.load(path, dev)
        for task in hb.TASKS:
            hdr[f"HyperBRDF ({m})", task] = hb.reconstruct(model, values, bins, median, views,
                                                           task, p.sparse_samples, p.seed, names)
    srgb = {k: {v: rec.srgb(img) for v, img in d.items()} for k, d in hdr.items()}
    masks = {v: vw.mask.cpu().numpy() for v, vw in views.items()}
    scores = pd.concat([rec.score(srgb["truth", "-"], imgs, masks, names, method=k[0], task=k[1])
                        for k, imgs in srgb.items() if k[0] != "truth"], ignore_index=True)
    scores.to_csv(out.scores, sep="\t", index=False, float_format="%.6g")
    np.savez_compressed(out.renders, names=np.array(names),
                        keys=np.array([f"{m}|{t}" for m, t in srgb]),
                        **{f"{m}|{t}|{v}": sphere.tonemap(img) for (m, t), d in hdr.items()
                           for v, img in d.items()})
    for (m, t), g in scores.groupby(["method", "task"], sort=False):
        log.info("%-28s %-12s PSNR %.2f  dE %.3f  SSIM %.4f", m, t, g["PSNR"].mean(),
                 g["dE"].mean(), g["SSIM"].mean())
