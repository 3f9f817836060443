"""Constraints on sampling: edits of each DDIM step's predicted x0 that pull it toward a
property of the NBRDF it decodes to. Two kinds:

1. The clamp-aware constraint (`NegativeConstraint`, config diffusion.sample.negative_step = lambda):
the NBRDF output max(exp(x) - 1, 0) hides every bin whose log-space value x < 0. At each DDIM
step the predicted x0 (normalised) is de-standardised, evaluated at a fixed seeded set of
valid MERL directions, and moved one gradient step down the clamp penalty
    P(x0) = mean over directions and channels of relu(-x),
    x0 <- x0 - lambda * dP/dx0   (per sample; lambda = 0: unchanged),
before the DDIM update. It adds an NBRDF forward and backward pass at those directions per
step: 2.3x the sampling time of the realistic run's denoiser on a 2-core CPU (docs/stages.md,
Hyperdiffusion).

2. Category guidance (`CategoryConstraint`, config constrained.guidance_step = lambda), for the
two categories the paper defines by formula (eqs. 9-10, `neumat.constrained`): f > 1/pi in the
largest channel is raw > TAU = log(1 + 1/pi), so at the same kind of direction set
    metallic: P(x0) = mean over directions of relu(TAU + MARGIN - max_c raw)   (all above)
    diffuse:  P(x0) = mean over directions of relu(max_c raw - TAU + MARGIN)   (all below)
and x0 <- x0 - lambda * dP/dx0 after the clamp-aware step. Rejection sampling still decides:
a guided draw counts only if the exact rule on the statistics grid accepts it.

3. Render guidance (`RenderConstraint`, config conditions.image.render_step = lambda), for an
image condition shown in the metric view (`neumat.render.sphere`): each sample has its target
image y, and with r(x0) the sRGB metric-view render of the NBRDF x0 decodes to,
    P(x0) = sqrt(mean over the sphere's pixels and channels of (r(x0) - y)^2),
    x0 <- x0 - lambda * dP/dx0   (the RMSE, so a step's size does not scale with the error),
after the other steps: reconstruction guidance as in diffusion posterior sampling (Chung et al.
2023), the diffusion model as the prior of an inverse rendering. It needs the image's view
and lighting, so it applies to metric-view renders, not to arbitrary photographs.

4. Particle guidance (`ParticleGuidance`, config diffusion.sample.particle_step = lambda;
Corso et al. 2023, "Particle Guidance: non-I.I.D. Diverse Sampling with Diffusion Models"):
the samples of a DDIM batch are drawn jointly, each pushed away from the others' looks. With
f_i the sRGB render of sample i's x0 in an approximate metric view (PARTICLE_VIEW) and an RBF
kernel whose bandwidth h is the median squared pairwise distance over log B (SVGD's heuristic),
    P(x0_1..B) = (1/B) sum_{i,j} exp(-|f_i - f_j|^2 / h),    x0 <- x0 - lambda * dP/dx0,
after the clamp-aware step. Independent draws bunch near common materials and leave distinct
ones uncovered; the repulsion spreads a batch over looks (Table 2's image coverage +4.5 to
+4.8 points at lambda 0.05 on the realistic run, with more samples clamping: docs/stages.md,
Hyperdiffusion). A sample then depends on the others of its batch (diffusion.sample.batch_size),
deterministically.

Its own module, imported by both `train.Sampler.sample` and `sample.py` (which imports train).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from neumat import nbrdf
from neumat.seeds import seed_for

CONSTRAINT_DIRECTIONS = 4096  # valid MERL bins the clamp penalty is evaluated at
TAU = float(np.log1p(1.0 / np.pi))  # raw value at which the NBRDF output reaches f_diffuse = 1/pi
# The penalty pushes the raw value MARGIN past TAU: it sees 4096 directions while the rule judges
# 65,536, and a margin carries the directions it did not see across too. At step 10, of 64 draws
# of the realistic default-config model: metallic 30 accepted at margin 0, 59 at 0.1; diffuse 58
# and 63 (`python benchmarks/category_guidance.py --run <run>`, AMD EPYC AVX-512; docs/stages.md
# "Constrained synthesis").
MARGIN = 0.1
GUIDED_CATEGORIES = ("diffuse", "metallic")  # the categories with a published formula
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
    return bin_inputs(np.sort(np.random.default_rng(seed).choice(valid, size=min(n, len(valid)),
                                                                 replace=False)))


def bin_inputs(idx: np.ndarray) -> torch.Tensor:
    """(len(idx), 6) NBRDF inputs of MERL bins `idx` (flat indices)."""
    from neumat.io import merl

    th, td, pd_ = (a[idx] for a in merl.grid_angles())
    return torch.as_tensor(merl.half_diff_cartesian(th, td, pd_), dtype=torch.float32)


def negative_penalty(w: torch.Tensor, x: torch.Tensor, activation: str = "relu") -> torch.Tensor:
    """Per material (B,): mean over directions x (N, 6) and channels of relu(-raw), the
    log-space depth of the bins the output clamp max(exp(raw) - 1, 0) sets to 0."""
    return torch.relu(-nbrdf.forward_raw(w, x, activation)).flatten(1).mean(1)


class _PenaltyStep:
    """x0_hat (normalised weights) -> x0_hat - step * d penalty / d x0_hat, per sample, with the
    penalty evaluated at a fixed seeded set of valid MERL directions. Deterministic."""

    def __init__(self, norm, step: float, seed: int, activation: str = "relu",
                 n_directions: int = CONSTRAINT_DIRECTIONS):
        self.norm, self.step, self.activation = norm, float(step), activation
        self.x = constraint_directions(seed, n_directions)

    def penalty(self, w: torch.Tensor) -> torch.Tensor:  # (B, 675) weights -> (B,)
        raise NotImplementedError

    def __call__(self, x0: torch.Tensor) -> torch.Tensor:
        if self.step == 0:
            return x0
        z = x0.detach().float()
        # each sample's gradient is its own penalty's, so the batch splits freely; on the CPU in
        # blocks of CPU_BLOCK, whose activations (8 x 4096 x 21 floats a layer) stay in cache
        block = CPU_BLOCK if z.device.type == "cpu" else len(z)
        g = torch.cat([self._grad(z[s:s + block], slice(s, s + block))
                       for s in range(0, len(z), block)])
        return x0 - self.step * g.to(x0.dtype)

    def _grad(self, z: torch.Tensor, rows: slice) -> torch.Tensor:
        with torch.enable_grad():
            z = z.requires_grad_(True)
            return torch.autograd.grad(self.block_penalty(self.norm.decode(z), rows).sum(), z)[0]

    def block_penalty(self, w: torch.Tensor, rows: slice) -> torch.Tensor:
        """The penalty of the batch's samples `rows` (weights w); per-sample targets use rows."""
        return self.penalty(w)


