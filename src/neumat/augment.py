"""AugMERL: RGB permutations and PCA interpolation of measured BRDFs (M3ashy paper §3.1).

Every source material yields 6 channel permutations ("rows"). Pairs of rows are linearly
interpolated in a PCA space of `pca_dims` dimensions, up to `size` materials in total.

The PCA works on log(1 + f) over the bins valid in every source table. Interpolating
coefficients and reconstructing equals projecting the linear interpolant onto the top-k
principal subspace, so every material is an exact linear mixture of the rows:

    log(1 + f_i) = sum_j C[i, j] log(1 + row_j)         (C one-hot for rows themselves)

`recipe.npz` stores C; any material is rebuilt exactly from the source tables, through their
log1p cache (float32, written once per run by rule augmerl_log_tables and memory-mapped by
every consumer: write_log_tables / open_log_tables).

Splits are by source material: all rows of a source share its split, pairs are drawn inside a
split, and each split gets its own PCA, so no test material leaks into a training one.
"""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import numpy as np
import pandas as pd

from neumat.data.catalog import drop_colours
from neumat.io import merl
from neumat.io.atomic import NPZ_ERRORS
from neumat.linalg import one_blas_thread
from neumat.seeds import seed_for

log = logging.getLogger(__name__)

PERMS = ["".join(p) for p in itertools.permutations("rgb")]  # "rgb" (identity) first
MANIFEST_COLUMNS = ["id", "name", "operation", "sources", "weight", "permutation", "type",
                    "description", "split", "shard"]


def permute(table: np.ndarray, perm: str) -> np.ndarray:
    """Channel permutation of a (3, ...) array: output channel c = input channel perm[c]."""
    return table[["rgb".index(ch) for ch in perm]]


# ----------------------------------------------------------------------------- plan


def check_split(names: list[str], test_fraction: float, what: str = "merl.subset",
                permutations: bool = True, size: int = 0) -> None:
    """DAG-time check: the run needs a train and a test split of its source materials
    (split_sources gives each at least one when test_fraction > 0), and interpolations
    (augmerl.size above the rows) need a split of two rows to mix."""
    if test_fraction <= 0:
        raise ValueError(f"config augmerl.test_fraction = {test_fraction}: must be > 0 (the "
                         "test split is Table 2's reference set)")
    if len(names) < 2:
        raise ValueError(
            f"config {what}: {len(names)} material(s) {list(names)} with augmerl.test_fraction = "
            f"{test_fraction} leave no train/test split; at least 2 source materials are needed "
            "(one for training, one for the test split)")
    if not permutations and len(names) == 2 and size > 2:
        raise ValueError(
            f"config augmerl.size = {size} asks for interpolations, but {what} has 2 materials and "
            "augmerl.permutations is false: each split holds one row, with nothing to mix; set "
            "augmerl.permutations: true, add source materials, or set augmerl.size <= 2")


def split_sources(names: list[str], test_fraction: float, seed: int) -> dict[str, str]:
    """Assign each source material to train/test (at least one of each when test_fraction > 0).

    Draws from `seed` itself (the AugMERL stream); pairs and bins draw from named sub-streams
    of it, so none of the three shares numbers with another."""
    rng = np.random.default_rng(seed)
    n_test = int(round(test_fraction * len(names)))
    if test_fraction > 0:
        n_test = min(max(n_test, 1), len(names) - 1)
    test = set(rng.permutation(len(names))[:n_test].tolist())
    return {n: ("test" if i in test else "train") for i, n in enumerate(names)}


def plan_rows(catalog: pd.DataFrame, permutations: bool, split: dict[str, str]) -> pd.DataFrame:
    """The originals and their RGB permutations, one row each."""
    perms = PERMS if permutations else PERMS[:1]
    rows = []
    for rec in catalog.itertuples():
        for p in perms:
            desc = rec.description if p == "rgb" else drop_colours(rec.description, rec.colours)
            rows.append(dict(name=rec.name if p == "rgb" else f"{rec.name}@{p}",
                             operation="original" if p == "rgb" else "permutation",
                             sources=rec.name, weight=1.0, permutation=p, type=rec.type,
                             description=desc, split=split[rec.name]))
    return pd.DataFrame(rows)


