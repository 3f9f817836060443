import numpy as np
import torch
import pandas as pd
import pytest

from neumat import augment
from neumat.io import merl


def _catalog(names, types=None):
    types = types or [n.split("-")[-1] for n in names]
    return pd.DataFrame({
        "name": names, "sha256": "", "type": types,
        "description": [n.replace("-", " ") for n in names],
        "colours": [" ".join(w for w in n.split("-") if w in {"red", "blue", "green"})
                    for n in names],
    })


def _plan(names, size, test_fraction=0.25, seed=0, shard_size=8):
    cat = _catalog(names)
    split = augment.split_sources(names, test_fraction, seed)
    rows = augment.plan_rows(cat, True, split)
    pairs = augment.plan_pairs(rows, size - len(rows), seed)
    return rows, pairs, augment.build_manifest(rows, pairs, shard_size)


def test_permute_channels():
    t = np.arange(3)[:, None] * np.ones((3, 4))
    assert augment.permute(t, "gbr")[:, 0].tolist() == [1, 2, 0]
    assert augment.PERMS[0] == "rgb" and len(set(augment.PERMS)) == 6


def test_manifest_counts_descriptions_and_splits():
    names = ["red-plastic", "blue-acrylic", "green-fabric", "nickel"]
    rows, pairs, man = _plan(names, size=40)
    assert len(man) == 40 and man["id"].tolist() == list(range(40))
    assert (man["operation"] == "original").sum() == 4
    assert (man["operation"] == "permutation").sum() == 20
    assert (man["operation"] == "interpolation").sum() == 16
    perm = man[man["name"] == "red-plastic@gbr"].iloc[0]
    assert perm["description"] == "plastic" and perm["type"] == "plastic"
    mix = man[man["operation"] == "interpolation"].iloc[0]
    assert mix["description"].startswith("a mixture of ") and " and " in mix["description"]
    assert mix["type"] == ""
    # everything derived from one source stays in that source's split
    split_of = dict(zip(man.loc[man["operation"] == "original", "name"],
                        man.loc[man["operation"] == "original", "split"]))
    for r in man.itertuples():
        for s in r.sources.split("|"):
            assert split_of[s.split("@")[0]] == r.split
    assert set(man["split"]) == {"train", "test"}
    assert man["shard"].iloc[0] == "000" and man["shard"].iloc[-1] == "004"


def test_pairs_never_cross_splits_and_use_distinct_sources():
    names = [f"m{i}-plastic" for i in range(10)]
    rows, pairs, _ = _plan(names, size=200, test_fraction=0.3)
    src = rows["sources"].to_numpy()
    sp = rows["split"].to_numpy()
    for a, b, w in pairs:
        assert sp[a] == sp[b] and src[a] != src[b] and 0.2 <= w <= 0.8


def test_row_gram_matches_explicit_rows():
    rng = np.random.default_rng(1)
    logs = rng.random((3, 3, 50)).astype(np.float32)
    row_src = np.repeat(np.arange(3), 6)
    row_perm = np.tile(np.arange(6), 3)
    X = np.stack([augment.permute(logs[m], augment.PERMS[p]).ravel()
                  for m, p in zip(row_src, row_perm)]).astype(np.float64)
    G = augment.row_gram(logs, row_src, row_perm, chunk=16)
    np.testing.assert_allclose(G, X @ X.T, rtol=1e-6)


def _explicit_pca_interp(X, a, b, w, k):
    mean = X.mean(0)
    Xc = X - mean
    _, _, Vt = np.linalg.svd(Xc, full_matrices=False)
    z = Vt[:k] @ (w * Xc[a] + (1 - w) * Xc[b])
    return mean + Vt[:k].T @ z


@pytest.mark.parametrize("k", [2, 5])
def test_mixing_weights_equal_pca_interpolation(k):
    rng = np.random.default_rng(2)
    X = rng.random((8, 30))
    coefs, stats = augment.mixing_weights(X @ X.T, k, [(0, 3, 0.3), (5, 6, 0.7)])
    for c, (a, b, w) in zip(coefs, [(0, 3, 0.3), (5, 6, 0.7)]):
        np.testing.assert_allclose(c @ X, _explicit_pca_interp(X, a, b, w, k), atol=1e-10)
    assert stats[0] == k and 0 < stats[1] <= 1