class NegativeConstraint(_PenaltyStep):
    """The clamp-aware step: penalty `negative_penalty` (module docstring)."""

    def __init__(self, norm, step: float, seed: int, activation: str = "relu",
                 n_directions: int = CONSTRAINT_DIRECTIONS):
        if step < 0:
            raise ValueError(f"diffusion.sample.negative_step must be >= 0, got {step}")
        super().__init__(norm, step, seed, activation, n_directions)

    def penalty(self, w: torch.Tensor) -> torch.Tensor:
        return negative_penalty(w, self.x.to(w.device), self.activation)


def category_penalty(w: torch.Tensor, x: torch.Tensor, category: str, activation: str = "relu",
                     margin: float = MARGIN) -> torch.Tensor:
    """Per material (B,): how far the largest channel's raw value at directions x (N, 6) lies on
    the wrong side of TAU -/+ margin for `category` (module docstring); 0 inside it."""
    top = nbrdf.forward_raw(w, x, activation).amax(-1)
    if category == "metallic":
        return torch.relu(TAU + margin - top).mean(1)
    if category == "diffuse":
        return torch.relu(top - TAU + margin).mean(1)
    raise _not_guided(category)


def _not_guided(category: str) -> ValueError:
    return ValueError(f"category guidance exists for {', '.join(GUIDED_CATEGORIES)} (paper eqs. "
                      f"9-10), not {category!r}; the other categories are drawn by rejection")


class CategoryConstraint(_PenaltyStep):
    """Category guidance toward `category` (one of GUIDED_CATEGORIES; module docstring). Its
    directions come from the named stream (seed, "category_directions"), so they differ from
    the clamp-aware step's (drawn from `seed` itself, with numpy: the sampling noise uses torch's
    generator)."""

    def __init__(self, norm, category: str, step: float, seed: int, activation: str = "relu",
                 n_directions: int = CONSTRAINT_DIRECTIONS, margin: float = MARGIN):
        if category not in GUIDED_CATEGORIES:
            raise _not_guided(category)
        if step < 0:
            raise ValueError(f"constrained.guidance_step must be >= 0, got {step}")
        super().__init__(norm, step, seed_for(seed, "category_directions"), activation,
                         n_directions)
        self.category, self.margin = category, margin

    def penalty(self, w: torch.Tensor) -> torch.Tensor:
        return category_penalty(w, self.x.to(w.device), self.category, self.activation, self.margin)


# Particle guidance's approximate render: the metric view's point-light pixels at 16 px and an
# albedo quadrature of 8 x 4 x 8 nodes, 407 NBRDF evaluations a material against the metric
# render's 12439 at 16 px. Its pairwise distances correlate with the full render's at >= 0.99
# (tests/test_diffusion.py::test_particle_guidance_view_ranks_pairs_as_the_metric_render).
PARTICLE_VIEW = (16, (8, 4, 8))


