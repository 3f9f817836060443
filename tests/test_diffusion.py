"""Hyperdiffusion: denoiser shapes and conditioning, schedules, DDIM against closed forms on a
Gaussian, learning a two-mode toy distribution, exact resume, plausibility checks."""

import importlib
import math

import numpy as np
import pytest
import torch

from neumat import nbrdf
from neumat.diffusion import (Denoiser, DenoiserConfig, Diffusion, Normalizer, Sampler,
                              ScheduleConfig, TrainConfig, guided, train)
from neumat.diffusion.model import TENSOR_SIZES, token_sizes
from neumat.diffusion.plausibility import albedo_quadrature, directional_albedo, plausibility
from neumat.diffusion.schedule import RowNoise
from neumat.seeds import seed_for

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


SMALL = DenoiserConfig(width=32, depth=2, heads=4, mlp_ratio=2.0, n_classes=3)


def _model(cfg=SMALL, seed=0):
    torch.manual_seed(seed)
    m = Denoiser(cfg)
    for lin in m.embed_out:  # the zero-initialised heads would hide conditioning effects
        torch.nn.init.normal_(lin.weight, std=0.1)
    return m.eval()


# ----------------------------------------------------------------------------- model


def test_denoiser_shapes_and_condition_interface():
    cfg = DenoiserConfig(width=32, depth=1, heads=4, n_classes=5, vector_conditions={"text": 7})
    m = _model(cfg)
    x, t = torch.randn(4, nbrdf.N_PARAMS), torch.tensor([0, 5, 10, 999])
    assert m(x, t).shape == (4, 675)
    out = m(x, t, {"type": torch.tensor([0, 1, -1, 4]), "text": torch.randn(4, 7)})
    assert out.shape == (4, 675) and torch.isfinite(out).all()
    # 6 layer tokens + time + 2 conditions
    assert m.pos.shape == (9, 32)
    with pytest.raises(ValueError, match="class labels"):
        m(x, t, {"type": torch.tensor([0, 1, 2, 5])})
    with pytest.raises(ValueError, match="unknown condition"):
        m(x, t, {"image": torch.randn(4, 3)})
    with pytest.raises(ValueError, match="size 3, expected 7"):
        m(x, t, {"text": torch.randn(4, 3)})


