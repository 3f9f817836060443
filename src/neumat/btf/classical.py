"""Classical BTF compression baselines on the measurement grid (paper Fig. 8), per RGB channel
in linear space, all with the `GridBTF` query API:

- PCA: rank-k approximation of the (texels x light*view) matrix around the mean ABRDF
  (Koudelka et al. 2003; paper: 5 components per channel).
- SH: per texel and view, the light-dependent slice fitted by least squares with real
  spherical harmonics of bands 0-2 (9 per channel, 27 per view; Kawasaki et al. 2005).
- TD: Tucker decomposition of the (texel x light x view) tensor by sequentially truncated
  HOSVD (ranks r_texel, r_light, r_view), a dense stand-in for Ruiters & Klein's sparse
  tensor decomposition (paper: k1 = k2 = 13 angular ranks).
Fits stream texels in chunks through `BTFData.abrdf`, so the dense tensor is never held.
"""

from __future__ import annotations

import torch

from neumat.btf.grid import GridBTF, bilinear_texels
from neumat.seeds import seed_for


def _chunks(n, size):
    for s in range(0, n, size):
        yield torch.arange(s, min(n, s + size))


def _planar(data, texels: torch.Tensor, chunk: int) -> torch.Tensor:
    """ABRDFs of `texels` as contiguous channel planes (3, n, lights x views), decoded `chunk`
    texels at a time. svd_lowrank copied a strided channel (a permuted view) at every product,
    and decoding all texels at once mapped fresh pages for each 52 MB temporary (UBO2014's
    22,801 directions, 576 texels; the tiny run's `btf_pca` benchmark file has the cost). The
    mean is summed in another order than from the view: the fit moved by float32 rounding."""
    X = torch.empty(3, len(texels), data.n_lights * data.n_views)
    for s in range(0, len(texels), chunk):
        t = texels[s:s + chunk]
        X[:, s:s + len(t)] = data.abrdf(t).reshape(len(t), -1, 3).permute(2, 0, 1)
    return X


class PCA(GridBTF):
    method = "pca"

    def __init__(self, width, height, light_dirs, view_dirs, components=5):
        super().__init__(width, height, light_dirs, view_dirs)
        lv = len(light_dirs) * len(view_dirs)
        self.kwargs = dict(components=components)
        self.register_buffer("mean", torch.zeros(3, lv))
        self.register_buffer("basis", torch.zeros(3, components, lv))
        self.register_buffer("coef", torch.zeros(self.n_texels, 3, components))

    def values(self, t, l, v):
        lv = v * self.n_lights + l
        return self.mean[:, lv].T + torch.einsum("nck,ckn->nc", self.coef[t], self.basis[:, :, lv])

    @classmethod
    @torch.no_grad()
    def fit(cls, data, components=5, fit_texels=4096, chunk=256, seed=0):
        n = min(fit_texels, data.n_texels)
        if components > min(n, len(data.light_dirs) * len(data.view_dirs)):
            raise ValueError(f"btf.pca.components {components}: more than the {n} texels fitted "
                             f"(btf.pca.fit_texels, btf.crop) or the "
                             f"{len(data.light_dirs) * len(data.view_dirs)} light-view pairs; "
                             f"lower it or fit more texels")
        m = cls(data.width, data.height, data.light_dirs, data.view_dirs, components)
        gen = torch.Generator().manual_seed(seed)
        sub = torch.randperm(data.n_texels, generator=gen)[:fit_texels].sort().values
        X = _planar(data, sub, chunk)  # (3, n, LV)
        mean = X.mean(1, keepdim=True)
        X -= mean
        # svd_lowrank's random projection draws from the global generator: seeded from its own
        # stream (with `seed` itself it replayed the texel subset's numbers)
        torch.manual_seed(seed_for(seed, "svd"))
        for c in range(3):  # randomized SVD: only the top components of the (n x LV) matrix
            _, _, V = torch.svd_lowrank(X[c], q=min(components + 10, *X[c].shape), niter=4)
            m.basis[c] = V[:, :components].T
        m.mean.copy_(mean[:, 0].float())
        for t in _chunks(data.n_texels, chunk):
            Y = data.abrdf(t).reshape(len(t), -1, 3).permute(2, 0, 1) - m.mean[:, None]
            m.coef[t] = torch.einsum("cnj,ckj->nck", Y, m.basis)
        return m


