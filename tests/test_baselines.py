import numpy as np
import pytest
import torch

from neumat import nbrdf
from neumat.baselines import pca, vae
from neumat.io import merl


def _tables(n, bins, seed=0):
    """Plausible positive tables (n, 3, B): diffuse + a Blinn-like lobe, random per material."""
    rng = np.random.default_rng(seed)
    th = merl.grid_angles()[0][bins]
    kd = rng.uniform(0.02, 0.3, (n, 3, 1))
    ks = rng.uniform(0, 2, (n, 1, 1))
    e = rng.uniform(5, 60, (n, 1, 1))
    return kd / np.pi + ks * np.cos(th)[None, None] ** e


BINS = np.sort(np.random.default_rng(0).choice(np.flatnonzero(merl.valid_mask()), 500, replace=False))


def test_nielsen_map_round_trip():
    t = _tables(4, BINS)
    med, cm = np.median(t.reshape(-1, len(BINS)), 0), pca.cos_map(BINS)
    assert ((cm >= 0.01) & (cm <= 1)).all()
    np.testing.assert_allclose(pca.unmap(pca.log_map(t, med, cm), med, cm), t, rtol=1e-9, atol=1e-12)


def test_pca_a_reconstructs_training_tables_and_samples_deterministically():
    t = _tables(12, BINS)
    f = pca.NielsenPCA(3 * 12, BINS).fit(t)  # as many components as observations - 1: exact
    np.testing.assert_allclose(f.tables(f.coefficients(t)), t, rtol=1e-6, atol=1e-9)
    few = pca.NielsenPCA(4, BINS).fit(t)  # 4 components: a close, not exact, reconstruction
    err = np.abs(few.tables(few.coefficients(t)) - t).mean() / t.mean()
    assert 0 < err < 0.2
    s = few.sample(5, seed=3)
    assert s.shape == (5, 3, len(BINS)) and (s >= 0).all() and np.isfinite(s).all()
    np.testing.assert_array_equal(s, few.sample(5, seed=3))
    assert not np.array_equal(s, few.sample(5, seed=4))


def test_pca_a_fits_block_by_block_as_on_the_whole_tables():
    """fit_source reads the tables a block of bins at a time (twice), never whole, and gives
    the fit on the whole tables to float64 rounding: components, coefficients, samples."""
    t = _tables(12, BINS)
    whole = pca.NielsenPCA(8, BINS).fit(t)
    asked = []

    def read(sl):
        asked.append(sl.stop - sl.start)
        return t[:, :, sl]

    blocks = pca.NielsenPCA(8, BINS, block=37).fit_source(read, len(t))
    assert max(asked) == 37 and sum(asked) == 2 * len(BINS)
    np.testing.assert_allclose(np.abs(blocks.pca.components), np.abs(whole.pca.components),
                               atol=1e-9)  # a component's sign is the eigensolver's
    np.testing.assert_allclose(blocks.median, whole.median, rtol=0, atol=0)
    np.testing.assert_allclose(np.abs(blocks.coefficients(t)), np.abs(whole.coefficients(t)),
                               atol=1e-8)
    # the Gaussian is fitted to the rows' own coefficients (U S): their encoding
    np.testing.assert_allclose(blocks.pca.scores.reshape(len(t), -1), blocks.coefficients(t),
                               atol=1e-8)
    a, b = whole.sample(4, 5), blocks.sample(4, 5)
    assert a.dtype == b.dtype == np.float32
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_pca_n_shapes_determinism_and_round_trip():
    w = nbrdf.init_weights(30, torch.Generator().manual_seed(0)).numpy()
    f = pca.WeightPCA(29).fit(w)
    np.testing.assert_allclose(f.pca.decode(f.pca.encode(w)), w, atol=1e-5)
    s = f.sample(7, seed=1)
    assert s.shape == (7, nbrdf.N_PARAMS) and s.dtype == np.float32
    np.testing.assert_array_equal(s, f.sample(7, seed=1))
    # the Gaussian matches the training moments: the mean, and the spread along each component
    f8 = pca.WeightPCA(8).fit(w)
    big = f8.sample(4000, seed=2)
    assert np.abs(big.mean(0) - w.mean(0)).max() < 0.05
    np.testing.assert_allclose(f8.pca.encode(big).std(0), f8.pca.encode(w).std(0, ddof=1), rtol=0.1)


def test_pca_keeps_to_the_rank_of_its_data():
    """Components beyond the data's rank are dropped: rank-2 rows (30 x 300) asked for 29
    components give 2, and samples within the data's range (a round-off eigenvalue had divided
    a component by ~1e-150: samples near 1e273)."""
    rng = np.random.default_rng(0)
    X = rng.normal(size=(30, 2)) @ rng.normal(size=(2, 300))
    g = pca.GaussianPCA(29).fit(X)
    assert g.components.shape == (2, 300)
    np.testing.assert_allclose(g.decode(g.encode(X)), X, atol=1e-9)
    s = g.decode(pca.CoefficientGaussian(g.encode(X)).sample(50, 0))
    assert np.isfinite(s).all() and np.abs(s).max() < 10 * np.abs(X).max()