def test_full_rank_pca_interpolation_is_linear():
    rng = np.random.default_rng(3)
    X = rng.random((6, 40))
    (c,), _ = augment.mixing_weights(X @ X.T, 10, [(1, 4, 0.25)])  # k capped at P - 1
    np.testing.assert_allclose(c @ X, 0.25 * X[1] + 0.75 * X[4], atol=1e-10)


def _lambert_table(rgb):
    wi, wo = merl.half_diff_to_dirs(*merl.grid_angles())
    t = np.repeat(np.asarray(rgb, float)[:, None] / np.pi, merl.N_BINS, 1)
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
    t[:, below] = -merl.SCALE[:, None]
    return t.reshape(merl.SHAPE)


def test_augmerl_materialises_rows_and_interpolations(tmp_path):
    names = ["red-plastic", "blue-acrylic", "green-fabric"]
    albedo = {"red-plastic": [0.8, 0.1, 0.1], "blue-acrylic": [0.1, 0.2, 0.9],
              "green-fabric": [0.2, 0.6, 0.3]}
    paths = {}
    for n in names:
        paths[n] = tmp_path / f"{n}.binary"
        merl.write_merl(paths[n], _lambert_table(albedo[n]))
    rows, pairs, man = _plan(names, size=24, test_fraction=0.0)
    logs, valid = augment.load_log_tables([paths[n] for n in names])
    recipe = augment.build_recipe(man, rows, pairs, logs, names, pca_dims=17)
    bins = augment.choose_bins(valid, 100, seed=0)
    np.savez(tmp_path / "recipe.npz", bins=bins, valid_bins=valid,
             **{k: v for k, v in recipe.items() if k != "pca_stats"})
    cache = tmp_path / "logs.npy", tmp_path / "logs_index.npz"
    augment.write_log_tables([paths[n] for n in names], names, *cache)
    aug = augment.AugMERL(tmp_path / "recipe.npz", *cache)
    assert isinstance(aug.logs, np.memmap)

    vals = aug.values(man["id"].to_numpy())
    assert vals.shape == (24, 3, 100) and (vals >= 0).all()
    r = man.set_index("name")
    gbr = vals[r.at["blue-acrylic@gbr", "id"]]
    np.testing.assert_allclose(gbr[0], albedo["blue-acrylic"][1] / np.pi, rtol=1e-5)
    np.testing.assert_allclose(gbr[2], albedo["blue-acrylic"][0] / np.pi, rtol=1e-5)
    # 18 rows span at most 17 dims: full-rank PCA -> interpolation is linear in log space
    for rec in man[man["operation"] == "interpolation"].itertuples():
        a, b = (r.at[s, "id"] for s in rec.sources.split("|"))
        expect = np.expm1(rec.weight * np.log1p(vals[a]) + (1 - rec.weight) * np.log1p(vals[b]))
        np.testing.assert_allclose(vals[rec.id], expect, rtol=1e-4)
    full = aug.table(int(r.at["red-plastic", "id"]))
    np.testing.assert_allclose(full.reshape(3, -1)[:, valid],
                               _lambert_table(albedo["red-plastic"]).reshape(3, -1)[:, valid],
                               rtol=1e-5)
    assert (full.reshape(3, -1)[:, ~merl.valid_mask()] < 0).all()
    # fit_eval's cheap path: view-bin values render exactly like the full tables
    from neumat.render import sphere
    ids = man["id"].to_numpy()[:5]
    view_bins = sphere.sphere_view(32).bins.numpy()
    torch.testing.assert_close(
        sphere.render_view_values(aug.values_or_zero(ids, view_bins), 32),
        sphere.render_tables(aug.tables_from_coefs(aug.coef[ids]), 32), rtol=1e-5, atol=1e-7)


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    """4 random tables (log1p far from linear) with 7 negative bins each, written once."""
    tmp_path = tmp_path_factory.mktemp("sources")
    rng = np.random.default_rng(5)
    valid = merl.valid_mask()
    paths = []
    for i in range(4):
        t = np.where(valid, rng.gamma(0.5, 2.0, (3, merl.N_BINS)), -merl.SCALE[:, None])
        t[:, rng.choice(np.flatnonzero(valid), 7, replace=False)] = -0.5
        paths.append(tmp_path / f"m{i}.binary")
        merl.write_merl(paths[-1], t.reshape(merl.SHAPE))
    return paths


