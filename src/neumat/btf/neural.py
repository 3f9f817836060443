"""Neural BTF representations: Triple Plane (Xu et al. 2024) and NeuMIP without offset module
and pyramid (Kuznetsov et al. 2021, finest level only), trained on random grid samples.

Both output log(1 + RGB) from the MLP; training minimises L1 in that space (highlights do not
swamp the diffuse texture), queries return max(exp(y) - 1, 0).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time

import torch
from torch import nn

from neumat.btf.directions import half_diff
from neumat.io import modelfile
from neumat.io.atomic import save_torch
from neumat.seeds import seed_for

log = logging.getLogger(__name__)
# the planes' scale before training: train() redraws them at its own init_std (_reset), so a
# model's constructor takes none (one that did was ignored by training)
PLACEHOLDER_STD = 0.1


def fetch(plane: torch.Tensor, xy: torch.Tensor, wrap: bool) -> torch.Tensor:
    """Bilinear fetch of plane (H, W, C) at xy (N, 2) in [0, 1]^2 (texel centres at (i+.5)/W).
    wrap=True tiles the plane; otherwise coordinates clamp to the border."""
    H, W, _ = plane.shape
    x, y = xy[:, 0] * W - 0.5, xy[:, 1] * H - 0.5
    if not wrap:
        x, y = x.clamp(0, W - 1), y.clamp(0, H - 1)
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    if wrap:
        x0, y0, x1, y1 = x0 % W, y0 % H, (x0 + 1) % W, (y0 + 1) % H
    else:
        x1, y1 = (x0 + 1).clamp(max=W - 1), (y0 + 1).clamp(max=H - 1)
    # one gather of the 4 taps and one batched weighted sum (fewer passes over memory).
    # index_select, not plane[idx]: on the CPU the backward of advanced indexing sums the taps'
    # gradients in an order that depends on the threads (the tiny run's Triple Plane texture
    # PSNR: 31.96 dB with btf.threads 1, 32.27 with 2; README, known limits); index_select's
    # backward sums in a fixed order (tests/test_threads.py)
    idx = torch.stack([y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1], 1)
    w = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    C = plane.shape[-1]  # not -1: a view of no queries (N = 0) would be ambiguous
    taps = plane.reshape(H * W, C).index_select(0, idx.reshape(-1)).view(*idx.shape, C)
    return torch.bmm(w[:, None, :], taps)[:, 0]


def mlp(n_in: int, hidden: int, layers: int) -> nn.Sequential:
    """`layers` linear layers: n_in -> hidden (ReLU) ... -> 3."""
    dims = [n_in] + [hidden] * (layers - 1) + [3]
    mods = []
    for a, b in zip(dims[:-1], dims[1:]):
        mods += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*mods[:-1])


def _disc(w: torch.Tensor) -> torch.Tensor:
    """Unit vector -> projected-hemisphere coordinate in [0, 1]^2."""
    return (w[:, :2] + 1) / 2


class _PlaneModel(nn.Module):
    """Shared by the plane models: a positional feature plane f_u read by `features_u`, and a
    `decode` MLP giving log(1 + RGB); synthesis swaps the positional features."""

    def raw(self, u, wi, wo):
        return self.decode(self.features_u(u), wi, wo)

    def forward(self, u, wi, wo):
        return torch.relu(torch.expm1(self.raw(u, wi, wo)))

    def n_params(self) -> int:
        return sum(p.numel() for p in self.parameters())


class TriplePlane(_PlaneModel):
    """BTF(u, h, d) = MLP(f_U(u), f_H(h), f_D(d)); f_U tiles (u wraps), f_H, f_D clamp."""

    method = "triple_plane"

    def __init__(self, width, height, u_channels=8, dir_res=32, dir_channels=8, hidden=32,
                 layers=4):
        super().__init__()
        self.kwargs = dict(width=width, height=height, u_channels=u_channels, dir_res=dir_res,
                           dir_channels=dir_channels, hidden=hidden, layers=layers)
        # a placeholder: train() draws the planes from its seed and init_std (_reset)
        g = torch.Generator().manual_seed(0)
        self.f_u = nn.Parameter(torch.randn(height, width, u_channels, generator=g) * PLACEHOLDER_STD)
        self.f_h = nn.Parameter(torch.randn(dir_res, dir_res, dir_channels, generator=g) * PLACEHOLDER_STD)
        self.f_d = nn.Parameter(torch.randn(dir_res, dir_res, dir_channels, generator=g) * PLACEHOLDER_STD)
        self.net = mlp(u_channels + 2 * dir_channels, hidden, layers)

    def features_u(self, u: torch.Tensor) -> torch.Tensor:
        """Positional features (N, C_U): the plane texture synthesis operates on."""
        return fetch(self.f_u, u, wrap=True)

    def decode(self, feat_u, wi, wo) -> torch.Tensor:
        """log(1 + RGB) from positional features and directions; synthesis swaps feat_u."""
        h, d = half_diff(wi, wo)
        x = torch.cat([feat_u, fetch(self.f_h, _disc(h), False), fetch(self.f_d, _disc(d), False)], -1)
        return self.net(x)


class NeuMIP(_PlaneModel):
    """Positional neural texture + MLP conditioned on (wi.xy, wo.xy) (no offset, no pyramid)."""

    method = "neumip"

    def __init__(self, width, height, u_channels=8, hidden=32, layers=4):
        super().__init__()
        self.kwargs = dict(width=width, height=height, u_channels=u_channels, hidden=hidden,
                           layers=layers)
        g = torch.Generator().manual_seed(0)  # a placeholder, as TriplePlane's
        self.f_u = nn.Parameter(torch.randn(height, width, u_channels, generator=g) * PLACEHOLDER_STD)
        self.net = mlp(u_channels + 4, hidden, layers)

    def features_u(self, u):
        return fetch(self.f_u, u, wrap=True)

    def decode(self, feat_u, wi, wo):
        return self.net(torch.cat([feat_u, wi[:, :2], wo[:, :2]], -1))


def _reset(model: nn.Module, seed: int, init_std: float):
    """Seeded init of planes and MLP, so results depend on the config seed only."""
    torch.manual_seed(seed)
    for name, p in model.named_parameters():
        if name.startswith("f_"):
            nn.init.normal_(p, 0.0, init_std)
    for m in model.modules():
        if isinstance(m, nn.Linear):
            m.reset_parameters()


def fingerprint(model: nn.Module, data, steps: int, batch: int, lr: float, seed: int,
                init_std: float) -> str:
    """What a checkpoint must match to be resumed: the model's shape, the training settings
    and the data (its file, crop and angular factors); checkpoint_every only sets when."""
    h = hashlib.sha256(json.dumps([model.method, getattr(model, "kwargs", {}), steps, batch, lr,
                                   seed, init_std, str(getattr(data, "path", "")), data.width,
                                   data.height], sort_keys=True, default=str).encode())
    for u in getattr(data, "U", []):
        h.update(u.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def _non_finite(data, target, step):
    """The error for a non-finite loss: the data's decoded values, or a diverged training."""
    src = getattr(data, "path", "the BTF")
    if not torch.isfinite(target).all():
        raise ValueError(f"{src}: its decoded colours overflow to NaN or inf (finite factors "
                         f"whose product exceeds float32); the file is damaged: delete it and "
                         f"fetch it again")
    raise ValueError(f"{src}: the fit's loss became NaN or inf at step {step + 1}; the "
                     f"training diverged: lower btf.<method>.lr")


