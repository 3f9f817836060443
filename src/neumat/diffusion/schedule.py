"""DDPM noise schedules, the training loss, and a DDIM sampler with classifier-free guidance.

Conventions (Ho et al. 2020; Song et al. 2021): timesteps t = 0..T-1, alpha_bar[t] =
prod_{s<=t} (1 - beta_s), x_t = sqrt(alpha_bar[t]) x0 + sqrt(1 - alpha_bar[t]) eps.
The denoiser predicts x0, eps or v = sqrt(alpha_bar) eps - sqrt(1 - alpha_bar) x0 (`prediction`;
Salimans & Ho 2022); x0 and eps are derived from it and x_t. v is x0 prediction with EDM's skip
connection for unit-variance data (Karras et al. 2022: x0 = sqrt(ab) x_t - sqrt(1 - ab) v): at low
noise the network adds a small correction to x_t instead of rebuilding x0, and its loss,
|x0 error|^2 / (1 - ab), weights the low-noise end that decides the fine detail.

`loss` picks where the squared error is measured: on the prediction target itself, or on the x0
it implies (`loss: x0`). v with the x0 loss keeps the skip connection, so the low-noise x0 error
is sqrt(1 - ab) times the network's and has no floor, while every noise level keeps the weight
that x0 training gives it. On the realistic run it removed the floor but lost Table 2's image
rows as v does (docs/stages.md, "x0 prediction"), so the skip connection, not the weighting, costs them.

DDIM (Song et al. 2021, eq. 12) on a sub-sequence tau_1 > ... > tau_S of timesteps:
  x_prev = sqrt(ab_prev) x0_hat + sqrt(1 - ab_prev - sigma^2) eps_hat + sigma z,
  sigma  = eta sqrt((1 - ab_prev) / (1 - ab_t)) sqrt(1 - ab_t / ab_prev),
with ab_prev = 1 after the last step (the output is x0_hat). eta = 0: deterministic DDIM;
eta = 1 on the full sequence: ancestral DDPM.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import torch

from neumat.device import to_device

PREDICTIONS = ("x0", "eps", "v")
LOSSES = ("prediction", "x0")
SCHEDULES = ("cosine", "linear")


@dataclass
class ScheduleConfig:
    timesteps: int = 1000
    kind: str = "cosine"
    beta_start: float = 1e-4  # linear schedule only
    beta_end: float = 2e-2
    prediction: str = "x0"
    loss: str = "prediction"  # squared error on the prediction target, or on the implied x0

    def to_dict(self):
        return asdict(self)


def make_betas(cfg: ScheduleConfig) -> torch.Tensor:
    if cfg.kind == "linear":
        return torch.linspace(cfg.beta_start, cfg.beta_end, cfg.timesteps, dtype=torch.float64)
    if cfg.kind == "cosine":  # Nichol & Dhariwal 2021, s = 0.008, betas clipped at 0.999
        s, T = 0.008, cfg.timesteps
        f = torch.cos((torch.arange(T + 1, dtype=torch.float64) / T + s) / (1 + s) * math.pi / 2) ** 2
        return (1 - f[1:] / f[:-1]).clamp(max=0.999)
    raise ValueError(f"diffusion.schedule.kind: unknown schedule {cfg.kind!r}; choose from {SCHEDULES}")


def check_pairing(prediction: str, loss: str) -> None:
    """Refuse prediction eps with an x0 loss (also at DAG time, workflow/rules/diffusion.smk):
    x0 = (x_t - sqrt(1 - ab) eps) / sqrt(ab), so the x0 error weights each step by
    (1 - ab) / ab, 99.8 % of the total on the last step of the cosine schedule."""
    if prediction == "eps" and loss == "x0":
        raise ValueError("diffusion.schedule.prediction: eps with diffusion.schedule.loss: x0 "
                         "weights the loss by (1 - alpha_bar) / alpha_bar, almost all of it on "
                         "the last timestep; use loss: prediction, or prediction: x0 or v")


class Diffusion:
    """Schedule tensors + forward process, loss and DDIM sampling for one ScheduleConfig."""

    def __init__(self, cfg: ScheduleConfig):
        if cfg.prediction not in PREDICTIONS:
            raise ValueError(f"diffusion.schedule.prediction: {cfg.prediction!r} is not one of "
                             f"{PREDICTIONS}")
        if cfg.loss not in LOSSES:
            raise ValueError(f"diffusion.schedule.loss: {cfg.loss!r} is not one of {LOSSES}")
        if cfg.timesteps < 1:
            raise ValueError("diffusion.schedule.timesteps must be >= 1")
        check_pairing(cfg.prediction, cfg.loss)
        self.cfg = cfg
        self.T = cfg.timesteps
        self.betas = make_betas(cfg)
        self.alpha_bar = torch.cumprod(1 - self.betas, 0)  # float64, (T,)

    def _ab(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return self.alpha_bar.to(like.device)[t].to(like.dtype)[:, None]

    def q_sample(self, x0, t, noise):
        ab = self._ab(t, x0)
        return ab.sqrt() * x0 + (1 - ab).sqrt() * noise

    def split(self, out, x_t, ab):
        """Model output -> (x0_hat, eps_hat) for x_t at cumulative alpha ab (B, 1)."""
        if self.cfg.prediction == "x0":
            return out, (x_t - ab.sqrt() * out) / (1 - ab).sqrt()
        if self.cfg.prediction == "v":
            return ab.sqrt() * x_t - (1 - ab).sqrt() * out, (1 - ab).sqrt() * x_t + ab.sqrt() * out
        return (x_t - (1 - ab).sqrt() * out) / ab.sqrt(), out

    def loss(self, model, x0, cond=None, drop=None, generator=None, extra=None):
        """Mean squared error on the prediction target at uniformly drawn timesteps, plus
        `extra(x0_hat, x0, alpha_bar, generator)` if given (`neumat.diffusion.field_loss`).

        All randomness comes from `generator` (CPU), so training is reproducible and resumable."""
        b = x0.shape[0]
        t = to_device(torch.randint(0, self.T, (b,), generator=generator), x0.device)
        noise = to_device(torch.randn(x0.shape, generator=generator), x0.device, x0.dtype)
        x_t = self.q_sample(x0, t, noise)
        ab = self._ab(t, x0)
        out = model(x_t, t, cond, drop)
        if self.cfg.loss == "x0":
            loss = torch.mean((self.split(out, x_t, ab)[0] - x0) ** 2)
        else:
            if self.cfg.prediction == "v":
                target = ab.sqrt() * noise - (1 - ab).sqrt() * x0
            else:
                target = x0 if self.cfg.prediction == "x0" else noise
            loss = torch.mean((out - target) ** 2)
        if extra is not None:
            loss = loss + extra(self.split(out, x_t, ab)[0], x0, ab, generator)
        return loss

    def timesteps_for(self, steps: int) -> list[int]:
        """Evenly spaced DDIM timesteps, descending, always ending at t = 0."""
        if not 1 <= steps <= self.T:
            raise ValueError(f"diffusion sampling steps must be in [1, {self.T}], got {steps}")
        ts = torch.linspace(self.T - 1, 0, steps).round().long().tolist()
        return list(dict.fromkeys(ts))  # rounding could repeat a step for steps close to T

    @torch.no_grad()
    def ddim_sample(self, predict: Callable, shape, steps: int = 50, eta: float = 0.0,
                    generator: torch.Generator | None = None, device="cpu",
                    x_T: torch.Tensor | None = None, clip: float | None = None,
                    constrain: Callable | None = None, x0_start: torch.Tensor | None = None,
                    strength: float = 1.0, noise: Callable | None = None) -> torch.Tensor:
        """Sample with `predict(x_t, t_batch) -> model output` (already guided).

        `constrain(x0_hat) -> x0_hat'` (e.g. `neumat.diffusion.constraints.NegativeConstraint`)
        edits each predicted x0 before the DDIM update; eps_hat is kept from the model, so the
        edit moves x_prev by sqrt(ab_prev) times the edit and the next prediction sees it.

        `x0_start` (SDEdit, Meng et al. 2022): start from x0_start noised to t_s = strength (T - 1)
        instead of pure noise, and run the DDIM steps below t_s: strength 1 is ordinary
        sampling, small strengths stay near x0_start.

        `noise(k)` (e.g. a `RowNoise` for a batch's rows), if given, supplies the Gaussian noise
        in place of `generator`: k = 0 for x_T, k = i + 1 for step i's (eta > 0)."""
        def draw(k):
            return noise(k) if noise is not None else torch.randn(shape, generator=generator)

        x_T = draw(0) if x_T is None else x_T.clone()
        ts = self.timesteps_for(steps)
        if x0_start is not None and strength < 1.0:
            if not 0.0 < strength <= 1.0:
                raise ValueError(f"strength must be in (0, 1], got {strength}")
            t_s = int(round(strength * (self.T - 1)))
            ts = [t_s] + [t for t in ts if t < t_s]
            ab = self.alpha_bar[t_s].to(x_T.dtype)
            x_T = ab.sqrt() * x0_start.to(x_T) + (1 - ab).sqrt() * x_T
        x = x_T.to(device)
        for i, t in enumerate(ts):
            ab = self.alpha_bar[t].item()
            ab_prev = self.alpha_bar[ts[i + 1]].item() if i + 1 < len(ts) else 1.0
            tb = torch.full((shape[0],), t, device=device, dtype=torch.long)
            ab_t = torch.full((shape[0], 1), ab, device=device, dtype=x.dtype)
            x0, eps = self.split(predict(x, tb), x, ab_t)
            if clip is not None:  # keep x0 inside the data range; re-derive eps consistently
                x0 = x0.clamp(-clip, clip)
                eps = (x - math.sqrt(ab) * x0) / math.sqrt(1 - ab)
            if constrain is not None:
                x0 = constrain(x0)
            sigma = eta * math.sqrt((1 - ab_prev) / (1 - ab) * (1 - ab / ab_prev))
            x = math.sqrt(ab_prev) * x0 + math.sqrt(max(1 - ab_prev - sigma ** 2, 0.0)) * eps
            if sigma > 0:
                x = x + sigma * draw(i + 1).to(device, x.dtype)
        return x


class RowNoise:
    """Gaussian noise of sample rows that does not depend on how the rows are batched: stage k
    (0 = x_T, i + 1 = DDIM step i) of rows s ... s + b - 1, each block of CHUNK rows from its own
    stream of `seed`. One generator consumed batch by batch made diffusion.sample.batch_size
    change the samples: torch's CPU randn fills in blocks of 16, so 8 + 12 rows are not the
    first 20 (tests/test_diffusion.py samples in batches of 8, 13 and 20).

    `temperature` scales stage 0, the DDIM start x_T (diffusion.sample.temperature): with
    eta 0 the sampler is deterministic in x_T, so a wider start spreads the samples."""
    CHUNK = 64

    def __init__(self, seed: int, dim: int, temperature: float = 1.0):
        if not temperature > 0:
            raise ValueError(f"diffusion.sample.temperature must be > 0, got {temperature}")
        self.seed, self.dim, self.temperature = int(seed), int(dim), float(temperature)

    def __call__(self, k: int, s: int, b: int) -> torch.Tensor:
        c0, c1 = s // self.CHUNK, (s + b - 1) // self.CHUNK + 1
        blocks = [torch.randn((self.CHUNK, self.dim), generator=torch.Generator().manual_seed(
            int(np.random.SeedSequence(self.seed, spawn_key=(k, c)).generate_state(1)[0])))
            for c in range(c0, c1)]
        z = torch.cat(blocks)[s - c0 * self.CHUNK:s - c0 * self.CHUNK + b]
        return z * self.temperature if k == 0 and self.temperature != 1.0 else z

    def batch(self, s: int, b: int) -> Callable:
        """`ddim_sample`'s `noise` for the batch of rows s ... s + b - 1."""
        return lambda k: self(k, s, b)


def guided(model, cond: dict | None, scale: float) -> Callable:
    """Classifier-free guidance (Ho & Salimans 2022): out = u + scale (c - u), with u the
    null-condition output. scale = 1: conditional model alone; 0: unconditional.

    Both passes run as one batch. With no condition, the model is simply run unconditionally."""
    if not cond or scale == 1.0:
        return lambda x, t: model(x, t, cond or None)
    if scale == 0.0:
        return lambda x, t: model(x, t, None)

    def predict(x, t):
        b = x.shape[0]
        both = {k: torch.cat([v, v]) for k, v in cond.items()}
        drop = {k: torch.cat([torch.zeros(b, dtype=torch.bool, device=x.device),
                              torch.ones(b, dtype=torch.bool, device=x.device)]) for k in cond}
        out = model(torch.cat([x, x]), torch.cat([t, t]), both, drop)
        c, u = out[:b], out[b:]
        return u + scale * (c - u)

    return predict