def test_log_table_cache_round_trips_the_converted_sources(tmp_path, sources):
    paths = sources[:3]
    names = [p.stem for p in paths]
    cache = tmp_path / "logs.npy", tmp_path / "idx.npz"
    assert augment.write_log_tables(paths, names, *cache)[0] == 3
    logs, valid, got_names, negative = augment.open_log_tables(*cache)
    assert isinstance(logs, np.memmap) and not logs.flags.writeable
    ref_negative = {}
    ref, ref_valid = augment.load_log_tables(paths, ref_negative)
    np.testing.assert_array_equal(logs, ref)  # bit for bit
    np.testing.assert_array_equal(valid, ref_valid)
    assert got_names == names and negative.tolist() == [ref_negative[str(p)] for p in paths]
    assert negative.tolist() == [7, 7, 7] and len(valid) < merl.valid_mask().sum() - 7
    # the values are float64 log1p of the physical tables, rounded once to float32
    t = merl.read_merl(paths[1]).reshape(3, -1)[:, valid]
    np.testing.assert_array_equal(logs[1], np.log1p(t).astype(np.float32))


def test_cached_augmerl_equals_the_in_memory_path(tmp_path, sources):
    """Consumers (AugMERL.values, tables, the figures' Gram matrix) give the same numbers from
    the memory map as from the tables read and converted in the job (the old path)."""
    paths = sources
    names = [p.stem for p in paths]
    rows, pairs, man = _plan(names, size=40, test_fraction=0.25)
    logs, valid = augment.load_log_tables(paths)
    recipe = augment.build_recipe(man, rows, pairs, logs, names, pca_dims=5)
    bins = augment.choose_bins(valid, 5000, seed=0)
    recipe.pop("pca_stats")
    np.savez(tmp_path / "recipe.npz", bins=bins, valid_bins=valid, **recipe)
    cache = tmp_path / "logs.npy", tmp_path / "idx.npz"
    augment.write_log_tables(paths, names, *cache)
    aug = augment.AugMERL(tmp_path / "recipe.npz", *cache)
    ids = man["id"].to_numpy()
    pos = np.searchsorted(valid, bins)
    old = augment.mix_values(logs, recipe["row_src"], recipe["row_perm"], recipe["coef"][ids], pos)
    np.testing.assert_array_equal(aug.values(ids), old)
    # the pre-cache indexing (all sources at the columns, then the used rows): same values
    coef = recipe["coef"][ids][:, np.abs(recipe["coef"]).sum(0) > 0].astype(np.float32)
    used = np.flatnonzero(np.abs(recipe["coef"]).sum(0) > 0)
    ch = np.array(["rgb".index(augment.PERMS[p][1]) for p in recipe["row_perm"][used]])
    rows_g = logs[:, :, pos][recipe["row_src"][used], ch]
    np.testing.assert_array_equal(old[:, 1], np.maximum(np.expm1(coef @ rows_g), 0))
    np.testing.assert_array_equal(
        augment.row_gram(aug.logs, aug.row_src, aug.row_perm),
        augment.row_gram(logs, recipe["row_src"], recipe["row_perm"]))
    # the recipe's interpolations rebuild from the cache as from the in-memory logs
    mix = ids[man["operation"] == "interpolation"][:3]
    np.testing.assert_array_equal(
        aug.tables_from_coefs(aug.coef[mix]).reshape(3, 3, -1)[:, :, valid],
        augment.mix_values(logs, recipe["row_src"], recipe["row_perm"], recipe["coef"][mix],
                           np.arange(len(valid))))