def train(model: nn.Module, data, steps: int, batch: int, lr: float, seed: int,
          checkpoint: str | os.PathLike | None = None, checkpoint_every: int = 500,
          init_std: float = 0.1) -> list[float]:
    """Joint training of planes and MLP on random (texel, light, view) samples of `data`
    (a `BTFData`), L1 on log(1 + RGB). Resumes from `checkpoint` when it exists; returns the
    per-step losses of this run (from the resumed step on)."""
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(steps, 1), eta_min=lr * 0.05)
    gen = torch.Generator().manual_seed(seed_for(seed, "draws"))  # not the init's numbers (_reset)
    start = 0
    # a checkpoint of other settings or data is ignored (logged), not resumed with its own
    # learning rate and schedule
    fp = fingerprint(model, data, steps, batch, lr, seed, init_std)
    ck = modelfile.resume(checkpoint, fp, model=model, opt=opt, sched=sched, gen=gen) \
        if checkpoint else None
    if ck is not None:
        start = ck["step"]
    else:
        _reset(model, seed, init_std)
    losses, t0 = [], time.time()
    for step in range(start, steps):
        t, l, v, target = data.sample(batch, gen)
        pred = model.raw(data.texel_uv(t), data.light_dirs[l], data.view_dirs[v])
        loss = (pred - torch.log1p(target.clamp_min(0))).abs().mean()
        if not torch.isfinite(loss):  # saved anyway, a NaN model scored as a poor fit
            _non_finite(data, target, step)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
        if (step + 1) % max(steps // 10, 1) == 0:
            log.info("%s step %d/%d loss %.5f (%.1fs)", model.method, step + 1, steps,
                     sum(losses[-50:]) / len(losses[-50:]), time.time() - t0)
        if checkpoint and ((step + 1) % checkpoint_every == 0 or step + 1 == steps):
            save_torch(checkpoint, {"fingerprint": fp, "model": model.state_dict(),
                                    "opt": opt.state_dict(), "sched": sched.state_dict(),
                                    "gen": gen.get_state(), "step": step + 1})
    if checkpoint:  # the last step's: a rerun of the finished fit resumes there (modelfile.finish)
        modelfile.finish(checkpoint)
    return losses
