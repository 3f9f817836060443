"""PCA baselines of Table 2 (M3ashy §4.3): a Gaussian over PCA coefficients, sampled.

* PCA-A: PCA of the AugMERL training tables in the log mapping of Nielsen, Jensen and
  Ramamoorthi 2015 ("On optimal, minimal BRDF sampling for reflectance acquisition", §4):
  observations are material x channel over the bins; cosMap = clip(cos θi cos θo, 0.01, 1);
  ρ̃ = log((ρ cosMap + 0.001) / (median + 0.001)), median per bin over all observations;
  PCA by SVD of ρ̃ - mean; unmap ρ = (exp(ρ̃)(median + 0.001) - 0.001) / cosMap. A material's
  coefficients are its three channels' coefficients side by side (3k values), so the Gaussian
  also models how the channels co-vary. Samples are unmapped and clamped at 0.
* PCA-N: PCA of the NeuMERL training weight vectors (N, 675) and a Gaussian over its
  coefficients; samples are weight vectors.
"""

from __future__ import annotations

import logging

import numpy as np

from neumat.io import merl
from neumat.linalg import one_blas_thread

log = logging.getLogger(__name__)
EPS = 0.001  # Nielsen et al.'s offset in the log mapping
BLOCK_BYTES = 1 << 26  # PCA-A's float64 observations a block of bins holds (64 MiB)
COS_FLOOR = 0.01


class GaussianPCA:
    """PCA with k components of rows X (n, D), and a full-covariance Gaussian over the rows'
    coefficients. SVD of the (n, n) Gram matrix when n < D (float64), so D can be large; and
    `fit_blocks` reads X a block of columns at a time, so X need never be held whole."""

    def __init__(self, k: int):
        if k < 1:
            raise ValueError(f"PCA needs at least one component, got {k}")
        self.k = k

    def fit(self, X: np.ndarray) -> "GaussianPCA":
        X = np.asarray(X, dtype=np.float64)
        return self.fit_blocks(lambda sl: X[:, sl], len(X), X.shape[1], max(X.shape[1], 1))

    def fit_blocks(self, columns, n: int, D: int, block: int) -> "GaussianPCA":
        """Fit on X (n, D) given as `columns(sl)` -> X[:, sl] (float64), in two passes over
        blocks of `block` columns: the means and the Gram matrix, then the components. Each
        block is read twice and X never whole (PCA-A's tables at every bin are tens of GB at
        paper scale). One block gives the bits of the whole-matrix fit."""
        spans = [slice(a, min(a + block, D)) for a in range(0, D, block)]
        self.mean, G = np.empty(D), np.zeros((n, n))
        with one_blas_thread():  # the same bits on any core count
            for sl in spans:
                Xc = columns(sl)
                self.mean[sl] = Xc.mean(0)
                Xc = Xc - self.mean[sl]
                G += Xc @ Xc.T  # Gram: Xc = U S V^T -> Xc Xc^T = U S^2 U^T
            evals, U = np.linalg.eigh(G)
            del G
            k = min(self.k, n - 1 if n > 1 else 1, D)
            # the rank first: a round-off eigenvalue would divide a component by ~1e-150 (rows
            # repeat under RGB permutations, so a small AugMERL can have fewer than k)
            rank = int(np.sum(evals > n * np.finfo(np.float64).eps * max(evals.max(), 1e-300)))
            if rank < k:
                log.warning("PCA of rank %d: %d components, not %d", rank, max(rank, 1), k)
                k = max(rank, 1)
            order = np.argsort(evals)[::-1][:k]
            s = np.sqrt(np.clip(evals[order], 1e-300, None))
            Uk = U[:, order]
            self.components = np.empty((k, D))  # rows = V^T, orthonormal
            for sl in spans:
                self.components[:, sl] = (Uk.T @ (columns(sl) - self.mean[sl])) / s[:, None]
            # the rows' own coefficients, Xc V = U S: no third pass over X to encode them
            self.scores = Uk * s
        self.explained = evals[order].clip(0).sum() / max(evals.clip(0).sum(), 1e-300)
        return self

    # encode and decode too: PCA-A's tables moved by 3e-8 between baselines.threads 1 and 2
    # (OpenBLAS splits a product over the table's bins by threads; tests/test_threads.py)
    def encode(self, X) -> np.ndarray:
        with one_blas_thread():
            return (np.asarray(X, dtype=np.float64) - self.mean) @ self.components.T

    def decode(self, C) -> np.ndarray:
        with one_blas_thread():
            return np.asarray(C, dtype=np.float64) @ self.components + self.mean