def test_token_sizes_split_tensors_into_near_equal_pieces():
    assert token_sizes(0) == TENSOR_SIZES == [126, 21, 441, 21, 63, 3]
    assert token_sizes(256) == [126, 21, 221, 220, 21, 63, 3]
    for k in (1, 5, 32, 100, 441, 1000):
        pieces = iter(token_sizes(k))
        for n in TENSOR_SIZES:  # each tensor in the fewest pieces of <= k, differing by <= 1
            mine = [next(pieces) for _ in range(-(-n // k))]
            assert sum(mine) == n and max(mine) <= k and max(mine) - min(mine) <= 1
        assert next(pieces, None) is None


def test_tokens_no_wider_than_the_model_reach_every_weight():
    """Outputs for W2 span at most width - 1 dimensions when its 441 values share one token
    (the final LayerNorm leaves a token width - 1 free directions): the low-noise error floor.
    Split into pieces of fewer values than that, they span all 441."""
    def w2_rank(token_values):
        m = _model(DenoiserConfig(width=32, depth=1, heads=4, n_classes=0,
                                  token_values=token_values))
        with torch.no_grad():
            out = m(torch.randn(600, 675), torch.full((600,), 3))
        return int(torch.linalg.matrix_rank(out[:, 147:588]))  # float32 tolerance

    assert w2_rank(0) <= 31
    assert w2_rank(16) == 441


def test_model_files_from_before_token_values_load():
    """A model file without `token_values` was written with one token per tensor."""
    cfg = DenoiserConfig(width=16, depth=1, heads=2, n_classes=0, token_values=0)
    assert DenoiserConfig.from_dict({**cfg.to_dict(), "token_values": 8}).token_values == 8
    torch.manual_seed(0)
    m = Denoiser(cfg)
    old = {k: v for k, v in cfg.to_dict().items() if k != "token_values"}
    again = Denoiser(DenoiserConfig.from_dict(old))
    again.load_state_dict(m.state_dict())  # raises on a token-count mismatch
    assert again.sizes == TENSOR_SIZES


def test_null_condition_paths_agree():
    """No condition, label -1, a NaN embedding and dropout all mean the same null token."""
    cfg = DenoiserConfig(width=32, depth=1, heads=4, n_classes=3, vector_conditions={"text": 5})
    m = _model(cfg)
    x, t = torch.randn(3, 675), torch.tensor([1, 2, 3])
    base = m(x, t)
    assert torch.allclose(m(x, t, {"type": torch.full((3,), -1)}), base, atol=1e-6)
    assert torch.allclose(m(x, t, {"text": torch.full((3, 5), float("nan"))}), base, atol=1e-6)
    drop = {"type": torch.ones(3, dtype=torch.bool)}
    assert torch.allclose(m(x, t, {"type": torch.tensor([0, 1, 2])}, drop), base, atol=1e-6)
    # and a real label changes the output
    assert not torch.allclose(m(x, t, {"type": torch.tensor([0, 1, 2])}), base, atol=1e-4)


def test_classifier_free_guidance_combination():
    m = _model()
    x, t = torch.randn(4, 675), torch.tensor([3, 3, 7, 7])
    cond = {"type": torch.tensor([0, 1, 2, 0])}
    c, u = m(x, t, cond), m(x, t)
    assert torch.allclose(guided(m, cond, 1.0)(x, t), c, atol=1e-6)
    assert torch.allclose(guided(m, cond, 0.0)(x, t), u, atol=1e-6)
    assert torch.allclose(guided(m, cond, 3.0)(x, t), u + 3.0 * (c - u), atol=1e-5)
    assert torch.allclose(guided(m, None, 3.0)(x, t), u, atol=1e-6)


def test_normalizer_round_trip_and_constant_coordinates():
    w = torch.randn(50, 675) * 3 + 1
    w[:, 10] = 0.25  # a weight no fit ever changed
    n = Normalizer.fit(w)
    z = n.encode(w)
    assert torch.allclose(z.mean(0)[:10], torch.zeros(10), atol=1e-5)
    assert torch.allclose(z.std(0)[:10], torch.ones(10), atol=1e-5)
    assert torch.isfinite(z).all() and torch.allclose(n.decode(z), w, atol=1e-5)


# ----------------------------------------------------------------------------- schedule


def test_schedules():
    lin = Diffusion(ScheduleConfig(timesteps=100, kind="linear", beta_start=1e-4, beta_end=2e-2))
    assert lin.betas[0].item() == pytest.approx(1e-4) and lin.betas[-1].item() == pytest.approx(2e-2)
    cos = Diffusion(ScheduleConfig(timesteps=1000, kind="cosine"))
    ab = cos.alpha_bar
    assert (ab[1:] < ab[:-1]).all() and ab[0] > 0.9999 and ab[-1] < 1e-4
    # Nichol & Dhariwal: alpha_bar(t) = f(t)/f(0), f(t) = cos^2(((t/T + s)/(1+s)) pi/2)
    f = lambda x: math.cos((x / 1000 + 0.008) / 1.008 * math.pi / 2) ** 2
    assert ab[499].item() == pytest.approx(f(500) / f(0), rel=1e-9)
    assert cos.timesteps_for(4) == [999, 666, 333, 0]
    assert cos.timesteps_for(1000) == list(range(999, -1, -1))
    with pytest.raises(ValueError, match="kind"):
        Diffusion(ScheduleConfig(kind="sigmoid"))
    with pytest.raises(ValueError, match="prediction"):
        Diffusion(ScheduleConfig(prediction="score"))


def _gaussian_posterior(mu, s2, diffusion, prediction):
    """Exact E[x0 | x_t] for x0 ~ N(mu, s2), returned as the model output (x0, eps or v)."""
    def predict(x, t):
        ab = diffusion.alpha_bar[t].to(x.dtype)[:, None]
        var_t = ab * s2 + 1 - ab
        x0 = mu + ab.sqrt() * s2 / var_t * (x - ab.sqrt() * mu)
        eps = (x - ab.sqrt() * x0) / (1 - ab).sqrt()
        return {"x0": x0, "eps": eps, "v": ab.sqrt() * eps - (1 - ab).sqrt() * x0}[prediction]
    return predict


@pytest.mark.parametrize("prediction", ["x0", "eps", "v"])
def test_split_inverts_each_target(prediction):
    """The loss's target for (x0, eps) at t, split back from x_t, gives that x0 and eps."""
    d = Diffusion(ScheduleConfig(timesteps=100, kind="cosine", prediction=prediction))
    g = torch.Generator().manual_seed(1)
    x0, eps = torch.randn(6, 5, generator=g, dtype=torch.float64), torch.randn(6, 5, generator=g, dtype=torch.float64)
    t = torch.tensor([0, 1, 20, 50, 98, 99])
    ab = d.alpha_bar[t][:, None]
    x_t = d.q_sample(x0, t, eps)
    target = {"x0": x0, "eps": eps, "v": ab.sqrt() * eps - (1 - ab).sqrt() * x0}[prediction]
    x0_hat, eps_hat = d.split(target, x_t, ab)
    assert torch.allclose(x0_hat, x0, atol=1e-9) and torch.allclose(eps_hat, eps, atol=1e-9)
    # the training loss regresses that same target: a model that returns it has loss 0
    def oracle(x, tt, cond, drop):
        a = d.alpha_bar[tt][:, None].to(x.dtype)
        e = (x - a.sqrt() * x0) / (1 - a).sqrt()
        return {"x0": x0, "eps": e, "v": a.sqrt() * e - (1 - a).sqrt() * x0}[prediction]
    x0 = x0.float()
    assert d.loss(oracle, x0, generator=torch.Generator().manual_seed(0)).item() < 1e-8


@pytest.mark.parametrize("prediction", ["v"])
def test_x0_loss_measures_the_implied_x0(prediction):
    """loss x0: a model whose output implies x0_hat = x0 + delta has the x0 model's loss,
    mean(delta^2), at every t; the default loss weights it by t. (eps with an x0 loss is
    refused: test_eps_prediction_with_an_x0_loss_is_refused.)"""
    torch.manual_seed(0)
    x0 = torch.randn(64, 5, dtype=torch.float64)
    delta = 0.1 * torch.randn(64, 5, dtype=torch.float64)
    losses = {}
    for loss in ("prediction", "x0"):
        d = Diffusion(ScheduleConfig(timesteps=100, kind="cosine", prediction=prediction, loss=loss))
        def biased(x, tt, cond, drop):
            a = d.alpha_bar[tt][:, None].to(x.dtype)
            xh = x0 + delta
            e = (x - a.sqrt() * xh) / (1 - a).sqrt()
            return {"eps": e, "v": a.sqrt() * e - (1 - a).sqrt() * xh}[prediction]
        losses[loss] = d.loss(biased, x0, generator=torch.Generator().manual_seed(0)).item()
    assert losses["x0"] == pytest.approx(torch.mean(delta ** 2).item(), rel=1e-9)
    assert losses["prediction"] > 2 * losses["x0"]  # v and eps weight x0 errors by 1/(1 - ab) or more
    with pytest.raises(ValueError, match="diffusion.schedule.loss"):
        Diffusion(ScheduleConfig(loss="eps"))


@pytest.mark.parametrize("prediction", ["x0", "eps", "v"])
def test_ddim_matches_closed_form_on_gaussian(prediction):
    """With the exact posterior mean, deterministic DDIM on Gaussian data is the linear map
    x_prev - sqrt(ab') mu = g (x_t - sqrt(ab) mu), g = (sqrt(ab ab') s2 + sqrt((1-ab)(1-ab')))
    / (ab s2 + 1 - ab); the sampler must reproduce it exactly."""
    d = Diffusion(ScheduleConfig(timesteps=200, kind="cosine", prediction=prediction))
    mu, s2 = 1.5, 0.25
    x_T = torch.linspace(-2, 2, 9, dtype=torch.float64)[:, None]
    got = d.ddim_sample(_gaussian_posterior(mu, s2, d, prediction), x_T.shape, steps=20, x_T=x_T)
    y, ts = x_T.clone(), d.timesteps_for(20)
    y = y - d.alpha_bar[ts[0]].sqrt() * mu
    for i, t in enumerate(ts):
        ab = d.alpha_bar[t].item()
        abp = d.alpha_bar[ts[i + 1]].item() if i + 1 < len(ts) else 1.0
        y = y * (math.sqrt(ab * abp) * s2 + math.sqrt((1 - ab) * (1 - abp))) / (ab * s2 + 1 - ab)
    assert torch.allclose(got, y + mu, atol=1e-10)


@pytest.mark.parametrize("strength", [0.3, 0.75])
def test_ddim_from_a_start_matches_closed_form(strength):
    """SDEdit start: x0_start noised to t_s = strength (T - 1), then the DDIM steps below t_s.
    With the exact Gaussian posterior the sampler is the same linear recurrence from t_s."""
    d = Diffusion(ScheduleConfig(timesteps=200, kind="cosine", prediction="v"))
    mu, s2 = 1.5, 0.25
    x0s = torch.linspace(-1, 3, 9, dtype=torch.float64)[:, None]
    z = torch.randn(9, 1, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    got = d.ddim_sample(_gaussian_posterior(mu, s2, d, "v"), x0s.shape, steps=20, x_T=z,
                        x0_start=x0s, strength=strength)
    t_s = round(strength * 199)
    ts = [t_s] + [t for t in d.timesteps_for(20) if t < t_s]
    ab_s = d.alpha_bar[t_s]
    y = ab_s.sqrt() * x0s + (1 - ab_s).sqrt() * z - ab_s.sqrt() * mu
    for i, t in enumerate(ts):
        ab = d.alpha_bar[t].item()
        abp = d.alpha_bar[ts[i + 1]].item() if i + 1 < len(ts) else 1.0
        y = y * (math.sqrt(ab * abp) * s2 + math.sqrt((1 - ab) * (1 - abp))) / (ab * s2 + 1 - ab)
    assert torch.allclose(got, y + mu, atol=1e-10)
    # strength 1: the start is ignored, ordinary sampling from x_T
    full = d.ddim_sample(_gaussian_posterior(mu, s2, d, "v"), x0s.shape, steps=20, x_T=z)
    same = d.ddim_sample(_gaussian_posterior(mu, s2, d, "v"), x0s.shape, steps=20, x_T=z,
                         x0_start=x0s, strength=1.0)
    assert torch.equal(full, same)
    with pytest.raises(ValueError, match="strength"):
        d.ddim_sample(_gaussian_posterior(mu, s2, d, "v"), x0s.shape, steps=20, x_T=z,
                      x0_start=x0s, strength=0.0)


def _exact_moments(d, mu, s2, steps, eta):
    """Mean and variance of the sampler's output for x0 ~ N(mu, s2) and the exact posterior
    mean: each step is y' = g y + sigma z with y = x_t - sqrt(ab) mu, a linear recurrence."""
    ts = d.timesteps_for(steps)
    m, v = -d.alpha_bar[ts[0]].sqrt() * mu, torch.ones_like(s2)
    for i, t in enumerate(ts):
        ab = d.alpha_bar[t].item()
        abp = d.alpha_bar[ts[i + 1]].item() if i + 1 < len(ts) else 1.0
        sig2 = eta ** 2 * (1 - abp) / (1 - ab) * (1 - ab / abp)
        g = (math.sqrt(ab * abp) * s2 + math.sqrt((1 - abp - sig2) * (1 - ab))) / (ab * s2 + 1 - ab)
        m, v = g * m, g ** 2 * v + sig2
    return mu + m, v


def test_eps_prediction_with_an_x0_loss_is_refused():
    """eps recovered as x0 divides by sqrt(alpha_bar): the loss would sit on the last step."""
    d = Diffusion(ScheduleConfig(timesteps=1000, kind="cosine", prediction="eps"))
    w = (1 - d.alpha_bar) / d.alpha_bar
    assert w[-1] / w.sum() > 0.99  # 99.8 % of the x0 loss weight on t = T - 1
    with pytest.raises(ValueError, match="prediction: eps with diffusion.schedule.loss: x0"):
        Diffusion(ScheduleConfig(timesteps=1000, kind="cosine", prediction="eps", loss="x0"))
    Diffusion(ScheduleConfig(timesteps=1000, kind="cosine", prediction="v", loss="x0"))


@pytest.mark.parametrize("eta,steps", [(0.0, 200), (1.0, 200), (0.5, 50)])
def test_ddim_recovers_gaussian_moments(eta, steps):
    """Sampling with the true posterior mean recovers the data's mean and variance (exactly
    as the discrete-time recurrence predicts, and within 10 % of the data variance)."""
    d = Diffusion(ScheduleConfig(timesteps=200, kind="cosine", prediction="eps"))
    mu = torch.tensor([-1.0, 0.5, 2.0], dtype=torch.float64)
    s2 = torch.tensor([0.09, 0.25, 1.0], dtype=torch.float64)
    n = 4000
    gen = torch.Generator().manual_seed(0)
    x_T = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    x = d.ddim_sample(_gaussian_posterior(mu, s2, d, "eps"), x_T.shape, steps=steps, eta=eta,
                      generator=gen, x_T=x_T)
    m_exact, v_exact = _exact_moments(d, mu, s2, steps, eta)
    # within 4 standard errors of the exact moments
    assert ((x.mean(0) - m_exact).abs() < 4 * (v_exact / n).sqrt()).all()
    assert ((x.var(0) / v_exact - 1).abs() < 4 * math.sqrt(2 / n)).all()
    assert torch.allclose(m_exact, mu, atol=1e-3)
    if steps == d.T:  # all steps: close to the data distribution (strided eta > 0 is coarser)
        assert torch.allclose(v_exact, s2, rtol=0.1)


# ----------------------------------------------------------------------------- training


def _two_modes(n=256, seed=0):
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(2, 675)).astype(np.float32)
    labels = rng.integers(0, 2, n)
    w = centres[labels] + 0.05 * rng.normal(size=(n, 675)).astype(np.float32)
    return w, labels, centres


TOY_TRAIN = TrainConfig(steps=400, batch_size=64, lr=2e-3, warmup_steps=20, ema_decay=0.99,
                        cond_drop=0.2, checkpoint_every=100, log_every=50)
TOY_MODEL = DenoiserConfig(width=64, depth=2, heads=4, mlp_ratio=2.0, n_classes=2)
TOY_SCHED = ScheduleConfig(timesteps=100, kind="cosine", prediction="x0")


@pytest.mark.slow
def test_learns_two_mode_distribution(tmp_path):
    w, labels, centres = _two_modes()
    bundle = train(w, labels, ["a", "b"], TOY_MODEL, TOY_SCHED, TOY_TRAIN,
                   tmp_path / "m.pt", tmp_path / "ck.pt", seed=1, device="cpu")
    assert bundle["history"][-1][1] < 0.5 * bundle["history"][0][1]
    s = Sampler(tmp_path / "m.pt", device="cpu")
    x = s.sample(200, seed=0, steps=20, negative_step=0.0)  # toy vectors, not BRDFs: no clamp
    dist = np.linalg.norm(x[:, None] - centres[None], axis=-1) / math.sqrt(675)  # RMS distance
    nearest = dist.argmin(1)
    assert np.median(dist.min(1)) < 0.25  # on a mode (modes are ~1.4 apart), not in between
    assert 0.25 < nearest.mean() < 0.75  # both modes, not collapsed onto one
    # type conditioning with guidance picks the requested mode
    xc = s.sample(40, seed=1, types=["a"] * 20 + ["b"] * 20, steps=20, guidance=2.0,
                  negative_step=0.0)
    dc = np.linalg.norm(xc[:, None] - centres[None], axis=-1)
    assert (dc.argmin(1) == np.repeat([0, 1], 20)).mean() >= 0.9


def test_resume_after_kill_is_identical(tmp_path):
    w, labels, _ = _two_modes(64)
    # log_every not dividing checkpoint_every: the checkpoint at 20 falls between logged
    # steps (18, 21), so the loss summed since 18 must be resumed too
    cfg = TrainConfig(steps=30, batch_size=16, lr=1e-3, warmup_steps=5, checkpoint_every=10,
                      log_every=3)
    mcfg = DenoiserConfig(width=32, depth=1, heads=4, n_classes=2)
    args = (w, labels, ["a", "b"], mcfg, TOY_SCHED, cfg)
    full = train(*args, tmp_path / "full.pt", tmp_path / "full_ck.pt", seed=3, device="cpu")
    # the final checkpoint stays: rerun (Snakemake reruns a finished job whose outputs it
    # marked incomplete), the training takes no step and writes the same model
    ran = []
    again = train(*args, tmp_path / "again.pt", tmp_path / "full_ck.pt", seed=3, device="cpu",
                  on_step=lambda step, loss: ran.append(step))
    assert ran == [] and again["history"] == full["history"]
    for k, v in full["ema"].items():
        assert torch.equal(v, again["ema"][k]), k

    def kill(step, loss):
        if step == 23:  # after the checkpoint at 20: steps 21-23 are lost and redone
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(*args, tmp_path / "r.pt", tmp_path / "r_ck.pt", seed=3, device="cpu", on_step=kill)
    assert not (tmp_path / "r.pt").exists()
    # resumed with another checkpoint_every (a speed key): the same run
    later = TrainConfig(**{**cfg.__dict__, "checkpoint_every": 7})
    ran = []
    resumed = train(*args[:-1], later, tmp_path / "r.pt", tmp_path / "r_ck.pt", seed=3, device="cpu",
                    on_step=lambda step, loss: ran.append(step))
    assert ran[0] == 21  # from the checkpoint at 20, not from the start
    for k, v in full["ema"].items():
        assert torch.equal(v, resumed["ema"][k]), k
    assert full["history"] == resumed["history"]
    # a checkpoint written for other settings is ignored, not resumed
    other = TrainConfig(**{**cfg.__dict__, "lr": 2e-3})
    fresh = train(w, labels, ["a", "b"], mcfg, TOY_SCHED, other, tmp_path / "o.pt",
                  tmp_path / "r_ck.pt", seed=3, device="cpu")
    assert fresh["history"][0] != full["history"][0]


def test_checkpoint_of_another_seed_is_not_resumed(tmp_path, caplog):
    """The seed is in the fingerprint: a checkpoint of seed 1 resumed under seed 2 finished the
    seed-1 run and recorded seed 2 in the bundle."""
    from neumat.diffusion.train import fingerprint
    w, labels, _ = _two_modes(32)
    cfg = TrainConfig(steps=6, batch_size=8, warmup_steps=1, checkpoint_every=3, log_every=3)
    mcfg = DenoiserConfig(width=16, depth=1, heads=2, n_classes=2)
    args = (w, labels, ["a", "b"], mcfg, TOY_SCHED, cfg)

    def kill(step, loss):
        if step == 4:  # after the checkpoint at 3
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(*args, tmp_path / "r.pt", tmp_path / "r_ck.pt", seed=1, device="cpu", on_step=kill)
    ran = []
    resumed = train(*args, tmp_path / "r.pt", tmp_path / "r_ck.pt", seed=2, device="cpu",
                    on_step=lambda step, loss: ran.append(step))
    assert ran[0] == 1  # started over
    assert "r_ck.pt" in caplog.text and "written for other data or settings" in caplog.text
    fresh = train(*args, tmp_path / "f.pt", tmp_path / "f_ck.pt", seed=2, device="cpu")
    assert resumed["seed"] == 2 and resumed["history"] == fresh["history"]
    assert all(torch.equal(v, resumed["ema"][k]) for k, v in fresh["ema"].items())
    # the same seed still resumes
    with pytest.raises(KeyboardInterrupt):
        train(*args, tmp_path / "s.pt", tmp_path / "s_ck.pt", seed=2, device="cpu", on_step=kill)
    ran.clear()
    again = train(*args, tmp_path / "s.pt", tmp_path / "s_ck.pt", seed=2, device="cpu",
                  on_step=lambda step, loss: ran.append(step))
    assert ran[0] == 4 and again["history"] == fresh["history"]
    assert fingerprint(w, labels, mcfg, cfg, seed=1) != fingerprint(w, labels, mcfg, cfg, seed=2)


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="no CUDA device: the CUDA random state (dropout on a GPU) needs one")
def test_cuda_checkpoint_restores_the_cuda_random_state(tmp_path):
    """On a GPU, dropout draws from the CUDA generators: a checkpoint saves them and a resumed
    run restores them, so its dropout masks are the uninterrupted run's (differences left:
    the GPU's own float nondeterminism, far below what other masks make)."""
    w, labels, _ = _two_modes(32)
    cfg = TrainConfig(steps=8, batch_size=8, warmup_steps=1, checkpoint_every=4, log_every=4)
    mcfg = DenoiserConfig(width=16, depth=1, heads=2, n_classes=0, dropout=0.3)
    args = (w, np.full(len(w), -1), [], mcfg, TOY_SCHED, cfg)
    full = train(*args, tmp_path / "full.pt", tmp_path / "full_ck.pt", seed=0, device="cuda")

    def kill(step, loss):
        if step == 6:  # after the checkpoint at 4
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(*args, tmp_path / "r.pt", tmp_path / "r_ck.pt", seed=0, device="cuda", on_step=kill)
    ck = torch.load(tmp_path / "r_ck.pt", weights_only=True)
    assert len(ck["cuda_rng"]) == torch.cuda.device_count()
    ran = []
    resumed = train(*args, tmp_path / "r.pt", tmp_path / "r_ck.pt", seed=0, device="cuda",
                    on_step=lambda step, loss: ran.append(step))
    assert ran[0] == 5
    for k, v in full["ema"].items():
        torch.testing.assert_close(resumed["ema"][k], v, rtol=0, atol=1e-5)


def test_training_rejects_bad_input(tmp_path):
    w, labels, _ = _two_modes(8)
    args = (["a", "b"], TOY_MODEL, TOY_SCHED, TOY_TRAIN, tmp_path / "m.pt", tmp_path / "c.pt", 0)
    with pytest.raises(ValueError, match=r"\(N, 675\)"):
        train(w[:, :600], labels, *args)
    bad = w.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        train(bad, labels, *args)


def test_bf16_training_learns_like_fp32_and_is_refused_without_native_bf16(tmp_path, monkeypatch):
    """diffusion.train.precision: bf16 trains the same toy to a loss close to fp32's (its own
    model: the arithmetic differs), deterministically; a device without native bf16 is refused
    before any step, naming the key. Native support is faked so every CPU runs the bf16 path."""
    train_mod = importlib.import_module("neumat.diffusion.train")  # the package exports `train`

    w, labels, _ = _two_modes(128)
    mcfg = DenoiserConfig(width=32, depth=1, heads=4, n_classes=2)
    cfg = TrainConfig(steps=60, batch_size=32, lr=2e-3, warmup_steps=5, checkpoint_every=1000,
                      log_every=20)
    bf = TrainConfig(**{**cfg.__dict__, "precision": "bf16"})
    real = train_mod.native_bf16
    monkeypatch.setattr(train_mod, "native_bf16", lambda dev: None)
    runs = [train(w, labels, ["a", "b"], mcfg, TOY_SCHED, c, tmp_path / f"{i}.pt",
                  tmp_path / f"{i}_ck.pt", seed=2, device="cpu")
            for i, c in enumerate((cfg, bf, bf))]
    f32, b1, b2 = ([l for _, l in r["history"]] for r in runs)
    assert b1 == b2  # deterministic
    assert b1 != f32  # bf16 arithmetic really ran
    assert b1[-1] < 0.5 * b1[0] and abs(b1[-1] - f32[-1]) < 0.2 * f32[-1]
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False)
    monkeypatch.setattr(train_mod, "native_bf16", real)
    with pytest.raises(ValueError, match=r"diffusion.train.precision: bf16 .*AVX512-BF16"):
        train(w, labels, ["a", "b"], mcfg, TOY_SCHED, bf, tmp_path / "x.pt", tmp_path / "x_ck.pt",
              seed=2, device="cpu")
    assert not (tmp_path / "x_ck.pt").exists()
    with pytest.raises(ValueError, match=r"one of \('fp32', 'bf16'\), got 'fp16'"):
        train(w, labels, ["a", "b"], mcfg, TOY_SCHED, TrainConfig(precision="fp16"),
              tmp_path / "y.pt", tmp_path / "y_ck.pt", seed=2, device="cpu")


def test_training_reads_the_loss_once_per_log_interval(tmp_path, monkeypatch):
    """No host sync per step (#19): neumat reads the loss (Tensor.item) only when it logs it, so
    a GPU is never made to wait each step. (On the CPU, torch's AdamW reads its step counters
    with .item(); on a GPU the fused AdamW keeps them on the device.)"""
    import sys

    w, labels, _ = _two_modes(32)
    cfg = TrainConfig(steps=20, batch_size=8, warmup_steps=2, checkpoint_every=100, log_every=10)
    calls = []
    item = torch.Tensor.item

    def counted(t):
        if "neumat" in sys._getframe(1).f_code.co_filename:
            calls.append(1)
        return item(t)

    monkeypatch.setattr(torch.Tensor, "item", counted)
    bundle = train(w, labels, ["a", "b"], DenoiserConfig(width=32, depth=1, heads=4, n_classes=2),
                   TOY_SCHED, cfg, tmp_path / "m.pt", tmp_path / "ck.pt", seed=0, device="cpu")
    assert [h[0] for h in bundle["history"]] == [10, 20]
    assert len(calls) == 2


def test_foreach_ema_equals_per_tensor_lerp():
    from neumat.diffusion.train import ema_update

    model, ema = _model(seed=0), _model(seed=1)
    want = [e.detach().clone().lerp_(p, 1 - min(0.999, 8 / 17))
            for e, p in zip(ema.parameters(), model.parameters())]
    ema_update(ema, model, step=7, decay=0.999)
    for e, w_ in zip(ema.parameters(), want):
        assert torch.equal(e, w_)


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="no CUDA device: the fused-AdamW / pinned-copy training path needs one")
def test_cuda_training_follows_the_cpu_loss_curve(tmp_path):
    w, labels, _ = _two_modes(64)
    cfg = TrainConfig(steps=40, batch_size=16, warmup_steps=5, log_every=10)
    mcfg = DenoiserConfig(width=32, depth=1, heads=4, n_classes=2)
    runs = [train(w, labels, ["a", "b"], mcfg, TOY_SCHED, cfg, tmp_path / f"{d}.pt",
                  tmp_path / f"{d}_ck.pt", seed=0, device=d)["history"] for d in ("cpu", "cuda")]
    np.testing.assert_allclose([h[1] for h in runs[0]], [h[1] for h in runs[1]], rtol=1e-3)