def test_corrupt_or_mismatched_cache_errors_naming_the_file(tmp_path, sources):
    paths = sources[:2]
    names = [p.stem for p in paths]
    npy, idx = tmp_path / "logs.npy", tmp_path / "idx.npz"
    augment.write_log_tables(paths, names, npy, idx)
    data = npy.read_bytes()
    npy.write_bytes(data[: len(data) // 2])  # truncated
    with pytest.raises(ValueError, match=r"logs\.npy: not a readable AugMERL log-table cache"):
        augment.open_log_tables(npy, idx)
    npy.write_bytes(b"garbage" * 100)
    with pytest.raises(ValueError, match=r"logs\.npy.*augmerl_log_tables rebuilds it"):
        augment.open_log_tables(npy, idx)
    np.save(npy, np.zeros((2, 3, 10), np.float32))  # a valid .npy of the wrong shape
    with pytest.raises(ValueError, match=r"logs\.npy: float32 array of shape \(2, 3, 10\)"):
        augment.open_log_tables(npy, idx)
    idx.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"idx\.npz: not a readable AugMERL log-table index"):
        augment.open_log_tables(npy, idx)
    # a recipe planned on other sources than the cache holds
    augment.write_log_tables(paths, names, npy, idx)
    np.savez(tmp_path / "recipe.npz", coef=np.eye(1), row_src=[0], row_perm=[0], bins=[0],
             source_names=np.array(names[::-1]))
    with pytest.raises(ValueError, match="recipe.npz was planned on other sources"):
        augment.AugMERL(tmp_path / "recipe.npz", npy, idx)


def test_cache_refuses_a_table_with_nan_naming_it(tmp_path, sources):
    raw = bytearray(sources[1].read_bytes())
    raw[12 + 8 * 1000: 12 + 8 * 1001] = np.array([np.nan]).tobytes()
    paths = [sources[0], tmp_path / "m1.binary"]
    paths[1].write_bytes(bytes(raw))
    with pytest.raises(merl.MerlFormatError, match=r"m1\.binary: contains NaN"):
        augment.write_log_tables(paths, ["m0", "m1"], tmp_path / "l.npy", tmp_path / "i.npz")
    assert not (tmp_path / "l.npy").exists()


def test_choose_bins_errors():
    valid = np.arange(10)
    assert augment.choose_bins(valid, "all", 0) is valid
    with pytest.raises(ValueError, match="augmerl.bins"):
        augment.choose_bins(valid, 11, 0)
    with pytest.raises(ValueError, match="augmerl.bins"):
        augment.choose_bins(valid, "some", 0)


def test_shard_roundtrip_and_shape_check(tmp_path):
    ids, bins = np.array([7, 2, 11]), np.array([5, 9])
    vals = np.arange(18, dtype=np.float32).reshape(3, 3, 2) / 7  # every value its own
    augment.save_shard(tmp_path / "000.npz", ids, bins, vals)
    d = augment.load_shard(tmp_path / "000.npz")
    assert d["values"].dtype == np.float32
    np.testing.assert_array_equal(d["ids"], ids)
    np.testing.assert_array_equal(d["bins"], bins)
    np.testing.assert_array_equal(d["values"], vals)
    np.savez(tmp_path / "bad.npz", ids=ids, bins=bins, values=vals[:2])
    with pytest.raises(ValueError, match="bad.npz"):
        augment.load_shard(tmp_path / "bad.npz")


def test_damaged_shard_recipe_or_index_errors_name_the_file_and_its_rule(tmp_path):
    """A shard or recipe missing an array, empty or not a zip: a ValueError naming the file and
    the rule that writes it, not a KeyError / EOFError / BadZipFile from inside numpy."""
    np.savez(tmp_path / "001.npz", ids=np.arange(2), bins=np.arange(3))  # no values
    with pytest.raises(ValueError, match=r"001\.npz: not a readable AugMERL shard \(KeyError: "
                                         r"'values.*rule augmerl_shard writes it"):
        augment.load_shard(tmp_path / "001.npz")
    for content, error in ((b"", "EOFError"), (b"PK\x03\x04junk", "BadZipFile")):
        (tmp_path / "002.npz").write_bytes(content)
        with pytest.raises(ValueError, match=rf"002\.npz: not a readable AugMERL shard "
                                             rf"\({error}.*rule augmerl_shard writes it"):
            augment.load_shard(tmp_path / "002.npz")
    recipe = tmp_path / "recipe.npz"
    np.savez(recipe, coef=np.eye(2), row_src=np.arange(2), row_perm=np.zeros(2, int),
             source_names=np.array(["a", "b"]))  # no bins
    with pytest.raises(ValueError, match=r"recipe\.npz: not a readable AugMERL recipe "
                                         r"\(KeyError: 'bins.*rule augmerl_pca writes it"):
        augment.AugMERL(recipe, tmp_path / "logs.npy", tmp_path / "idx.npz")
    recipe.write_bytes(b"PK\x03\x04junk")
    with pytest.raises(ValueError, match=r"recipe\.npz: not a readable AugMERL recipe "
                                         r"\(BadZipFile.*rule augmerl_pca writes it"):
        augment.AugMERL(recipe, tmp_path / "logs.npy", tmp_path / "idx.npz")
    (tmp_path / "idx.npz").write_bytes(b"PK\x03\x04junk")  # the cache's index: a damaged zip
    with pytest.raises(ValueError, match=r"idx\.npz: not a readable AugMERL log-table index"):
        augment.open_log_tables(tmp_path / "logs.npy", tmp_path / "idx.npz")


def test_pca_gram_is_the_same_on_any_core_count():
    """OpenBLAS split this product (300 rows over 7e4 bins) differently with 2 threads than with
    1, so AugMERL's PCA, and every fit after it, depended on `snakemake --cores`."""
    from threadpoolctl import threadpool_limits

    rng = np.random.default_rng(0)
    logs = rng.normal(size=(100, 3, 70000)).astype(np.float32)
    src, perm = np.arange(100), np.zeros(100, dtype=int)
    grams = []
    for n in (1, 2):
        with threadpool_limits(n):
            grams.append(augment.row_gram(logs, src, perm))
    assert np.array_equal(grams[0], grams[1])


def test_template_is_the_first_train_split_original():
    """The template's fit starts every other: never a held-out source's (id 0 when its source
    trains), and its manifest id is its row (the manifest's ids)."""
    names = [f"m{i}-plastic" for i in range(6)]
    seen = set()
    for seed in range(8):
        rows, pairs, man = _plan(names, size=60, seed=seed)
        t = augment.template_id(rows)
        r = man.loc[man["id"] == t].iloc[0]
        assert r["split"] == "train" and r["operation"] == "original"
        first = man[(man["split"] == "train") & (man["operation"] == "original")]["id"].min()
        assert t == first
        seen.add(t == 0)
    assert seen == {True, False}  # some seeds hold out the first source
    rows = augment.plan_rows(_catalog(names[:2]), True, {names[0]: "test", names[1]: "test"})
    with pytest.raises(ValueError, match="no source material in the train split"):
        augment.template_id(rows)


def test_pca_cut_keeps_pca_dims_where_the_small_eigenvalues_are_distinct():
    """Distinct small eigenvalues are no tie: k stays as asked (a tie test against the largest
    eigenvalue alone had kept every component above 1e-9 of it: 24 for 8 here)."""
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.standard_normal((40, 40)))
    J = np.eye(40) - 1 / 40
    Q = J @ Q  # centred directions, so the double centring keeps the spectrum
    ev = np.r_[1.0, 0.5, 0.25, 0.12, 0.06, np.linspace(8e-9, 2e-9, 20), np.zeros(15)]
    G = (Q * ev) @ Q.T
    _, stats = augment.mixing_weights(G, 5, [(0, 1, 0.5)])
    assert stats[0] == 5
    _, stats = augment.mixing_weights(G, 8, [(0, 1, 0.5)])
    assert stats[0] == 8


