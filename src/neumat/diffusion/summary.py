"""The hyperdiffusion report section's numbers and figures (rule `diffusion_section`,
workflow/scripts/diffusion_section.py), from the files the training and sampling rules write:
training cost, sampling speed, novelty, the share of type-conditioned samples that hit their
type, the loss curves and the galleries of samples beside their nearest training materials.
The script writes the prose around them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from neumat.render.gallery import gallery as image_grid

NOVELTY = "median BRDF-L1 to nearest training"
RELATIVE = "median, relative to the nearest's mean value"


def novelty(nearest: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """Per sample set (`nearest.tsv` tables, `reference` among them: the test split): the median
    BRDF-L1 to the nearest training material, the median of that distance relative to the
    nearest's mean value (`relative_l1`: comparable between sets of other mixes of diffuse and
    specular materials), and the share of its materials closer than a tenth of the reference's
    median (near-copies)."""
    near_copy = 0.1 * nearest["reference"]["brdf_l1"].median()
    return pd.DataFrame([{"set": k, NOVELTY: v["brdf_l1"].median(),
                          RELATIVE: v["relative_l1"].median(),
                          "share closer than 10 % of the reference median":
                              (v["brdf_l1"] < near_copy).mean()}
                         for k, v in nearest.items()])


@dataclass
class TypeMatch:
    """Type hits of type-conditioned samples, and the same measure for the test split."""
    hits: pd.Series       # per sample: its nearest typed training material has the asked type
    per_type: pd.DataFrame  # per asked type: "match %" and the median relative distance
    ref_hits: pd.Series   # per typed test material: the same for its own type
    ref_known: pd.Series  # per typed test material (index as ref_hits): training has its type


def type_match(typed: pd.DataFrame, reference: pd.DataFrame, manifest: pd.DataFrame) -> TypeMatch:
    """`typed`, `reference`: nearest.tsv tables (columns type, nearest_typed_type; "" = no
    type) of the type-conditioned samples and of the test split; `manifest`: NeuMERL's, whose
    train split says which types training has."""
    hits = typed["type"] == typed["nearest_typed_type"]
    ref_hits = (reference["type"] == reference["nearest_typed_type"])[reference["type"] != ""]
    train_types = set(manifest.loc[manifest["split"] == "train", "type"]) - {""}
    ref_known = reference.loc[reference["type"] != "", "type"].isin(train_types)
    by_type = typed.assign(match=hits).groupby("type")
    per_type = pd.DataFrame({"match %": by_type["match"].mean().mul(100),
                             RELATIVE: by_type["relative_l1"].median()})
    return TypeMatch(hits, per_type, ref_hits, ref_known)


def training_table(bundles: dict[str, dict]) -> pd.DataFrame:
    """One row per trained denoiser (model files as `neumat.io.modelfile.load` gives them)."""
    return pd.DataFrame([{
        "model": k, "training materials": b["n_train"], "steps": b["train_cfg"]["steps"],
        "batch": b["train_cfg"]["batch_size"], "train wall time (s)": b["train_seconds"],
        "final loss": b["history"][-1][1]} for k, b in bundles.items()])


def speed_table(timing: dict[str, pd.Series]) -> pd.DataFrame:
    """One row per sample set from the first row of its `timing.tsv`."""
    return pd.DataFrame([{"set": k, "samples": int(t["samples"]), "seconds": t["seconds"],
                          "samples / s": t["samples_per_second"], "guidance": t["guidance"]}
                         for k, t in timing.items()])


def plot_losses(histories, path) -> None:
    """Training loss per model (history.tsv files; the model is the parent folder's name)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3))
    for f in histories:
        h = pd.read_csv(f, sep="\t")
        ax.plot(h["step"], h["loss"], label=Path(f).parent.name)
    ax.set(xlabel="step", ylabel="training loss (MSE, normalised)", yscale="log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def spread(n: int, k: int) -> np.ndarray:
    """min(k, n) indices spread evenly over 0 ... n - 1, both ends included."""
    return np.linspace(0, n - 1, min(k, n)).round().astype(int)


def nearest_gallery(samples, near: pd.DataFrame, weights, k: int,
                    render: Callable[[np.ndarray], np.ndarray], path, title: str) -> None:
    """Top row: k samples spread over the set; bottom row: their nearest training materials
    (`near`: the set's nearest.tsv, rows as samples; `weights`: NeuMERL's, indexed by its
    nearest_id). `render` maps weight vectors to tonemapped images."""
    pick = spread(len(samples), k)
    rows = near.iloc[pick]
    top, bottom = render(samples[pick]), render(weights[rows["nearest_id"].to_numpy()])
    labels = [f"sample {i}" for i in pick] + \
             [f"{r.nearest_name}\nL1 {r.brdf_l1:.3g}" for r in rows.itertuples()]
    image_grid(np.concatenate([top, bottom]), labels, path, ncols=len(pick), min_cell=96,
               title=title)


def type_gallery(samples, typed: pd.DataFrame, n_types: int, per_type: int,
                 render: Callable[[np.ndarray], np.ndarray], path) -> None:
    """One row per asked type (the first n_types in the order `typed` asks them), its first
    per_type (at most 6) samples, each labelled with the asked type and the type of its nearest
    typed training material."""
    shown = list(dict.fromkeys(typed["type"]))[:n_types]
    per_row = min(per_type, 6)
    pick = np.concatenate([np.flatnonzero(typed["type"] == t)[:per_row] for t in shown])
    labels = [f"{r.type}\n(nn: {r.nearest_typed_type})" for r in typed.iloc[pick].itertuples()]
    image_grid(render(samples[pick]), labels, path, ncols=per_row, min_cell=96,
               title="type-conditioned samples (label: requested type, and the type "
                     "of the nearest typed training material)")
