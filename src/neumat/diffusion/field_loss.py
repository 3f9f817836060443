"""The field term of the training loss (opt-in: `diffusion.train.field_loss` > 0).

The denoiser's loss is measured on standardised weights, where an error counts by how far it
moves a weight, not by what it does to the BRDF. Near black that is where Table 2's image rows
are lost (docs/results.md, "Where PCA-A wins the image MMD rows: near black"): the NBRDF output
max(exp(x) - 1, 0) turns a small negative excursion into black, and the sRGB metric renders
weigh an error near black up to 12.92x. On the realistic run's trained `ours`, the x0 the
model predicts at t = 0 from a training material clamps 3.4 % of its bins where the fit itself
clamps 0.6 %.

This term evaluates the NBRDF of the predicted and of the clean x0 at `bins` random valid MERL
bins, maps both through a log mapping that resolves values near zero, e(f) = sign(f)
log(1 + |f| / eps) (Nielsen et al.'s mapping, the one PCA-A samples in, without its cosine
and reference), and adds their mean squared difference. Where the clean value is clamped (f <=
0: black in the render), a predicted value below zero costs nothing. Each example's term is
weighted by alpha_bar(t) ** power, so it fades at high noise, where the x0 prediction is a
blurred mean of many materials.
"""

from __future__ import annotations

import numpy as np
import torch

from neumat import nbrdf
from neumat.device import to_device
from neumat.diffusion.constraints import bin_inputs


def log_map(f: torch.Tensor, eps: float) -> torch.Tensor:
    """sign(f) log(1 + |f| / eps): odd, so a clamped (negative) prediction is pulled back up."""
    return torch.sign(f) * torch.log1p(f.abs() / eps)


def field_error(w_hat: torch.Tensor, w: torch.Tensor, x: torch.Tensor, eps: float,
                activation: str = "relu") -> torch.Tensor:
    """Per material (B,): mean over directions x (N, 6) and channels of the squared log-mapped
    difference between the BRDFs of weights w_hat (predicted) and w (clean)."""
    f_hat = torch.expm1(nbrdf.forward_raw(w_hat, x, activation))
    with torch.no_grad():
        f = torch.expm1(nbrdf.forward_raw(w, x, activation))
    e_hat = log_map(f_hat, eps)
    e_hat = torch.where(f <= 0, torch.relu(e_hat), e_hat)  # both black in the render
    return ((e_hat - log_map(f.clamp_min(0), eps)) ** 2).flatten(1).mean(1)


def valid_directions() -> torch.Tensor:
    """(n, 6) NBRDF inputs of every valid MERL bin."""
    from neumat.io import merl

    return bin_inputs(np.flatnonzero(merl.valid_mask()))


class FieldLoss:
    """weight * mean over the batch of alpha_bar(t) ** power * field_error(decode(x0_hat),
    decode(x0)), at `bins` valid MERL bins drawn per step from the training generator."""

    def __init__(self, norm, weight: float, eps: float, bins: int, activation: str = "relu",
                 power: float = 1.0):
        if weight < 0 or eps <= 0 or bins < 1 or power < 0:
            raise ValueError(f"diffusion.train: field_loss must be >= 0 (got {weight}), "
                             f"field_eps > 0 (got {eps}), field_bins >= 1 (got {bins}) and "
                             f"field_power >= 0 (got {power})")
        self.norm, self.weight, self.eps, self.bins = norm, float(weight), float(eps), int(bins)
        self.activation, self.power = activation, float(power)
        self.x = valid_directions()

    def __call__(self, x0_hat: torch.Tensor, x0: torch.Tensor, ab: torch.Tensor,
                 generator: torch.Generator) -> torch.Tensor:
        idx = torch.randint(0, len(self.x), (self.bins,), generator=generator)
        x = to_device(self.x[idx], x0.device)
        err = field_error(self.norm.decode(x0_hat.float()), self.norm.decode(x0.float()), x,
                          self.eps, self.activation)
        return self.weight * (ab.reshape(-1) ** self.power * err).mean()
