"""`neumat sample`'s output folder: which files a draw writes, the check that --out holds no
one else's files, the draw written beside it and moved in whole."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from neumat.cli.render import _render_scene, _write_scene
from neumat.cli.run import CLIError, Run, _progress

# the files `neumat sample` writes into --out; a new draw replaces an earlier one's (a draw of
# fewer samples or without --mitsuba / with --no-binary would otherwise leave some beside it)
OUT_FILES = ("weights.npy", "samples.tsv", "scene.xml", "scene.png", "sky.exr")
OUT_SAMPLE = re.compile(r"sample_\d{3,}\.(binary|png)")  # f"sample_{i:03d}.binary" and .png


def outputs(out: Path) -> list[Path]:
    """The files in `out` with the names `neumat sample` writes (OUT_FILES, OUT_SAMPLE)."""
    if not out.is_dir():
        return []
    return [p for p in out.iterdir()
            if (p.name in OUT_FILES or OUT_SAMPLE.fullmatch(p.name)) and p.is_file()]


def check_out(out: Path, run: Run) -> None:
    """Before any drawing: --out is not in the run's folder (its files are the workflow's:
    `--out results/<run>/neumerl` had replaced the run's NeuMERL weights), and the files there
    with this command's output names are an earlier `neumat sample` draw (its samples.tsv has
    the columns sample and steps, as every draw's), which the new draw replaces; anything else
    is the user's and is not overwritten (a review, 2026-11-29: `weights.npy` and `samples.tsv`
    of another tool were deleted)."""
    target, root = out.resolve(), run.path.resolve()
    if target == root or root in target.parents:
        raise CLIError(f"--out {out} is inside the run's folder {run.path}/, whose files the "
                       f"workflow writes and reads: choose a folder outside it")
    found = outputs(out)
    if not found:
        return
    header = ""
    try:
        with open(out / "samples.tsv", encoding="utf-8") as f:
            header = f.readline()
    except (OSError, UnicodeDecodeError):
        pass
    if not {"sample", "steps"} <= set(header.rstrip("\n").split("\t")):
        names = ", ".join(sorted(p.name for p in found)[:5])
        raise CLIError(f"--out {out} holds {names}{' ...' if len(found) > 5 else ''}, which no "
                       f"`neumat sample` wrote (its samples.tsv names the columns sample and "
                       f"steps): move them or choose another folder")


def replace_draw(out: Path, staged: Path | None) -> None:
    """Remove the earlier draw's files from `out` (other files are left alone), then move the
    new draw's in from `staged` (None: nothing was drawn)."""
    for p in outputs(out):
        p.unlink()
    if staged is not None:
        out.mkdir(parents=True, exist_ok=True)
        for p in staged.iterdir():
            os.replace(p, out / p.name)


def write_draw(args, out: Path, w: np.ndarray, table) -> None:
    """weights.npy, samples.tsv, sample_NNN.binary/.png, scene.xml (and scene.png)."""
    import torch

    from neumat import nbrdf
    from neumat.io import merl
    from neumat.render import sphere

    np.save(out / "weights.npy", w.astype(np.float32))
    table.to_csv(out / "samples.tsv", sep="\t", index=False, float_format="%.6g")
    imgs = sphere.tonemap(sphere.render_fields(w, args.resolution, args.activation))
    from PIL import Image
    with _progress(len(w), "writing .binary + .png") as bar:
        for i in range(len(w)):
            if not args.no_binary:
                table_i = nbrdf.evaluate_grid(torch.as_tensor(w[i:i + 1]), args.activation)[0]
                merl.write_merl(out / f"sample_{i:03d}.binary", table_i)
            Image.fromarray(imgs[i]).save(out / f"sample_{i:03d}.png")
            bar.update(1)
    scene = _write_scene(out, len(w), args.activation)
    if args.mitsuba:
        _render_scene(scene, out / "scene.png", args.variant,
                      256 if args.mitsuba_resolution is None else args.mitsuba_resolution,
                      32 if args.spp is None else args.spp)