def test_compile_is_ignored_on_the_cpu_and_checked(tmp_path):
    """diffusion.train.compile is a GPU speed key: on the CPU the run is bit-identical, resumes
    across it (not in the fingerprint), and a mode torch does not have is refused by name."""
    w, labels, _ = _two_modes(32)
    mcfg = DenoiserConfig(width=16, depth=1, heads=2, n_classes=2)
    runs = [train(w, labels, ["a", "b"], mcfg, TOY_SCHED,
                  TrainConfig(steps=6, batch_size=8, warmup_steps=2, log_every=3, compile=c),
                  tmp_path / f"{c}.pt", tmp_path / f"{c}_ck.pt", seed=0, device="cpu")
            for c in ("none", "reduce-overhead")]
    assert runs[0]["history"] == runs[1]["history"]
    assert runs[0]["fingerprint"] == runs[1]["fingerprint"]
    assert all(torch.equal(runs[0]["ema"][k], runs[1]["ema"][k]) for k in runs[0]["ema"])
    with pytest.raises(ValueError, match="diffusion.train.compile must be one of"):
        train(w, labels, ["a", "b"], mcfg, TOY_SCHED, TrainConfig(steps=2, compile="fast"),
              tmp_path / "x.pt", tmp_path / "x_ck.pt", seed=0, device="cpu")


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="no CUDA device: torch.compile's CUDA graphs need one")
def test_compiled_cuda_training_follows_the_eager_loss_curve(tmp_path):
    w, labels, _ = _two_modes(64)
    mcfg = DenoiserConfig(width=32, depth=2, heads=4, n_classes=2)
    runs = [train(w, labels, ["a", "b"], mcfg, TOY_SCHED,
                  TrainConfig(steps=40, batch_size=16, warmup_steps=5, log_every=10, compile=c),
                  tmp_path / f"{c}.pt", tmp_path / f"{c}_ck.pt", seed=0, device="cuda")["history"]
            for c in ("none", "reduce-overhead")]
    np.testing.assert_allclose([h[1] for h in runs[0]], [h[1] for h in runs[1]], rtol=1e-3)


