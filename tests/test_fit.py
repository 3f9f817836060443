"""Batched NBRDF fitting: gradients, batch == single fits, splits, checkpoints, export, merge."""

import dataclasses
import warnings

import numpy as np
import pandas as pd
import pytest
import torch

from neumat import fit, fit_kernel, nbrdf
from neumat.io import merl

# both step implementations: the C kernel (where a compiler is) and torch's batched matmuls
KERNELS = [pytest.param("c", marks=pytest.mark.skipif(not fit_kernel.available(),
                                                      reason="the C kernel cannot be built")),
           "torch"]

SMALL = fit.FitSettings(steps=40, lr=5e-3, lr_final=5e-4, batch=64, materials_per_batch=2,
                        eval_every=20, eval_bins=256, checkpoint_every=10)


@pytest.fixture(scope="module")
def data():
    """Three 'materials' that are random NBRDF fields (teachers), at 2000 valid MERL bins."""
    rng = np.random.default_rng(0)
    bins = np.sort(rng.choice(np.flatnonzero(merl.valid_mask()), 2000, replace=False))
    teach = nbrdf.init_weights(3, torch.Generator().manual_seed(7)) * 2
    x, _ = fit.bin_inputs(bins)
    values = nbrdf.forward(teach, x).transpose(1, 2).numpy()  # (3, 3, B)
    init = nbrdf.init_weights(1, torch.Generator().manual_seed(1))[0].numpy()
    return bins, values, init, teach


