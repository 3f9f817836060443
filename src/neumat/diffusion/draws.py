"""Finished draws of a sampling job, kept beside its output so that a killed job resumes at its
next draw. A draw (of a seed, or of a constrained-synthesis category) is a pure function of its
key, the model and the settings (the `fingerprint`), so the resumed job writes what an unkilled
one writes (tests/test_diffusion_draws.py); the job removes the folder once its output is
written."""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from neumat.io.atomic import NPZ_ERRORS, save_npz

log = logging.getLogger(__name__)


def fingerprint(files, settings: dict) -> str:
    """What a draw depends on besides its seed: the bytes of `files` (model, manifest) and
    `settings` (JSON)."""
    h = hashlib.sha256()
    for f in files:
        h.update(Path(f).read_bytes())
    h.update(json.dumps(settings, sort_keys=True, default=str).encode())
    return h.hexdigest()


def table_arrays(t: pd.DataFrame) -> dict:
    """A table as arrays a draw file holds without pickle: each column with its dtype (an empty
    one too), strings as unicode, and the column order as JSON (`table` reads it back)."""
    cols = {f"col_{c}": (t[c].to_numpy() if pd.api.types.is_numeric_dtype(t[c])
                         else t[c].to_numpy().astype(str)) for c in t.columns}
    return {"columns": np.array(json.dumps(list(t.columns))), **cols}


def table(arrays: dict) -> pd.DataFrame:
    """The table `table_arrays` stored."""
    return pd.DataFrame({c: arrays[f"col_{c}"] for c in json.loads(str(arrays["columns"]))})


def seconds(done: list[dict], fallback: float) -> float:
    """The sampling time of the draws `done` (each draw's "seconds", kept with it, so a resumed
    job's timing counts the draws it read back too), or `fallback` (this job's own time) where a
    draw file from before the time was kept lacks it."""
    if all("seconds" in d for d in done):
        return float(sum(float(d["seconds"]) for d in done))
    return fallback


class DrawCache:
    """draw_<key>.npz files in `folder`, each with the fingerprint it was made for."""

    def __init__(self, folder: str | Path, fp: str):
        self.folder, self.fp = Path(folder), fp

    def get(self, seed: int | str, make: Callable[[], dict]) -> dict:
        """The arrays of draw `seed` (a seed, or another key such as a category name): from its
        file when that was made for this fingerprint, else `make()`'s (name -> array), saved
        first. A file of other settings or one that cannot be read is logged and replaced."""
        f = self.folder / f"draw_{seed}.npz"
        if f.exists():
            try:
                with np.load(f, allow_pickle=False) as z:
                    if str(z["fingerprint"]) == self.fp:
                        log.info("draw %s: resumed from %s", seed, f)
                        return {k: z[k] for k in z.files if k != "fingerprint"}
                log.info("%s: made for another model or settings; drawing again", f)
            except NPZ_ERRORS as e:
                log.warning("%s: unreadable (%s: %s); drawing again", f, type(e).__name__, e)
        arrays = make()
        self.folder.mkdir(parents=True, exist_ok=True)
        save_npz(f, fingerprint=np.array(self.fp), **arrays)
        return arrays

    def clear(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