# ----------------------------------------------------------------------------- plausibility


def test_albedo_quadrature_integrates_cosine():
    _, w, _ = albedo_quadrature(n_theta_o=4, n_theta_h=64, n_phi_h=64)
    assert np.allclose(w.sum(1), np.pi, rtol=2e-3)  # integral of cos(theta_i) dw_i = pi


def _constant_brdf(values):
    """Weight vectors whose field is the constant BRDF `values` (B,) in every channel."""
    w = np.zeros((len(values), 675), np.float32)
    w[:, -3:] = np.log1p(np.asarray(values, np.float32))[:, None]
    return w


def test_lambertian_albedo_and_passivity():
    w = _constant_brdf([1 / np.pi, 0.5 / np.pi, 1.3 / np.pi])
    a = directional_albedo(w)
    assert np.allclose(a[0], 1.0, atol=1e-3) and np.allclose(a[1], 0.5, atol=1e-3)
    bad = np.zeros((1, 675), np.float32)
    bad[0, 0] = np.nan
    df = plausibility(np.concatenate([w, bad]), reference_max=0.2)
    assert df["passivity_violation"].tolist() == [False, False, True, True]
    assert df["nonfinite"].tolist() == [False, False, False, True]
    assert df["exploding"].tolist() == [False, False, False, True]  # NaN counts as exploding
    assert np.allclose(df["max_value"][:3], [1 / np.pi, 0.5 / np.pi, 1.3 / np.pi], rtol=1e-5)
    assert (df["negative_share"][:3] == 0).all()
    neg = _constant_brdf([0.1])
    neg[0, -3:] = -0.5  # exp(-0.5) - 1 < 0 everywhere: clamped to black
    assert plausibility(neg)["negative_share"][0] == 1.0


