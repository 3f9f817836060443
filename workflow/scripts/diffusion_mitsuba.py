"""Mitsuba 3 galleries of the hyperdiffusion samples (paper Fig. 5 / Fig. 7 style): spheres
under the generated sky - unconditional samples of `ours` over their nearest training materials
(BRDF-L1), and type-conditioned samples, one row per type."""
import json
import time

import numpy as np
import pandas as pd

from neumat.logs import script_logging
from neumat.render import mitsuba_bsdf as mb
from neumat.render import scenes
from neumat.render.gallery import gallery


def spheres(weights, names, cfg, activation, seed):
    env = scenes.sky_envmap(cfg["envmap_size"])
    mats = [mb.Material(n, weights=np.nan_to_num(w), activation=activation)
            for n, w in zip(names, weights)]
    return [scenes.render(scenes.sphere_scene(m, cfg["resolution"], cfg["spp"], env), seed=seed)
            for m in mats]


with script_logging(snakemake) as log:
    inp, out, p = snakemake.input, snakemake.output, snakemake.params
    t0 = time.time()
    variant = mb.select_variant(p.cfg["variant"])
    weights = np.load(inp.weights)

    samples, near = np.load(inp.ours), pd.read_csv(inp.ours_nearest, sep="\t", keep_default_na=False)
    k = min(p.n_samples, len(samples))
    pick = np.linspace(0, len(samples) - 1, k).round().astype(int)
    rows = near.iloc[pick]
    imgs = spheres(np.concatenate([samples[pick], weights[rows["nearest_id"].to_numpy()]]),
                   [f"s{i}" for i in pick] + [f"n{i}" for i in pick], p.cfg, p.activation, p.seed)
    labels = [f"sample {i}" for i in pick] + \
             [f"nn: {r.nearest_name} (L1 {r.brdf_l1:.3g})" for r in rows.itertuples()]
    gallery(imgs, labels, out.ours, ncols=k, min_cell=96)

    typed, tnear = np.load(inp.types), pd.read_csv(inp.types_nearest, sep="\t", keep_default_na=False)
    shown = list(dict.fromkeys(tnear["type"]))[:p.n_types]
    per_row = min(p.per_type, 4)
    tp = np.concatenate([np.flatnonzero(tnear["type"] == t)[:per_row] for t in shown])
    imgs_t = spheres(typed[tp], [f"t{i}" for i in tp], p.cfg, p.activation, p.seed)
    gallery(imgs_t, [f"{r.type} (nn: {r.nearest_typed_type})" for r in tnear.iloc[tp].itertuples()],
            out.types, ncols=per_row, min_cell=96)
    info = {"variant": variant, "images": len(imgs) + len(imgs_t), "seconds": round(time.time() - t0, 1),
            "resolution": p.cfg["resolution"], "spp": p.cfg["spp"]}
    with open(out.info, "w") as f:
        json.dump(info, f, indent=1)
    log.info("%s", info)