class CoefficientGaussian:
    """Gaussian fitted to coefficient vectors (n, m); `sample(n, seed)` draws new ones."""

    def __init__(self, C: np.ndarray):
        C = np.asarray(C, dtype=np.float64)
        self.mean = C.mean(0)
        self.cov = np.cov(C, rowvar=False).reshape(C.shape[1], C.shape[1]) if len(C) > 1 \
            else np.zeros((C.shape[1],) * 2)

    def sample(self, n: int, seed) -> np.ndarray:
        rng = np.random.default_rng(seed)
        # eigh, not Cholesky: with fewer materials than dimensions the covariance is singular
        with one_blas_thread():
            evals, vecs = np.linalg.eigh(self.cov)
            z = rng.standard_normal((n, len(self.mean)))
            return self.mean + (z * np.sqrt(evals.clip(0))) @ vecs.T


# ----------------------------------------------------------------------------- Nielsen mapping


def cos_map(bins) -> np.ndarray:
    """clip(cos θi cos θo, 0.01, 1) at the centres of flat MERL bins."""
    th, td, pd = (a[np.asarray(bins)] for a in merl.grid_angles())
    wi, wo = merl.half_diff_to_dirs(th, td, pd)
    return np.clip(wi[:, 2] * wo[:, 2], COS_FLOOR, 1.0)


def log_map(rho, median, cosmap):
    return np.log((rho * cosmap + EPS) / (median + EPS))


def unmap(mapped, median, cosmap):
    return (np.exp(mapped) * (median + EPS) - EPS) / cosmap


class NielsenPCA:
    """PCA-A: fit on tables (n, 3, B) at flat MERL bins `bins`, sample new tables (n, 3, B).
    `fit_source` reads the tables a block of bins at a time, as do `tables` and `sample`."""

    def __init__(self, k: int, bins, block: int | None = None):
        self.k, self.bins = k, np.asarray(bins)
        self.cosmap = cos_map(self.bins)
        self.block = block  # bins a block; None: BLOCK_BYTES of float64 observations

    def _observations(self, tables, nbins=None) -> np.ndarray:
        t = np.clip(np.asarray(tables, dtype=np.float64), 0, None)
        nbins = len(self.bins) if nbins is None else nbins
        if t.ndim != 3 or t.shape[1:] != (3, nbins):
            raise ValueError(f"tables must be (n, 3, {nbins}), got {t.shape}")
        return t.reshape(-1, nbins)  # material-major, channel-minor observations

    def _block(self, rows: int) -> int:
        return self.block or max(1, BLOCK_BYTES // (8 * rows))

    def fit(self, tables) -> "NielsenPCA":
        tables = np.asarray(tables)
        return self.fit_source(lambda sl: tables[:, :, sl], len(tables))

    def fit_source(self, read, n: int) -> "NielsenPCA":
        """Fit on n tables given as `read(sl)` -> (n, 3, len) tables at bins[sl]. Per block of
        bins: the observations' median (per bin, so blocks give the same), the log mapping,
        then GaussianPCA.fit_blocks."""
        self.median = np.empty(len(self.bins))

        def columns(sl):
            obs = self._observations(read(sl), sl.stop - sl.start)
            self.median[sl] = np.median(obs, 0)  # the same in both passes
            return log_map(obs, self.median[sl], self.cosmap[sl])

        rows = 3 * n
        self.pca = GaussianPCA(self.k).fit_blocks(columns, rows, len(self.bins), self._block(rows))
        self.gauss = CoefficientGaussian(self.pca.scores.reshape(n, -1))
        return self

    def coefficients(self, tables) -> np.ndarray:
        """(n, 3k): each material's channel coefficients side by side."""
        obs = self._observations(tables)
        c = self.pca.encode(log_map(obs, self.median, self.cosmap))
        return c.reshape(len(obs) // 3, -1)

    def tables(self, coefs) -> np.ndarray:
        """Coefficients (n, 3k) -> tables (n, 3, B) float32, unmapped and clamped at 0, a block
        of bins at a time (no float64 copy of them all)."""
        c = np.asarray(coefs, dtype=np.float64).reshape(-1, self.pca.components.shape[0])
        out = np.empty((len(c), len(self.bins)), dtype=np.float32)
        step = self._block(len(c))
        with one_blas_thread():
            for a in range(0, len(self.bins), step):
                sl = slice(a, a + step)
                mapped = c @ self.pca.components[:, sl] + self.pca.mean[sl]
                out[:, sl] = np.clip(unmap(mapped, self.median[sl], self.cosmap[sl]), 0, None)
        return out.reshape(-1, 3, len(self.bins))

    def sample(self, n: int, seed) -> np.ndarray:
        return self.tables(self.gauss.sample(n, seed))


class WeightPCA:
    """PCA-N: fit on weight vectors (n, 675), sample new ones."""

    def __init__(self, k: int):
        self.k = k

    def fit(self, weights) -> "WeightPCA":
        self.pca = GaussianPCA(self.k).fit(weights)
        self.gauss = CoefficientGaussian(self.pca.encode(weights))
        return self

    def sample(self, n: int, seed) -> np.ndarray:
        return self.pca.decode(self.gauss.sample(n, seed)).astype(np.float32)