def test_plausibility_does_not_depend_on_the_block_of_materials():
    """The checks run 1-2 materials per NBRDF pass (cache-sized); any block gives the same
    table, up to float64 rounding in the albedo sums."""
    from neumat import nbrdf
    w = nbrdf.init_weights(7, torch.Generator().manual_seed(3)).numpy() * 2
    w[2, 4] = np.nan
    kw = dict(reference_max=1.0, n_angles=3000, albedo_kw=dict(n_theta_o=2, n_theta_h=16, n_phi_h=16))
    ref = plausibility(w, block=7, **kw)
    for block in (None, 1, 3):
        df = plausibility(w, block=block, **kw)
        assert df.drop(columns="max_albedo").equals(ref.drop(columns="max_albedo")), block
        np.testing.assert_allclose(df["max_albedo"], ref["max_albedo"], rtol=1e-12)
    assert ref["nonfinite"].tolist() == [False, False, True] + [False] * 4


# ----------------------------------------------------------------------------- dataset


def _manifest():
    import pandas as pd
    return pd.DataFrame({
        "id": range(8),
        "name": ["a", "b", "c", "a@grb", "b@grb", "mix0", "mix1", "c@grb"],
        "operation": ["original"] * 3 + ["permutation"] * 2 + ["interpolation"] * 2 + ["permutation"],
        "type": ["paint", "metal", "felt", "paint", "metal", "", "", "felt"],
        "split": ["train", "train", "test", "train", "train", "train", "train", "test"],
    })


def test_model_rows_labels_and_training_subset():
    from neumat.diffusion import dataset
    man = _manifest()
    assert dataset.training_rows(man, "ours").tolist() == [0, 1, 3, 4, 5, 6]
    assert dataset.training_rows(man, "merl100").tolist() == [0, 1]
    assert dataset.reference_rows(man).tolist() == [2, 7]
    # felt is a class (a held-out material has it) that no training material has
    assert dataset.training_types(man) == {"paint", "metal"}
    dataset.require_trained(["paint", ""], man, "--type")
    with pytest.raises(ValueError, match=r"^config diffusion.types asks for felt: no training "
                                         r"material has this type .*types it learnt: metal, paint$"):
        dataset.require_trained(["metal", "felt"], man, "config diffusion.types asks for")
    names = dataset.class_names(man["type"])
    assert names == ["felt", "metal", "paint"]
    assert dataset.labels(man["type"], names).tolist() == [2, 1, 0, 2, 1, -1, -1, 0]
    with pytest.raises(ValueError, match="not among"):
        dataset.labels(["wood"], names)
    with pytest.raises(ValueError, match="unknown diffusion model"):
        dataset.training_rows(man, "pca")
    sub = dataset.training_subset(man, seed=0)
    assert len(sub) == 2 and set(sub) <= {0, 1, 3, 4, 5, 6}
    assert (dataset.training_subset(man, seed=0) == sub).all()
    three = dataset.training_subset(man, seed=0, draws=3)  # 6 train rows: draws of 2, disjoint
    assert len(three) == 6 and len(set(three)) == 6 and set(three) <= {0, 1, 3, 4, 5, 6}
    # a draw does not depend on the draws after it (metrics.draws changed draw 0 before)
    two = dataset.training_subset(man, seed=0, draws=2)
    assert (three[:2] == two[:2]).all() and (three[2:4] == two[2:4]).all()
    assert (sub == two[:2]).all()


def test_keep_look_keeps_the_free_draw_where_the_step_moved_the_render():
    """diffusion.sample.keep_look: a sample keeps its free draw exactly where the renders of its
    two draws are less than `db` apart in PSNR; an unmoved sample keeps its stepped draw."""
    from neumat.diffusion.sample import keep_look
    from neumat.render import sphere
    rng = np.random.default_rng(0)
    stepped = rng.normal(0, 0.3, (3, nbrdf.N_PARAMS)).astype(np.float32)
    free = stepped.copy()
    free[1] = rng.normal(0, 0.3, nbrdf.N_PARAMS)  # the step moved sample 1 to another look
    r = [sphere.to_srgb(sphere.render_fields(w[1:2], 16, "relu")) for w in (stepped, free)]
    apart = float(-10 * torch.log10(((r[0] - r[1]) ** 2).mean().double()))
    w, kept = keep_look(stepped, free, apart + 0.5, 16)
    assert kept.tolist() == [False, True, False]
    np.testing.assert_array_equal(w, np.stack([stepped[0], free[1], stepped[2]]))
    w, kept = keep_look(stepped, free, apart - 0.5, 16)  # moved by less than the threshold
    assert not kept.any() and (w == stepped).all()
    with pytest.raises(ValueError, match="keep_look"):
        keep_look(stepped, free[:2], 25.0, 16)


def test_draw_keeping_look_is_the_step_draw_or_keep_look_of_both_draws():
    """sample_uncond's and `neumat sample`'s shared draw: without keep look (or without the
    clamp step) the sampler's draw; with it, keep_look of the stepped and the free draw of the
    same rows (a later block of rows via `offset` as the same rows of a larger draw)."""
    from neumat.diffusion.sample import draw_keeping_look, keep_look
    s = _tiny_sampler()
    cfg = {"steps": 6, "eta": 0.0, "batch_size": 8, "clip": None, "negative_step": 30.0}
    w, kept = draw_keeping_look(s, 6, 3, cfg)
    assert kept is None and np.array_equal(w, s.sample(6, 3, None, 6, 0.0, 1.0, 8, None, 30.0))
    stepped, free = (s.sample(6, 3, None, 6, 0.0, 1.0, 8, None, st) for st in (30.0, 0.0))
    w, kept = draw_keeping_look(s, 6, 3, cfg, look=60.0, look_resolution=16)
    want, want_kept = keep_look(stepped, free, 60.0, 16)
    assert kept.tolist() == want_kept.tolist() and kept.any() and np.array_equal(w, want)
    w0, k0 = draw_keeping_look(s, 6, 3, {**cfg, "negative_step": 0.0}, look=60.0,
                               look_resolution=16)
    assert k0 is None and np.array_equal(w0, free)
    tail, _ = draw_keeping_look(s, 2, 3, cfg, offset=4)
    np.testing.assert_allclose(tail, stepped[4:], rtol=0, atol=1e-5)


