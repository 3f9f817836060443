"""Channel-permutation symmetry of unconditional samples (`diffusion.sample.rgb_permute`).

AugMERL holds every source material in all six RGB channel orders (neumat.augment.PERMS), and
its interpolations mix permuted rows, so the distribution `ours` learns is unchanged by a
channel permutation. A trained model only approximates that. Giving each unconditional sample
a uniformly random channel order averages the model over the permutation group: its samples
keep their shape, brightness and clamping, and their hues spread as the data's do. In an NBRDF
a channel permutation is exact: the output layer's rows (W3, b3) are permuted.

Not for models whose training rows are not closed under permutation (`merl100`: originals
only), nor for conditioned samples, whose colour a condition may name.
"""

from __future__ import annotations

import numpy as np

from neumat import nbrdf
from neumat.augment import PERMS

# AugMERL's six orders as channel indices, in its order (identity first)
PERMUTATIONS = np.array([["rgb".index(ch) for ch in p] for p in PERMS])


def permute_channels(weights: np.ndarray, perms: np.ndarray) -> np.ndarray:
    """(N, 675) NBRDF weights, (N, 3) channel orders -> (N, 675): output channel c of field i
    becomes its channel perms[i, c] (augment.permute's convention), exactly."""
    w = np.array(weights, copy=True)
    perms = np.asarray(perms)
    if perms.shape != (len(w), 3):
        raise ValueError(f"{perms.shape} channel orders for {len(w)} fields; need ({len(w)}, 3)")
    *_, W3, b3 = nbrdf.unflatten(w)  # views into w: (N, 3, 21) and (N, 3)
    W3[:] = np.take_along_axis(W3, perms[:, :, None], 1)
    b3[:] = np.take_along_axis(b3, perms, 1)
    return w


def random_channels(weights: np.ndarray, seed: int) -> np.ndarray:
    """Each field in a uniformly random channel order, drawn from `seed` (a named stream)."""
    pick = np.random.default_rng(seed).integers(0, len(PERMUTATIONS), len(weights))
    return permute_channels(weights, PERMUTATIONS[pick])
