"""What the workflow's sample_conditions draws under each condition: the test-split images and
the user's images with their embeddings (mode 'image'), the test prompts whose type the model
was trained on ('mm_type'), and, below strength 1, each condition's starting training materials
(type and text starts; the image start is `neumat.conditions.image.retrieve`). The training
materials are `ours`'s training rows of NeuMERL (`dataset.training_rows`), conditions_eval's
retrieval set."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from neumat.conditions import image, starts, text
from neumat.diffusion import dataset
from neumat.render import sphere

log = logging.getLogger(__name__)


def image_conditions(weights: np.ndarray, man: pd.DataFrame, test_images: int, paths,
                     enc, resolution: int, activation: str):
    """Test-split typed materials (`test_images` of them evenly picked, 0: all) and the images
    at `paths` -> (table, embeddings (M, D), conditioning images (M, R, R, 3) linear HDR in the
    metric view at `resolution`)."""
    test = dataset.reference_rows(man)
    test = test[man["type"].iloc[test].to_numpy() != ""]
    k = test_images or len(test)
    test = test[np.unique(np.linspace(0, len(test) - 1, min(k, len(test))).round().astype(int))]
    emb = [image.embed(enc, sphere.render_fields(weights[test], enc.cfg.resolution, activation))]
    imgs = [sphere.render_fields(weights[test], resolution, activation).numpy()]
    table = pd.DataFrame({"source": man["name"].iloc[test].to_numpy(), "id": test,
                          "type": man["type"].iloc[test].to_numpy()})
    paths = list(paths)
    if paths:
        emb.append(np.concatenate([image.embed(enc, image.load_image(f, enc.cfg.resolution)[None])
                                   for f in paths]))
        imgs.append(np.stack([image.load_image(f, resolution) for f in paths]))
        table = pd.concat([table, pd.DataFrame({"source": paths, "id": -1, "type": ""})],
                          ignore_index=True)
    return table, np.concatenate(emb), np.concatenate(imgs).astype(np.float32)


def trained_conditions(conds: pd.DataFrame, man: pd.DataFrame) -> pd.DataFrame:
    """The rows of `conds` whose type some training material has; all of them, with a
    warning, when none has (the model never saw the others' types: their class embeddings are
    untrained)."""
    have = dataset.training_types(man)
    ok = conds["type"].isin(have).to_numpy()
    if not ok.any():
        log.warning("mm_type: no test prompt's type is among the training materials' types: "
                    "all %d drawn from noise, their class embeddings untrained", len(conds))
        return conds
    if not ok.all():
        log.info("mm_type: %d of %d test prompts have a type no training material has (%s): not "
                 "drawn, the model never saw it", int((~ok).sum()), len(conds),
                 ", ".join(sorted(set(conds["type"][~ok]))))
    return conds[ok]


def type_starts(weights: np.ndarray, man: pd.DataFrame, rows: np.ndarray, conds: pd.DataFrame,
                k: int, seed: int):
    """(start vectors (len(conds) k, 675), conds with a `start` column): for each of a
    condition's k samples a training material (of `rows`) of its type, drawn with `seed`; NaN
    rows (from noise) where training has no such type."""
    picks = starts.type_picks(conds["type"], rows, man["type"].iloc[rows].to_numpy(), k,
                              np.random.default_rng(seed))
    got = picks.reshape(-1)
    start = np.where(got[:, None] >= 0, weights[np.maximum(got, 0)], np.nan)
    conds = conds.assign(start=[",".join(man["name"].iloc[r] for r in g) if (g >= 0).all() else ""
                                for g in picks])
    log.info("mm_type: %d of %d samples start from a training material of their type",
             int((got >= 0).sum()), len(got))
    return start, conds


def text_starts(weights: np.ndarray, man: pd.DataFrame, rows: np.ndarray, library: np.ndarray,
                conds: pd.DataFrame, emb: np.ndarray, k: int, vote: bool, activation: str):
    """(start vectors (len(conds) k, 675), conds with `start` (and `voted_type`) columns): for
    each prompt embedding (rows of `emb`) its k nearest training materials (of `rows`, whose
    description embeddings are `library`) by cosine (text.embed writes unit vectors), sample i
    from the i-th nearest; ties (shared descriptions) in row order. With `vote`
    (conditions.text.start_match) only materials of the type voted by the prompt's nearest typed
    descriptions (text.vote_types, vote size by text.choose_votes) are drawn, those whose
    metric-view colour matches the prompt's colour word first."""
    if vote:
        got, voted, size, acc = text.training_starts(emb, library, weights, man, rows,
                                                     list(conds["colour"]), k, activation)
        log.info("text: type vote over the %d nearest typed descriptions (leave-source-out "
                 "accuracy on the training originals by vote size: %s)", size,
                 ", ".join(f"{n}: {a:.3f}" for n, a in acc.items()))
        conds = conds.assign(voted_type=voted)
    else:  # the nearest of any type; fewer rows than k: cycled
        sim = emb.astype(np.float64) @ library.astype(np.float64).T
        got = rows[text.typed_starts(sim, np.full(len(rows), ""), np.full(len(sim), ""), k)]
    conds = conds.assign(start=[",".join(man["name"].iloc[g]) for g in got])
    log.info("text: each prompt's %d samples start from its %d nearest training descriptions%s",
             k, k, " of its voted type, those of its colour word first" if vote else "")
    return weights[got.reshape(-1)], conds