def test_prior_types_follow_the_training_split_and_untyped_is_the_null_class():
    """diffusion.sample.type_prior: types drawn as `ours` saw them in training (train rows
    only, '' for untyped rows), deterministic per seed; '' samples through the null class."""
    from neumat.diffusion import dataset
    man = _manifest()  # train-split types: paint metal paint metal '' ''
    t = dataset.prior_types(man, 6000, seed=1)
    assert t == dataset.prior_types(man, 6000, seed=1) and t != dataset.prior_types(man, 6000, seed=2)
    share = {k: t.count(k) / len(t) for k in set(t)}
    assert set(share) == {"paint", "metal", ""}  # felt lies in the test split only
    assert all(abs(v - 1 / 3) < 0.03 for v in share.values()), share
    cfg = DenoiserConfig(width=32, depth=1, heads=4, n_classes=2)
    s = Sampler({"model_cfg": cfg.to_dict(), "sched_cfg": ScheduleConfig(timesteps=50).to_dict(),
                 "class_names": ["metal", "paint"], "ema": _model(cfg).state_dict(),
                 "normalizer": Normalizer.fit(torch.randn(32, nbrdf.N_PARAMS)).state_dict()}, "cpu")
    assert s.labels_of(["paint", "", "metal"]).tolist() == [1, -1, 0]
    kw = dict(steps=5, guidance=1.0, negative_step=0.0)
    assert np.array_equal(s.sample(3, 7, ["", "", ""], **kw), s.sample(3, 7, None, **kw))
    assert not np.array_equal(s.sample(3, 7, ["paint"] * 3, **kw), s.sample(3, 7, None, **kw))
    with pytest.raises(ValueError, match="unknown material type"):
        s.labels_of(["wood"])


def test_nearest_finds_identical_rows():
    from neumat.diffusion import dataset
    b = torch.randn(20, 30)
    idx, dist = dataset.nearest(b[[3, 17, 5]] + 1e-4, b, chunk=2)
    assert idx.tolist() == [3, 17, 5] and np.allclose(dist, 1e-4, atol=1e-6)


# ----------------------------------------------------------------------------- clamp constraint


def _tiny_sampler(seed=0):
    """A random tiny model whose normaliser comes from random NBRDFs (about half their log-space
    outputs are negative, so the clamp constraint has work to do)."""
    w = nbrdf.init_weights(64, torch.Generator().manual_seed(seed))
    norm = Normalizer.fit(w)
    cfg = DenoiserConfig(width=32, depth=1, heads=4, n_classes=0)
    return Sampler({"model_cfg": cfg.to_dict(), "sched_cfg": ScheduleConfig(timesteps=50).to_dict(),
                    "class_names": [], "ema": _model(cfg, seed).state_dict(),
                    "normalizer": norm.state_dict()}, "cpu")


def test_negative_constraint_step_lowers_the_penalty():
    from neumat.diffusion.constraints import NegativeConstraint, negative_penalty
    s = _tiny_sampler()
    x0 = torch.randn(8, nbrdf.N_PARAMS, generator=torch.Generator().manual_seed(1))
    c = NegativeConstraint(s.norm, 0.5, seed=3, n_directions=512)
    pen = lambda z: negative_penalty(s.norm.decode(z), c.x)  # noqa: E731
    assert (pen(c(x0)) < pen(x0)).all()  # every sample moves down its own penalty
    assert torch.equal(NegativeConstraint(s.norm, 0.0, seed=3)(x0), x0)
    with pytest.raises(ValueError, match="negative_step"):
        NegativeConstraint(s.norm, -1.0, seed=3)


@pytest.mark.parametrize("eta", [0.0, 0.5])
def test_samples_do_not_depend_on_the_batch_size(eta):
    """diffusion.sample.batch_size is a memory knob: the same seed gives the same samples in
    batches of 8, 13 or all 20 at once (to float rounding of the batched model), at eta 0 and
    with step noise (eta > 0); one generator consumed batch by batch had moved rows past the
    first batch by more than this tolerance (schedule.RowNoise)."""
    from neumat.diffusion.sample import sample
    s = _tiny_sampler()
    kw = dict(steps=10, eta=eta, negative_step=0.0)
    one = s.sample(20, 5, guidance=1.0, batch_size=20, **kw)
    for b in (8, 13):
        np.testing.assert_allclose(s.sample(20, 5, guidance=1.0, batch_size=b, **kw), one,
                                   rtol=0, atol=1e-5)
        np.testing.assert_allclose(sample(s, 20, 5, batch_size=b, **kw), one, rtol=0, atol=1e-5)
    assert not np.allclose(s.sample(20, 6, guidance=1.0, batch_size=20, **kw), one, atol=1e-3)


def test_row_noise_blocks_are_independent_of_the_slicing():
    from neumat.diffusion.schedule import RowNoise
    r = RowNoise(7, 5)
    whole = r(0, 0, 150)
    assert whole.shape == (150, 5)
    assert torch.equal(torch.cat([r(0, 0, 10), r(0, 10, 100), r(0, 110, 40)]), whole)
    assert not torch.equal(r(1, 0, 150), whole)  # each stage its own noise
    assert abs(whole.mean()) < 0.2 and abs(whole.std() - 1) < 0.1


def test_temperature_scales_the_ddim_start_alone_and_spreads_the_samples():
    """diffusion.sample.temperature: stage 0 (x_T) is the unit draw times it, exactly, and the
    step noises are untouched; 1 is the draw as before the key; with eta 0 the samples are a
    function of x_T, so a wider start gives samples further apart (a narrower one, closer); a
    temperature <= 0 is
    refused with the key's name."""
    base, hot = RowNoise(7, 5), RowNoise(7, 5, 1.5)
    assert torch.equal(hot(0, 3, 70), 1.5 * base(0, 3, 70))
    assert torch.equal(hot(4, 3, 70), base(4, 3, 70))
    assert torch.equal(RowNoise(7, 5, 1.0)(0, 0, 9), base(0, 0, 9))
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match="diffusion.sample.temperature must be > 0"):
            RowNoise(7, 5, bad)
    s = _tiny_sampler()
    kw = dict(steps=10, guidance=1.0, negative_step=0.0)
    plain = s.sample(32, 5, **kw)
    assert np.array_equal(s.sample(32, 5, temperature=1.0, **kw), plain)
    warm = s.sample(32, 5, temperature=1.5, **kw)
    assert np.array_equal(s.sample(32, 5, temperature=1.5, **kw), warm)  # deterministic
    spread = lambda w: torch.pdist(s.norm.encode(torch.as_tensor(w))).mean()  # noqa: E731
    cold = s.sample(32, 5, temperature=0.5, **kw)
    assert spread(cold) < spread(plain) < spread(warm), (spread(cold), spread(plain), spread(warm))
    # the workflow's and the CLI's entry point reads the key from the settings
    from neumat.diffusion.sample import draw_keeping_look
    cfg = dict(steps=10, eta=0.0, batch_size=256, clip=None, negative_step=0.0)
    assert np.array_equal(draw_keeping_look(s, 32, 5, {**cfg, "temperature": 1.5})[0], warm)
    assert np.array_equal(draw_keeping_look(s, 32, 5, cfg)[0], plain)


def test_constrained_sampling_fewer_negative_bins_and_off_is_unchanged():
    s = _tiny_sampler()
    kw = dict(steps=10, guidance=1.0)
    plain = s.sample(16, 5, negative_step=0.0, **kw)
    z = s.diffusion.ddim_sample(lambda x, t: s.model(x, t, None), (16, nbrdf.N_PARAMS), 10,
                                noise=RowNoise(seed_for(5, "ddim"), nbrdf.N_PARAMS).batch(0, 16))  # no hook at all
    assert np.array_equal(s.norm.decode(z).numpy(), plain)
    on = s.sample(16, 5, negative_step=20.0, **kw)
    assert np.array_equal(s.sample(16, 5, negative_step=20.0, **kw), on)  # deterministic
    neg = lambda w: plausibility(w, n_angles=2000, albedo_kw=dict(  # noqa: E731
        n_theta_o=1, n_theta_h=4, n_phi_h=4))["negative_share"].mean()
    assert neg(on) < 0.8 * neg(plain), (neg(on), neg(plain))
    # the library entry point (conditions, CLI) takes the same key
    from neumat.diffusion.sample import sample
    assert np.array_equal(sample(s, 16, 5, steps=10, negative_step=20.0), on)


