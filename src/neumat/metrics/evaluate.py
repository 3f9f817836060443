"""The Table-2 evaluation of one synthesized set against a reference set, and the table writer.

`evaluate_fields` computes the 12 set metrics (MMD, COV, 1-NNA x BRDF-L1, RMSE, NegPSNR,
NegSSIM) and FID, as a long table with columns metric, distance, value, note. `table2` lays
several such tables out like M3ashy Table 2 (models as columns, display units as in the paper).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import pandas as pd
import torch

from neumat.metrics import distances as D
from neumat.metrics import sets
from neumat.render import sphere

log = logging.getLogger(__name__)
COLUMNS = ["metric", "distance", "value", "note"]
SET_METRICS = ("MMD", "COV", "1-NNA")


def distance_matrices(ref_values, smp_values, ref_images, smp_images) -> dict[str, tuple]:
    """{distance: (d_rr, d_ss, d_rs)} for BRDF-L1 (BRDF values) and the image distances."""
    out = {"BRDF-L1": (D.pairwise_l1(ref_values, ref_values), D.pairwise_l1(smp_values, smp_values),
                       D.pairwise_l1(ref_values, smp_values))}
    for name, fn in D.IMAGE_DISTANCES.items():
        out[name] = (fn(ref_images), fn(smp_images), fn(ref_images, smp_images))
    return out


def set_metric_rows(matrices: dict[str, tuple]) -> pd.DataFrame:
    rows = []
    for name, (d_rr, d_ss, d_rs) in matrices.items():
        for metric, value in sets.set_metrics(d_rr, d_ss, d_rs).items():
            rows.append((metric, name, value, ""))
    return pd.DataFrame(rows, columns=COLUMNS)


def evaluate_fields(ref_weights, smp_weights, *, resolution: int, bins, activation="relu",
                    fid_model=None, fid_unavailable: str = "", device="cpu") -> pd.DataFrame:
    """All Table-2 metrics of neural-field set `smp_weights` against `ref_weights`.

    `fid_model`: an `inception.FIDInception` (or None, with the reason in `fid_unavailable`)."""
    t0 = time.time()
    vals = [D.field_values(w, bins, activation) for w in (ref_weights, smp_weights)]
    imgs = [sphere.to_srgb(sphere.render_fields(w, resolution, activation, device))
            for w in (ref_weights, smp_weights)]
    log.info("BRDF values and %d renders in %.1fs", len(imgs[0]) + len(imgs[1]), time.time() - t0)
    table = set_metric_rows(distance_matrices(*vals, *imgs))
    log.info("12 set metrics after %.1fs", time.time() - t0)
    if fid_model is None:
        fid = (np.nan, f"unavailable: {fid_unavailable or 'no Inception-v3 weights'}")
    else:
        from neumat.metrics import fid as fidlib
        fid = (fidlib.fid(fid_model, *imgs, device=device), "Inception-v3 pool3, sRGB sphere renders")
    fid_row = pd.DataFrame([("FID", "Inception-v3", *fid)], columns=COLUMNS)
    return pd.concat([fid_row, table], ignore_index=True)


# ----------------------------------------------------------------------------- Table 2

# display factors of the paper's row labels, shown = value x factor ("RMSE x10^2": 0.0754 ->
# 7.54; "NegSSIM x10": -0.955 -> -9.55; "BRDF-L1 x10^-3" on physical MERL values)
FACTORS = {("MMD", "BRDF-L1"): 1e-3, ("MMD", "RMSE"): 1e2, ("MMD", "NegSSIM"): 1e1}
_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")
ARROWS = {"FID": "↓", "MMD": "↓", "COV": "↑", "1-NNA": "↓"}


def _row_label(metric, distance):
    if metric == "FID":
        return "FID (↓)", ""
    factor = FACTORS.get((metric, distance))
    exp = round(np.log10(factor)) if factor else 0
    scale = "" if not factor else " ×10" + ("" if exp == 1 else str(exp).translate(_SUPERSCRIPT))
    pct = " (%)" if metric in ("COV", "1-NNA") else ""
    return f"{metric}{pct} ({ARROWS[metric]})", f"{distance}{scale}"


def table2(results: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """{model: metrics table} -> wide table: rows (metric, distance) in paper order, one column
    per model, values x the paper's display factors; unavailable entries are 'n/a'."""
    order = [("FID", "Inception-v3")] + [(m, d) for m in SET_METRICS for d in D.DISTANCES]
    cols = {}
    for model, df in results.items():
        missing = set(order) - set(zip(df["metric"], df["distance"]))
        if missing:
            raise ValueError(f"metrics of model {model!r} lack rows {sorted(missing)}")
        v = df.set_index(["metric", "distance"])["value"]
        cols[model] = [_display(m, d, v[(m, d)]) for m, d in order]
    index = pd.MultiIndex.from_tuples([_row_label(m, d) for m, d in order], names=["metric", "distance"])
    return pd.DataFrame(cols, index=index)


def _display(metric, distance, value):
    if not np.isfinite(value):
        return "n/a"
    if metric in ("COV", "1-NNA"):
        value = 100 * value
    value *= FACTORS.get((metric, distance), 1.0)
    return f"{value:.3g}"


def write_table2(results: dict[str, pd.DataFrame], csv, md, html) -> pd.DataFrame:
    t = table2(results)
    t.to_csv(csv)
    flat = t.reset_index()
    flat.loc[flat["metric"].duplicated(), "metric"] = ""  # paper style: label once per block
    with open(md, "w") as f:
        f.write(flat.to_markdown(index=False) + "\n")
    with open(html, "w") as f:
        f.write(t.to_html(border=0, classes="table2") + "\n")
    return t
