"""Type hits against the classifier-free guidance scale, per modality, with the median BRDF-L1
to the nearest training material and the share of samples clamping negative values beside them.
Conditions: the test-split descriptions (type, text) and the metric-view image embeddings of
the test-split typed materials (image)."""
import time

import numpy as np
import pandas as pd

from neumat.conditions import evaluate as ev
from neumat.diffusion import Sampler, dataset
from neumat.diffusion.sample import sample
from neumat.logs import script_logging
from neumat.metrics import distances
from neumat.seeds import seed_for

with script_logging(snakemake) as log:
    p, inp = snakemake.params, snakemake.input
    weights = np.load(inp.weights)
    man = dataset.read_manifest(inp.manifest, len(weights))
    # its own stream: the sampling seed also draws the clamp step's bins, which the scoring
    # bins must not be (at nn_bins 4096 they were the same bins)
    ts = ev.TrainingSet(weights, man, distances.brdf_sample(p.bins, seed_for(p.seed, "nn_bins")),
                        p.activation)
    prompts = pd.read_csv(inp.prompts, sep="\t", keep_default_na=False)
    # conditions whose type some training material has (the others cannot score a hit); when
    # there are none (e.g. the tiny config), all test conditions, and the hits are n/a
    test_prompts = prompts["kind"].to_numpy() == "test"
    if (test_prompts & ts.scorable(prompts["type"])).any():
        test_prompts &= ts.scorable(prompts["type"])
    else:
        log.warning("no test prompt has a type found in training: type hits unavailable")
    text_emb = np.load(inp.prompt_embeddings)[test_prompts]
    test = dataset.reference_rows(man)
    ok = ts.scorable(man["type"].iloc[test])
    test = test[ok] if ok.any() else test
    k = p.per_prompt
    modalities = {
        "type": ({"type": list(np.repeat(prompts["type"][test_prompts].to_numpy(), k))},
                 np.repeat(prompts["type"][test_prompts].to_numpy(), k)),
        "text": ({"text": np.repeat(text_emb, k, 0)},
                 np.repeat(prompts["type"][test_prompts].to_numpy(), k)),
        "image": ({"image": np.repeat(np.load(inp.image_embeddings)[test, 0], k, 0)},
                  np.repeat(man["type"].iloc[test].to_numpy(), k)),
    }
    sampler = Sampler(inp.model, snakemake.config["device"])
    s = {**p.sample, "batch_size": snakemake.config["diffusion"]["sample"]["batch_size"]}  # a memory knob: not a param
    rows = []
    for name, (cond, want) in modalities.items():
        for scale in p.scales:
            t0 = time.perf_counter()
            w = sample(sampler, len(want), p.seed, cond, {name: scale}, s["steps"], s["eta"],
                       s["batch_size"], s["clip"], negative_step=s["negative_step"],
                       activation=p.activation, refit_steps=s.get("refit_steps", 0))
            near = ts.nearest(w)
            ok = ts.scorable(want)  # asked types that some training material has
            hits = near["nearest_type"].to_numpy()[ok] == want[ok]
            rows.append({"modality": name, "scale": scale, "samples": len(w),
                         "samples with a training type": int(ok.sum()),
                         "type hits": float(hits.mean()) if ok.any() else float("nan"),
                         "median BRDF-L1 to nearest training": float(near["brdf_l1"].median()),
                         "share clamping negatives": float(
                             ev.negative_share(w, p.angles, seed_for(p.seed, "negative_share"),
                                               p.activation).mean()),
                         "seconds": time.perf_counter() - t0})
            log.info("%s", rows[-1])
    pd.DataFrame(rows).to_csv(snakemake.output[0], sep="\t", index=False, float_format="%.4g")
