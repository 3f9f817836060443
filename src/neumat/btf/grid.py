"""Query API for representations stored on the measurement grid (reference data, PCA, SH,
tensor decomposition): `btf(u, wi, wo)` interpolates bilinearly between texels (wrapping, i.e.
repetitive tiling) and barycentrically between the 151 light and the 151 view directions
(Delaunay triangulation of their projected-hemisphere xy; a query beyond the outermost ring at
75 deg is moved along its own ray onto the ring's polygon, so values are continuous across it)."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import ConvexHull, Delaunay


class DirectionInterp:
    """Barycentric weights over a direction set, on the projected hemisphere (unit disc)."""

    def __init__(self, dirs: np.ndarray):
        xy = np.asarray(dirs, np.float64)[:, :2]
        self.tri = Delaunay(xy)
        # the hull's edges as n.x + c <= 0 inside (the origin, c < 0): a point outside is
        # scaled along its ray onto the nearest edge it crosses. (Pulling it radially onto the
        # inscribed circle, as before, jumped by ~0.008 in xy at the ring: 14 % in value.)
        eq = ConvexHull(xy).equations
        self.normals, self.offsets = eq[:, :2], eq[:, 2]

    def __call__(self, w: torch.Tensor):
        """(N, 3) unit directions -> vertex indices (N, 3) long and weights (N, 3)."""
        xy = w[:, :2].detach().cpu().double().numpy().copy()  # scaled in place below: a float64
        # CPU input would share its memory (and the caller's directions would move)
        s = self.tri.find_simplex(xy)
        out = s < 0
        if out.any():
            d = xy[out] @ self.normals.T                      # (M, edges)
            with np.errstate(divide="ignore"):
                t = np.where(d > 0, -self.offsets / d, np.inf).min(1)
            xy[out] *= np.minimum(t, 1.0)[:, None] * (1 - 1e-9)
            s[out] = self.tri.find_simplex(xy[out])
        s = np.maximum(s, 0)
        T = self.tri.transform[s]                         # (N, 3, 2) affine maps
        b = np.einsum("nij,nj->ni", T[:, :2], xy - T[:, 2])
        wts = np.clip(np.concatenate([b, 1 - b.sum(1, keepdims=True)], 1), 0, 1)
        wts /= wts.sum(1, keepdims=True)
        idx = torch.from_numpy(self.tri.simplices[s].astype(np.int64)).to(w.device)
        return idx, torch.from_numpy(wts).to(w)


def bilinear_texels(u: torch.Tensor, width: int, height: int):
    """Texture coords (N, 2) (wrapping) -> 4 texel indices (N, 4) and bilinear weights (N, 4)."""
    x = u[:, 0] * width - 0.5
    y = u[:, 1] * height - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    xs = torch.stack([x0, x0 + 1, x0, x0 + 1], 1) % width
    ys = torch.stack([y0, y0, y0 + 1, y0 + 1], 1) % height
    w = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], 1)
    return ys * width + xs, w


class GridBTF(torch.nn.Module):
    """Base class: subclasses give `values(t, l, v)` (N,) long each -> (N, 3) RGB."""

    method = "grid"

    def __init__(self, width, height, light_dirs, view_dirs):
        super().__init__()
        self.width, self.height = int(width), int(height)
        self.register_buffer("light_dirs", torch.as_tensor(np.asarray(light_dirs), dtype=torch.float32))
        self.register_buffer("view_dirs", torch.as_tensor(np.asarray(view_dirs), dtype=torch.float32))
        self._interp = None

    @property
    def n_texels(self):
        return self.width * self.height

    @property
    def n_lights(self):
        return len(self.light_dirs)

    @property
    def n_views(self):
        return len(self.view_dirs)

    def interps(self):
        if self._interp is None:
            self._interp = (DirectionInterp(self.light_dirs.numpy()),
                            DirectionInterp(self.view_dirs.numpy()))
        return self._interp

    def values(self, t, l, v):  # abstract: every representation defines its grid lookup
        raise NotImplementedError(f"{type(self).__name__} must define values(t, l, v)")

    @torch.no_grad()
    def forward(self, u, wi, wo, chunk: int = 1 << 14):
        """RGB (N, 3) at texture coords u (N, 2), light wi and view wo (N, 3, unit, z up)."""
        return torch.cat([self._query(u[s:s + chunk], wi[s:s + chunk], wo[s:s + chunk])
                          for s in range(0, len(u), chunk)]) if len(u) else u.new_zeros(0, 3)

    def _query(self, u, wi, wo):
        ti, tw = bilinear_texels(u, self.width, self.height)
        li, lw = self.interps()[0](wi)
        vi, vw = self.interps()[1](wo)
        t = ti[:, :, None, None].expand(-1, 4, 3, 3)
        l = li[:, None, :, None].expand(-1, 4, 3, 3)
        v = vi[:, None, None, :].expand(-1, 4, 3, 3)
        w = tw[:, :, None, None] * lw[:, None, :, None] * vw[:, None, None, :]
        val = self.values(t.reshape(-1), l.reshape(-1), v.reshape(-1)).reshape(len(u), 36, 3)
        return (val * w.reshape(len(u), 36, 1)).sum(1)

    def n_params(self) -> int:
        return sum(b.numel() for n, b in self.named_buffers() if not n.endswith("_dirs"))
