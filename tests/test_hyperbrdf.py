"""HyperBRDF (Table 3): set-encoder permutation invariance, hypernetwork output shapes, the
value mapping, exact resume after a kill, learning a toy family, and the Table 3 metrics."""

import numpy as np
import pandas as pd
import pytest
import torch

from neumat.baselines import hyperbrdf as hb
from neumat.io import merl
from neumat.metrics import reconstruction as rec


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


SMALL = hb.HyperConfig(latent=8, encoder_width=16, head_width=16, target_width=12)


def _bins(n, seed=0):
    valid = np.flatnonzero(merl.valid_mask())
    return np.sort(np.random.default_rng(seed).choice(valid, n, replace=False))


def _lambertian(albedos, bins):
    """(M, 3) albedos -> (M, 3, B) constant BRDF values albedo / pi."""
    a = np.asarray(albedos, dtype=np.float32)
    return np.repeat(a[:, :, None] / np.pi, len(bins), axis=2)


def test_encoder_is_permutation_invariant():
    torch.manual_seed(0)
    model = hb.HyperBRDF(SMALL)
    x, y = torch.randn(2, 500, 6), torch.rand(2, 500, 3)
    perm = torch.randperm(500)
    z = model.encode(x, y)
    assert z.shape == (2, 8)
    torch.testing.assert_close(model.encode(x[:, perm], y[:, perm]), z, rtol=1e-5, atol=1e-6)
    # chunked pooling (many samples) is the same mean
    s = torch.cat([x, y], -1)
    torch.testing.assert_close(model.encoder(s, chunk=128), model.encoder(s), rtol=1e-5, atol=1e-6)
    # ...and the latent does depend on the samples
    assert not torch.allclose(model.encode(x, y + 1), z)


def test_hypernetwork_output_shapes():
    cfg = hb.HyperConfig()  # the reference architecture: target 6-60-60-60-60-3
    torch.manual_seed(0)
    model = hb.HyperBRDF(cfg)
    assert cfg.target_shapes() == [(60, 6), (60,), (60, 60), (60,), (60, 60), (60,),
                                   (60, 60), (60,), (3, 60), (3,)]
    assert model.n_target == 6 * 60 + 60 + 3 * (60 * 60 + 60) + 60 * 3 + 3 == 11583
    z = torch.randn(3, 40)
    params = model.params(z)
    assert [tuple(p.shape) for p in params] == [(3, *s) for s in cfg.target_shapes()]
    assert hb.flatten_params(params).shape == (3, 11583)
    x6 = hb.bin_inputs(_bins(100))[0]
    y = model.decode(z, x6, chunk=33)
    assert y.shape == (3, 100, 3) and torch.isfinite(y).all()
    # per-material weights: material 1's field alone equals its row of the batch
    torch.testing.assert_close(model.field([p[1:2] for p in params], x6), y[1:2],
                               rtol=1e-5, atol=1e-6)


def test_value_mapping_round_trip():
    f = np.random.default_rng(1).lognormal(-2, 2, (2, 50, 3)).astype(np.float32)
    med = hb.bin_median(f.transpose(0, 2, 1))
    assert med.shape == (50,)
    y = hb.to_target(f, med)
    assert (y > 0).all()
    torch.testing.assert_close(hb.from_target(y, med), torch.as_tensor(f), rtol=1e-4, atol=1e-6)


def test_training_targets_equal_to_target_bit_for_bit():
    """The in-place mapping of `train` is `to_target` of the transposed values to the bit, so
    the checkpoint fingerprint (which hashes it) is unchanged; it leaves the input alone."""
    import hashlib

    rng = np.random.default_rng(2)
    vals = rng.lognormal(-3, 3, (4, 3, 257)).astype(np.float32)
    vals[:, :, ::7] *= -1  # invalid (negative) entries are clamped to 0 by both
    vals[0, 0, :3] = [0.0, -0.0, 1e-30]
    med = hb.bin_median(vals)
    med[5] = 0.0
    keep = vals.copy()
    old = hb.to_target(vals.transpose(0, 2, 1), med)  # (M, B, 3), not contiguous
    new = hb.training_targets(vals, med)
    assert new.is_contiguous() and new.shape == (4, 257, 3)
    assert np.array_equal(new.numpy().view(np.uint32), old.numpy().view(np.uint32))
    assert np.array_equal(vals.view(np.uint32), keep.view(np.uint32))
    # one bin: the transposed view is already contiguous, and must still not be mapped in place
    one = vals[:, :, :1].copy()
    hb.training_targets(one, med[:1])
    assert np.array_equal(one, vals[:, :, :1])
    # the fingerprint hashes the same bytes as before (then a tobytes() copy of y)
    bins = np.arange(257)
    ref = hashlib.sha256(np.ascontiguousarray(old.numpy()).tobytes())
    ref.update(bins.astype(np.int64).tobytes())
    ref.update(b'[{"latent": 8}, 5]')
    import dataclasses

    @dataclasses.dataclass
    class C:
        latent: int = 8

    assert hb.fingerprint(new.numpy(), bins, 5, C()) == ref.hexdigest()
    assert hb.fingerprint(old.numpy(), bins, 5, C()) == ref.hexdigest()
    # train's fingerprint also names the draw scheme: an argsort-era checkpoint is not resumed
    assert hb.fingerprint(new.numpy(), bins, 5, C(), draws=hb.DRAWS) != ref.hexdigest()