def test_clamp_refit_lifts_negative_bins_and_keeps_the_clamped_output():
    """Random NBRDFs (about half their log-space outputs below 0): the refit leaves almost no
    bin below -0.01 at directions it never saw, while the output the renderer sees, max(x, 0),
    moves by under 0.01 on average; deterministic; whole or in parts the
    same to float rounding; 0 steps returns the input; bad settings are refused by key."""
    from neumat.diffusion.constraints import constraint_directions
    from neumat.diffusion.refit import clamp_refit
    w = nbrdf.init_weights(16, torch.Generator().manual_seed(2)).numpy()
    kw = dict(seed=4, n_directions=1024)  # the default 4096 costs 4x: the same behaviour
    x = constraint_directions(99, 2000)  # not the refit's own directions
    raw = lambda v: nbrdf.forward_raw(torch.as_tensor(v), x)  # noqa: E731
    r = clamp_refit(w, 60, **kw)
    before, after = raw(w), raw(r)
    assert (before < -0.01).float().mean() > 0.25
    assert (after < -0.01).float().mean() < 0.005, (after < -0.01).float().mean()
    moved = (after.clamp_min(0) - before.clamp_min(0)).abs()
    assert moved.mean() < 0.01 and torch.quantile(moved.flatten(), 0.99) < 0.05, moved.max()
    part = clamp_refit(w[11:], 60, **kw)
    assert np.array_equal(clamp_refit(w[11:], 60, **kw), part)  # deterministic
    assert np.abs(part - r[11:]).max() < 1e-5
    assert np.array_equal(clamp_refit(w, 0, **kw), w)
    with pytest.raises(ValueError, match="refit_steps"):
        clamp_refit(w, -1, **kw)
    # the samplers take it as a post-step
    s = _tiny_sampler()
    plain = s.sample(8, 5, steps=5, guidance=1.0, negative_step=0.0)
    assert np.array_equal(s.sample(8, 5, steps=5, guidance=1.0, negative_step=0.0, refit_steps=20),
                          clamp_refit(plain, 20, seed=5))


def test_clamp_refit_adam_is_torch_adam_to_the_bit():
    """The refit's own Adam step (torch.optim's first optimizer imports torch._dynamo) is
    torch.optim.Adam's CPU path, bit for bit."""
    from neumat.diffusion.constraints import constraint_directions
    from neumat.diffusion.refit import _refit_block
    w0 = nbrdf.init_weights(4, torch.Generator().manual_seed(1))
    x = constraint_directions(3, 256)
    ours = _refit_block(w0, x, 10, 0.002, 10.0, 3e-3, "relu")
    target = nbrdf.forward_raw(w0, x).clamp_min(0.002)
    w = w0.clone().requires_grad_(True)
    opt = torch.optim.Adam([w], lr=3e-3)
    for _ in range(10):
        e = nbrdf.forward_raw(w, x) - target
        loss = (e * e * torch.where(e < 0, 10.0, 1.0)).flatten(1).mean(1).sum()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    assert torch.equal(ours, w.detach())


def test_render_guidance_pulls_each_sample_toward_its_own_image():
    """Known answer: at the material that rendered the target the penalty is 0; one step
    lowers every sample's own image error; sampling with it gets closer to the targets, each
    sample to its own; step 0 is the plain sampler; bad targets are refused by name."""
    from neumat.diffusion.constraints import RenderConstraint
    from neumat.diffusion.sample import sample
    from neumat.render import sphere
    s = _tiny_sampler()
    truth = torch.as_tensor(_constant_brdf([0.02, 0.08, 0.2, 0.5]))  # Lambertian spheres
    y = sphere.render_fields(truth, 16)
    c = RenderConstraint(s.norm, y, 0.5)
    assert torch.allclose(c.penalty(truth, c.y), torch.zeros(4), atol=1e-5)
    x0 = torch.randn(4, nbrdf.N_PARAMS, generator=torch.Generator().manual_seed(1))
    pen = lambda z: c.penalty(s.norm.decode(z), c.y)  # noqa: E731
    assert (pen(c(x0)) < pen(x0)).all()
    tgt = y.repeat_interleave(4, 0)  # 4 samples per target image
    # the clamp-aware step keeps samples off the all-clamped (black, gradient-free) region
    kw = dict(steps=10, negative_step=20.0)
    plain, guided = (sample(s, 16, 5, render_targets=tgt, render_step=r, **kw) for r in (0, 20.0))
    assert np.array_equal(plain, sample(s, 16, 5, **kw))
    srgb = lambda w: sphere.to_srgb(sphere.render_fields(w, 16))  # noqa: E731
    err = lambda w, t: ((srgb(w) - sphere.to_srgb(t)) ** 2).flatten(1).mean(1)  # noqa: E731
    # a random toy denoiser fights the step (larger steps overshoot here); what must hold is
    # that the error falls and that each sample went to its own image, not the others'
    assert err(guided, tgt).mean() < 0.85 * err(plain, tgt).mean()
    own = lambda w: (err(w, tgt) < err(w, tgt.roll(4, 0))).float().mean()  # noqa: E731
    assert own(guided) > 0.9 and own(plain) < 0.75
    with pytest.raises(ValueError, match="render targets must be"):
        RenderConstraint(s.norm, y[..., 0], 0.5)
    with pytest.raises(ValueError, match="render_step must be >= 0"):
        RenderConstraint(s.norm, y, -1.0)
    with pytest.raises(ValueError, match="4 render targets for 16 samples"):
        sample(s, 16, 5, render_targets=y, render_step=0.3, **kw)


def test_category_guidance_composes_after_the_clamp_step():
    from neumat.diffusion.constraints import (CategoryConstraint, NegativeConstraint,
                                              category_penalty, constraint_for)
    s = _tiny_sampler()
    assert constraint_for(s, 0.0, 5, category="metallic", category_step=0.0) is None
    assert isinstance(constraint_for(s, 0.0, 5, category="metallic", category_step=2.0),
                      CategoryConstraint)
    x0 = torch.randn(8, nbrdf.N_PARAMS, generator=torch.Generator().manual_seed(1))
    both = constraint_for(s, 20.0, 5, category="metallic", category_step=2.0)
    neg, cat = NegativeConstraint(s.norm, 20.0, 5), CategoryConstraint(s.norm, "metallic", 2.0, 5)
    assert torch.equal(both(x0), cat(neg(x0)))  # in that order
    assert not torch.equal(cat.x, neg.x)  # its own directions
    kw = dict(steps=10, guidance=1.0, negative_step=20.0)
    plain = s.sample(16, 5, **kw)
    guided = s.sample(16, 5, category="metallic", category_step=5.0, **kw)
    x = cat.x
    pen = lambda w: category_penalty(torch.as_tensor(w), x, "metallic")  # noqa: E731
    assert (pen(guided) < pen(plain)).all() and pen(guided).mean() < 0.8 * pen(plain).mean()
    from neumat.diffusion.sample import sample
    assert np.array_equal(sample(s, 16, 5, steps=10, negative_step=20.0, category="metallic",
                                 category_step=5.0), guided)


