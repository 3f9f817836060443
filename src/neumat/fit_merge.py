"""Fit results on disk and NeuMERL assembly: shard results (`fit_many`) are saved and loaded
here, and merged into one weight matrix in manifest order."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from neumat import nbrdf
from neumat.io.atomic import NPZ_ERRORS, save_npz

if TYPE_CHECKING:
    import pandas as pd


def save_fits(path: str | Path, result: dict) -> None:
    """Write a `fit_many` result atomically (`neumerl/shards/NNN.npz`, `neumerl/template.npz`)."""
    save_npz(path, **result)


def load_fits(path: str | Path) -> dict[str, np.ndarray]:
    """A shard's fit result (rule fit_shard), or ValueError naming the file and the rule."""
    try:
        with np.load(path) as z:
            d = {k: z[k] for k in z.files}
    except NPZ_ERRORS as e:
        raise ValueError(f"{path}: not a readable fit result ({type(e).__name__}: {e}); delete "
                         f"it and rebuild it with rule fit_shard") from e
    missing = {"ids", "weights", "train_loss", "val_loss"} - set(d)
    if missing or d["weights"].shape != (len(d["ids"]), nbrdf.N_PARAMS):
        raise ValueError(f"{path}: not a fit result (missing {sorted(missing)} or bad weights shape)")
    return d


def merge_fits(fits: list[dict], evals: list, manifest) -> tuple[np.ndarray, "pd.DataFrame"]:
    """Shard fit results + render-PSNR tables -> (weights (N, 675) float32 in manifest order,
    fit table with columns id, name, train_loss, val_loss, render_psnr)."""
    import pandas as pd

    ids = np.concatenate([f["ids"] for f in fits])
    want = manifest["id"].to_numpy()
    if len(ids) != len(set(ids.tolist())) or set(ids.tolist()) != set(want.tolist()):
        missing = sorted(set(want.tolist()) - set(ids.tolist()))[:5]
        raise ValueError(f"shard fits do not cover the manifest exactly once (missing e.g. "
                         f"{missing}, {len(ids)} fits for {len(want)} materials)")
    pos = {int(i): k for k, i in enumerate(ids)}
    order = np.array([pos[int(i)] for i in want])
    psnr = pd.concat(evals).set_index("id")["render_psnr"]
    table = pd.DataFrame({
        "id": want, "name": manifest["name"].to_numpy(),
        "train_loss": np.concatenate([f["train_loss"] for f in fits])[order],
        "val_loss": np.concatenate([f["val_loss"] for f in fits])[order],
        "render_psnr": psnr.reindex(want).to_numpy()})
    if table["render_psnr"].isna().any():
        raise ValueError(f"no render PSNR for ids {table.loc[table['render_psnr'].isna(), 'id'].tolist()[:5]}")
    weights = np.concatenate([f["weights"] for f in fits])[order].astype(np.float32)
    return weights, table