def test_training_targets_memory():
    """Mapping and fingerprinting the training values grows the peak RSS by about one copy of
    the values (the targets), not ~4 (to_target's temporaries and the hash's copies)."""
    import os
    import subprocess
    import sys

    if not os.access("/proc/self/clear_refs", os.W_OK):
        pytest.skip("needs Linux /proc/self/clear_refs (resetting the peak RSS)")
    code = """
import numpy as np, torch
from neumat.baselines import hyperbrdf as hb
def kib(key):  # VmRSS (now) or VmHWM (peak since the reset) of this process
    return int(next(l for l in open("/proc/self/status") if l.startswith(key)).split()[1])
torch.set_num_threads(1)
v = np.random.default_rng(0).random((64, 3, 1 << 17), dtype=np.float32)  # 96 MiB
med = np.full(1 << 17, 0.5, np.float32)
w = hb.training_targets(v[:2, :, :4096], med[:4096]); hb.fingerprint(w.numpy(), np.arange(3), 0)
open("/proc/self/clear_refs", "w").write("5")  # reset the peak to the current RSS
r0 = kib("VmRSS")
y = hb.training_targets(v, med)
hb.fingerprint(y.numpy(), np.arange(3), 0)
print((kib("VmHWM") - r0) * 1024 / v.nbytes)
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    growth = float(res.stdout.split()[-1])
    assert 0.9 < growth < 1.3, growth


def _train_args(tmp_path, steps=12, tag="a"):
    bins = _bins(600)
    vals = _lambertian([[0.2, 0.5, 0.8], [0.9, 0.1, 0.3], [0.4, 0.4, 0.4]], bins)
    cfg = hb.HyperTrainConfig(steps=steps, lr=1e-3, materials_per_step=2, context=200,
                              query=100, checkpoint_every=4, log_every=3)  # 4 between logs
    return (vals, bins, hb.bin_median(vals), SMALL, cfg, tmp_path / f"{tag}.pt",
            tmp_path / f"{tag}_ck.pt")


def test_resume_after_kill_is_identical(tmp_path):
    full = hb.train(*_train_args(tmp_path, tag="full"), seed=5)
    # the final checkpoint stays: a rerun takes no step and writes the same model
    ran = []
    again = hb.train(*_train_args(tmp_path, tag="full"), seed=5,
                     on_step=lambda step, loss: ran.append(step))
    assert ran == [] and again["history"] == full["history"]
    for k, v in full["state"].items():
        assert torch.equal(v, again["state"][k]), k

    class Kill(Exception):
        pass

    def kill(step, loss):
        if step == 7:  # after the checkpoint at step 4: steps 5-7 are lost and redone
            raise Kill

    args = _train_args(tmp_path, tag="r")
    with pytest.raises(Kill):
        hb.train(*args, seed=5, on_step=kill)
    assert args[-1].exists() and not args[-2].exists()
    # resumed with another checkpoint_every (a speed key): the same run
    later = hb.HyperTrainConfig(**{**args[4].__dict__, "checkpoint_every": 5})
    ran = []
    resumed = hb.train(*args[:4], later, *args[5:], seed=5, on_step=lambda step, loss: ran.append(step))
    assert ran[0] == 5  # from the checkpoint at 4, not from the start
    for k, v in full["state"].items():
        assert torch.equal(v, resumed["state"][k]), k
    assert full["history"] == resumed["history"]
    # a checkpoint written for other settings is ignored, not resumed
    other = hb.train(*_train_args(tmp_path, tag="r"), seed=6)
    assert other["history"] != full["history"]


def test_history_is_the_mean_loss_per_log_window(tmp_path):
    """The losses are read from the device once per log_every steps; a history row is still
    the mean total loss of the steps since the previous row (the last row: the remainder)."""
    args = _train_args(tmp_path, steps=8, tag="h")  # log_every 3: rows at 3, 6 and 8
    losses = []
    bundle = hb.train(*args, seed=2, on_step=lambda step, loss: losses.append(loss))
    assert [r[0] for r in bundle["history"]] == [3, 6, 8]
    for row, window in zip(bundle["history"], (losses[0:3], losses[3:6], losses[6:8])):
        assert row[1] == np.mean(window)
        assert row[2] < row[1]  # the MSE part of it


def test_training_rejects_bad_input(tmp_path):
    vals, bins, med, mcfg, cfg, out, ck = _train_args(tmp_path)
    with pytest.raises(ValueError, match="values must be"):
        hb.train(vals[:, :2], bins, med, mcfg, cfg, out, ck, seed=0)
    with pytest.raises(ValueError, match=r"\(hyperbrdf.train_bins\), fewer than hyperbrdf.train.context"):
        hb.train(vals[:, :, :150], bins[:150], med[:150], mcfg, cfg, out, ck, seed=0)
    # where the shards store fewer bins than train_bins, the message names augmerl.bins
    with pytest.raises(ValueError, match=r"150 bins per material \(augmerl.bins\), fewer"):
        hb.train(vals[:, :, :150], bins[:150], med[:150], mcfg, cfg, out, ck, seed=0,
                 bins_key="augmerl.bins")


@pytest.mark.slow
def test_learns_lambertian_family_and_reconstructs(tmp_path):
    """Trained on Lambertians of random albedo, an unseen albedo is recovered from its samples
    (sparse and compression) much better than by the untrained model."""
    rng = np.random.default_rng(0)
    bins = _bins(2000)
    vals = _lambertian(rng.uniform(0.05, 0.95, (24, 3)), bins)
    cfg = hb.HyperTrainConfig(steps=300, lr=2e-3, materials_per_step=4, context=300, query=300,
                              theta_weight=1e-4, z_weight=1e-4, checkpoint_every=1000,
                              log_every=25)
    med = np.full(merl.N_BINS, np.median(vals), np.float32)
    bundle = hb.train(vals, bins, med[bins], SMALL, cfg, tmp_path / "m.pt", tmp_path / "c.pt",
                      seed=0)
    assert bundle["history"][-1][2] < 0.3 * bundle["history"][0][2]  # MSE part
    test = _lambertian([[0.3, 0.6, 0.15]], bins)
    views = {n: rec.view(n, 16) for n in rec.VIEWS}
    truth = {n: v.composite(torch.as_tensor(test[:, :, :1]).transpose(1, 2).expand(-1, len(v), -1))
             for n, v in views.items()}
    torch.manual_seed(0)
    err = {}
    for name, model in (("trained", hb.load(bundle)), ("untrained", hb.HyperBRDF(SMALL).eval())):
        for task in hb.TASKS:
            out = hb.reconstruct(model, test, bins, med, views, task, 500, seed=1)
            err[name, task] = np.mean([rec.psnr(rec.srgb(truth[v]), rec.srgb(out[v]))
                                       for v in views])
    for task in hb.TASKS:
        assert err["trained", task] > 20 and err["trained", task] > err["untrained", task] + 10


def test_task_bins():
    bins = np.arange(100)
    a = hb.task_bins("sparse", bins, 10, seed=0, key="red-plastic")
    assert len(a) == 10 and len(set(a)) == 10
    assert np.array_equal(a, hb.task_bins("sparse", bins, 10, seed=0, key="red-plastic"))
    assert not np.array_equal(a, hb.task_bins("sparse", bins, 10, seed=0, key="blue-fabric"))
    assert np.array_equal(hb.task_bins("compression", bins, 10, 0, 0), bins)
    with pytest.raises(ValueError, match="augmerl.bins"):
        hb.task_bins("sparse", bins, 101, 0, 0)


def test_delta_e_psnr_ssim_known_answers():
    rng = np.random.default_rng(0)
    img = rng.random((16, 16, 3))
    mask = np.ones((16, 16), bool)
    assert rec.delta_e(img, img, mask) == 0.0
    assert rec.ssim(img, img) == pytest.approx(1.0)
    # flat images: only the luminance term, (2 mu_a mu_b + C1) / (mu_a^2 + mu_b^2 + C1) with
    # C1 = (0.01 data range)^2, data range 1 (255 would give 0.9986)
    flat_a, flat_b = np.full((16, 16, 3), 0.5), np.full((16, 16, 3), 0.6)
    assert rec.ssim(flat_a, flat_b) == pytest.approx((0.6 + 1e-4) / (0.61 + 1e-4), rel=1e-9)
    assert rec.psnr(flat_a, flat_b) == pytest.approx(20.0)
    assert rec.psnr(img, img) == 100.0
    # sRGB white vs black: L* 100 vs 0, and CIEDE2000 of a pure lightness difference of 100
    # with mean L' = 50 is 100 / S_L, S_L = 1 (the weighting is centred at L' = 50)
    white, black = np.ones((4, 4, 3)), np.zeros((4, 4, 3))
    assert rec.delta_e(white, black, np.ones((4, 4), bool)) == pytest.approx(100.0, abs=1e-3)
    assert rec.psnr(white, black) == pytest.approx(0.0)
    # ΔE is taken over the mask only
    half = white.copy()
    half[:2] = 0
    m = np.zeros((4, 4), bool)
    m[2:] = True
    assert rec.delta_e(white, half, m) == 0.0


def test_table3_layout_and_wins():
    scores = pd.DataFrame([
        dict(method="merl", task="sparse", view="metric", material="a", PSNR=30, dE=3, SSIM=.9),
        dict(method="merl", task="compression", view="metric", material="a", PSNR=35, dE=2, SSIM=.95),
        dict(method="augmerl", task="sparse", view="metric", material="a", PSNR=32, dE=2.5, SSIM=.92),
        dict(method="augmerl", task="compression", view="metric", material="a", PSNR=34, dE=1, SSIM=.96),
        dict(method="fit", task="any", view="metric", material="a", PSNR=45, dE=.5, SSIM=.99),
    ])
    t = rec.table3(scores, ["merl", "augmerl", "fit"], list(hb.TASKS))
    assert list(t.columns) == ["method"] + [f"{a} {m}" for a in hb.TASKS for m in rec.METRICS]
    assert t.set_index("method").loc["fit", "compression PSNR"] == 45
    w = rec.wins(t, "augmerl", "merl")
    assert w == {"sparse PSNR": True, "sparse dE": True, "sparse SSIM": True,
                 "compression PSNR": False, "compression dE": True, "compression SSIM": True}


def _paired_scores(shift, noise, n=12):
    """merl and augmerl on n materials x 2 views; augmerl = merl + shift (+ noise per material)."""
    rng = np.random.default_rng(0)
    rows = []
    for task in hb.TASKS:
        for i in range(n):
            e = noise * rng.normal()
            for view in ("metric", "grazing"):
                base = dict(task=task, view=view, material=f"m{i}")
                rows.append(dict(base, method="merl", PSNR=30.0, dE=3.0, SSIM=0.9))
                rows.append(dict(base, method="augmerl", PSNR=30.0 + shift + e, dE=3.0 - shift - e,
                                 SSIM=0.9 + (shift + e) / 100))
    return pd.DataFrame(rows)


def test_paired_comparison_known_answers():
    # a constant gain on 12 materials: every pair won, the interval is the gain itself, and
    # only the observed signs and their mirror image reach the observed |mean|: p = 2 / 2^12
    p = rec.paired(_paired_scores(1.0, 0.0), "augmerl", "merl", list(hb.TASKS), seed=0)
    assert list(p["cell"]) == [f"{t} {m}" for t in hb.TASKS for m in rec.METRICS]
    assert (p["beyond noise"] == True).all() and (p["pairs won"] == "24/24").all()  # noqa: E712
    assert (p["materials"] == 12).all() and np.allclose(p["p (sign-flip)"], 2 / 2 ** 12)
    row = p.set_index("cell").loc["sparse dE"]
    assert row["mean difference"] == pytest.approx(-1.0) and row["95 % interval"] == "[-1, -1]"
    # the same gain for the other method is not a win of `better` (two-sided p, one direction)
    p = rec.paired(_paired_scores(-1.0, 0.0), "augmerl", "merl", list(hb.TASKS), seed=0)
    assert (p["beyond noise"] == False).all()  # noqa: E712
    # no gain but material-to-material noise: no cell beyond noise
    p = rec.paired(_paired_scores(0.0, 1.0), "augmerl", "merl", list(hb.TASKS), seed=0)
    assert (p["beyond noise"] == False).all() and (p["p (sign-flip)"] > 0.05).all()  # noqa: E712
    # deterministic given the seed
    assert rec.paired(_paired_scores(0.0, 1.0), "augmerl", "merl", list(hb.TASKS), seed=0).equals(p)
    # a task's draws are its own: its rows do not depend on the tasks scored before it
    last = rec.paired(_paired_scores(0.0, 1.0), "augmerl", "merl", list(hb.TASKS)[-1:], seed=0)
    assert last.equals(p.iloc[-len(last):].reset_index(drop=True))
    with pytest.raises(ValueError, match="same materials"):
        s = _paired_scores(1.0, 0.0)
        rec.paired(s[~((s.method == "merl") & (s.material == "m0"))], "augmerl", "merl",
                   list(hb.TASKS), seed=0)


def test_sign_flip_p_known_answers():
    # 6 materials, all positive: of the 64 sign patterns only all-plus and all-minus reach the
    # observed |sum| 21
    assert rec.sign_flip_p(np.arange(1.0, 7.0)) == 2 / 64
    # the smallest one negative: |sum| 19 is reached by flipping nothing or {1}, and mirrors
    assert rec.sign_flip_p(np.array([-1.0, 2, 3, 4, 5, 6])) == 4 / 64
    # -2: flipping {}, {1} or {2} (or their complements) reaches |sum| >= 17
    assert rec.sign_flip_p(np.array([1.0, -2, 3, 4, 5, 6])) == 6 / 64
    # no difference at all: every pattern ties, p = 1; columns are tested separately
    assert np.array_equal(rec.sign_flip_p(np.c_[np.zeros(6), np.arange(1.0, 7.0)]), [1, 2 / 64])


def test_sign_flip_p_monte_carlo_matches_exact(monkeypatch):
    d = np.random.default_rng(3).normal(0.4, 1.0, (20, 3))
    with pytest.raises(ValueError, match="seeded rng"):
        rec.sign_flip_p(d)  # 20 > EXACT_MAX: Monte Carlo, which needs a seeded generator
    mc = rec.sign_flip_p(d, np.random.default_rng(0))
    assert np.array_equal(mc, rec.sign_flip_p(d, np.random.default_rng(0)))  # seeded
    monkeypatch.setattr(rec, "EXACT_MAX", 20)
    exact = rec.sign_flip_p(d)  # all 2^20 patterns
    assert np.abs(mc - exact).max() < 0.01, (mc, exact)


@pytest.mark.parametrize("n", [6, 9, 24])
def test_sign_flip_false_win_rate_under_the_null(n):
    """No true difference (per-material differences symmetric about 0): p < 0.05 in at most
    5 % of cells (+ the simulation's noise; the percentile bootstrap interval it replaces
    excluded 0 in 17 % of such cells at 5 materials, 8 % at 20). Exact for 6 and 9 materials,
    Monte Carlo for 24."""
    rng = np.random.default_rng(n)
    reps = 1500 if n <= 9 else 300
    ps = np.concatenate([rec.sign_flip_p(rng.standard_t(3, (n, 3)), rng, 1 << 12)
                         for _ in range(reps)])
    rate = float(np.mean(ps < rec.ALPHA))
    assert rate <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / len(ps)), rate
    assert rate > 0.01  # the test is not vacuous: it does reject at about its level


def test_too_few_materials_to_judge():
    """With n <= 5 materials even a perfect, consistent gain cannot reach p < 0.05 (the
    smallest attainable p is 2 / 2^n >= 0.0625): the verdict says so instead of True/False."""
    assert rec.min_p(5) == 2 / 32 >= rec.ALPHA > rec.min_p(6) == 2 / 64
    for n in (1, 2, 5):
        p = rec.paired(_paired_scores(1.0, 0.0, n=n), "augmerl", "merl", list(hb.TASKS), seed=0)
        assert (p["beyond noise"] == rec.TOO_FEW).all() and (p["materials"] == n).all()
    p = rec.paired(_paired_scores(1.0, 0.0, n=6), "augmerl", "merl", list(hb.TASKS), seed=0)
    assert (p["beyond noise"] == True).all()  # noqa: E712


def test_views_differ():
    a, b = rec.view("metric", 16), rec.view("grazing", 16)
    assert a.n_lit != b.n_lit or not torch.equal(a.wi[:a.n_lit], b.wi[:b.n_lit])
    with pytest.raises(ValueError, match="unknown view"):
        rec.view("nope", 16)
