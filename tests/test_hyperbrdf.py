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


def _train_args(tmp_path, steps=12, tag="a"):
    bins = _bins(600)
    vals = _lambertian([[0.2, 0.5, 0.8], [0.9, 0.1, 0.3], [0.4, 0.4, 0.4]], bins)
    cfg = hb.HyperTrainConfig(steps=steps, lr=1e-3, materials_per_step=2, context=200,
                              query=100, checkpoint_every=4, log_every=3)  # 4 between logs
    return (vals, bins, hb.bin_median(vals), SMALL, cfg, tmp_path / f"{tag}.pt",
            tmp_path / f"{tag}_ck.pt")


def test_resume_after_kill_is_identical(tmp_path):
    full = hb.train(*_train_args(tmp_path, tag="full"), seed=5)

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


def test_training_rejects_bad_input(tmp_path):
    vals, bins, med, mcfg, cfg, out, ck = _train_args(tmp_path)
    with pytest.raises(ValueError, match="values must be"):
        hb.train(vals[:, :2], bins, med, mcfg, cfg, out, ck, seed=0)
    with pytest.raises(ValueError, match=r"\(hyperbrdf.train_bins\), fewer than hyperbrdf.train.context"):
        hb.train(vals[:, :, :150], bins[:150], med[:150], mcfg, cfg, out, ck, seed=0)


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
    a = hb.task_bins("sparse", bins, 10, seed=0, i=3)
    assert len(a) == 10 and len(set(a)) == 10
    assert np.array_equal(a, hb.task_bins("sparse", bins, 10, seed=0, i=3))
    assert not np.array_equal(a, hb.task_bins("sparse", bins, 10, seed=0, i=4))
    assert np.array_equal(hb.task_bins("compression", bins, 10, 0, 0), bins)
    with pytest.raises(ValueError, match="augmerl.bins"):
        hb.task_bins("sparse", bins, 101, 0, 0)


def test_delta_e_psnr_ssim_known_answers():
    rng = np.random.default_rng(0)
    img = rng.random((16, 16, 3))
    mask = np.ones((16, 16), bool)
    assert rec.delta_e(img, img, mask) == 0.0
    assert rec.ssim(img, img) == pytest.approx(1.0)
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
    # a constant gain: every pair won, the interval is the gain itself, beyond noise everywhere
    p = rec.paired(_paired_scores(1.0, 0.0), "augmerl", "merl", list(hb.TASKS), seed=0)
    assert list(p["cell"]) == [f"{t} {m}" for t in hb.TASKS for m in rec.METRICS]
    assert p["beyond noise"].all() and (p["pairs won"] == "24/24").all()
    row = p.set_index("cell").loc["sparse dE"]
    assert row["mean difference"] == pytest.approx(-1.0) and row["95 % interval"] == "[-1, -1]"
    # no gain but material-to-material noise: the interval straddles 0, no cell beyond noise
    p = rec.paired(_paired_scores(0.0, 1.0), "augmerl", "merl", list(hb.TASKS), seed=0)
    assert not p["beyond noise"].any()
    # deterministic given the seed
    assert rec.paired(_paired_scores(0.0, 1.0), "augmerl", "merl", list(hb.TASKS), seed=0).equals(p)
    with pytest.raises(ValueError, match="same materials"):
        s = _paired_scores(1.0, 0.0)
        rec.paired(s[~((s.method == "merl") & (s.material == "m0"))], "augmerl", "merl",
                   list(hb.TASKS), seed=0)


def test_views_differ():
    a, b = rec.view("metric", 16), rec.view("grazing", 16)
    assert a.n_lit != b.n_lit or not torch.equal(a.wi[:a.n_lit], b.wi[:b.n_lit])
    with pytest.raises(ValueError, match="unknown view"):
        rec.view("nope", 16)
