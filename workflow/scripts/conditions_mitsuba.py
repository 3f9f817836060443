"""Mitsuba 3 figures of the conditioned samples (paper Figs. 8-9 style): each row one prompt
(test-split descriptions first, then unseen prompts) or one conditioning image (its metric-view
render in the first column) with its samples, spheres under the generated sky."""
import json
import time

import numpy as np
import pandas as pd
from PIL import Image

from neumat.logs import script_logging
from neumat.render import mitsuba_bsdf as mb
from neumat.render import scenes, sphere
from neumat.render.gallery import gallery


def spheres(weights, cfg, activation, seed):
    env = scenes.sky_envmap(cfg["envmap_size"])
    mats = [mb.Material(f"m{i}", weights=np.nan_to_num(w), activation=activation)
            for i, w in enumerate(weights)]
    return [scenes.render(scenes.sphere_scene(m, cfg["resolution"], cfg["spp"], env), seed=seed)
            for m in mats]


def rows_of(table, n_rows, per_row):
    """Samples of up to n_rows conditions (evenly over test and unseen kinds), per_row each."""
    conds = list(dict.fromkeys(table["condition"]))
    if "kind" in table and (table["kind"] == "unseen").any():  # show both kinds of prompt
        unseen = list(dict.fromkeys(table.loc[table["kind"] == "unseen", "condition"]))
        seen = [c for c in conds if c not in unseen]
        half = min(len(unseen), n_rows // 2)
        conds = seen[:n_rows - half] + unseen[:half]
    conds = conds[:n_rows]
    pick = [np.flatnonzero(table["condition"] == c)[:per_row] for c in conds]
    return conds, pick


with script_logging(snakemake) as log:
    inp, out, p = snakemake.input, snakemake.output, snakemake.params
    t0 = time.time()
    variant = mb.select_variant(p.cfg["variant"])
    per_row = p.per_row

    t = pd.read_csv(inp.text_table, sep="\t", keep_default_na=False)
    w = np.load(inp.text)
    conds, pick = rows_of(t, p.rows, per_row)
    idx = np.concatenate(pick)
    imgs = spheres(w[idx], p.cfg, p.activation, p.seed)
    labels = [f'"{t.loc[i, "prompt"]}"' for i in idx]
    ncols = max(len(x) for x in pick)
    padded, plabels, k = [], [], 0
    for x in pick:  # rows may be short when per_condition < per_row
        for j in range(ncols):
            padded.append(imgs[k] if j < len(x) else np.zeros_like(imgs[0]))
            plabels.append(labels[k] if j < len(x) else "")
            k += j < len(x)
    gallery(padded, plabels, out.text, ncols=ncols, min_cell=120,
            title="text-conditioned samples (row label: prompt)")

    t = pd.read_csv(inp.image_table, sep="\t", keep_default_na=False)
    w, cond = np.load(inp.image), np.load(inp.conditioning)
    conds, pick = rows_of(t, p.rows, per_row)
    imgs = spheres(w[np.concatenate(pick)], p.cfg, p.activation, p.seed)
    grid, glabels, k = [], [], 0
    res = p.cfg["resolution"]
    for c, x in zip(conds, pick):
        ref = Image.fromarray(sphere.tonemap(cond[c])).resize((res, res), Image.NEAREST)
        grid.append(np.asarray(ref))
        glabels.append(f"image: {t.loc[x[0], 'source']}")
        for j in range(per_row):
            grid.append(imgs[k] if j < len(x) else np.zeros_like(imgs[0]))
            glabels.append("sample" if j < len(x) else "")
            k += j < len(x)
    gallery(grid, glabels, out.image, ncols=per_row + 1, min_cell=120,
            title="image-conditioned samples (first column: conditioning image, metric view)")
    info = {"variant": variant, "seconds": round(time.time() - t0, 1),
            "resolution": p.cfg["resolution"], "spp": p.cfg["spp"]}
    with open(out.info, "w") as f:
        json.dump(info, f, indent=1)
    log.info("%s", info)
