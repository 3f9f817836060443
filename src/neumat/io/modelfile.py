"""Loading model and checkpoint files safely. Users share model files, so a file is read with
`torch.load(weights_only=True)`: tensors and plain values only, never arbitrary pickled objects
(which would run code on load). Every file neumat writes is of that kind."""

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import torch


def load(path: str | Path, map_location="cpu", finite: bool = False):
    """The contents of a torch file at `path`, refusing anything but tensors and plain values,
    with an error that names the file and says what to do. `finite`: also refuse a floating
    tensor holding NaN or inf (model files: a shared model with NaN weights would otherwise
    sample NaN materials and black renders without a word; not for files whose matrices hold
    inf on purpose, e.g. metrics/reference.pt's distances)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such model file")
    try:
        bundle = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # UnpicklingError for foreign objects, RuntimeError for corrupt zips
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(
            f"{path}: not a model file neumat can load safely ({first}). neumat reads tensors "
            "and plain values only (torch.load weights_only=True), never pickled objects. If the "
            "file is truncated or from elsewhere, delete it and rebuild it with the snakemake "
            "rule that writes it.") from e
    if finite:
        bad = first_non_finite(bundle)
        if bad is not None:
            raise ValueError(f"{path}: tensor {bad} holds NaN or inf values, so the model cannot "
                             f"give valid results; rebuild the file with the snakemake rule that "
                             f"writes it (a training that diverged: lower its learning rate)")
    return bundle


def first_non_finite(obj, where: str = "") -> str | None:
    """The key path (e.g. `ema.blocks.0.w`) of the first floating tensor in a nested
    dict / list holding NaN or inf, or None."""
    if torch.is_tensor(obj):
        flat = obj.reshape(-1)  # in blocks: no boolean copy of a 2.6 GB SH model at once
        ok = not obj.is_floating_point() or all(
            bool(torch.isfinite(flat[s:s + (1 << 24)]).all()) for s in range(0, len(flat), 1 << 24))
        return None if ok else (where or "<root>")
    items = obj.items() if isinstance(obj, dict) else \
        enumerate(obj) if isinstance(obj, (list, tuple)) else ()
    for k, v in items:
        bad = first_non_finite(v, f"{where}.{k}" if where else str(k))
        if bad is not None:
            return bad
    return None


def fingerprint(arrays, settings) -> str:
    """What a training checkpoint was written for: sha256 over `arrays` (their float32 bytes,
    one after another, without concatenating them; None skipped) and `settings` (JSON), so a
    changed input or setting starts over rather than resuming another training."""
    h = hashlib.sha256()
    for a in arrays:
        if a is not None:
            h.update(np.ascontiguousarray(np.asarray(a, dtype=np.float32)))
    h.update(json.dumps(settings, sort_keys=True, default=float).encode())
    return h.hexdigest()


def require(bundle, keys, source, kind: str) -> dict:
    """`bundle` if it is a dict holding every one of `keys`, else an error that names the file
    (`source`) and the kind of model file expected (e.g. "a diffusion model (rule
    train_diffusion)"), rather than a KeyError from deep inside the loader."""
    missing = [k for k in keys if not isinstance(bundle, dict) or k not in bundle]
    if missing:
        raise ValueError(f"{source}: not {kind}: it lacks {', '.join(missing)}. Pass the file "
                         f"that rule writes, or rebuild it with that rule.")
    return bundle


def build(make, state, source, rule: str, **load_kw):
    """`make()` with `state` loaded into it, or an error that names the file (`source`) and the
    rule that rebuilds it where the state does not fit the file's own config (another version's
    layout, a foreign model), rather than torch's RuntimeError from load_state_dict."""
    try:
        model = make()
        model.load_state_dict(state, **load_kw)
    except (TypeError, KeyError, RuntimeError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"{source}: its state does not fit its config ({first}); rebuild it "
                         f"with rule {rule}") from e
    return model


def final_path(path: str | Path) -> Path:
    """Where `finish` keeps a finished training's last checkpoint: checkpoint.pt ->
    checkpoint.final.pt."""
    path = Path(path)
    return path.with_suffix(".final" + path.suffix)


def finish(path: str | Path) -> None:
    """Keep a finished training's last checkpoint as `final_path(path)`, where `resume` finds it.
    After `kill -INT` of Snakemake alone, a running job finishes, but Snakemake marks its
    outputs incomplete and --rerun-incomplete runs it again: it then resumes at the last step
    and only writes its model (before, the job script had deleted the checkpoint, and hours of
    training at paper scale were redone: a review on the tiny run, 2026-11-29). A separate
    name, so that the job scripts' removal of `path` (kept as it was, so that existing runs do
    not retrain for an edited script) leaves it. Its fingerprint keeps it from being resumed
    for other data or settings."""
    path = Path(path)
    if path.exists():
        os.replace(path, final_path(path))


def resume(path: str | Path, fingerprint: str | None = None, map_location="cpu",
           **state) -> dict | None:
    """A training checkpoint at `path`, loaded into `state` (name -> object with
    `load_state_dict`, or a torch.Generator, restored from the checkpoint's entry of that name),
    or None: no file, one written for another fingerprint (other data or settings), or one that
    cannot be read (logged and ignored, so training starts over and overwrites it: a checkpoint
    is no Snakemake output, so --rerun-incomplete never removes a damaged one, and failing on
    it would fail every rerun, as in neumat.fit's resume). `fingerprint` None accepts any
    checkpoint."""
    import logging

    log = logging.getLogger(__name__)
    path = Path(path)
    if not path.exists():
        final = final_path(path)  # a finished training's (`finish`): resumed at its last step
        return resume(final, fingerprint, map_location, **state) if final.exists() else None
    try:
        ck = load(path, map_location=map_location)
    except ValueError as e:
        log.warning("ignoring unreadable checkpoint %s, starting over (it is overwritten at the "
                    "next checkpoint): %s", path, str(e).split(". neumat reads")[0])
        return None
    if fingerprint is not None and ck.get("fingerprint") != fingerprint:
        log.warning("ignoring %s: written for other data or settings", path)
        return None
    for name, obj in state.items():
        if isinstance(obj, torch.Generator):  # a CPU state, wherever map_location put it
            obj.set_state(ck[name].cpu())
        else:
            obj.load_state_dict(ck[name])
    log.info("resumed from %s at step %s", path, ck.get("step"))
    return ck