def template_id(rows: pd.DataFrame) -> int:
    """Manifest id of the template material, whose fit initialises every other (paper §3.2):
    the first original of the train split (plan_rows' rows lead the manifest, so a row's index
    is its id). Not simply id 0: when that source falls in the test split, every training
    field would start from a test material's fit."""
    hit = np.flatnonzero(((rows["split"] == "train") & (rows["operation"] == "original")).to_numpy())
    if not len(hit):
        raise ValueError("no source material in the train split to fit the template from")
    return int(hit[0])


def interpolation_counts(rows: pd.DataFrame, n_interp: int) -> dict[str, int]:
    """Interpolations per split (plan_pairs draws them): `n_interp` in proportion to the
    splits' rows, none in a split of one row (one source, no permutations)."""
    splits = sorted(rows["split"].unique())
    sizes = np.array([(rows["split"] == s).sum() for s in splits])
    sizes[sizes < 2] = 0  # a split of one row has no pair
    if n_interp > 0 and not sizes.any():
        raise ValueError(f"{n_interp} interpolations asked (augmerl.size), but no split has two "
                         f"rows to mix: set augmerl.permutations: true, add source materials, "
                         f"or set augmerl.size <= {len(rows)}")
    if not sizes.any():
        return {s: 0 for s in splits}
    counts = np.floor(n_interp * sizes / sizes.sum()).astype(int)
    counts[np.argmax(sizes)] += n_interp - counts.sum()
    return dict(zip(splits, counts.tolist()))


def plan_pairs(rows: pd.DataFrame, n_interp: int, seed: int):
    """Draw `n_interp` (row_a, row_b, weight_a) triples inside splits, in proportion to their size.

    Rows of different source materials are paired when the split has more than one source."""
    rng = np.random.default_rng(seed_for(seed, "augmerl_pairs"))
    counts = interpolation_counts(rows, n_interp)
    pairs = []
    for s, n in counts.items():
        idx = np.flatnonzero(rows["split"].to_numpy() == s)
        src = rows["sources"].to_numpy()
        multi = len(set(src[idx])) > 1
        while n > 0:
            a, b = rng.choice(idx, 2, replace=False)
            if multi and src[a] == src[b]:
                continue
            pairs.append((int(a), int(b), float(rng.uniform(0.2, 0.8))))
            n -= 1
    return pairs


def build_manifest(rows: pd.DataFrame, pairs, shard_size: int) -> pd.DataFrame:
    interp = [dict(name=f"mix{k:04d}", operation="interpolation",
                   sources=f"{rows.at[a, 'name']}|{rows.at[b, 'name']}", weight=w,
                   permutation="", type="",
                   description=f"a mixture of {rows.at[a, 'description']} and "
                               f"{rows.at[b, 'description']}",
                   split=rows.at[a, "split"])
              for k, (a, b, w) in enumerate(pairs)]
    man = pd.concat([rows, pd.DataFrame(interp, columns=rows.columns)], ignore_index=True)
    man.insert(0, "id", np.arange(len(man)))
    man["shard"] = [f"{i // shard_size:03d}" for i in range(len(man))]
    return man[MANIFEST_COLUMNS]


# ----------------------------------------------------------------------------- PCA


