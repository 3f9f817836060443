"""Constrained synthesis: for each category, draw from the `ours` model in batches until
`per_category` samples fall into it or `budget` draws are spent (unconditionally, type-guided
or with category guidance, whichever accepted most in a pilot batch) -> samples/constrained/
(weights.npy, samples.tsv with each sample's category and statistics) and
constrained/acceptance.tsv (acceptance rate per category; incomplete categories say so).
Each finished category is kept in draws.partial/ beside the output (neumat.diffusion.draws): a
killed job resumes at its next category, and the folder goes once the output is written."""
import json
from pathlib import Path

import numpy as np
import pandas as pd

from neumat import constrained
from neumat.diffusion import Sampler, dataset, draws
from neumat.io.atomic import save_npy
from neumat.logs import script_logging
from neumat.seeds import seed_for

with script_logging(snakemake) as log:
    inp, p, out = snakemake.input, snakemake.params, snakemake.output
    cfg = p.cfg
    th = constrained.Thresholds.from_tsv(inp.rules, cfg["thresholds"])
    sampler = Sampler(inp.model, snakemake.config["device"])
    classes = pd.read_csv(inp.classes, sep="\t", keep_default_na=False)
    src = classes[classes["set"] == "source"]
    guides = constrained.category_types(src["type"], src["category"])
    # guide only with types some training material has: the others are classes whose
    # embeddings never trained (types only held-out sources have)
    trained = dataset.training_types(dataset.read_manifest(inp.manifest))
    bins = constrained.grid_bins(cfg["bins"], p.bins_seed)  # constrained_classify's bins
    # a param only where it acts (guide auto, a guided category listed); none: the paper's setting
    step = cfg.get("guidance_step", 0.0)
    # diffusion.sample.batch_size: a memory knob (the draws do not depend on it), not a param
    sample_cfg = {**p.sample, "batch_size": snakemake.config["diffusion"]["sample"]["batch_size"]}
    # a category's draws depend on the model, the manifest (trained types), the derived rules,
    # the source classes and the settings
    cache = draws.DrawCache(Path(out.weights).with_name("draws.partial"), draws.fingerprint(
        [inp.model, inp.manifest, inp.rules, inp.classes],
        {"cfg": cfg, "sample": p.sample, "seed": p.seed, "bins_seed": p.bins_seed,
         "activation": p.activation,
         "device": str(sampler.device)}))  # resolved: auto differs between nodes
    rows, weights, tables = [], [], []
    for cat in cfg["categories"]:
        types = [t for t in guides[cat] if t in sampler.class_names and t in trained] \
            if cfg["guide"] == "auto" else []
        untrained = sorted(set(guides[cat]) - trained)
        if cfg["guide"] == "auto" and untrained:
            log.info("%s: guide types %s left out: no training material has them", cat,
                     ", ".join(untrained))

        def draw(cat=cat, types=types):
            r = constrained.sample_category(sampler, cat, th, cfg["per_category"],
                                            cfg["budget"], cfg["batch"],
                                            seed_for(p.seed, "category", cat), sample_cfg, types,
                                            bins, p.activation, guidance_step=step)
            # each sample's own mode (a pilot's hits are kept first, whatever mode won after it)
            t = r.stats.drop(columns="name").assign(category=cat)
            t = t.assign(guide=t.pop("guide"))
            # the acceptance row as JSON (numpy scalars as numbers)
            row = json.dumps(constrained.acceptance_row(r, cfg["per_category"]),
                             default=lambda x: x.item())
            return {"w": r.weights, **draws.table_arrays(t), "row": np.array(row)}

        got = cache.get(cat, draw)
        row = json.loads(str(got["row"]))
        rows.append(row)
        log.info("%s", row)
        weights.append(got["w"])
        tables.append(draws.table(got))
    w = np.concatenate(weights).astype(np.float32)
    save_npy(out.weights, w)
    table = pd.concat(tables, ignore_index=True)
    table.insert(0, "sample", np.arange(len(table)))
    table.to_csv(out.table, sep="\t", index=False, float_format="%.6g")
    pd.DataFrame(rows).to_csv(out.acceptance, sep="\t", index=False, float_format="%.4g")
    cache.clear()  # written: the kept categories are no longer needed
