"""Nearest training material (BRDF-L1 over a fixed sample of MERL bins) of every material of
each sample set: novelty (distance to the nearest of all training materials; `relative_l1`: that
distance over the nearest's mean value on the same bins, as a specular material's values run
tens of times a diffuse one's) and type match
(the nearest *typed* training material - interpolations carry no type - against the requested
type; for the reference set, the material's own type)."""
import numpy as np
import pandas as pd

from neumat.diffusion import dataset
from neumat.logs import script_logging
from neumat.metrics import distances

with script_logging(snakemake) as log:
    p, inp = snakemake.params, snakemake.input
    weights = np.load(inp.weights)
    man = dataset.read_manifest(inp.manifest, len(weights))
    train = dataset.training_rows(man, "ours")
    typed = train[man["type"].iloc[train].to_numpy() != ""]
    bins = distances.brdf_sample(p.bins, p.seed)
    fv = lambda w: distances.field_values(np.nan_to_num(w), bins, p.activation)  # noqa: E731
    f_train = fv(weights[train])
    f_typed = f_train[np.searchsorted(train, typed)]
    train_mean = f_train.abs().mean(1).numpy()  # each training material's mean value
    for samples_path, table_path, out_path in zip(inp.samples, inp.tables, snakemake.output):
        samples = np.load(samples_path)
        info = pd.read_csv(table_path, sep="\t", keep_default_na=False, dtype=str)
        f = fv(samples)
        idx, dist = dataset.nearest(f, f_train)
        tidx, tdist = dataset.nearest(f, f_typed) if len(typed) else (np.zeros(len(f), int), np.full(len(f), np.inf))
        near, tnear = man.iloc[train[idx]], man.iloc[typed[tidx]] if len(typed) else None
        res = pd.DataFrame({
            "sample": np.arange(len(samples)),
            "type": info["type"] if "type" in info else "",
            "nearest_id": near["id"].to_numpy(), "nearest_name": near["name"].to_numpy(),
            "brdf_l1": dist,
            "relative_l1": dataset.relative(dist, idx, train_mean),
            "nearest_typed_name": tnear["name"].to_numpy() if tnear is not None else "",
            "nearest_typed_type": tnear["type"].to_numpy() if tnear is not None else "",
            "typed_brdf_l1": tdist,
            "finite": np.isfinite(samples).all(1)})
        res.to_csv(out_path, sep="\t", index=False, float_format="%.6g")
        asked = res[res["type"] != ""]
        log.info("%s: median BRDF-L1 to nearest training material %.4g%s", out_path,
                 res["brdf_l1"].median(),
                 f"; type match {100 * (asked['type'] == asked['nearest_typed_type']).mean():.1f} %"
                 if len(asked) else "")