def load_log_tables(paths: list[str | Path], negative: dict | None = None):
    """Read source tables -> (log1p values (M, 3, V) float32, valid flat bin indices (V,)).

    Valid = above the horizon at the bin centre and non-negative in every table. Tables are
    reduced to float32 logs one at a time, so 100 sources need ~1.3 GB, not 3.5 GB (twice that
    at the peak: above-horizon bins, then the common valid ones). With a
    `negative` dict, each table is checked (merl.check_negative: a warning with the count, an
    error for far more negative bins than real MERL tables have) and its count stored there.

    Consumers read these once, through the cache (write_log_tables / open_log_tables)."""
    geo = np.flatnonzero(merl.valid_mask())
    keep = np.ones(len(geo), dtype=bool)
    logs = np.empty((len(paths), 3, len(geo)), dtype=np.float32)
    for i, p in enumerate(paths):
        t = merl.read_merl(p).reshape(3, -1)
        if negative is not None:
            negative[str(p)] = merl.check_negative(p, t)
        t = t[:, geo]
        keep &= (t >= 0).all(0)
        logs[i] = np.log1p(np.maximum(t, 0))  # float64 log, rounded once to float32
    return logs[:, :, keep], geo[keep]


# ----------------------------------------------------------------------------- log-table cache
# Every AugMERL consumer needs log1p of all source tables over their common valid bins. Reading
# and converting 100 float64 tables (3.5 GB) costs each job tens of seconds; the cache holds the
# float32 result once (`.npy`, memory-mapped: jobs share the page cache and touch only the rows
# and columns they use) and its index (`.npz`: source names, valid bins, negative-bin counts).


def write_log_tables(paths: list[str | Path], names: list[str], npy_path: str | Path,
                     index_path: str | Path) -> tuple[int, int]:
    """Convert the source tables (load_log_tables, with its checks) into the cache files.

    The values are exactly load_log_tables' float32 array. Returns (sources, valid bins)."""
    if len(paths) != len(names):
        raise ValueError(f"{len(paths)} tables for {len(names)} names")
    negative = {}
    logs, valid = load_log_tables(paths, negative)
    if not np.isfinite(logs).all():  # read_merl refuses NaN/inf; log1p of finite >= 0 is finite
        raise ValueError(f"{npy_path}: non-finite log values from the source tables")
    npy_path, index_path = Path(npy_path), Path(index_path)
    tmp = npy_path.with_name(npy_path.name + ".part.npy")
    np.save(tmp, logs)
    tmp.replace(npy_path)
    tmp = index_path.with_name(index_path.name + ".part.npz")
    np.savez(tmp, source_names=np.array(names), valid_bins=valid.astype(np.int64),
             negative_bins=np.array([negative[str(p)] for p in paths], dtype=np.int64))
    tmp.replace(index_path)
    return logs.shape[0], logs.shape[2]


