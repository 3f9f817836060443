"""Physical plausibility of every sample set (and of the training split, for reference):
shares of NaN/inf, clamped-negative, exploding and energy-passivity-violating materials."""
import numpy as np
import pandas as pd

from neumat.diffusion import dataset, plausibility
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p = snakemake.params
    weights = np.load(snakemake.input.weights)
    man = dataset.read_manifest(snakemake.input.manifest, len(weights))
    kw = dict(n_angles=p.angles, seed=p.seed, activation=p.activation)
    train = plausibility.plausibility(weights[dataset.training_rows(man, "ours")], **kw)
    ref_max = float(train["max_value"].max())
    train["exploding"] = train["max_value"] > p.explode_factor * ref_max
    sets = {"NeuMERL train split": None}
    sets.update({name: np.load(f) for name, f in zip(p.names, snakemake.input.samples)})
    rows, per = [], []
    for name, w in sets.items():
        df = train if w is None else plausibility.plausibility(
            w, reference_max=ref_max, explode_factor=p.explode_factor, **kw)
        rows.append({"set": name, **plausibility.summarize(df)})
        per.append(df.assign(set=name, sample=np.arange(len(df))))
        log.info("%s: %s", name, rows[-1])
    pd.DataFrame(rows).to_csv(snakemake.output.summary, sep="\t", index=False, float_format="%.6g")
    pd.concat(per).to_csv(snakemake.output.per_sample, sep="\t", index=False, float_format="%.6g")