def sh_basis(w: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics, bands 0-2, at unit vectors (N, 3) -> (N, 9)."""
    x, y, z = w[:, 0], w[:, 1], w[:, 2]
    return torch.stack([
        torch.full_like(x, 0.282095), 0.488603 * y, 0.488603 * z, 0.488603 * x,
        1.092548 * x * y, 1.092548 * y * z, 0.315392 * (3 * z * z - 1), 1.092548 * x * z,
        0.546274 * (x * x - y * y)], -1)


class SH(GridBTF):
    """Per texel and view: 9 SH coefficients per channel of the light-dependent slice."""

    method = "sh"

    def __init__(self, width, height, light_dirs, view_dirs):
        super().__init__(width, height, light_dirs, view_dirs)
        self.kwargs = {}
        self.register_buffer("coef", torch.zeros(self.n_texels, len(view_dirs), 3, 9))

    def values(self, t, l, v):
        return torch.einsum("nck,nk->nc", self.coef[t, v], sh_basis(self.light_dirs[l]))

    def _query(self, u, wi, wo):
        # The light dependence is continuous (SH), only texels and views are interpolated.
        ti, tw = bilinear_texels(u, self.width, self.height)
        vi, vw = self.interps()[1](wo)
        c = self.coef[ti[:, :, None], vi[:, None, :]]               # (N, 4, 3, 3ch, 9)
        w = (tw[:, :, None] * vw[:, None, :])[..., None, None]
        return torch.einsum("nck,nk->nc", (c * w).sum((1, 2)), sh_basis(wi))

    @classmethod
    @torch.no_grad()
    def fit(cls, data, chunk=256):
        m = cls(data.width, data.height, data.light_dirs, data.view_dirs)
        P = torch.linalg.pinv(sh_basis(data.light_dirs.double())).float()   # (9, L)
        for t in _chunks(data.n_texels, chunk):
            m.coef[t] = torch.einsum("kl,nvlc->nvck", P, data.abrdf(t))
        return m


TD_BLOCK = 1 << 15  # samples per block of Tucker.values: a core of 66 MB at 13 x 13 ranks


class Tucker(GridBTF):
    """X_c[t, l, v] ~ sum A_c[t, a] G_c[a, i, j] B_c[l, i] C_c[v, j] per channel c."""

    method = "td"

    def __init__(self, width, height, light_dirs, view_dirs, ranks=(32, 13, 13)):
        super().__init__(width, height, light_dirs, view_dirs)
        rt, rl, rv = ranks
        self.kwargs = dict(ranks=tuple(ranks))
        self.register_buffer("A", torch.zeros(3, self.n_texels, rt))
        self.register_buffer("G", torch.zeros(3, rt, rl, rv))
        self.register_buffer("B", torch.zeros(3, len(light_dirs), rl))
        self.register_buffer("C", torch.zeros(3, len(view_dirs), rv))

    def values(self, t, l, v):
        # in blocks: each sample's core is 3 x rl x rv floats, and a grid query asks 36 samples
        # a query (GridBTF._query), so one chunk of 16384 queries held a 1.2 GB core (13 x 13
        # ranks): btf_eval's peak on a 96^2 synthetic BTF, 2,115 MB max_rss (2026-11-29)
        return torch.cat([self._values(t[s:s + TD_BLOCK], l[s:s + TD_BLOCK], v[s:s + TD_BLOCK])
                          for s in range(0, len(t), TD_BLOCK)]) if len(t) else self.A.new_zeros(0, 3)

    def _values(self, t, l, v):
        core = torch.einsum("cna,caij->ncij", self.A[:, t], self.G)      # per-sample texel core
        return torch.einsum("ncij,cni,cnj->nc", core, self.B[:, l], self.C[:, v])

    @classmethod
    @torch.no_grad()
    def fit(cls, data, ranks=(32, 13, 13), chunk=128):
        rt, rl, rv = (min(r, n) for r, n in zip(ranks, (data.n_texels, data.n_lights, data.n_views)))
        rt = min(rt, rl * rv)                                          # texel rank <= core size
        m = cls(data.width, data.height, data.light_dirs, data.view_dirs, (rt, rl, rv))
        gl = torch.zeros(3, data.n_lights, data.n_lights, dtype=torch.float64)
        gv = torch.zeros(3, data.n_views, data.n_views, dtype=torch.float64)
        for t in _chunks(data.n_texels, chunk):
            X = data.abrdf(t).permute(3, 0, 1, 2)                         # (3, n, V, L)
            XL = X.reshape(3, -1, data.n_lights)                          # mode-light unfolding
            XV = X.transpose(2, 3).reshape(3, -1, data.n_views)           # mode-view unfolding
            gl += (XL.transpose(1, 2) @ XL).double()
            gv += (XV.transpose(1, 2) @ XV).double()
        for c in range(3):
            m.B[c] = torch.linalg.eigh(gl[c])[1][:, -rl:].flip(1).float()
            m.C[c] = torch.linalg.eigh(gv[c])[1][:, -rv:].flip(1).float()
        Y = torch.zeros(3, data.n_texels, rv * rl)
        for t in _chunks(data.n_texels, chunk):
            X = data.abrdf(t).permute(3, 0, 1, 2)                         # (3, n, V, L)
            Y[:, t] = torch.einsum("cnvl,cvj,cli->cnij", X, m.C, m.B).reshape(3, len(t), -1)
        for c in range(3):
            A, W = _top_right_vectors(Y[c].double(), rt)                # (T, rt), (rl*rv, rt)
            m.A[c] = A.float()
            m.G[c] = W.T.reshape(rt, rl, rv).float()
        return m


def _top_right_vectors(Y: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(Y @ W, W) for W the top-k right singular vectors of Y (n, d), from the smaller Gram
    matrix: Y^T Y (d x d), or Y Y^T (n x n) when there are fewer rows, whose eigenvectors U give
    W = Y^T U / s and Y @ W = U s. Same subspace, O(min(n, d)^3): a 64-texel crop with 40 x 40
    angular ranks is a 64² eigenproblem, not 1600²."""
    n, d = Y.shape
    if d <= n:
        W = torch.linalg.eigh(Y.T @ Y)[1][:, -k:].flip(1)
        return Y @ W, W
    w, U = torch.linalg.eigh(Y @ Y.T)
    s, U = w[-k:].flip(0).clamp_min(0).sqrt(), U[:, -k:].flip(1)
    live = s > s.max() * 1e-12                  # a rank-deficient Y has no direction for s = 0
    W = (Y.T @ U) / torch.where(live, s, 1.0)
    return U * s, W * live