def open_log_tables(npy_path: str | Path, index_path: str | Path):
    """The cache, memory-mapped -> (logs (M, 3, V) float32 read-only memmap, valid bins (V,),
    source names, negative-bin counts (M,)).

    Checks the header, dtype and shapes against the index (a truncated or foreign file fails
    here, naming it); the values were checked finite when the cache was written."""
    redo = "delete it and rerun the workflow (rule augmerl_log_tables rebuilds it)"
    try:
        with np.load(index_path, allow_pickle=False) as z:
            names = [str(s) for s in z["source_names"]]
            valid, negative = z["valid_bins"], z["negative_bins"]
    except NPZ_ERRORS as e:
        raise ValueError(f"{index_path}: not a readable AugMERL log-table index ({e}); "
                         f"{redo}") from e
    try:
        logs = np.load(npy_path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise ValueError(f"{npy_path}: not a readable AugMERL log-table cache ({e}); "
                         f"{redo}") from e
    expect = (len(names), 3, len(valid))
    if logs.dtype != np.float32 or logs.shape != expect:
        raise ValueError(f"{npy_path}: {logs.dtype} array of shape {logs.shape}, its index "
                         f"{index_path} says float32 {expect}; {redo}")
    if len(negative) != len(names) or (len(valid) and (valid.min() < 0 or
                                                       valid.max() >= merl.N_BINS)):
        raise ValueError(f"{index_path}: inconsistent index (bins outside the MERL grid or "
                         f"counts for {len(negative)} of {len(names)} sources); {redo}")
    return logs, valid, names, negative


def row_gram(logs: np.ndarray, row_src: np.ndarray, row_perm: np.ndarray,
             chunk: int = 1 << 16) -> np.ndarray:
    """Gram matrix of the permuted rows without materialising them.

    Channel cross-products H[(m,c),(m',c')] are summed over bins once (chunked, float64);
    row (m, p) . row (m', p') = sum_c H[(m, p[c]), (m', p'[c])]."""
    M, _, V = logs.shape
    flat = logs.reshape(M * 3, V)
    H = np.zeros((M * 3, M * 3))
    with one_blas_thread():  # the same bits on any core count
        for s in range(0, V, chunk):
            blk = flat[:, s:s + chunk].astype(np.float64)
            H += blk @ blk.T
    H = H.reshape(M, 3, M, 3)
    chans = np.array([["rgb".index(ch) for ch in PERMS[p]] for p in row_perm])  # (P, 3)
    G = np.zeros((len(row_src), len(row_src)))
    for c in range(3):
        G += H[row_src[:, None], chans[:, None, c], row_src[None, :], chans[None, :, c]]
    return G


def mixing_weights(G: np.ndarray, k: int, pairs_local) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients over the rows of one split for each interpolated pair, and the explained
    variance ratio of the kept k components.

    recon = mean + Xc^T U_k U_k^T e,  e = w e_a + (1 - w) e_b  (derivation in module doc);
    the coefficient of raw row j is m_j + (1 - sum m) / P."""
    P = G.shape[0]
    J = np.eye(P) - 1.0 / P
    with one_blas_thread():
        evals, U = np.linalg.eigh(J @ G @ J)
    order = np.argsort(evals)[::-1]
    evals, U = np.clip(evals[order], 0, None), U[:, order]
    k = min(k, P - 1)
    # a cut inside a degenerate eigenspace (RGB permutations make the Gram invariant under
    # channel permutations, so its eigenvalues come in equal pairs) keeps an arbitrary part of
    # it, whichever basis LAPACK returned: keep or drop a tie whole (here: keep). A tie is a gap
    # within rounding of the pair itself (eigh's error is about eps * evals[0] absolute): a gap
    # measured against evals[0] alone called every gap of the spectrum's tail a tie (a run's
    # pca_dims 300 kept 343 components, its 300th and 301st 1.2 % apart)
    def tied(k):
        return evals[k - 1] - evals[k] <= 1e-6 * evals[k - 1] + 1e-12 * evals[0]
    while 0 < k < P - 1 and evals[k] > 1e-9 * evals[0] and tied(k):
        k += 1
    Uk = U[:, :k]
    coefs = np.zeros((len(pairs_local), P))
    for i, (a, b, w) in enumerate(pairs_local):
        e = np.zeros(P)
        e[a] += w
        e[b] += 1 - w
        m = Uk @ (Uk.T @ e)
        coefs[i] = m + (1 - m.sum()) / P
    explained = evals[:k].sum() / max(evals.sum(), 1e-300)
    return coefs, np.array([k, explained])


def build_recipe(manifest: pd.DataFrame, rows: pd.DataFrame, pairs, logs, source_names,
                 pca_dims: int) -> dict:
    """The exact mixing matrix C (N, P) over rows, per split PCA."""
    src_index = {n: i for i, n in enumerate(source_names)}
    row_src = np.array([src_index[s] for s in rows["sources"]])
    row_perm = np.array([PERMS.index(p) for p in rows["permutation"]])
    N, P = len(manifest), len(rows)
    C = np.zeros((N, P))
    C[np.arange(P), np.arange(P)] = 1.0
    stats = {}
    split_of_row = rows["split"].to_numpy()
    for s in sorted(set(split_of_row)):
        idx = np.flatnonzero(split_of_row == s)
        local = {g: l for l, g in enumerate(idx)}
        which = [i for i, (a, _, _) in enumerate(pairs) if split_of_row[a] == s]
        if not which:
            continue
        G = row_gram(logs, row_src[idx], row_perm[idx])
        coefs, st = mixing_weights(G, pca_dims, [(local[pairs[i][0]], local[pairs[i][1]],
                                                   pairs[i][2]) for i in which])
        C[np.ix_(P + np.array(which), idx)] = coefs
        stats[s] = st
        log.info("split %s: %d rows, PCA k=%d keeps %.4f of the variance", s, len(idx),
                 int(st[0]), st[1])
    return dict(coef=C, row_src=row_src, row_perm=row_perm,
                source_names=np.array(source_names), pca_stats=stats)


# ----------------------------------------------------------------------------- materialise


def mix_values(logs, row_src, row_perm, coef, cols, chunk: int = 1 << 15) -> np.ndarray:
    """expm1(coef @ log1p(rows)) at columns `cols` of `logs` -> (n, 3, len(cols)) float32.

    Rows are (source, permutation) pairs; only rows with a non-zero coefficient are read, and
    each source channel they use is gathered once per chunk of columns (logs may be a memory
    map: a job touches only the pages it needs)."""
    used = np.flatnonzero(np.abs(coef).sum(0) > 0)
    coef = coef[:, used].astype(np.float32)
    src, perm = row_src[used], row_perm[used]
    # row j, output channel c reads source channel PERMS[perm_j][c]: flat row 3 src + that
    need = src[None, :] * 3 + np.array([["rgb".index(PERMS[p][c]) for p in perm]
                                        for c in range(3)])  # (3, rows)
    uniq, inv = np.unique(need, return_inverse=True)
    inv = inv.reshape(need.shape)
    flat = logs.reshape(-1, logs.shape[-1])
    out = np.empty((len(coef), 3, len(cols)), dtype=np.float32)
    for s in range(0, len(cols), chunk):
        cc = cols[s:s + chunk]
        block = np.empty((len(uniq), len(cc)), dtype=np.float32)
        for i, r in enumerate(uniq):
            np.take(flat[r], cc, out=block[i])
        for c in range(3):
            out[:, c, s:s + chunk] = np.maximum(np.expm1(coef @ block[inv[c]]), 0.0)
    return out


def interpolation_coefs(logs, row_src, row_perm, a: int, b: int, weights, k: int,
                        return_k: bool = False):
    """Coefficient vectors over all rows for PCA-space interpolation of rows a -> b; with
    `return_k`, also the number of components kept (mixing_weights keeps a tie across the cut
    whole, so it can exceed k)."""
    G = row_gram(logs, row_src, row_perm)
    coefs, info = mixing_weights(G, k, [(a, b, float(w)) for w in weights])
    return (coefs, int(info[0])) if return_k else coefs


class AugMERL:
    """Materialise AugMERL materials from the recipe and the log-table cache.

    Maps log1p of the sources over their common valid bins (open_log_tables); `values(ids,
    bins)` gives the physical BRDF of materials at chosen bins, `table(id)` a full MERL table."""

    def __init__(self, recipe_path: str | Path, log_tables: str | Path, log_index: str | Path):
        try:
            with np.load(recipe_path, allow_pickle=False) as r:
                self.coef, self.row_src, self.row_perm = r["coef"], r["row_src"], r["row_perm"]
                self.source_names = [str(s) for s in r["source_names"]]
                self.shard_bins = r["bins"]
                recipe_valid = r["valid_bins"] if "valid_bins" in r.files else None
        except NPZ_ERRORS as e:
            raise ValueError(f"{recipe_path}: not a readable AugMERL recipe ({type(e).__name__}: "
                             f"{e}); delete it and rerun the workflow (rule augmerl_pca writes "
                             "it)") from e
        self.logs, self.valid_bins, names, _ = open_log_tables(log_tables, log_index)
        if names != self.source_names or (recipe_valid is not None and
                                           not np.array_equal(recipe_valid, self.valid_bins)):
            raise ValueError(f"{recipe_path} was planned on other sources or bins than the cache "
                             f"{log_tables} holds ({len(self.source_names)} vs {len(names)} "
                             "sources); rerun the workflow")
        self._pos = np.full(merl.N_BINS, -1)
        self._pos[self.valid_bins] = np.arange(len(self.valid_bins))

    def values(self, ids, bins=None, chunk: int = 1 << 15) -> np.ndarray:
        """Physical BRDF (n, 3, B) float32 at flat bin indices `bins` (default: shard bins)."""
        bins = self.shard_bins if bins is None else np.asarray(bins)
        cols = self._pos[bins]
        if (cols < 0).any():
            raise ValueError("requested bins outside the common valid region of the sources")
        return mix_values(self.logs, self.row_src, self.row_perm, self.coef[np.asarray(ids)],
                          cols, chunk)

    def values_or_zero(self, ids, bins) -> np.ndarray:
        """As `values`, but 0 at bins outside the common valid region (where a full table is
        negative, i.e. counts as 0 in renders). For renders that need only a view's bins."""
        bins = np.asarray(bins)
        ok = self._pos[bins] >= 0
        out = np.zeros((len(np.atleast_1d(ids)), 3, len(bins)), dtype=np.float32)
        out[:, :, ok] = self.values(ids, bins[ok])
        return out

    def tables_from_coefs(self, coefs: np.ndarray) -> np.ndarray:
        """Full physical MERL tables (n, 3, 90, 90, 180) of row mixtures; invalid bins negative
        as in MERL files."""
        t = np.empty((len(coefs), 3, merl.N_BINS))
        t[:] = -1.0 * merl.SCALE[:, None]
        t[:, :, self.valid_bins] = mix_values(self.logs, self.row_src, self.row_perm, coefs,
                                              np.arange(len(self.valid_bins)))
        return t.reshape(len(coefs), *merl.SHAPE)

    def table(self, i: int) -> np.ndarray:
        """Full physical MERL table (3, 90, 90, 180) of material `i`."""
        return self.tables_from_coefs(self.coef[[i]])[0]


def choose_bins(valid_bins: np.ndarray, bins, seed: int) -> np.ndarray:
    """All valid bins, or a fixed random subset of `bins` of them (sorted)."""
    if bins == "all":
        return valid_bins
    if not isinstance(bins, int) or bins < 1:
        raise ValueError(f"config augmerl.bins must be 'all' or a positive integer, got {bins!r}")
    if bins > len(valid_bins):
        raise ValueError(f"config augmerl.bins = {bins} exceeds the {len(valid_bins)} valid bins")
    rng = np.random.default_rng(seed_for(seed, "augmerl_bins"))
    return np.sort(rng.choice(valid_bins, bins, replace=False))


def save_shard(path: str | Path, ids: np.ndarray, bins: np.ndarray, values: np.ndarray) -> None:
    path = Path(path)
    tmp = path.with_name(path.name + ".part.npz")
    np.savez(tmp, ids=ids.astype(np.int64), bins=bins.astype(np.int64),
             values=values.astype(np.float32))
    tmp.replace(path)


def load_shard(path: str | Path) -> dict[str, np.ndarray]:
    """A shard: ids (n,), bins (B,) flat MERL bin indices, values (n, 3, B) physical BRDF."""
    redo = "delete it and rerun the workflow (rule augmerl_shard writes it)"
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in ("ids", "bins", "values")}
    except NPZ_ERRORS as e:
        raise ValueError(f"{path}: not a readable AugMERL shard ({type(e).__name__}: {e}); "
                         f"{redo}") from e
    if d["values"].shape != (len(d["ids"]), 3, len(d["bins"])):
        raise ValueError(f"{path}: inconsistent shard shapes "
                         f"{d['values'].shape} vs ids {d['ids'].shape}, bins {d['bins'].shape}; "
                         f"{redo}")
    return d
