"""Render PSNR of each fit of one shard against its tabulated AugMERL material (metric view)."""
import numpy as np
import pandas as pd

from neumat import augment, fit
from neumat.device import resolve_device
from neumat.logs import script_logging
from neumat.render import sphere

with script_logging(snakemake) as log:
    p = snakemake.params
    fits = fit.load_fits(snakemake.input.fits)
    inp = snakemake.input
    aug = augment.AugMERL(inp.recipe, inp.log_tables, inp.log_index)
    device = str(resolve_device(snakemake.config["device"]))
    # the reference renders need each material only at the view's bins, not as a full table
    view_bins = sphere.sphere_view(p.resolution, device).bins.cpu().numpy()
    psnr = np.concatenate([
        fit.render_psnr(fits["weights"][s:s + 64], resolution=p.resolution, activation=p.activation,
                        device=device, view_values=aug.values_or_zero(fits["ids"][s:s + 64], view_bins))
        for s in range(0, len(fits["ids"]), 64)])
    pd.DataFrame({"id": fits["ids"], "render_psnr": psnr}).to_csv(
        snakemake.output[0], sep="\t", index=False, float_format="%.4f")
    log.info("shard %s: render PSNR median %.2f dB, min %.2f dB", snakemake.wildcards.shard,
             np.median(psnr), psnr.min())
