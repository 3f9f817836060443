"""Clamp-aware refit: a post-step on sampled NBRDF weights (config diffusion.sample.refit_steps).

The NBRDF output max(exp(x) - 1, 0) hides every bin whose log-space value x < 0, and the
renderer only ever sees max(x, 0). Samples of `ours` leave many bins well below 0: dark
materials sit near x = 0, and the denoiser's error floor scatters them across it. The per-step
constraint (`constraints.NegativeConstraint`) lifts those bins by pulling the whole field up,
which brightens dark samples and costs Table 2 its image coverage (docs/results.md, Table 2).

The refit changes what the sample *is* as little as possible instead: each sample's NBRDF is fitted
again, from its own weights, to its own clamped output raised to a small floor,
    target = max(x(w_sample), floor)   at a seeded set of valid MERL bins,
by Adam on a squared error whose errors below the target weigh `below` times more (so the fit
settles above the floor rather than around it). The rendered BRDF moves by at most `floor` in
the bins that were clamped, and by the fit error elsewhere. Each sample's loss is its own (a sum
over samples), so a sample's result does not depend on the others beyond matmul blocking.
"""

from __future__ import annotations

import numpy as np
import torch

from neumat import nbrdf
from neumat.diffusion.constraints import constraint_directions
from neumat.seeds import seed_for

FLOOR = 0.002  # log space (~0.2 % of a unit BRDF): the most a clamped bin is lifted
REFIT_DIRECTIONS = 4096  # valid MERL bins the refit fits at (those of the clamp-aware step's kind)
BLOCK = 32  # samples per Adam run on the CPU: the activations of 32 x 4096 bins stay small


def clamp_refit(weights: np.ndarray, steps: int, seed: int, floor: float = FLOOR,
                below: float = 10.0, lr: float = 3e-3, activation: str = "relu",
                n_directions: int = REFIT_DIRECTIONS, device="cpu") -> np.ndarray:
    """(n, 675) weights refitted to their own clamped log-space output, raised to `floor`
    (module docstring), on `device` (the sampler's); `steps` = 0 returns them unchanged.
    Deterministic given `seed` (on a GPU, to its float rounding)."""
    if steps < 0 or floor < 0 or below < 1:
        raise ValueError(f"clamp refit needs steps >= 0, floor >= 0 and below >= 1; got "
                         f"{steps}, {floor}, {below} (diffusion.sample.refit_steps)")
    weights = np.asarray(weights, dtype=np.float32)
    if steps == 0 or len(weights) == 0:
        return weights
    x = constraint_directions(seed_for(seed, "clamp_refit"), n_directions).to(device)
    block = BLOCK if torch.device(device).type == "cpu" else len(weights)
    out = [_refit_block(torch.from_numpy(weights[s:s + block]).to(device), x, steps, floor,
                        below, lr, activation) for s in range(0, len(weights), block)]
    return torch.cat(out).cpu().numpy()


def _refit_block(w0: torch.Tensor, x: torch.Tensor, steps: int, floor: float, below: float,
                 lr: float, activation: str) -> torch.Tensor:
    with torch.no_grad():
        target = nbrdf.forward_raw(w0, x, activation).clamp_min(floor)
    w = w0.clone()
    m, v = torch.zeros_like(w), torch.zeros_like(w)
    for step in range(1, steps + 1):
        with torch.enable_grad():
            p = w.requires_grad_(True)
            e = nbrdf.forward_raw(p, x, activation) - target
            loss = (e * e * torch.where(e < 0, below, 1.0)).flatten(1).mean(1).sum()
            g = torch.autograd.grad(loss, p)[0]
        w = w.detach()
        _adam_step(w, g, m, v, step, lr)
    return w


def _adam_step(w, g, m, v, step: int, lr: float, betas=(0.9, 0.999), eps=1e-8) -> None:
    """One Adam step in place, the operations of torch.optim.Adam's single-tensor path (its
    CPU default), so the two agree to the bit (tests/test_diffusion.py). Not torch.optim itself:
    constructing its first optimizer imports torch._dynamo in every sampling process, which
    cost the test suite more CPU than the refits themselves (README, "pytest")."""
    b1, b2 = betas
    m.lerp_(g, 1 - b1)
    v.mul_(b2).addcmul_(g, g, value=1 - b2)
    denom = (v.sqrt() / (1 - b2 ** step) ** 0.5).add_(eps)
    w.addcdiv_(m, denom, value=-(lr / (1 - b1 ** step)))