def test_vae_n_trains_and_samples_deterministically(tmp_path):
    w = nbrdf.init_weights(40, torch.Generator().manual_seed(0)).numpy()
    kw = dict(latent=4, hidden=16, steps=30, batch_size=16, lr=1e-3, beta=1.0)
    net, hist = vae.train_weight_vae(w, **kw, seed=0)
    net2, _ = vae.train_weight_vae(w, **kw, seed=0)
    assert len(hist) == 1 and hist[0]["step"] == 30
    vae.save(tmp_path / "m.pt", net, "vae_n", {"latent": 4, "hidden": 16})
    back = vae.load(tmp_path / "m.pt")
    s = vae.prior_samples(back, 6, seed=5)
    assert s.shape == (6, nbrdf.N_PARAMS) and np.isfinite(s).all()
    np.testing.assert_array_equal(s, vae.prior_samples(net2, 6, seed=5))
    assert not np.array_equal(s, vae.prior_samples(back, 6, seed=6))


@pytest.mark.parametrize("kind", ["vae_n", "vae_a"])
def test_vae_training_resumes_bit_for_bit_after_a_kill(tmp_path, monkeypatch, kind):
    """A VAE training killed after step 7 of 12 resumes from its checkpoint (model, Adam, the
    draws' generator, step, history) and ends where an unkilled training ends, to the bit."""
    monkeypatch.setattr(vae, "CHECKPOINT_SECONDS", -1.0)  # a checkpoint at every step
    if kind == "vae_n":
        data = nbrdf.init_weights(20, torch.Generator().manual_seed(0)).numpy()
        train = lambda **k: vae.train_weight_vae(data, latent=4, hidden=16, steps=12,  # noqa: E731
                                                 batch_size=8, lr=1e-3, beta=1.0, seed=2, **k)
    else:
        t, x6, cos = _set_data(4)
        train = lambda **k: vae.train_set_vae(t, x6, cos, latent=4, hidden=16, steps=12,  # noqa: E731
                                              batch_size=2, context=32, queries=32, lr=3e-3,
                                              beta=0.1, seed=2, **k)
    ref, ref_hist = train()
    real, calls = torch.nn.utils.clip_grad_norm_, []

    def killed(*a, **k):  # the 8th step dies after the 7th was checkpointed
        calls.append(1)
        if len(calls) == 8:
            raise KeyboardInterrupt
        return real(*a, **k)

    ck = tmp_path / "checkpoint.pt"
    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_", killed)
    with pytest.raises(KeyboardInterrupt):
        train(checkpoint=ck)
    assert torch.load(ck, weights_only=True)["step"] == 7
    counted = []  # the resumed run takes steps 8-12 only

    def count(*a, **k):
        counted.append(1)
        return real(*a, **k)

    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_", count)
    got, hist = train(checkpoint=ck)
    assert len(counted) == 5
    for p, q in zip(ref.state_dict().values(), got.state_dict().values()):
        assert torch.equal(p, q)
    assert hist == ref_hist


def _set_data(n):
    """n tables at BINS, with the bins' NBRDF inputs and cos(theta_i), for VAE-A."""
    th, td, pd_ = (a[BINS] for a in merl.grid_angles())
    return (_tables(n, BINS).astype(np.float32), merl.half_diff_cartesian(th, td, pd_),
            merl.cos_theta_i(th, td, pd_))


def test_vae_a_is_deterministic_and_refuses_overlapping_bins():
    """Two trainings with one seed give the same model; context + queries more than the stored
    bins (the queries are meant to be other bins) is refused, naming the keys."""
    t, x6, cos = _set_data(4)
    kw = dict(latent=4, hidden=16, batch_size=2, context=32, queries=32, lr=3e-3, beta=0.1)
    a, _ = vae.train_set_vae(t, x6, cos, steps=5, **kw, seed=3)
    b, _ = vae.train_set_vae(t, x6, cos, steps=5, **kw, seed=3)
    for p, q in zip(a.state_dict().values(), b.state_dict().values()):
        assert torch.equal(p, q)
    with pytest.raises(ValueError, match="baselines.vae_a.context"):
        vae.train_set_vae(t, x6, cos, steps=1, **dict(kw, context=len(BINS), queries=1), seed=0)


