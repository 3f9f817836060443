"""A BTF held as torch factors for fast batched decoding: training samples, dense ABRDF chunks
for the classical fits, and the interpolated reference `btf(u, wi, wo)` (it is a `GridBTF`)."""

from __future__ import annotations

import torch

from neumat.btf.grid import GridBTF
from neumat.io import dfmf

def to_rgb(raw: torch.Tensor, model: int) -> torch.Tensor:
    """Torch twin of `dfmf.to_rgb` for (..., 3) decorrelated values."""
    return _rgb3(raw[..., 0], raw[..., 1], raw[..., 2], model)


def _rgb3(c0, c1, c2, model):
    # YUV -> RGB written out elementwise: an (N x 3) @ (3 x 3) matmul is slower on CPU
    if model == 0:
        return torch.stack([c0, c1, c2], -1)
    y = torch.exp(c0) - dfmf.DRR_EPS
    s = y + dfmf.DRR_EPS
    u, v = c1 * s, c2 * s
    (_, _, rv), (_, gu, gv), (_, bu, _) = dfmf.YUV2RGB.tolist()
    return torch.stack([y + rv * v, y + gu * u + gv * v, y + bu * u], -1)


class BTFData(GridBTF):
    """Decoded-on-demand BTF (roi of a DFMF file) with the `GridBTF` query API."""

    method = "reference"

    def __init__(self, path, roi=None):
        src = dfmf.DFMF(path, roi)
        super().__init__(src.width, src.height, src.light_dirs(), src.view_dirs())
        U, SV = src.factors()
        self.U = [torch.from_numpy(u) for u in U]
        self.SV = [torch.from_numpy(s) for s in SV]
        self.model, self.path = src.header.color_model, src.path

    def values(self, t, l, v):
        row = v * self.n_lights + l
        raw = torch.stack([(u[row] * s[t]).sum(-1) for u, s in zip(self.U, self.SV)], -1)
        return to_rgb(raw, self.model)

    def abrdf(self, texels: torch.Tensor) -> torch.Tensor:
        """Full angular slices of some texels: (n,) -> (n, views, lights, 3)."""
        c0, c1, c2 = (s[texels] @ u.T for u, s in zip(self.U, self.SV))  # contiguous planes
        return _rgb3(c0, c1, c2, self.model).reshape(len(texels), self.n_views, self.n_lights, 3)

    def sample(self, n: int, gen: torch.Generator):
        """n random grid samples: texel, light, view indices and RGB targets."""
        t = torch.randint(self.n_texels, (n,), generator=gen)
        l = torch.randint(self.n_lights, (n,), generator=gen)
        v = torch.randint(self.n_views, (n,), generator=gen)
        return t, l, v, self.values(t, l, v)

    def texel_uv(self, t: torch.Tensor) -> torch.Tensor:
        """Texture coordinates in [0, 1)^2 of texel centres."""
        return torch.stack([(t % self.width + 0.5) / self.width,
                            (t // self.width + 0.5) / self.height], -1)
