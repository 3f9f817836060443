"""The reference set prepared once for every model's Table-2 metrics (rule metrics_reference):
BRDF values at the metric bins, metric renders, self-distance matrices and Inception features
-> metrics/reference.pt, read by each metrics job (neumat.metrics.evaluate.prepare_reference)."""
from neumat.device import resolve_device
from neumat.logs import script_logging
from neumat.metrics import distances, evaluate, inception, materials

with script_logging(snakemake) as log:
    p = snakemake.params
    device = str(resolve_device(snakemake.config["device"]))
    ref = materials.load(snakemake.input.reference)
    net, reason = inception.fid_network(p.inception_weights, device, log)
    if net is None:
        log.warning("no Inception features in %s: %s (each metrics job reports FID as such)",
                    snakemake.output[0], reason)
    prepared = evaluate.prepare_reference(
        ref, resolution=p.resolution, bins=distances.brdf_sample(p.brdf_samples, p.seed),
        activation=p.activation, fid_model=net, device=device)
    evaluate.save_reference(prepared, snakemake.output[0])
    log.info("%d references: values %s, renders %s, FID features %s", len(ref),
             tuple(prepared["values"].shape), tuple(prepared["images"].shape),
             sorted(prepared.get("fid", {})) or "none")
