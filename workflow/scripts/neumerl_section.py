"""Report section: NeuMERL fit quality (histograms, loss curve), best and worst fits side by
side with their ground truth, the fit table."""
from pathlib import Path

import numpy as np
import pandas as pd

from neumat import augment, fit, report
from neumat.device import resolve_device
from neumat.logs import script_logging
from neumat.render import sphere
from neumat.render.gallery import gallery


with script_logging(snakemake) as log:
    inp, out, p = snakemake.input, snakemake.output, snakemake.params
    cfg, dev = p.cfg, str(resolve_device(snakemake.config["device"]))
    fits = pd.read_csv(inp.fits, sep="\t", keep_default_na=False)
    man = pd.read_csv(inp.manifest, sep="\t", keep_default_na=False)
    fits = fits.merge(man[["id", "operation", "split"]], on="id")
    weights = np.load(inp.weights)
    shards = [fit.load_fits(f) for f in inp.shards]
    template = fit.load_fits(inp.template)
    steps = shards[0]["history_steps"]
    curve = np.concatenate([s["val_history"] for s in shards], 1)  # (k, N)
    fit.plot_fit_quality(fits["render_psnr"], fits["val_loss"], steps, curve, out.quality)

    aug = augment.AugMERL(inp.recipe, inp.log_tables, inp.log_index)
    k = min(cfg["report_examples"], len(fits))
    ranked = fits.sort_values("render_psnr")
    for rows, path, what in ((ranked.tail(k)[::-1], out.best, "best"),
                             (ranked.head(k), out.worst, "worst")):
        ids = rows["id"].to_numpy()
        gt = sphere.tonemap(sphere.render_tables(aug.tables_from_coefs(aug.coef[ids]),
                                                 p.resolution, dev))
        fitted = sphere.tonemap(sphere.render_fields(weights[ids], p.resolution,
                                                     cfg["activation"], dev))
        labels = [f"{n}\nground truth" for n in rows["name"]] + \
                 [f"fit {q:.1f} dB" for q in rows["render_psnr"]]
        gallery(np.concatenate([gt, fitted]), labels, path, ncols=k, min_cell=96,
                title=f"NeuMERL: the {k} {what} fits (top: AugMERL table, bottom: fitted field)")

    seconds = template["seconds"] + sum(float(s["seconds"]) for s in shards)
    q = fits["render_psnr"]
    by_op = fits.groupby("operation").agg(
        materials=("id", "size"), median_psnr=("render_psnr", "median"),
        p10_psnr=("render_psnr", lambda x: x.quantile(0.1)),
        median_val_loss=("val_loss", "median")).reset_index()
    cols = ["id", "name", "operation", "train_loss", "val_loss", "render_psnr"]
    n_rows = 10
    md = [
        "## NeuMERL: neural fields of AugMERL",
        f"**{len(fits)}** NBRDF fields (6-21-21-3, 675 weights, {cfg['activation']}), one per "
        f"AugMERL material, fitted with the eq. 2 loss (mean absolute log error of f cos θi), "
        f"Adam, batch {cfg['batch']}, lr {cfg['lr']:g} → {cfg['lr_final']:g} (cosine), "
        f"{cfg['steps']} steps, "
        f"{1 - cfg['val_fraction']:.0%}/{cfg['val_fraction']:.0%} train/val split of each "
        f"material's stored bins. Every fit starts from the template (manifest id "
        f"{int(template['ids'][0])}, the first train-split original, "
        f"{cfg['template_steps']} steps, val loss {template['val_loss'][0]:.4g}).",
        f"Render PSNR (metric sphere view, {cfg['render_resolution']} px, sRGB, sphere pixels) "
        f"of each fit against its tabulated material: median **{q.median():.2f} dB**, "
        f"10th percentile {q.quantile(0.1):.2f} dB, min {q.min():.2f} dB. "
        f"Validation loss: median {fits['val_loss'].median():.4g}, 90th percentile "
        f"{fits['val_loss'].quantile(0.9):.4g}. Fitting time (sum over jobs): "
        f"{report.duration(seconds)}.",
        "### Fit quality per operation", report.md_table(by_op),
        "![fit quality](figures/neumerl_quality.png)",
        "### Best and worst fits",
        "![best fits](figures/neumerl_best.png)",
        "![worst fits](figures/neumerl_worst.png)",
        f"### Fit table (the {min(n_rows, len(fits))} worst by render PSNR; all in "
        f"`neumerl/fits.tsv`)",
        report.md_table(ranked.head(n_rows)[cols]),
    ]
    if inp.exports:
        md += ["### Exported as MERL .binary",
               "\n".join(f"- `{Path(e).relative_to(Path(out.section).parents[2])}`"
                         for e in inp.exports)]
    Path(out.section).write_text("\n\n".join(md) + "\n")
    log.info("neumerl section: %d fits, median render PSNR %.2f dB", len(fits), q.median())