def test_pca_cut_keeps_a_tied_pair_of_components_whole():
    """Rows and their channel permutations make the Gram's eigenvalues come in equal pairs; a
    cut inside a pair would keep whichever half LAPACK returned. k grows to the pair's end, and
    the result is the interpolation in the (unique) subspace of both."""
    rng = np.random.default_rng(4)
    base = rng.random((2, 3, 20))
    X = np.stack([augment.permute(b, p) for b in base for p in augment.PERMS]).reshape(12, -1)
    G = X @ X.T
    Xc = X - X.mean(0)
    ev = np.sort(np.linalg.eigvalsh(Xc @ Xc.T))[::-1]
    tied = [k for k in range(1, 10) if ev[k - 1] - ev[k] <= 1e-9 * ev[0] and ev[k] > 1e-9 * ev[0]]
    assert tied, ev  # the symmetry does make pairs
    k = tied[0]
    coefs, stats = augment.mixing_weights(G, k, [(0, 7, 0.4)])
    assert stats[0] == k + 1
    np.testing.assert_allclose(coefs[0] @ X, _explicit_pca_interp(X, 0, 7, 0.4, k + 1), atol=1e-9)


def test_interpolation_coefs_report_the_components_kept():
    """RGB permutations pair the Gram's eigenvalues: a cut inside a pair keeps it whole, so the
    interpolation figure's k (the components used) can exceed the k asked for."""
    rng = np.random.default_rng(4)
    logs = rng.random((3, 3, 50))
    row_src = np.repeat(np.arange(3), 6)
    row_perm = np.tile(np.arange(6), 3)
    G = augment.row_gram(logs, row_src, row_perm)
    widened = 0
    for k in range(1, 17):
        coefs, kept = augment.interpolation_coefs(logs, row_src, row_perm, 0, 7, [0.3, 0.6], k,
                                                  return_k=True)
        assert kept == augment.mixing_weights(G, k, [(0, 7, 0.3)])[1][0] >= k
        np.testing.assert_array_equal(
            coefs, augment.interpolation_coefs(logs, row_src, row_perm, 0, 7, [0.3, 0.6], k))
        widened += kept > k
    assert widened
