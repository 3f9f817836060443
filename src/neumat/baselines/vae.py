"""VAE baselines of Table 2 (M3ashy §4.3), sampled from the prior N(0, I).

* VAE-N: a VAE over NeuMERL weight vectors (N, 675), standardised per entry; MLP encoder and
  decoder; loss = MSE of the standardised weights + beta KL.
* VAE-A: "Gokbudak et al. extended with a VAE". The HyperBRDF set encoder (Gokbudak et al.
  2023; github faziletgokbudak/Hyper-neural-materials) reads a set of BRDF samples of one
  material - 6-D [h, d] Cartesian input plus the RGB value, 9-D - through a per-sample MLP
  9 -> 128 -> 128 -> 128 and a mean over the set; two heads give the latent's mean and log
  variance. A hypernetwork (one head per target tensor, latent -> 128 -> 128 -> numel, as
  HyperBRDF) outputs an NBRDF with this project's 6 -> 21 -> 21 -> 3 layout (675 weights), so
  its samples are scored exactly like the other fields. Trained on AugMERL tables with the
  NBRDF loss (paper eq. 2, |log(1 + f cos θi) - log(1 + f̂ cos θi)|) + beta KL.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from neumat import nbrdf
from neumat.io import modelfile
from neumat.io.atomic import save_torch
from neumat.seeds import seed_for


def mlp(sizes, last_act=False) -> nn.Sequential:
    layers = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2 or last_act:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def kl_normal(mu, logvar) -> torch.Tensor:
    """KL(N(mu, exp(logvar)) || N(0, I)), mean over the batch, sum over latent dims."""
    return 0.5 * (mu.pow(2) + logvar.exp() - 1 - logvar).sum(-1).mean()


def reparameterise(mu, logvar, generator=None):
    eps = torch.randn(mu.shape, generator=generator, dtype=mu.dtype, device=mu.device)
    return mu + eps * (0.5 * logvar).exp()


# ----------------------------------------------------------------------------- VAE-N


class WeightVAE(nn.Module):
    """VAE over standardised NBRDF weight vectors."""

    def __init__(self, latent: int = 32, hidden: int = 256, mean=None, std=None):
        super().__init__()
        d = nbrdf.N_PARAMS
        self.latent = latent
        self.enc = mlp([d, hidden, hidden], last_act=True)
        self.mu, self.logvar = nn.Linear(hidden, latent), nn.Linear(hidden, latent)
        self.dec = mlp([latent, hidden, hidden, d])
        self.register_buffer("w_mean", torch.zeros(d) if mean is None else torch.as_tensor(mean).float())
        self.register_buffer("w_std", torch.ones(d) if std is None else torch.as_tensor(std).float())

    def loss(self, w, beta: float, generator=None) -> tuple[torch.Tensor, dict]:
        x = (w - self.w_mean) / self.w_std
        h = self.enc(x)
        mu, logvar = self.mu(h), self.logvar(h).clamp(-10, 10)
        rec = (self.dec(reparameterise(mu, logvar, generator)) - x).pow(2).mean()
        kl = kl_normal(mu, logvar)
        return rec + beta * kl / x.shape[1], {"rec": rec.item(), "kl": kl.item()}

    @torch.no_grad()
    def decode(self, z) -> torch.Tensor:
        return self.dec(z) * self.w_std + self.w_mean


# ----------------------------------------------------------------------------- VAE-A


class SetEncoder(nn.Module):
    """HyperBRDF set encoder (9 -> 128 -> 128 -> 128, mean over samples) with VAE heads."""

    def __init__(self, latent: int = 40, hidden: int = 128):
        super().__init__()
        self.net = mlp([9, hidden, hidden, hidden], last_act=True)
        self.mu, self.logvar = nn.Linear(hidden, latent), nn.Linear(hidden, latent)

    def forward(self, x6, rgb):
        """x6 (B, S, 6) or (S, 6), rgb (B, S, 3) physical BRDF -> (mu, logvar) (B, latent)."""
        if x6.dim() == 2:
            x6 = x6.expand(rgb.shape[0], -1, -1)
        h = self.net(torch.cat([x6, torch.log1p(rgb.clamp_min(0))], -1)).mean(1)
        return self.mu(h), self.logvar(h).clamp(-10, 10)


class HyperNet(nn.Module):
    """latent -> NBRDF weights (B, 675): one MLP head per target tensor (HyperBRDF).

    The last layer starts at zero with bias = a standard NBRDF initialisation, so training
    starts from a working field and the latent steers it."""

    def __init__(self, latent: int = 40, hidden: int = 128, seed: int = 0):
        super().__init__()
        init = nbrdf.init_weights(1, torch.Generator().manual_seed(seed))[0]
        self.heads, k = nn.ModuleList(), 0
        for shape in nbrdf.PARAM_SHAPES:
            n = math.prod(shape)
            head = mlp([latent, hidden, hidden, n])
            nn.init.zeros_(head[-1].weight)
            with torch.no_grad():
                head[-1].bias.copy_(init[k:k + n])
            self.heads.append(head)
            k += n

    def forward(self, z) -> torch.Tensor:
        return torch.cat([h(z) for h in self.heads], -1)


class SetVAE(nn.Module):
    def __init__(self, latent: int = 40, hidden: int = 128, seed: int = 0):
        super().__init__()
        self.latent = latent
        self.encoder = SetEncoder(latent, hidden)
        self.hyper = HyperNet(latent, hidden, seed)

    def loss(self, x6_ctx, rgb_ctx, x6_q, rgb_q, cos_q, beta: float, activation="relu",
             generator=None) -> tuple[torch.Tensor, dict]:
        """Context samples -> latent -> NBRDF; NBRDF loss at the query samples + beta KL.
        x6_* (S, 6) shared by the batch, rgb_* (B, S, 3), cos_q (Q,) cos θi at the queries."""
        mu, logvar = self.encoder(x6_ctx, rgb_ctx)
        w = self.hyper(reparameterise(mu, logvar, generator))
        pred = nbrdf.forward(w, x6_q, activation)
        c = cos_q[None, :, None]
        rec = (torch.log1p(pred * c) - torch.log1p(rgb_q.clamp_min(0) * c)).abs().mean()
        kl = kl_normal(mu, logvar)
        return rec + beta * kl / nbrdf.N_PARAMS, {"rec": rec.item(), "kl": kl.item()}

    @torch.no_grad()
    def decode(self, z) -> torch.Tensor:
        return self.hyper(z)


# ----------------------------------------------------------------------------- shared


def prior_samples(model, n: int, seed) -> np.ndarray:
    """n weight vectors decoded from z ~ N(0, I) (seeded)."""
    g = torch.Generator().manual_seed(int(seed) % (1 << 63))
    z = torch.randn(n, model.latent, generator=g)
    model.eval()
    return model.decode(z).numpy().astype(np.float32)


def save(path, model, kind: str, config: dict) -> None:
    save_torch(path, {"kind": kind, "config": config, "state": model.state_dict()})


def load(path) -> nn.Module:
    ck = modelfile.require(modelfile.load(path, finite=True), ("kind", "config", "state"), path,
                           "a VAE baseline (rule train_vae)")
    cls = {"vae_n": WeightVAE, "vae_a": SetVAE}.get(ck["kind"])
    if cls is None:
        raise ValueError(f"{path}: not a VAE baseline checkpoint (kind {ck['kind']!r})")
    # another config's weights, or an older layout: an error naming the file
    return modelfile.build(lambda: cls(**ck["config"]), ck["state"], path, "train_vae").eval()


# ----------------------------------------------------------------------------- training


CHECKPOINT_SECONDS = 30.0  # between checkpoints: when state is saved, not what it computes


def _adam_loop(model, batch_loss, steps: int, lr: float, log, generator: torch.Generator,
               checkpoint=None, fp: str | None = None, log_every: int = 100):
    """Adam with grad-norm clip 1 (HyperBRDF); returns rows (step, loss, rec, kl). With
    `checkpoint`, model, Adam, the draws' generator, step and history are saved there every
    CHECKPOINT_SECONDS and at the end, and a run killed before resumes from them, bit for bit
    (the draws come from `generator` alone; tests/test_baselines.py)."""
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    step, history = 0, []
    ck = modelfile.resume(checkpoint, fp, model=model, opt=opt, generator=generator) \
        if checkpoint else None
    if ck is not None:
        step, history = int(ck["step"]), list(ck["history"])
    model.train()
    saved = time.monotonic()
    while step < steps:
        step += 1
        loss, parts = batch_loss(step)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        if step % log_every == 0 or step == steps:
            history.append({"step": step, "loss": loss.item(), **parts})
            if log:
                log.info("step %d: loss %.5f (rec %.5f, kl %.3f)", step, loss.item(),
                         parts["rec"], parts["kl"])
        if checkpoint and (step == steps or time.monotonic() - saved > CHECKPOINT_SECONDS):
            Path(checkpoint).parent.mkdir(parents=True, exist_ok=True)
            save_torch(checkpoint, {"fingerprint": fp, "model": model.state_dict(),
                                    "opt": opt.state_dict(), "generator": generator.get_state(),
                                    "step": step, "history": history})
            saved = time.monotonic()
    return model.eval(), history


def train_weight_vae(weights, *, latent, hidden, steps, batch_size, lr, beta, seed, log=None,
                     checkpoint=None):
    """VAE-N on NeuMERL training weights (n, 675); `checkpoint`: see _adam_loop."""
    fp = modelfile.fingerprint([weights], dict(
        kind="vae_n", latent=latent, hidden=hidden, steps=steps, batch_size=batch_size, lr=lr,
        beta=beta, seed=seed))
    torch.manual_seed(seed)
    w = torch.as_tensor(np.asarray(weights), dtype=torch.float32)
    model = WeightVAE(latent, hidden, w.mean(0), w.std(0).clamp_min(1e-6))
    g = torch.Generator().manual_seed(seed_for(seed, "draws"))  # not the init's numbers

    def batch_loss(step):
        idx = torch.randint(len(w), (min(batch_size, len(w)),), generator=g)
        return model.loss(w[idx], beta, g)

    return _adam_loop(model, batch_loss, steps, lr, log, g, checkpoint, fp)


def train_set_vae(values, x6, cos_i, *, latent, hidden, steps, batch_size, context, queries,
                  lr, beta, seed, activation="relu", log=None, checkpoint=None):
    """VAE-A on AugMERL training tables: values (n, 3, B) physical BRDF at B bins with
    neural-field inputs x6 (B, 6) and cos θi (B,). Each step: `batch_size` materials,
    `context` random bins for the encoder and `queries` other random bins for the loss.
    `checkpoint`: see _adam_loop."""
    fp = modelfile.fingerprint([values, x6, cos_i], dict(
        kind="vae_a", latent=latent, hidden=hidden, steps=steps, batch_size=batch_size,
        context=context, queries=queries, lr=lr, beta=beta, activation=activation, seed=seed))
    torch.manual_seed(seed)
    v = torch.as_tensor(np.asarray(values), dtype=torch.float32).transpose(1, 2)  # (n, B, 3)
    x6 = torch.as_tensor(np.asarray(x6), dtype=torch.float32)
    cos_i = torch.as_tensor(np.asarray(cos_i), dtype=torch.float32).clamp_min(0)
    n_bins = v.shape[1]
    if context + queries > n_bins:  # the queries are other bins than the context's
        raise ValueError(f"VAE-A: context {context} + queries {queries} bins exceed the {n_bins} "
                         f"stored per table; lower baselines.vae_a.context or .queries, or raise "
                         f"baselines.vae_a.bins")
    # the hypernetwork's initial NBRDF from its own stream: seeded with `seed` as well, it
    # replayed the numbers torch.manual_seed(seed) gave the set encoder's first layer
    model = SetVAE(latent, hidden, seed_for(seed, "nbrdf_init"))
    g = torch.Generator().manual_seed(seed_for(seed, "draws"))  # not the init's numbers

    def batch_loss(step):
        idx = torch.randint(len(v), (min(batch_size, len(v)),), generator=g)
        perm = torch.randperm(n_bins, generator=g)
        ctx, q = perm[:context], perm[-queries:]
        return model.loss(x6[ctx], v[idx][:, ctx], x6[q], v[idx][:, q], cos_i[q], beta,
                          activation, g)

    return _adam_loop(model, batch_loss, steps, lr, log, g, checkpoint, fp)
