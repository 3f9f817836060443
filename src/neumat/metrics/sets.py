"""Set metrics from pairwise distance matrices (M3ashy eqs. 3-5, after Yang et al. 2019).

Conventions: R is the reference set, S the synthesized set, d_rs[i, j] = d(R_i, S_j).
Ties in a nearest-neighbour search go to the lowest index (torch.argmin), with the R block
before the S block in 1-NNA. Distances must be finite (a NaN would be everyone's nearest
neighbour): a matrix with a NaN or infinity is refused.
"""

from __future__ import annotations

import torch


def _as_matrix(d, name):
    d = torch.as_tensor(d, dtype=torch.float64)
    if d.dim() != 2 or 0 in d.shape:
        raise ValueError(f"{name} must be a non-empty 2-D distance matrix, got {tuple(d.shape)}")
    bad = ~torch.isfinite(d)
    if bad.any():  # torch's min / argmin take NaN as the minimum: COV and 1-NNA would be wrong
        i, j = (int(k) for k in torch.nonzero(bad)[0])
        raise ValueError(f"{name} holds {int(bad.sum())} NaN or infinite distances (first at "
                         f"[{i}, {j}]): a material's BRDF values or renders are not finite. "
                         "Refuse such sets before scoring (neumat.metrics.materials.require_finite)")
    return d


def mmd(d_rs) -> float:
    """Minimum matching distance: mean over references of the distance to the nearest sample."""
    return _as_matrix(d_rs, "d_rs").min(1).values.mean().item()


def cov(d_rs) -> float:
    """Coverage: fraction of references that are the nearest reference of at least one sample."""
    d = _as_matrix(d_rs, "d_rs")
    return d.argmin(0).unique().numel() / d.shape[0]


def one_nna(d_rr, d_ss, d_rs) -> float:
    """Leave-one-out 1-nearest-neighbour accuracy on R u S (0.5 is ideal, 1.0 = separable)."""
    d_rr, d_ss, d_rs = (_as_matrix(d, n) for d, n in ((d_rr, "d_rr"), (d_ss, "d_ss"), (d_rs, "d_rs")))
    nr, ns = d_rs.shape
    if d_rr.shape != (nr, nr) or d_ss.shape != (ns, ns):
        raise ValueError(f"1-NNA needs d_rr {nr}x{nr} and d_ss {ns}x{ns} for d_rs {nr}x{ns}, "
                         f"got {tuple(d_rr.shape)} and {tuple(d_ss.shape)}")
    full = torch.cat([torch.cat([d_rr, d_rs], 1), torch.cat([d_rs.T, d_ss], 1)], 0)
    full.fill_diagonal_(float("inf"))  # leave one out
    label = torch.arange(nr + ns) >= nr
    return (label[full.argmin(1)] == label).double().mean().item()


def set_metrics(d_rr, d_ss, d_rs) -> dict[str, float]:
    """{'MMD', 'COV', '1-NNA'} from the three distance matrices (COV and 1-NNA as fractions)."""
    return {"MMD": mmd(d_rs), "COV": cov(d_rs), "1-NNA": one_nna(d_rr, d_ss, d_rs)}