def test_vae_a_outputs_nbrdf_fields_and_learns(tmp_path):
    t, x6, cos = _set_data(6)
    kw = dict(latent=8, hidden=32, batch_size=4, context=64, queries=128, lr=3e-3, beta=0.1)
    _, short = vae.train_set_vae(t, x6, cos, steps=1, **kw, seed=0)
    net, hist = vae.train_set_vae(t, x6, cos, steps=150, **kw, seed=0)
    assert hist[-1]["rec"] < short[-1]["rec"]
    vae.save(tmp_path / "a.pt", net, "vae_a", {"latent": 8, "hidden": 32})
    s = vae.prior_samples(vae.load(tmp_path / "a.pt"), 5, seed=1)
    assert s.shape == (5, nbrdf.N_PARAMS)
    np.testing.assert_array_equal(s, vae.prior_samples(net, 5, seed=1))
    f = nbrdf.forward(torch.as_tensor(s), torch.as_tensor(x6, dtype=torch.float32))
    assert f.shape == (5, len(BINS), 3) and torch.isfinite(f).all()
    with pytest.raises(ValueError, match="not a VAE"):
        torch.save({"kind": "x"}, tmp_path / "b.pt")
        vae.load(tmp_path / "b.pt")


def test_a_file_that_is_not_a_vae_baseline_names_the_file(tmp_path):
    torch.save(torch.zeros(3), tmp_path / "bare.pt")
    with pytest.raises(ValueError, match=r"bare\.pt: not a VAE baseline \(rule train_vae\): it lacks kind"):
        vae.load(tmp_path / "bare.pt")
    w = nbrdf.init_weights(8, torch.Generator().manual_seed(0)).numpy()
    net, _ = vae.train_weight_vae(w, latent=4, hidden=16, steps=1, batch_size=8, lr=1e-3,
                                  beta=1.0, seed=0)
    vae.save(tmp_path / "m.pt", net, "vae_n", {"latent": 8, "hidden": 16})  # config != weights
    with pytest.raises(ValueError, match=r"m\.pt: its state does not fit its config"):
        vae.load(tmp_path / "m.pt")


RUN_SCRIPT = """
import runpy, sys, json
from types import SimpleNamespace as NS
a = json.loads(sys.argv[1])
smk = NS(params=NS(**a["params"]), wildcards=NS(model=a["model"]), input=NS(**a["input"]),
         output=NS(**a["output"]), log=[a["log"]], threads=1, rule=a["rule"])
runpy.run_path(a["script"], init_globals={"snakemake": smk}, run_name="__main__")
"""


@pytest.mark.parametrize("rule, model", [("baseline_pca", "pca_n"), ("train_vae", "vae_n")])
def test_weight_baselines_check_the_weights_against_the_manifest(tmp_path, rule, model):
    """PCA-N and VAE-N, as their rules run them: weights of as many rows as the manifest train
    and sample; one row short is refused, naming the manifest and both counts (before, PCA-N
    indexed past the end or took other materials' rows)."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    import pandas as pd
    root = Path(__file__).resolve().parents[1]
    w = nbrdf.init_weights(8, torch.Generator().manual_seed(0)).numpy()
    pd.DataFrame({"id": range(8), "name": [f"m{i}" for i in range(8)], "operation": "original",
                  "type": "", "split": ["train"] * 6 + ["test"] * 2}).to_csv(
        tmp_path / "manifest.tsv", sep="\t", index=False)
    if model == "pca_n":
        params, output = dict(components=3, seeds=[1, 2]), dict(
            samples=str(tmp_path / "weights_out.npy"), info=str(tmp_path / "info.tsv"))
    else:
        params = dict(cfg=dict(latent=4, hidden=16, steps=3, batch_size=4, lr=1e-3, beta=1e-3), seed=3,
                      checkpoint=str(tmp_path / "checkpoint.pt"))
        output = dict(model=str(tmp_path / "vae.pt"), history=str(tmp_path / "history.tsv"))

    def run(weights):
        np.save(tmp_path / "weights.npy", weights)
        args = dict(params=params, model=model, rule=rule, log=str(tmp_path / "job.log"),
                    script=str(root / f"workflow/scripts/{rule}.py"), output=output,
                    input=dict(manifest=str(tmp_path / "manifest.tsv"),
                               weights=str(tmp_path / "weights.npy")))
        return subprocess.run([sys.executable, "-c", RUN_SCRIPT, json.dumps(args)],
                              capture_output=True, text=True,
                              env={**os.environ, "OMP_NUM_THREADS": "1"})

    ok = run(w)
    assert ok.returncode == 0, ok.stderr[-3000:]
    if model == "pca_n":
        assert np.load(tmp_path / "weights_out.npy").shape == (2 * 2, nbrdf.N_PARAMS)
    else:  # trained: the checkpoint is gone, the model file holds the result
        assert (tmp_path / "vae.pt").is_file() and not (tmp_path / "checkpoint.pt").exists()
    bad = run(w[:7])
    assert bad.returncode != 0
    assert "manifest.tsv: 8 rows but the NeuMERL weights have 7" in bad.stderr
