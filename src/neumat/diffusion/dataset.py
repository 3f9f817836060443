"""Which NeuMERL rows each model trains on, type labels, and nearest-neighbour look-ups.

Models (paper §4.3, §4.6): `ours` trains on the NeuMERL train split (all of AugMERL there);
`merl100` on the train-split fits of the original MERL materials only. The reference set of
Table 2 is the test split; the `training` column is a random train subset of the same size.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

MODELS = ("ours", "merl100", "refiner")
MANIFEST_COLUMNS = ("id", "name", "operation", "type", "split")


def read_manifest(path: str | Path, n_weights: int | None = None) -> pd.DataFrame:
    man = pd.read_csv(path, sep="\t", keep_default_na=False, dtype={"type": str})
    missing = [c for c in MANIFEST_COLUMNS if c not in man.columns]
    if missing:
        raise ValueError(f"{path}: missing columns {missing}")
    if n_weights is not None and len(man) != n_weights:
        raise ValueError(f"{path}: {len(man)} rows but the NeuMERL weights have {n_weights}")
    return man


def class_names(types) -> list[str]:
    """Sorted distinct non-empty type names: the class index of a type is its position."""
    return sorted({t for t in types if t})


def training_rows(man: pd.DataFrame, model: str) -> np.ndarray:
    train = man["split"] == "train"
    if model in ("ours", "refiner"):  # the refiner (conditions.image.refiner): ours's rows
        rows = np.flatnonzero(train)
    elif model == "merl100":
        rows = np.flatnonzero(train & (man["operation"] == "original"))
    else:
        raise ValueError(f"unknown diffusion model {model!r}; choose from {MODELS}")
    if len(rows) == 0:
        raise ValueError(f"no training materials for model {model!r} in the manifest")
    return rows


def training_types(man: pd.DataFrame, model: str = "ours") -> set[str]:
    """The material types some training material of `model` has: the classes whose embeddings
    trained (a type only held-out materials have is a class too, never trained)."""
    return set(man["type"].iloc[training_rows(man, model)]) - {""}


def require_trained(types, man: pd.DataFrame, what: str, model: str = "ours") -> None:
    """ValueError, starting with `what` (the option or config key that asked), for the asked
    `types` ('' = none) that no training material of `model` has (training_types)."""
    have = training_types(man, model)
    missing = sorted(set(types) - have - {""})
    if missing:
        raise ValueError(f"{what} {', '.join(missing)}: no training material has this type (only "
                         f"held-out ones do), so the model never learnt it; types it learnt: "
                         f"{', '.join(sorted(have))}")


def reference_rows(man: pd.DataFrame) -> np.ndarray:
    rows = np.flatnonzero(man["split"] == "test")
    if len(rows) == 0:
        raise ValueError("the manifest has no test-split materials (augmerl.test_fraction)")
    return rows


def labels(types, names: list[str]) -> np.ndarray:
    """Type names -> class indices; '' (interpolated materials) -> -1 (the null class)."""
    index = {n: i for i, n in enumerate(names)}
    unknown = sorted({t for t in types if t and t not in index})
    if unknown:
        raise ValueError(f"types {unknown} are not among the model's classes {names}")
    return np.array([index[t] if t else -1 for t in types], dtype=np.int64)


def prior_types(man: pd.DataFrame, n: int, seed: int) -> list[str]:
    """n type names drawn as `ours` saw them in training: the types of n train-split rows
    picked uniformly with replacement ('' for untyped interpolations, i.e. the null class).
    Sampling each with its type and no guidance (scale 1) draws from sum_c p(c) p(x | c), the
    training distribution, through the conditional model (diffusion.sample.type_prior)."""
    types = man["type"].to_numpy()[training_rows(man, "ours")]
    return list(types[np.random.default_rng(seed).integers(0, len(types), n)])


def training_subset(man: pd.DataFrame, seed: int, draws: int = 1) -> np.ndarray:
    """Rows of `draws` disjoint random train-split subsets, each as large as the test split
    (Table 2 'Training set'), draw-major, each draw sorted. Too few training rows: the draws
    shrink to len(train) // draws each. Draw d is rows d n ... (d + 1) n - 1 of one permutation
    of the train split, so a draw does not depend on how many follow it (numpy's choice
    without replacement drew other rows for every draw count: `metrics.draws` changed draw 0)."""
    train, n = training_rows(man, "ours"), len(reference_rows(man))
    n = min(n, len(train) // draws)
    pick = np.random.default_rng(seed).permutation(train)[:n * draws]
    return np.concatenate([np.sort(d) for d in pick.reshape(draws, n)])


def nearest(a: torch.Tensor, b: torch.Tensor, chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """For each row of a (n, D), the index of and BRDF-L1 distance to its nearest row of b."""
    from neumat.metrics.distances import pairwise_l1

    idx, dist = [], []
    for s in range(0, len(a), chunk):
        d = pairwise_l1(a[s:s + chunk], b)
        m = d.min(1)
        idx.append(m.indices.numpy())
        dist.append(m.values.numpy())
    return np.concatenate(idx), np.concatenate(dist)


def relative(dist: np.ndarray, idx: np.ndarray, b_mean: np.ndarray) -> np.ndarray:
    """`nearest`'s distances over the nearest rows' mean absolute values `b_mean` (each row of b,
    `b.abs().mean(1)`): a specular material's values run tens of times a diffuse one's, so only
    this compares sets of other mixes (nearest.tsv `relative_l1`)."""
    return dist / np.maximum(b_mean[idx], 1e-12)


def same_source(sources) -> np.ndarray:
    """(N, N) bool: rows i, j share a MERL source material (manifest `sources`: 'name' for an
    original or its permuted copy, 'a@rgb|b@gbr' for a mixture), the diagonal included."""
    names = [{c.split("@")[0] for c in str(s).split("|")} for s in sources]
    index = {n: i for i, n in enumerate(sorted(set().union(*names)))}
    A = np.zeros((len(names), len(index)), np.float32)  # row x source incidence
    for i, ns in enumerate(names):
        A[i, [index[n] for n in ns]] = 1
    return (A @ A.T) > 0
