"""The two reference points of the synthesis comparison: plain repetitive tiling (the plane
wraps; zero storage, exact histogram, strict repetition) and naive linear blending of the
same randomly offset patches HPB uses (non-repeating, but averaging shrinks the variance and
washes out the histogram: the failure HPB exists to fix)."""

from __future__ import annotations

import torch

from neumat.btf.neural import fetch
from neumat.btf.synthesis import settings as _settings
from neumat.btf.synthesis.grid import triangle_grid, vertex_hash, wrap_fetch_coords


class Tiling:
    method, dynamic = "tiling", True

    def __init__(self, plane: torch.Tensor, seed: int = 0):
        self.plane, self.seed = plane, int(seed)

    @classmethod
    def build(cls, plane, seed, settings=None, luminance=None):
        _settings.check(cls.method, settings)  # none: a key is a mistake
        return cls(plane.detach().float().contiguous(), seed)

    def state(self) -> dict:
        return {}

    @classmethod
    def from_state(cls, plane, seed, state, settings=None):
        _settings.check(cls.method, settings)
        return cls(plane, seed)

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        return fetch(self.plane, torch.remainder(u.double(), 1.0).float(), wrap=True)


class LinearBlend(Tiling):
    """sum_i w_i f(u + h(v_i)) over the three triangle vertices: HPB's patches, given its seed
    (the evaluation builds it so: neumat.btf.synthesis.stage.references)."""

    method = "linear"

    def __call__(self, u):
        v, w = triangle_grid(u)
        xy = wrap_fetch_coords(u, vertex_hash(v, self.seed))
        taps = fetch(self.plane, xy.reshape(-1, 2), wrap=True).reshape(len(u), 3,
                                                                       self.plane.shape[-1])
        return (taps * w.float()[:, :, None]).sum(1)