@pytest.mark.parametrize("activation", nbrdf.ACTIVATIONS)
def test_hand_written_gradient_matches_autograd(activation):
    g = torch.Generator().manual_seed(0)
    w = nbrdf.init_weights(3, g).double() * 3
    x = torch.randn(200, 6, generator=g, dtype=torch.float64)  # inputs shared by the materials
    cos = torch.rand(200, 1, generator=g, dtype=torch.float64)
    target = torch.rand(3, 200, 3, generator=g, dtype=torch.float64)
    loss, grad = fit.loss_and_grad(w, x.T, target.transpose(1, 2), cos.T, activation)  # feature-major
    wr = w.clone().requires_grad_(True)
    raw = nbrdf.forward_raw(wr, x, activation)  # training uses exp(y) - 1 without the clamp
    ref = (torch.log1p(torch.expm1(raw) * cos) - target).abs().mean((1, 2))
    (ref_grad,) = torch.autograd.grad(ref.sum(), wr)
    torch.testing.assert_close(loss, ref)
    torch.testing.assert_close(grad, ref_grad)
    assert grad.abs().max() > 1e-3
    # float32 through a reused workspace: the second call must not see the first one's buffers
    ws = fit.Workspace(3, 200)
    fit.loss_and_grad(w.float() * 0.5, x.T.float(), target.transpose(1, 2).float(), cos.T.float(),
                      activation, ws)
    loss32, grad32 = fit.loss_and_grad(w.float(), x.T.float(), target.transpose(1, 2).float(),
                                       cos.T.float(), activation, ws)
    torch.testing.assert_close(loss32, ref.float(), rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(grad32, ref_grad.float(), rtol=1e-3, atol=1e-6)


def test_bin_inputs_match_merl_geometry():
    bins = np.array([0, 12345, merl.N_BINS - 1])
    x, cos = fit.bin_inputs(bins)
    th, td, pd_ = (a[bins] for a in merl.grid_angles())
    np.testing.assert_allclose(x.numpy(), merl.half_diff_cartesian(th, td, pd_), atol=1e-6)
    np.testing.assert_allclose(cos.numpy(), np.clip(merl.cos_theta_i(th, td, pd_), 0, None),
                               atol=1e-6)
    with pytest.raises(ValueError, match="indices"):
        fit.bin_inputs(np.array([merl.N_BINS]))


def test_split_and_order_are_80_20_disjoint_and_seeded():
    tr, va = fit.split_bins(1000, 0, 0.2)
    assert len(va) == 200 and len(tr) == 800
    assert set(tr.tolist()) | set(va.tolist()) == set(range(1000))
    assert torch.equal(va, fit.split_bins(1000, 0, 0.2)[1])  # deterministic
    assert not torch.equal(va, fit.split_bins(1000, 1, 0.2)[1])  # another seed
    order, mirror = fit.epoch_order(800, 0, 3)
    assert sorted(order.tolist()) == list(range(800)) and 300 < int(mirror.sum()) < 500
    assert torch.equal(order, fit.epoch_order(800, 0, 3)[0])
    assert not torch.equal(order, fit.epoch_order(800, 0, 4)[0])  # a fresh order every epoch


@pytest.mark.parametrize("kernel", KERNELS)
def test_batch_of_three_equals_three_single_fits(data, kernel):
    bins, values, init, _ = data
    s = dataclasses.replace(SMALL, materials_per_batch=3, kernel=kernel)
    batched = fit.fit_many(values, bins, [10, 11, 12], init, s, seed=3)
    for k, i in enumerate([10, 11, 12]):
        single = fit.fit_many(values[k:k + 1], bins, [i], init, s, seed=3)
        np.testing.assert_allclose(batched["weights"][k], single["weights"][0], atol=2e-5)
        np.testing.assert_allclose(batched["val_loss"][k], single["val_loss"][0], rtol=1e-4)
    # materials really differ, and got fitted
    assert np.abs(batched["weights"][0] - batched["weights"][1]).max() > 1e-3
    assert not np.allclose(batched["weights"][0], init)


def test_fitting_recovers_a_known_field(data):
    bins, values, init, teach = data
    s = dataclasses.replace(SMALL, steps=600, lr=1e-2, lr_final=1e-4, eval_every=600)
    x, cos = fit.bin_inputs(bins)
    start = fit.field_loss(torch.as_tensor(init)[None], x, fit.log_target(values[:1], cos),
                           cos[:, None]).item()
    res = fit.fit_many(values[:1], bins, [0], init, s, seed=0)
    assert res["val_loss"][0] < 0.2 * start
    assert res["train_loss"][0] < 0.2 * start
    assert res["val_history"].shape == (1, 1) and res["history_steps"].tolist() == [600]


@pytest.mark.parametrize("kernel", KERNELS)
def test_killed_run_resumes_to_the_same_result(data, tmp_path, monkeypatch, kernel):
    bins, values, init, _ = data
    ids = [0, 1, 2]  # groups of 2: a finished group and a running one get checkpointed
    s = dataclasses.replace(SMALL, kernel=kernel)
    ref = fit.fit_many(values, bins, ids, init, s, seed=0)
    ck = tmp_path / "ck.npz"
    real_save, calls = fit._save_npz, []

    def crash_after_fifth(path, **arrays):
        real_save(path, **arrays)
        calls.append(1)
        if len(calls) == 5:  # 4 in-group + 1 after group 0, then killed in group 1
            raise KeyboardInterrupt

    monkeypatch.setattr(fit, "_save_npz", crash_after_fifth)
    with pytest.raises(KeyboardInterrupt):
        fit.fit_many(values, bins, ids, init, s, seed=0, checkpoint=ck)
    monkeypatch.setattr(fit, "_save_npz", real_save)
    with np.load(ck) as z:
        assert len(z["weights"]) == 2 and "run_w" not in z.files
    res = fit.fit_many(values, bins, ids, init, s, seed=0, checkpoint=ck)
    np.testing.assert_array_equal(res["weights"], ref["weights"])
    np.testing.assert_array_equal(res["val_history"], ref["val_history"])
    # a mid-group checkpoint resumes bit-identically too
    monkeypatch.setattr(fit, "_save_npz", crash_after_fifth)
    calls.clear()
    calls.extend([1, 1, 1])  # crash at the 2nd save: group 0 at step 20
    with pytest.raises(KeyboardInterrupt):
        fit.fit_many(values, bins, ids, init, s, seed=1, checkpoint=ck)
    monkeypatch.setattr(fit, "_save_npz", real_save)
    with np.load(ck) as z:
        assert int(z["run_step"]) == 20 and len(z["weights"]) == 0
    res = fit.fit_many(values, bins, ids, init, s, seed=1, checkpoint=ck)
    ref1 = fit.fit_many(values, bins, ids, init, s, seed=1)
    np.testing.assert_array_equal(res["weights"], ref1["weights"])


def test_checkpoint_of_other_settings_is_not_resumed(data, tmp_path, caplog):
    bins, values, init, _ = data
    ck = tmp_path / "ck.npz"
    fit.fit_many(values[:1], bins, [0], init, SMALL, seed=0, checkpoint=ck)
    other = dataclasses.replace(SMALL, lr=1e-3)
    res = fit.fit_many(values[:1], bins, [0], init, other, seed=0, checkpoint=ck)
    assert "starting over" in caplog.text
    ref = fit.fit_many(values[:1], bins, [0], init, other, seed=0)
    np.testing.assert_array_equal(res["weights"], ref["weights"])


def _killed(monkeypatch, after: int, *args, **kw):
    """fit_many(*args, **kw), killed right after its `after`-th checkpoint save."""
    real_save, calls = fit._save_npz, []

    def crash(path, **arrays):
        real_save(path, **arrays)
        calls.append(1)
        if len(calls) == after:
            raise KeyboardInterrupt

    monkeypatch.setattr(fit, "_save_npz", crash)
    with pytest.raises(KeyboardInterrupt):
        fit.fit_many(*args, **kw)
    monkeypatch.setattr(fit, "_save_npz", real_save)


def test_checkpoint_of_other_data_with_the_same_ids_starts_over(data, tmp_path, monkeypatch,
                                                                 caplog):
    """A checkpoint outlives the config: after e.g. an augmerl.pca_dims change the shard holds
    other materials under the same ids, which must not be resumed (it returned the old
    materials' fields)."""
    bins, values, init, _ = data
    ids, ck = [0, 1, 2], tmp_path / "ck.npz"
    other = (values * 1.5).astype(np.float32)  # other materials, same ids and bins
    _killed(monkeypatch, 6, values, bins, ids, init, SMALL, seed=0, checkpoint=ck)
    with np.load(ck) as z:  # group 0 done (5 saves), group 1 running
        assert len(z["weights"]) == 2 and int(z["run_step"]) == 10
    with caplog.at_level("INFO", logger="neumat.fit"):
        res = fit.fit_many(other, bins, ids, init, SMALL, seed=0, checkpoint=ck)
    assert "checkpoint of other settings/data, starting over" in caplog.text
    assert "resuming" not in caplog.text
    np.testing.assert_array_equal(res["weights"],
                                  fit.fit_many(other, bins, ids, init, SMALL, seed=0)["weights"])
    # the fingerprint covers every value and the bins, not the speed keys
    kern = fit.resolve_kernel(SMALL, "cpu")
    fp = fit.fingerprint(SMALL, 0, ids, init, kern, bins, values)
    one = values.copy()
    one[2, 1, -1] = np.nextafter(one[2, 1, -1], np.float32(1))
    moved = bins.copy()
    moved[-1] += 1
    assert fit.fingerprint(SMALL, 0, ids, init, kern, bins, one) != fp
    assert fit.fingerprint(SMALL, 0, ids, init, kern, moved, values) != fp
    assert fit.fingerprint(dataclasses.replace(SMALL, lr=1e-3), 0, ids, init, kern, bins,
                           values) != fp
    speed = dataclasses.replace(SMALL, checkpoint_every=7, materials_per_batch=5)
    assert fit.fingerprint(speed, 0, ids, init, kern, bins, values.astype(np.float64)) == fp


@pytest.mark.parametrize("damage", ["empty", "not_a_zip", "no_fingerprint", "truncated"])
def test_unreadable_checkpoint_is_logged_and_replaced(data, tmp_path, monkeypatch, caplog,
                                                       damage):
    """A damaged checkpoint (a killed write, a full disk) is no Snakemake output, so
    --rerun-incomplete never removes it: the fit starts over (naming it) instead of failing
    every rerun, and overwrites it."""
    bins, values, init, _ = data
    ck = tmp_path / "shard_007.npz"
    if damage == "empty":
        ck.write_bytes(b"")
    elif damage == "not_a_zip":
        ck.write_bytes(b"PK\x03\x04junk")
    elif damage == "no_fingerprint":
        np.savez(ck, w=np.zeros(3))
    else:
        _killed(monkeypatch, 1, values[:2], bins, [0, 1], init, SMALL, seed=0, checkpoint=ck)
        ck.write_bytes(ck.read_bytes()[:-200])
    res = fit.fit_many(values[:2], bins, [0, 1], init, SMALL, seed=0, checkpoint=ck)
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and str(ck) in warned[0] and "starting over" in warned[0], warned
    assert "unreadable fit checkpoint" in warned[0]
    ref = fit.fit_many(values[:2], bins, [0, 1], init, SMALL, seed=0)
    np.testing.assert_array_equal(res["weights"], ref["weights"])
    with np.load(ck) as z:  # replaced by a checkpoint of this fit
        assert len(z["weights"]) == 2 and str(z["fingerprint"])


@pytest.mark.parametrize("kernel", KERNELS)
def test_resumes_across_checkpoint_every_and_materials_per_batch(data, tmp_path, monkeypatch,
                                                                 caplog, kernel):
    """Both are speed keys: a checkpoint written with other values is resumed, the running
    group at its own size, bit-identically; later groups take the new size."""
    bins, values, init, _ = data
    values = np.concatenate([values, values * 0.5]).astype(np.float32)
    ids, ck = list(range(6)), tmp_path / "ck.npz"
    s = dataclasses.replace(SMALL, kernel=kernel)  # groups [0 1] [2 3] [4 5]
    ref = fit.fit_many(values, bins, ids, init, s, seed=2)
    # 4 saves + 1 in group 0, then 2 in group 1: killed with [2 3] at step 20
    _killed(monkeypatch, 7, values, bins, ids, init, s, seed=2, checkpoint=ck)
    later = dataclasses.replace(s, checkpoint_every=7, materials_per_batch=1)
    with caplog.at_level("INFO", logger="neumat.fit"):
        res = fit.fit_many(values, bins, ids, init, later, seed=2, checkpoint=ck)
    assert "resuming, 2 materials done, group of 2 at step 20" in caplog.text
    assert "starting over" not in caplog.text
    groups = [r.getMessage() for r in caplog.records if r.getMessage().startswith("materials ")]
    assert groups == ["materials 2-3 of 6", "materials 4-4 of 6", "materials 5-5 of 6"]
    # the resumed group and the finished ones: bit for bit
    np.testing.assert_array_equal(res["weights"][:4], ref["weights"][:4])
    np.testing.assert_array_equal(res["val_history"][:, :4], ref["val_history"][:, :4])
    # 4 and 5 trained alone: the C kernel fits each material on its own (bit for bit), torch's
    # batched matmuls agree to float32 rounding
    if kernel == "c":
        np.testing.assert_array_equal(res["weights"], ref["weights"])
    np.testing.assert_allclose(res["weights"], ref["weights"], atol=2e-5)


def test_log_target_in_place_is_bit_identical_to_the_expression():
    """log_target builds the targets in one buffer, in place, also straight in the fitter's
    bin-major layout: the same bits as log1p(clamp_min(f, 0) * cos), on any thread count,
    float64 values, negative values, sizes off the vector width."""
    rng = np.random.default_rng(0)
    threads = torch.get_num_threads()
    try:
        for t in (1, 2):
            torch.set_num_threads(t)
            for M, B, dtype in [(1, 37, np.float32), (3, 2000, np.float32),
                                (5, 4099, np.float64), (2, 70001, np.float32)]:
                bins = np.sort(rng.choice(merl.N_BINS, B, replace=False))
                _, cos = fit.bin_inputs(bins)
                v = (rng.standard_normal((M, 3, B)) * rng.choice([1e-3, 1, 100], (M, 3, B)))
                v = v.astype(dtype)
                ref = torch.log1p(torch.as_tensor(v, dtype=torch.float32).clamp_min(0) * cos)
                ref = ref.transpose(1, 2)  # (M, B, 3): the former expression
                got = fit.log_target(v, cos)
                assert got.shape == (M, B, 3) and torch.equal(got, ref), (t, M, B)
                bm = fit.log_target(v, cos, bin_major=True)
                assert bm.shape == (B, M * 3) and bm.is_contiguous()
                assert torch.equal(bm, ref.permute(1, 0, 2).reshape(B, M * 3)), (t, M, B)
    finally:
        torch.set_num_threads(threads)
    with pytest.raises(ValueError, match=r"\(n, 3, 37\)"):
        fit.log_target(np.zeros((2, 37)), cos[:37])


@pytest.mark.parametrize("kernel", KERNELS)
def test_fitter_takes_bin_major_targets_as_they_are(kernel):
    """A bin-major target is used without a copy and trains as the (M, B, 3) one does; the
    torch path's evaluation, gathered chunk by chunk (over 32768 training bins here), gives
    the bits of field_loss over all points at once."""
    rng = np.random.default_rng(3)
    bins = np.sort(rng.choice(np.flatnonzero(merl.valid_mask()), 45000, replace=False))
    x, cos = fit.bin_inputs(bins)
    values = rng.random((2, 3, len(bins)), dtype=np.float32)
    init = nbrdf.init_weights(2, torch.Generator().manual_seed(4))
    s = dataclasses.replace(SMALL, steps=3, eval_every=3, kernel=kernel)
    bm = fit.log_target(values, cos, bin_major=True)
    a = fit.BatchFitter(x, cos, fit.log_target(values, cos), [0, 1], init, s, seed=0).train()
    b = fit.BatchFitter(x, cos, bm, [0, 1], init, s, seed=0)
    assert b.target.data_ptr() == bm.data_ptr()
    b.train()
    assert torch.equal(a.w, b.w)
    train = b.eval_loss("train")
    np.testing.assert_array_equal(train, a.eval_loss("train"))
    if kernel == "torch":
        assert len(b.train_idx) > fit.LOSS_CHUNK
        whole = fit.field_loss(b.w, *b._points(b.train_idx), s.activation).numpy()
        np.testing.assert_array_equal(train, whole)
    with pytest.raises(ValueError, match="inconsistent fit inputs"):
        fit.BatchFitter(x, cos, bm[:, :5], [0, 1], init, s, seed=0)


def test_settings_errors_name_the_config_key(data):
    with pytest.raises(ValueError, match="fit.activation"):
        fit.FitSettings(activation="tanh")
    with pytest.raises(ValueError, match="fit.val_fraction"):
        fit.FitSettings(val_fraction=1.5)
    bins, values, init, _ = data
    with pytest.raises(ValueError, match="fit.batch"):
        fit.fit_many(values[:1], bins, [0], init, dataclasses.replace(SMALL, batch=4096), seed=0)
    s = fit.FitSettings.from_config({"steps": 5, "template_steps": 9, "lr": 1e-3, "threads": 2},
                                    "template_steps")
    assert s.steps == 9 and s.lr == 1e-3


def test_save_load_fits_round_trip(data, tmp_path):
    bins, values, init, _ = data
    res = fit.fit_many(values[:1], bins, [4], init, dataclasses.replace(SMALL, steps=5), seed=0)
    fit.save_fits(tmp_path / "f.npz", res)
    back = fit.load_fits(tmp_path / "f.npz")
    np.testing.assert_array_equal(back["weights"], res["weights"])
    assert back["weights"].dtype == np.float32 and back["ids"].tolist() == [4]
    np.savez(tmp_path / "bad.npz", ids=np.arange(2), weights=np.zeros((2, 5)))
    with pytest.raises(ValueError, match="bad.npz"):
        fit.load_fits(tmp_path / "bad.npz")
    # a damaged file (a killed copy, a full disk) names itself and its rule, not BadZipFile
    (tmp_path / "cut.npz").write_bytes((tmp_path / "f.npz").read_bytes()[:100])
    with pytest.raises(ValueError, match=r"cut\.npz: not a readable fit result.*rule fit_shard"):
        fit.load_fits(tmp_path / "cut.npz")


def test_merge_orders_by_manifest_and_checks_coverage():
    def shard(ids):
        ids = np.array(ids)
        return dict(ids=ids, weights=np.tile(ids[:, None], (1, 675)).astype(np.float32),
                    train_loss=ids * 0.1, val_loss=ids * 0.2)

    man = pd.DataFrame({"id": [0, 1, 2, 3], "name": list("abcd")})
    evals = [pd.DataFrame({"id": [3, 1], "render_psnr": [33.0, 31.0]}),
             pd.DataFrame({"id": [0, 2], "render_psnr": [30.0, 32.0]})]
    w, table = fit.merge_fits([shard([3, 1]), shard([0, 2])], evals, man)
    assert w.shape == (4, 675) and w[:, 0].tolist() == [0, 1, 2, 3]
    assert table["name"].tolist() == list("abcd")
    np.testing.assert_allclose(table["val_loss"], [0, 0.2, 0.4, 0.6])
    np.testing.assert_allclose(table["render_psnr"], [30, 31, 32, 33])
    with pytest.raises(ValueError, match="exactly once"):
        fit.merge_fits([shard([3, 1])], evals, man)


def test_export_merl_round_trip(tmp_path):
    w = nbrdf.init_weights(1, torch.Generator().manual_seed(3))[0].numpy()
    fit.export_merl(w, tmp_path / "m.binary")
    table = merl.read_merl(tmp_path / "m.binary")
    valid = merl.valid_mask()
    flat = table.reshape(3, -1)
    assert (flat[:, ~valid] < 0).all() and (flat[:, valid] >= 0).all()
    idx = np.flatnonzero(valid)[::50000]
    x, _ = fit.bin_inputs(idx)
    ref = nbrdf.forward(torch.as_tensor(w)[None], x)[0].numpy().T
    np.testing.assert_allclose(flat[:, idx], ref, rtol=1e-5, atol=1e-7)
    # a row of a read-only memory map (neumerl_export's input): the same table, no warning
    # (torch warns once per process: alone, this test failed before export_merl copied)
    np.save(tmp_path / "w.npy", w[None])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit.export_merl(np.load(tmp_path / "w.npy", mmap_mode="r")[0], tmp_path / "mm.binary")
    assert (tmp_path / "mm.binary").read_bytes() == (tmp_path / "m.binary").read_bytes()


def test_psnr_known_answer():
    a = np.zeros((1, 4, 4, 3))
    b = a + 0.1  # MSE 0.01 -> 20 dB
    assert fit.psnr(a, b)[0] == pytest.approx(20.0)
    mask = np.zeros((4, 4), bool)
    mask[0, 0] = True
    b[0, 1:, :] = 1.0  # outside the mask: ignored
    assert fit.psnr(a, b, mask)[0] == pytest.approx(20.0)


def test_render_psnr_prefers_the_right_table(tmp_path):
    # a random field is not phi_d-symmetric, unlike the folded table: PSNR well below a fit's
    w = nbrdf.init_weights(2, torch.Generator().manual_seed(5))
    tables = nbrdf.evaluate_grid(w)
    same = fit.render_psnr(w, tables, resolution=32)
    swapped = fit.render_psnr(w, tables[::-1].copy(), resolution=32)
    assert (same > 25).all() and (same > swapped + 10).all()
    fit.plot_fit_quality(same, [0.01, 0.02], np.array([10, 20]), np.array([[0.1, 0.2], [0.05, 0.1]]),
                         tmp_path / "q.png")
    assert (tmp_path / "q.png").stat().st_size > 1000


def test_validation_loss_is_measured_on_the_held_out_bins(data):
    """Targets corrupted at the validation bins only (fit.split_bins with the fit's seed): the
    training loss stays low and the validation loss does not, so each is measured on its own
    bins."""
    bins, values, init, _ = data
    s = dataclasses.replace(SMALL, steps=300, lr=1e-2, lr_final=1e-4, eval_every=300)
    _, val = fit.split_bins(len(bins), 0, s.val_fraction)
    bad = values[:1].copy()
    bad[:, :, val.numpy()] *= 50.0
    res = fit.fit_many(bad, bins, [0], init, s, seed=0)
    assert res["val_loss"][0] > 5 * res["train_loss"][0], (res["val_loss"], res["train_loss"])


@pytest.mark.parametrize("kernel", KERNELS)
def test_mirror_setting_changes_the_fit(data, kernel):
    """fit.mirror_phi_d trains at phi_d + pi too: on and off give other weights (its sign
    vector set to 0 inside the fitter went unnoticed by the helper's own test below)."""
    bins, values, init, _ = data
    on = fit.fit_many(values[:1], bins, [0], init, dataclasses.replace(SMALL, kernel=kernel), seed=0)
    off = fit.fit_many(values[:1], bins, [0], init,
                       dataclasses.replace(SMALL, kernel=kernel, mirror_phi_d=False), seed=0)
    assert np.abs(on["weights"] - off["weights"]).max() > 1e-3


def test_mirror_is_phi_d_plus_pi_and_keeps_the_bin():
    rng = np.random.default_rng(1)
    th, td, pd_ = rng.uniform(0, np.pi / 2, 50), rng.uniform(0, np.pi / 2, 50), rng.uniform(0, np.pi, 50)
    x = torch.as_tensor(merl.half_diff_cartesian(th, td, pd_), dtype=torch.float32)
    flip = torch.arange(50) % 2 == 0
    got = fit.mirror_phi_d(x, flip)
    ref = merl.half_diff_cartesian(th, td, np.where(flip.numpy(), pd_ + np.pi, pd_))
    np.testing.assert_allclose(got.numpy(), ref, atol=1e-6)
    wi, wo = merl.half_diff_to_dirs(th, td, pd_ + np.pi)
    np.testing.assert_array_equal(merl.angles_to_index(*merl.dirs_to_half_diff(wi, wo)),
                                  merl.angles_to_index(th, td, pd_))
