"""Sets of materials as Table 2 scores them: neural fields or tables, read alike.

A *field set* is an (N, 675) array of NBRDF weights (`.npy`). A *table set* is measured-style
data: physical BRDF values (N, 3, B) at B flat MERL bins (`.npz` with `bins`, `values`), e.g.
PCA-A samples, which are tables, not fields. The metrics only ever need a set's values at the
BRDF-L1 bins and at the metric view's bins, so a table set stores exactly those
(`metric_bins`) and is rendered from them - the same nearest-bin lookup as
`neumat.render.sphere.render_tables` on a full table. Invalid (below-horizon) bins hold 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from neumat import nbrdf
from neumat.metrics import MetricsInputError
from neumat.metrics import distances as D
from neumat.render import sphere


@dataclass
class TableSet:
    bins: np.ndarray    # (B,) int64 flat MERL bin indices, sorted, unique
    values: np.ndarray  # (N, 3, B) float32 physical BRDF

    def __len__(self):
        return len(self.values)

    def at(self, bins) -> np.ndarray:
        """Values (N, 3, len(bins)) at flat bins, which must be among the stored ones."""
        bins = np.asarray(bins)
        pos = np.searchsorted(self.bins, bins).clip(0, len(self.bins) - 1)
        if not np.array_equal(self.bins[pos], bins):
            raise ValueError(f"table set lacks {int((self.bins[pos] != bins).sum())} of the "
                             "requested bins: was it sampled for other metric settings "
                             "(render.resolution, metrics.brdf_samples)?")
        return self.values[:, :, pos]


MaterialSet = np.ndarray | TableSet


def metric_bins(brdf_bins, resolution: int) -> np.ndarray:
    """Sorted union of the BRDF-L1 bins and the metric view's bins: what a table set stores."""
    view = sphere.sphere_view(resolution).bins.numpy()
    return np.union1d(np.asarray(brdf_bins), view)


def save(path: str | Path, s: MaterialSet) -> None:
    path = Path(path)
    if isinstance(s, TableSet):
        tmp = path.with_name(path.name + ".part.npz")
        np.savez(tmp, bins=s.bins.astype(np.int64), values=s.values.astype(np.float32))
    else:
        tmp = path.with_name(path.name + ".part.npy")
        np.save(tmp, np.asarray(s, dtype=np.float32))
    tmp.replace(path)


def load(path: str | Path) -> MaterialSet:
    """A field set (.npy, (N, 675)) or a table set (.npz with bins and values); a set with a
    NaN or infinite value is refused (`require_finite`)."""
    path = Path(path)
    if path.suffix == ".npz":
        with np.load(path) as z:
            if not {"bins", "values"} <= set(z.files):
                raise ValueError(f"{path}: a table set needs arrays 'bins' and 'values', "
                                 f"has {z.files}")
            # copy=False: a float32 file's values are not copied again (1.4 GB for PCA-A's
            # sets of the default config)
            s = TableSet(z["bins"].astype(np.int64, copy=False),
                         z["values"].astype(np.float32, copy=False))
        if s.values.ndim != 3 or s.values.shape[1:] != (3, len(s.bins)):
            raise ValueError(f"{path}: values {s.values.shape} do not match {len(s.bins)} bins")
        require_finite(s.values, f"{path} (table values)")
        return s
    w = np.load(path)
    if w.ndim != 2 or w.shape[1] != nbrdf.N_PARAMS:
        raise ValueError(f"{path}: a field set must be (N, {nbrdf.N_PARAMS}), got {w.shape}")
    require_finite(w, f"{path} (field weights)")
    return w


def require_finite(x, where: str, what: str = "NaN or infinite values") -> None:
    """MetricsInputError naming `where` and the first bad materials (rows of axis 0) when `x`
    holds a NaN or an infinity. A NaN would pass as everyone's nearest neighbour in COV and
    1-NNA (torch's min and argmin take NaN as the minimum) and an infinity would skew MMD, so
    the metrics refuse them rather than report numbers that only look valid."""
    x = torch.as_tensor(x)
    if x.numel() == 0:
        return
    bad = ~torch.isfinite(x.reshape(len(x), -1)).all(1)
    if bad.any():
        rows = torch.nonzero(bad).flatten().tolist()
        shown = ", ".join(map(str, rows[:8])) + (", ..." if len(rows) > 8 else "")
        raise MetricsInputError(
            f"{where}: {len(rows)} of {len(x)} materials have {what} (rows {shown}); the metrics "
            "cannot rank them. Find what wrote them (a diverged fit or sampler, a field whose "
            "output overflows exp) and rebuild that file with its rule, or drop those rows.")


def rows(s: MaterialSet, index) -> MaterialSet:
    """The materials at `index` (a slice or integer array)."""
    return TableSet(s.bins, s.values[index]) if isinstance(s, TableSet) else s[index]


def brdf_values(s: MaterialSet, bins, activation: str = "relu") -> torch.Tensor:
    """(N, len(bins) * 3) float32 physical BRDF at `bins`, bin-major, channel-minor, >= 0."""
    if isinstance(s, TableSet):
        v = torch.as_tensor(s.at(bins)).clamp_min(0)
        return v.transpose(1, 2).reshape(len(s), -1).float()
    return D.field_values(s, bins, activation)


def renders(s: MaterialSet, resolution: int, activation: str = "relu", device="cpu",
            exposure: float = 0.0) -> torch.Tensor:
    """sRGB metric renders (N, H, W, 3) in [0, 1]; `exposure`: stops added to the metric
    exposure (a diagnosis, benchmarks/diffusion_diagnose.py kinds --exposure; 0 in the metrics)."""
    if isinstance(s, TableSet):
        view_bins = sphere.sphere_view(resolution).bins.numpy()
        lin = sphere.render_view_values(s.at(view_bins), resolution, device)
    else:
        lin = sphere.render_fields(s, resolution, activation, device)
    return sphere.to_srgb(lin, sphere.EXPOSURE + exposure)
