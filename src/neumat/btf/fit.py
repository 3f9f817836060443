"""Stage entry points of the BTF branch (called by the workflow scripts, usable from a
notebook): fit one representation, evaluate a material, write the report section."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from neumat.btf import evaluate as ev
from neumat.btf import figures, models
from neumat.btf.classical import PCA, SH, Tucker
from neumat.btf.data import BTFData
from neumat.btf.neural import train

log = logging.getLogger(__name__)


def fit_method(method: str, btf_path, out_path, settings: dict, seed: int, roi=None):
    """Fit `method` to the BTF at btf_path (optionally a roi crop) and save it to out_path.
    Neural methods checkpoint to <out_path>.ckpt and resume from it."""
    data = BTFData(btf_path, roi)
    s = dict(settings)
    log.info("%s on %s: %d x %d texels, settings %s", method, btf_path, data.width, data.height, s)
    torch.manual_seed(seed)
    if method in models.NEURAL:
        train_keys = ("steps", "batch", "lr", "checkpoint_every")
        model = models.NEURAL[method](data.width, data.height,
                                      **{k: v for k, v in s.items() if k not in train_keys})
        ckpt = f"{out_path}.ckpt"
        losses = train(model, data, s["steps"], s["batch"], s["lr"], seed, ckpt,
                       s["checkpoint_every"])
        if losses:
            log.info("final loss %.5f", float(np.mean(losses[-50:])))
    elif method == "pca":
        model = PCA.fit(data, s["components"], s["fit_texels"], seed=seed)
    elif method == "sh":
        model = SH.fit(data)
    elif method == "td":
        model = Tucker.fit(data, tuple(s["ranks"]))
    else:
        raise ValueError(f"unknown BTF method {method!r}; choose from {models.METHODS}")
    log.info("%s: %d parameters", method, model.n_params())
    models.save(model, out_path)
    Path(f"{out_path}.ckpt").unlink(missing_ok=True)  # the last step's is kept (modelfile.finish)


def evaluate(name, btf_path, model_paths: dict, roi, pairs, tiling, metrics_out, textures_png,
             tiling_png):
    data = BTFData(btf_path, roi)
    loaded = {m: models.load(p) for m, p in model_paths.items()}
    for m, model in loaded.items():
        if m in models.NEURAL and (model.kwargs["width"], model.kwargs["height"]) != (data.width, data.height):
            raise ValueError(f"{model_paths[m]}: fitted on {model.kwargs['width']} x "
                             f"{model.kwargs['height']} texels, data has {data.width} x {data.height}")
    rows, tex, plane, _ = ev.evaluate_material(name, data, loaded, pairs, tiling)
    df = pd.DataFrame(rows)
    tmp = f"{metrics_out}.tmp"
    df.to_csv(tmp, sep="\t", index=False, float_format="%.6g")
    os.replace(tmp, metrics_out)

    cols = ["reference", *loaded]
    tex_rows = [f"light {l}, view {v}" for l, v in pairs]
    notes = [[""] + [_note(df, "texture", m, r) for m in loaded] for r in range(len(pairs))]
    figures.texture_grid(textures_png, tex_rows, [models.LABELS[c] for c in cols],
                         [[tex[c][r] for c in cols] for r in range(len(pairs))], notes,
                         f"{name}: textures at fixed light/view pairs (PSNR dB / DSSIM / FLIP)")
    pcols = list(plane)
    prow = [f"light {k + 1}" for k in range(len(tiling["lights"]))]
    pnotes = [[""] + [_note(df, "tiling", m, k) for m in pcols[1:]] for k in range(len(prow))]
    figures.texture_grid(tiling_png, prow, [models.LABELS[c] for c in pcols],
                         [[plane[c][k] for c in pcols] for k in range(len(prow))], pnotes,
                         f"{name}: plane with repetitive tiling x{tiling['tiles']}")


def _note(df, fig, method, r):
    sel = df[(df["figure"] == fig) & (df["method"] == method)].iloc[r]
    return f"{sel.psnr:.1f} / {sel.dssim:.3f} / {sel.flip:.3f}"


def write_section(metric_files, md_out, table_out, source, crop):
    df = pd.concat([pd.read_csv(f, sep="\t") for f in metric_files])
    q = (df.groupby(["figure", "material", "method"], sort=False)
           [["psnr", "dssim", "flip", "params"]].mean().reset_index())
    q.to_csv(table_out, sep="\t", index=False, float_format="%.5g")
    mats = list(dict.fromkeys(df["material"]))
    lines = ["## BTF representation (Triple Plane and baselines)", "",
             f"Data: {'synthetic procedural BTFs (DFMF, 151 x 151 UBO2014 directions)' if source == 'synthetic' else 'UBO2014'}"
             + (f", centre crop {crop} x {crop} texels" if crop else "") + ". "
             "Metrics on display images (reference exposure, clipped, sRGB): PSNR (dB, higher is "
             "better), DSSIM = (1 - SSIM) / 2 and FLIP (lower is better); `params` = stored "
             "floats of the representation.", ""]
    for fig, title in (("texture", "Textures at fixed light/view pairs (mean over pairs)"),
                       ("tiling", "Tiled plane under the point lights of btf.tiling.lights vs interpolated reference (mean)")):
        sub = q[q["figure"] == fig]
        if sub.empty:
            continue
        lines += [f"### {title}", "", "| material | method | PSNR | DSSIM | FLIP | params |",
                  "| --- | --- | --- | --- | --- | --- |"]
        lines += [f"| {r.material} | {models.LABELS.get(r.method, r.method)} | {r.psnr:.2f} | "
                  f"{r.dssim:.4f} | {r.flip:.4f} | {int(r.params)} |" for r in sub.itertuples()]
        lines.append("")
    for m in mats:
        lines += [f"![{m}: textures](figures/btf_{m}_textures.png)", "",
                  f"![{m}: tiled plane](figures/btf_{m}_tiling.png)", ""]
    Path(md_out).write_text("\n".join(lines))
