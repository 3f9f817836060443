"""The clamp-aware constraint on sampling (`NegativeConstraint`, config
diffusion.sample.negative_step = lambda):
the NBRDF output max(exp(x) - 1, 0) hides every bin whose log-space value x < 0. At each DDIM
step the predicted x0 (normalised) is de-standardised, evaluated at a fixed seeded set of
valid MERL directions, and moved one gradient step down the clamp penalty
    P(x0) = mean over directions and channels of relu(-x),
    x0 <- x0 - lambda * dP/dx0   (per sample; lambda = 0: unchanged),
before the DDIM update. It adds an NBRDF forward and backward pass at those directions per
step: 2.3x the sampling time of the realistic run's denoiser on a 2-core CPU (README,
Hyperdiffusion).

Its own module, imported by both `train.Sampler.sample` and `sample.py` (which imports train).
"""

from __future__ import annotations

import numpy as np
import torch

from neumat import nbrdf

CONSTRAINT_DIRECTIONS = 4096  # valid MERL bins the clamp penalty is evaluated at
# Samples per forward/backward pass on the CPU. The whole batch at once is memory-bound: 256
# samples x 4096 bins x 21 floats is 88 MB a layer. Blocks of 8, for 256 samples: 138 against
# 405 ms with 2 threads (2.9x), 283 against 674 ms with 1 (2.4x); 128 samples 2.6x either way;
# 16 samples no change. Gradients equal to 1.2e-7. AMD EPYC (AVX-512), 2 cores, idle:
# `OMP_NUM_THREADS=2 python benchmarks/constraint_step.py`.
CPU_BLOCK = 8


def constraint_directions(seed: int, n: int = CONSTRAINT_DIRECTIONS) -> torch.Tensor:
    """(n, 6) NBRDF inputs at a fixed random subset (from `seed`) of the valid MERL bins."""
    from neumat.io import merl

    valid = np.flatnonzero(merl.valid_mask())
    idx = np.sort(np.random.default_rng(seed).choice(valid, size=min(n, len(valid)), replace=False))
    th, td, pd_ = (a[idx] for a in merl.grid_angles())
    return torch.as_tensor(merl.half_diff_cartesian(th, td, pd_), dtype=torch.float32)


def negative_penalty(w: torch.Tensor, x: torch.Tensor, activation: str = "relu") -> torch.Tensor:
    """Per material (B,): mean over directions x (N, 6) and channels of relu(-raw), the
    log-space depth of the bins the output clamp max(exp(raw) - 1, 0) sets to 0."""
    return torch.relu(-nbrdf.forward_raw(w, x, activation)).flatten(1).mean(1)


class NegativeConstraint:
    """x0_hat (normalised weights) -> x0_hat - step * d negative_penalty / d x0_hat, per sample
    (module docstring). Deterministic: the directions come from `seed`."""

    def __init__(self, norm, step: float, seed: int, activation: str = "relu",
                 n_directions: int = CONSTRAINT_DIRECTIONS):
        if step < 0:
            raise ValueError(f"diffusion.sample.negative_step must be >= 0, got {step}")
        self.norm, self.step, self.activation = norm, float(step), activation
        self.x = constraint_directions(seed, n_directions)

    def __call__(self, x0: torch.Tensor) -> torch.Tensor:
        if self.step == 0:
            return x0
        z = x0.detach().float()
        x = self.x.to(z.device)
        # each sample's gradient is its own penalty's, so the batch splits freely; on the CPU in
        # blocks of CPU_BLOCK, whose activations (8 x 4096 x 21 floats a layer) stay in cache
        block = CPU_BLOCK if z.device.type == "cpu" else len(z)
        g = torch.cat([self._grad(z[s:s + block], x) for s in range(0, len(z), block)])
        return x0 - self.step * g.to(x0.dtype)

    def _grad(self, z: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        with torch.enable_grad():
            z = z.requires_grad_(True)
            pen = negative_penalty(self.norm.decode(z), x, self.activation).sum()
            return torch.autograd.grad(pen, z)[0]


def constraint_for(sampler, negative_step: float, seed: int, activation: str = "relu"):
    """The `constrain` hook of `Diffusion.ddim_sample` (None when negative_step is 0)."""
    if not negative_step:
        return None
    return NegativeConstraint(sampler.norm, negative_step, seed, activation)
