"""Sample weight vectors from a trained model: unconditional (as many as the test reference
set) or type-conditioned (`per_type` for each requested type, classifier-free guidance)."""
import time

import numpy as np
import pandas as pd

from neumat.diffusion import Sampler, dataset
from neumat.fit import save_npy
from neumat.logs import script_logging

with script_logging(snakemake) as log:
    p, out = snakemake.params, snakemake.output
    s = p.cfg["sample"]
    sampler = Sampler(snakemake.input.model, snakemake.config["device"])
    man = dataset.read_manifest(snakemake.input.manifest)
    if p.mode == "uncond":
        n, types, guidance = len(dataset.reference_rows(man)), None, 1.0
        requested = [""] * n
    else:
        train_types = man["type"].iloc[dataset.training_rows(man, "ours")]
        wanted = p.cfg["types"] or dataset.class_names(train_types)
        requested = [t for t in wanted for _ in range(p.cfg["per_type"])]
        n, types, guidance = len(requested), requested, s["guidance"]
    t0 = time.perf_counter()
    w = sampler.sample(n, p.seed, types, s["steps"], s["eta"], guidance, s["batch_size"], s["clip"])
    dt = time.perf_counter() - t0
    save_npy(out.weights, w.astype(np.float32))
    pd.DataFrame({"sample": np.arange(n), "type": requested}).to_csv(out.table, sep="\t", index=False)
    pd.DataFrame([{"samples": n, "seconds": dt, "samples_per_second": n / max(dt, 1e-9),
                   "steps": s["steps"], "eta": s["eta"], "guidance": guidance}]).to_csv(
        out.timing, sep="\t", index=False, float_format="%.6g")
    log.info("%d samples (%s) in %.2f s: %.1f samples/s", n, p.mode, dt, n / max(dt, 1e-9))