def test_particle_guidance_pushes_a_batchs_looks_apart():
    """diffusion.sample.particle_step: one step moves each sample away from the others' looks
    (the batch's mean pairwise render distance grows, its potential falls); deterministic; 0,
    or a batch of one, is the identity; composed after the clamp step; a negative step is
    refused with the key's name."""
    from neumat.diffusion.constraints import NegativeConstraint, ParticleGuidance, constraint_for
    s = _tiny_sampler()
    x0 = torch.randn(8, nbrdf.N_PARAMS, generator=torch.Generator().manual_seed(1))
    pg = ParticleGuidance(s.norm, 0.5)
    f = lambda z: pg.features(s.norm.decode(z))  # noqa: E731
    spread = lambda z: torch.pdist(f(z)).mean()  # noqa: E731
    moved = pg(x0)
    assert spread(moved) > 1.02 * spread(x0), (spread(moved), spread(x0))
    assert pg.potential(f(moved)) < pg.potential(f(x0))
    assert torch.equal(pg(x0), moved)
    assert torch.equal(ParticleGuidance(s.norm, 0.0)(x0), x0)
    assert torch.equal(pg(x0[:1]), x0[:1])
    both = constraint_for(s, 20.0, 5, particle_step=0.5)
    assert torch.equal(both(x0), pg(NegativeConstraint(s.norm, 20.0, 5)(x0)))
    assert constraint_for(s, 0.0, 5, particle_step=0.0) is None
    with pytest.raises(ValueError, match="particle_step must be >= 0"):
        ParticleGuidance(s.norm, -1.0)
    kw = dict(steps=10, guidance=1.0, negative_step=0.0)
    on = s.sample(16, 5, particle_step=0.05, **kw)
    assert np.array_equal(s.sample(16, 5, particle_step=0.05, **kw), on)
    assert not np.array_equal(s.sample(16, 5, **kw), on)


def test_particle_guidance_view_ranks_pairs_as_the_metric_render():
    """Particle guidance's cheap render (PARTICLE_VIEW: a coarse albedo quadrature) keeps the
    metric render's pairwise distances: correlation >= 0.99 over random NBRDFs."""
    from neumat.diffusion.constraints import ParticleGuidance
    from neumat.render import sphere
    w = nbrdf.init_weights(48, torch.Generator().manual_seed(2))
    pg = ParticleGuidance(None, 0.1)
    full = sphere.to_srgb(sphere.render_fields(w, 16)).flatten(1)
    d_cheap, d_full = torch.pdist(pg.features(w)), torch.pdist(full)
    assert np.corrcoef(d_cheap.numpy(), d_full.numpy())[0, 1] >= 0.99


def test_channel_permutation_permutes_the_fields_output():
    """diffusion.sample.rgb_permute: output channel c of a permuted field is channel perm[c] of
    the original at every input (to float32 rounding: the batched matmul may sum a row in
    another order), as augment.permute orders a table's channels; the draw is a
    pure function of the seed, and every order occurs."""
    from neumat.augment import PERMS, permute
    from neumat.diffusion import symmetry
    rng = np.random.default_rng(3)
    w = rng.normal(size=(6, nbrdf.N_PARAMS)).astype(np.float32)
    x = torch.as_tensor(rng.normal(size=(50, 6)), dtype=torch.float32)
    perms = symmetry.PERMUTATIONS
    got = nbrdf.forward_raw(torch.as_tensor(symmetry.permute_channels(w, perms)), x)
    want = nbrdf.forward_raw(torch.as_tensor(w), x)
    for i, p in enumerate(PERMS):  # the same order as augment's names, identity first
        assert list(perms[i]) == ["rgb".index(ch) for ch in p]
        np.testing.assert_allclose(got[i].T.numpy(), permute(want[i].T.numpy(), p), rtol=1e-6)
    a, b = symmetry.random_channels(w, 11), symmetry.random_channels(w, 11)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a[:, :609], w[:, :609])  # only W3 and b3 move
    many = symmetry.random_channels(np.repeat(w[:1], 600, 0), 5)[:, -3:]
    assert len(np.unique(many.round(6), axis=0)) == 6
    with pytest.raises(ValueError, match=r"\(6, 3\)"):
        symmetry.permute_channels(w, perms[:2])


# ----------------------------------------------------------------------------- field term


def _fields(n=4, seed=0):
    return torch.randn(n, nbrdf.N_PARAMS, generator=torch.Generator().manual_seed(seed)) * 0.3


def test_field_log_map_is_odd_and_resolves_values_near_zero():
    from neumat.diffusion.field_loss import log_map
    f = torch.tensor([0.0, 3e-3, -3e-3, 0.3])
    assert torch.allclose(log_map(f, 3e-3), torch.tensor([0.0, math.log(2), -math.log(2),
                                                          math.log(101)]))


def test_field_error_counts_what_the_render_sees():
    """Zero for the same weights; a bin clamped (black) in both costs nothing however deep the
    prediction goes; a prediction below zero where the clean field is positive costs the full
    log-mapped value."""
    from neumat.diffusion.field_loss import field_error, log_map
    w = _fields()
    x = torch.rand(64, 6)
    assert torch.equal(field_error(w, w, x, 3e-3), torch.zeros(4))
    # shift the output layer's bias: every raw value moves by the same amount, per channel
    b3 = slice(nbrdf.N_PARAMS - 3, nbrdf.N_PARAMS)
    up, down = w.clone(), w.clone()
    up[:, b3] += 50.0   # every bin of the clean field positive...
    down[:, b3] -= 50.0  # ...and every bin of this one clamped
    f_up = torch.expm1(nbrdf.forward_raw(up, x))
    err = field_error(down, up, x, 3e-3)
    want = ((log_map(torch.expm1(nbrdf.forward_raw(down, x)), 3e-3) - log_map(f_up, 3e-3)) ** 2)
    assert torch.allclose(err, want.flatten(1).mean(1))
    deeper = w.clone()
    deeper[:, b3] -= 100.0
    assert torch.equal(field_error(deeper, down, x, 3e-3), torch.zeros(4))  # both black


def test_field_term_trains_resumes_and_keeps_old_fingerprints(tmp_path):
    """field_loss > 0 changes the training; with it at 0 the other field keys change neither
    the fingerprint (checkpoints of before the keys resume) nor the run."""
    from dataclasses import replace

    from neumat.diffusion.train import fingerprint
    w, labels, _ = _two_modes(32)
    mcfg = DenoiserConfig(width=16, depth=1, heads=2, n_classes=2)
    cfg = TrainConfig(steps=6, batch_size=8, warmup_steps=1, checkpoint_every=3, log_every=3)
    assert (fingerprint(w, labels, mcfg, cfg, seed=1)
            == fingerprint(w, labels, mcfg, replace(cfg, field_eps=1.0, field_bins=7), seed=1))
    on = replace(cfg, field_loss=0.5, field_bins=64)
    assert fingerprint(w, labels, mcfg, on, seed=1) != fingerprint(w, labels, mcfg, cfg, seed=1)
    args = (w, labels, ["a", "b"], mcfg, TOY_SCHED)
    plain = train(*args, cfg, tmp_path / "p.pt", tmp_path / "p_ck.pt", seed=1, device="cpu")
    full = train(*args, on, tmp_path / "f.pt", tmp_path / "f_ck.pt", seed=1, device="cpu")
    assert full["history"][0][1] > plain["history"][0][1]  # the term adds to the loss

    def kill(step, loss):
        if step == 4:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(*args, on, tmp_path / "r.pt", tmp_path / "r_ck.pt", seed=1, device="cpu",
              on_step=kill)
    resumed = train(*args, on, tmp_path / "r.pt", tmp_path / "r_ck.pt", seed=1, device="cpu")
    assert resumed["history"] == full["history"]
    assert all(torch.equal(v, resumed["ema"][k]) for k, v in full["ema"].items())
    with pytest.raises(ValueError, match="field_eps > 0"):
        train(*args, replace(on, field_eps=0.0), tmp_path / "e.pt", tmp_path / "e_ck.pt", seed=1,
              device="cpu")


def test_field_term_weight_is_alpha_bar_to_the_power():
    from neumat.diffusion.field_loss import FieldLoss
    norm = Normalizer(torch.zeros(nbrdf.N_PARAMS), torch.ones(nbrdf.N_PARAMS))
    x0, x0_hat = _fields(2, seed=1), _fields(2, seed=2)
    ab = torch.tensor([[0.5], [0.5]])
    terms = [FieldLoss(norm, 0.1, 3e-3, 256, power=p)(x0_hat, x0, ab, torch.Generator().manual_seed(0))
             for p in (0.0, 1.0, 4.0)]
    assert terms[0] > 0
    assert torch.allclose(torch.stack(terms[1:]), terms[0] * torch.tensor([0.5, 0.5 ** 4]))
    with pytest.raises(ValueError, match="field_power >= 0"):
        FieldLoss(norm, 0.1, 3e-3, 256, power=-1.0)
