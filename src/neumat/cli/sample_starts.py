"""`neumat sample`'s reading of a run for its starts and type checks: the run's NeuMERL
weights, manifest and training rows, and the training-material starts of `--start` (as the
workflow's sample_conditions draws them: `neumat.conditions.starts`, `text.training_starts`,
`image.retrieve`)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from neumat.cli.run import CLIError, Run, _progress


def run_file(run: Run, rel: str, rule: str, why: str = "--start") -> Path:
    p = run.path / rel
    if not p.exists():
        raise CLIError(f"{why} needs {p}; build it with rule {rule}: `{run.target(rel)}`")
    return p


def read_manifest(run: Run, path, n_rows=None):
    """dataset.read_manifest of the run's `path`, or the `unreadable` error naming it and rule
    neumerl (a manifest without its columns, or of another row count than the weights, gave a
    bare traceback; a review, 2026-11-29)."""
    from neumat.diffusion import dataset
    try:
        return dataset.read_manifest(path, n_rows)
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise run.unreadable("neumerl/manifest.tsv", "neumerl", e) from None


def run_manifest(run: Run):
    """The run's NeuMERL manifest, or None where it has none (a shared model alone)."""
    path = run.path / "neumerl/manifest.tsv"
    return read_manifest(run, path) if path.exists() else None


def trained_types(run: Run) -> set[str] | None:
    """The types some training material (`ours`'s rows, on which the run's models train) has:
    a type only held-out materials have is among the model's classes, but its class embedding
    never trained, so samples asked for it follow no type (the workflow's mm_type and
    constrained synthesis leave such types out). None without a manifest: nothing is checked."""
    from neumat.diffusion import dataset

    man = run_manifest(run)
    return None if man is None else dataset.training_types(man)


def check_trained_type(run: Run, typ: str) -> None:
    """CLIError where the run's training materials do not have type `typ` (trained_types)."""
    from neumat.diffusion import dataset

    man = run_manifest(run)
    if man is not None:
        try:
            dataset.require_trained([typ], man, "--type")
        except ValueError as e:
            raise CLIError(f"{e} (run {run.path})") from None


def training_set(run: Run):
    """(NeuMERL weights, manifest, `ours`'s training rows) of the run: where --start draws from."""
    from neumat.diffusion import dataset

    run_file(run, "neumerl/weights.npy", "neumerl")
    weights = run.array("neumerl/weights.npy", "neumerl")
    man = read_manifest(run, run_file(run, "neumerl/manifest.tsv", "neumerl"), len(weights))
    return weights, man, dataset.training_rows(man, "ours")


def image_start(run: Run, emb: np.ndarray) -> tuple[np.ndarray, str]:
    """--image --start: the training material (`ours`'s rows) whose metric-view embedding
    (`conditions/image.npy`, under the first training light) is nearest the image's, as the
    workflow's sample_image retrieves it with conditions.image.strength < 1: its weights and
    name."""
    from neumat.conditions import image

    weights, man, rows = training_set(run)
    run_file(run, "conditions/image.npy", "image_embeddings")
    library = run.array("conditions/image.npy", "image_embeddings")[rows, 0]
    got = image.retrieve(emb, library, rows)[0]
    print(f"--image --start: from the training material {man['name'].iloc[got]!r} (nearest image "
          f"embedding)", file=sys.stderr)
    return weights[got], man["name"].iloc[got]


def draw_from_start(args, run: Run, sampler, fixed: dict, scales: dict, neg: float,
                     refit: int = 0):
    """(weights, table): --start. Each sample starts from a training material (`ours`'s rows)
    noised to args.start: for --type one of the type (drawn with the seed's stream
    "cli_type_start"), for --text the matched starts of the workflow's
    conditions.text.start_match (sample i from the i-th); denoised by the model under its
    condition, or by the refiner (--refiner) without one."""
    import pandas as pd

    from neumat.conditions import starts
    from neumat.diffusion.sample import sample
    from neumat.seeds import seed_for

    weights, man, rows = training_set(run)
    extra = {}
    if args.type:
        got = starts.type_picks([args.type], rows, man["type"].iloc[rows].to_numpy(), args.n,
                                np.random.default_rng(seed_for(args.seed, "cli_type_start")))[0]
        if (got < 0).any():  # check_trained_type refused it before: a backstop, not a message
            raise CLIError(f"--type {args.type}: no training material of the run has it")
        cond, guidance = {"type": [args.type] * args.n}, {"type": scales.get("type", 1.0)}
    else:
        from neumat.conditions import evaluate, text
        run_file(run, "conditions/text.npy", "text_embeddings")
        library = run.array("conditions/text.npy", "text_embeddings")[rows]
        got, voted, size, _ = text.training_starts(fixed["text"], library, weights, man, rows,
                                                   [evaluate.colour_of(args.text)], args.n,
                                                   args.activation)
        got, extra = got[0], {"voted_type": voted[0]}
        print(f"--text {args.text!r}: starts of type {voted[0]!r} (vote over the {size} nearest "
              f"typed training descriptions)", file=sys.stderr)
        cond, guidance = {"text": np.repeat(fixed["text"], args.n, 0)}, {"text": scales["text"]}
    if args.refiner:
        cond, guidance = {}, {}
    with _progress(args.n, "refining" if args.refiner else "sampling from starts") as bar:
        w = sample(sampler, args.n, seed_for(args.seed, "cli_start"), cond, guidance, args.steps,
                   args.eta, args.batch, args.clip, negative_step=neg, activation=args.activation,
                   start=weights[got], strength=args.start, refit_steps=refit)
        bar.update(args.n)
    table = pd.DataFrame({"sample": range(args.n), "type": args.type or "",
                          "start": man["name"].iloc[got].to_numpy(), "strength": args.start,
                          "refiner": args.refiner, **extra})
    return w, table
