"""Table-2 metrics of one model's samples against the reference set -> one CSV."""
from pathlib import Path

import numpy as np

from neumat.device import resolve_device
from neumat.logs import script_logging
from neumat.metrics import distances, evaluate
from neumat.metrics.inception import load_fid_inception


def inception(path, device, log):
    """(model, reason): the FID network, or None with why it is unavailable."""
    if not path:
        return None, "metrics.inception_weights not set"
    if not Path(path).is_file():
        return None, f"Inception weights {path} not found (metrics.inception_weights)"
    log.info("FID network from %s", path)
    return load_fid_inception(path, device), ""


with script_logging(snakemake) as log:
    p = snakemake.params
    device = str(resolve_device(snakemake.config["device"]))
    ref, smp = (np.load(f) for f in (snakemake.input.reference, snakemake.input.samples))
    log.info("%s: %d samples vs %d references", snakemake.wildcards.model, len(smp), len(ref))
    model, reason = inception(p.inception_weights, device, log)
    table = evaluate.evaluate_fields(ref, smp, resolution=p.resolution,
                                     bins=distances.brdf_sample(p.brdf_samples, p.seed),
                                     activation=p.activation, fid_model=model,
                                     fid_unavailable=reason, device=device)
    table.to_csv(snakemake.output[0], index=False, float_format="%.8g")
    log.info("metrics:\n%s", table.to_string(index=False))
