"""Embed every AugMERL description once (conditions/text.npy, manifest order) and the sampling
prompts: test-split descriptions of typed materials plus the config's prompts, meant to be
unseen (prompts.tsv's in_training marks any prompt that is word for word a training
description, as embedded). Fails naming the package when the offline text encoder is not
installed."""
import time
from pathlib import Path

import numpy as np
import pandas as pd

from neumat.conditions import evaluate, text
from neumat.diffusion import dataset
from neumat.io.atomic import save_npy
from neumat.logs import script_logging
from neumat.render import sphere

with script_logging(snakemake) as log:
    p, out = snakemake.params, snakemake.output
    man = dataset.read_manifest(snakemake.input.manifest)
    t0 = time.perf_counter()
    text.load_encoder()
    log.info("text encoder %s loaded from %s in %.1f s", text.PACKAGE, text.model_dir(),
             time.perf_counter() - t0)
    descriptions = list(man["description"])
    if getattr(p, "colour_words", "source") == "measured":  # named by their own mean colour
        t0 = time.perf_counter()
        rgb = evaluate.mean_colour(sphere.render_fields(np.load(snakemake.input.weights),
                                                        text.COLOUR_RESOLUTION, p.activation))
        descriptions = text.measured_descriptions(man, rgb)
        pd.DataFrame({"id": man["id"], "name": man["name"], "operation": man["operation"],
                      "description": man["description"], "embedded": descriptions}
                     ).to_csv(out.descriptions, sep="\t", index=False)
        changed = sum(a != b for a, b in zip(descriptions, man["description"]))
        log.info("colour_words measured: %d of %d descriptions renamed by their metric-view "
                 "colour (%.1f s)", changed, len(man), time.perf_counter() - t0)
    else:  # a measured run's descriptions.tsv left behind would name rows it no longer holds
        stale = Path(out.text).with_name("descriptions.tsv")  # (neumat sample --text reads it)
        if stale.exists():
            stale.unlink()
            log.info("removed %s: colour_words is now source, so text.npy embeds the manifest's "
                     "descriptions", stale)
    t0 = time.perf_counter()
    save_npy(out.text, text.embed(descriptions))
    log.info("%d descriptions (%d distinct) embedded in %.1f s", len(man),
             len(set(descriptions)), time.perf_counter() - t0)

    test = man[(man["split"] == "test") & (man["type"] != "")].drop_duplicates("description")
    k = p.test_prompts or len(test)
    pick = np.unique(np.linspace(0, len(test) - 1, min(k, len(test))).round().astype(int)) \
        if len(test) else []
    test = test.iloc[pick]
    # the descriptions training saw, as embedded (measured colour words included): a prompt
    # word for word among them is not held out as text, whatever its kind
    seen = {d for d, s in zip(descriptions, man["split"]) if s == "train"}
    prompts = pd.DataFrame({
        "prompt": list(test["description"]) + list(p.prompts),
        "kind": ["test"] * len(test) + ["unseen"] * len(p.prompts),
        "type": list(test["type"]) + [""] * len(p.prompts)})
    prompts["colour"] = [evaluate.colour_of(q) for q in prompts["prompt"]]
    prompts["in_training"] = [q in seen for q in prompts["prompt"]]
    for kind, g in prompts[prompts["in_training"]].groupby("kind"):
        log.warning("%d %s prompt(s) occur word for word as training descriptions (scored "
                    "apart in conditions/eval_summary.tsv): %s", len(g), kind, list(g["prompt"]))
    prompts.to_csv(out.prompts, sep="\t", index=False)
    save_npy(out.prompt_embeddings, text.embed(list(prompts["prompt"])))
    log.info("%d prompts (%d test-split descriptions)", len(prompts), len(test))