class ParticleGuidance:
    """Particle guidance over a batch (module docstring, 4)."""

    def __init__(self, norm, step: float, activation: str = "relu"):
        if step < 0:
            raise ValueError(f"diffusion.sample.particle_step must be >= 0, got {step}")
        self.norm, self.step, self.activation = norm, float(step), activation

    def features(self, w: torch.Tensor) -> torch.Tensor:
        """(B, 675) weights -> (B, D) sRGB values of the approximate metric render's sphere."""
        from neumat.render import sphere

        res, quadrature = PARTICLE_VIEW
        v = sphere.sphere_view(res, str(w.device), quadrature=quadrature)
        img = sphere.to_srgb(v.composite(nbrdf.forward(w, v.x6, self.activation)))
        return img.reshape(len(w), -1, 3)[:, v.mask.reshape(-1)].flatten(1)

    @staticmethod
    def potential(f: torch.Tensor) -> torch.Tensor:
        """The batch's RBF potential; the bandwidth is a constant of the step (no gradient)."""
        sq = f.square().sum(1)
        d2 = (sq[:, None] + sq[None, :] - 2 * f @ f.T).clamp_min(0)
        off = ~torch.eye(len(f), dtype=torch.bool, device=f.device)
        h = d2[off].median().detach().clamp_min(1e-12) / math.log(len(f))
        return torch.exp(-d2 / h).sum() / len(f)

    def __call__(self, x0: torch.Tensor) -> torch.Tensor:
        if self.step == 0 or len(x0) < 2:  # one sample has no others to move away from
            return x0
        with torch.enable_grad():
            z = x0.detach().float().requires_grad_(True)
            g = torch.autograd.grad(self.potential(self.features(self.norm.decode(z))), z)[0]
        return x0 - self.step * g.to(x0.dtype)


def chain(*steps):
    """One `constrain` hook applying the given ones in order (None entries skipped; None if
    nothing is left)."""
    steps = [s for s in steps if s is not None]
    if not steps:
        return None
    if len(steps) == 1:
        return steps[0]
    return lambda x0: functools.reduce(lambda x, f: f(x), steps, x0)


def constraint_for(sampler, negative_step: float, seed: int, activation: str = "relu",
                   category: str | None = None, category_step: float = 0.0,
                   particle_step: float = 0.0):
    """The `constrain` hook of `Diffusion.ddim_sample`: the clamp-aware step (negative_step > 0),
    then category guidance (category given and category_step > 0), then particle guidance
    (particle_step > 0); None when none is on."""
    neg = NegativeConstraint(sampler.norm, negative_step, seed, activation) if negative_step else None
    cat = (CategoryConstraint(sampler.norm, category, category_step, seed, activation)
           if category is not None and category_step else None)
    pg = ParticleGuidance(sampler.norm, particle_step, activation) if particle_step else None
    return chain(neg, cat, pg)


class RenderConstraint(_PenaltyStep):
    """Render guidance (module docstring, 3): targets (B, H, W, 3) linear HDR metric-view images,
    one per sample of the batch this hook serves, in order; the render is at their resolution."""

    def __init__(self, norm, targets: torch.Tensor, step: float, activation: str = "relu"):
        from neumat.render import sphere

        if step < 0:
            raise ValueError(f"conditions.image.render_step must be >= 0, got {step}")
        t = torch.as_tensor(targets, dtype=torch.float32)
        if t.dim() != 4 or t.shape[1] != t.shape[2] or t.shape[3] != 3:
            raise ValueError(f"render targets must be (B, H, H, 3) images, got {tuple(t.shape)}")
        # not _PenaltyStep.__init__: no direction set; the penalty is over the image's pixels
        self.norm, self.step, self.activation = norm, float(step), activation
        self.sphere, self.resolution = sphere, t.shape[1]
        mask = sphere.sphere_view(self.resolution).mask.reshape(-1)
        self.y = sphere.to_srgb(t).reshape(len(t), -1, 3)[:, mask]

    def __call__(self, x0: torch.Tensor) -> torch.Tensor:
        if self.step and len(x0) != len(self.y):
            raise ValueError(f"{len(self.y)} render targets for a batch of {len(x0)}")
        return super().__call__(x0)

    def block_penalty(self, w: torch.Tensor, rows: slice) -> torch.Tensor:
        return self.penalty(w, self.y[rows].to(w.device))

    def penalty(self, w: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        v = self.sphere.sphere_view(self.resolution, str(w.device))  # cached per device
        img = v.composite(nbrdf.forward(w, v.x6, self.activation))
        r = self.sphere.to_srgb(img).reshape(len(w), -1, 3)[:, v.mask.reshape(-1)]
        return ((r - y) ** 2).flatten(1).mean(1).add(1e-12).sqrt()
