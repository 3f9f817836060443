"""Embed every AugMERL description once (conditions/text.npy, manifest order); with measured
colour words, as renamed by each field's own colour (descriptions.tsv). The sampling prompts
are rule prompt_embeddings'. Fails naming the package when the offline text encoder is not
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
