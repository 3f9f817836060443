"""Table 3 protocol: how well a method reconstructs known materials, scored on renders.

M3ashy §4.6 reports PSNR, ΔE (CIEDE2000) and SSIM but not the renderer, views or colour
pipeline; ours, fixed here (and in config/schema.yaml, `hyperbrdf`):
  * views (`VIEWS`): the metric sphere (`neumat.render.sphere`, point light at (-2, 2, 3)) and
    the same sphere under a grazing side light at (3, 0.5, 0.5); each view also has the
    uniform ambient term, so unlit parts still show the albedo;
  * images: linear HDR -> `sphere.to_srgb` (clip to [0, 1], sRGB curve), float;
  * PSNR: peak 1 over the whole image (as Table 2's NegPSNR); SSIM: scikit-image
    `structural_similarity(channel_axis=-1, data_range=1)` (7x7 window, as Table 2);
    ΔE: mean `skimage.color.deltaE_ciede2000` between `rgb2lab` of the two sRGB images over
    the sphere pixels (the black background would dilute it);
  * a table cell is the mean over test materials and views.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from neumat.render import sphere

VIEWS = {"metric": tuple(sphere.LIGHT_POS), "grazing": (3.0, 0.5, 0.5)}
METRICS = ("PSNR", "dE", "SSIM")
HIGHER_IS_BETTER = {"PSNR": True, "dE": False, "SSIM": True}


def view(name: str, resolution: int, device: str = "cpu") -> sphere.SphereView:
    if name not in VIEWS:
        raise ValueError(f"unknown view {name!r}; choose from {sorted(VIEWS)}")
    return sphere.sphere_view(resolution, str(device), VIEWS[name])


def srgb(img) -> np.ndarray:
    """Linear HDR (..., 3) -> float64 sRGB in [0, 1]."""
    return sphere.to_srgb(torch.as_tensor(img)).double().numpy()


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 100.0 if mse < 1e-10 else -10 * np.log10(mse)


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    return float(structural_similarity(a, b, channel_axis=-1, data_range=1.0))


def delta_e(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean CIEDE2000 between two sRGB images (H, W, 3) in [0, 1], over `mask` pixels."""
    from skimage.color import deltaE_ciede2000, rgb2lab

    d = deltaE_ciede2000(rgb2lab(a), rgb2lab(b))
    return float(d[mask].mean() if mask is not None else d.mean())


def image_metrics(ref: np.ndarray, img: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """PSNR, ΔE, SSIM of one sRGB image against its reference."""
    return {"PSNR": psnr(ref, img), "dE": delta_e(ref, img, mask), "SSIM": ssim(ref, img)}


def score(refs: dict[str, np.ndarray], imgs: dict[str, np.ndarray], masks: dict[str, np.ndarray],
          names: list[str], **labels) -> pd.DataFrame:
    """Per material and view metrics. refs/imgs: view -> sRGB (n, H, W, 3); masks: view ->
    (H, W) bool; `labels` (e.g. method=, task=) become constant columns."""
    rows = []
    for v in refs:
        for i, n in enumerate(names):
            rows.append({**labels, "view": v, "material": n,
                         **image_metrics(refs[v][i], imgs[v][i], masks[v])})
    return pd.DataFrame(rows)


def table3(scores: pd.DataFrame, methods: list[str], tasks: list[str]) -> pd.DataFrame:
    """Long per-material scores (method, task, view, material, PSNR, dE, SSIM) -> Table 3:
    one row per method, columns `<task> <metric>` = mean over materials and views. Rows whose
    task is 'any' (anchors that do not depend on the task) fill every task."""
    out = []
    for m in methods:
        row = {"method": m}
        for t in tasks:
            sel = scores[(scores["method"] == m) & scores["task"].isin([t, "any"])]
            for k in METRICS:
                row[f"{t} {k}"] = float(sel[k].mean()) if len(sel) else float("nan")
        out.append(row)
    return pd.DataFrame(out)


def wins(table: pd.DataFrame, better: str, worse: str) -> dict[str, bool]:
    """Cell -> whether method `better` beats `worse` in that cell of a Table 3."""
    a = table.set_index("method").loc[better]
    b = table.set_index("method").loc[worse]
    return {c: bool(a[c] > b[c]) if HIGHER_IS_BETTER[c.split()[-1]] else bool(a[c] < b[c])
            for c in table.columns if c != "method"}


ALPHA = 0.05  # level of the paired test's "beyond noise" verdict
EXACT_MAX = 16  # up to this many materials the sign-flip test enumerates all 2^n patterns
N_MC = 1 << 16  # random sign patterns of the test for more materials
TOO_FEW = "too few materials to judge"


def min_p(n: int) -> float:
    """The smallest two-sided p the sign-flip test can give with n materials: 2 / 2^n (only the
    observed signs and their mirror image reach the observed |mean|)."""
    return min(1.0, 2.0 / 2.0 ** n)


def sign_flip_p(d, rng: np.random.Generator | None = None, n_mc: int = N_MC) -> np.ndarray:
    """Two-sided p-values of a paired sign-flip permutation test of mean 0, per column.

    d: per-material differences (n,) or (n, k) (one column per metric). Under the null that
    neither method is better, each material's difference is as likely to have the other sign,
    so the observed |mean| is compared with |mean| under every sign pattern: all 2^n patterns
    when n <= EXACT_MAX (exact), else `n_mc` random patterns from `rng` (p = (1 + hits) /
    (1 + n_mc), a valid p-value). Ties with the observed |mean| count as at least as extreme
    (to a relative 1e-9, so rounding of the sums does not split them)."""
    d = np.asarray(d, dtype=np.float64)
    one = d.ndim == 1
    d = d[:, None] if one else d
    n = len(d)
    if n == 0:
        raise ValueError("sign-flip test of no materials")
    obs = np.abs(d.sum(0))
    tol = 1e-9 * np.maximum(np.abs(d).sum(0), np.finfo(float).tiny)
    hits = np.zeros(d.shape[1], np.int64)
    if n <= EXACT_MAX:
        total, plus = 2 ** n, 0
        codes = np.arange(2 ** n)
        for s in range(0, total, 1 << 14):  # bounded memory: 16384 patterns at a time
            bits = (codes[s:s + (1 << 14), None] >> np.arange(n)) & 1
            sums = (1 - 2 * bits).astype(np.float64) @ d
            hits += (np.abs(sums) >= obs - tol).sum(0)
    else:
        if rng is None:
            raise ValueError(f"{n} materials: the Monte Carlo sign-flip test needs a seeded rng")
        total, plus = n_mc, 1
        for s in range(0, n_mc, 1 << 12):
            signs = rng.choice(np.array([-1.0, 1.0]), (min(1 << 12, n_mc - s), n))
            hits += (np.abs(signs @ d) >= obs - tol).sum(0)
    p = (hits + plus) / (total + plus)
    return p[0] if one else p


def paired(scores: pd.DataFrame, better: str, worse: str, tasks: list[str], seed: int,
           n_boot: int = 2000, n_mc: int = N_MC) -> pd.DataFrame:
    """How firmly method `better` beats `worse`, per Table 3 cell, on the same materials and
    views. Per cell: the mean difference (better - worse; positive = better wins for PSNR and
    SSIM, negative for dE), the share of (material, view) pairs it wins, a 95 % bootstrap
    interval of the mean difference resampling materials (descriptive only), the number of
    materials, and the verdict: the two-sided p of a paired sign-flip permutation test on the
    per-material differences (both views of a material averaged first, since they are not
    independent; `sign_flip_p`). A cell is beyond material-to-material noise (True) when p <
    ALPHA and the mean difference favours `better`, not (False) otherwise, and "too few
    materials to judge" when even the most extreme outcome could not reach ALPHA (2 / 2^n >=
    0.05: n <= 5 materials). The percentile bootstrap is not the verdict: with few materials
    its interval is far too narrow (with no true difference it excluded 0 in 25 % of simulated
    cells at 3 materials, 17 % at 5, 8 % at 20). Random draws, per task from its own named
    streams: the bootstrap seed_for(seed, "bootstrap", task), the Monte Carlo sign patterns
    (more than EXACT_MAX materials) seed_for(seed, "sign_flip", task), so a task's interval does
    not depend on the tasks before it or on their material count."""
    from neumat.seeds import seed_for

    rows = []
    for t in tasks:
        rng = np.random.default_rng(seed_for(seed, "bootstrap", t))
        flip_rng = np.random.default_rng(seed_for(seed, "sign_flip", t))
        a = scores[(scores["method"] == better) & (scores["task"] == t)]
        b = scores[(scores["method"] == worse) & (scores["task"] == t)]
        d = (a.set_index(["material", "view"])[list(METRICS)]
             - b.set_index(["material", "view"])[list(METRICS)])
        if d.isna().any().any() or len(d) == 0:
            raise ValueError(f"task {t!r}: {better!r} and {worse!r} are not scored on the same "
                             "materials and views")
        per_mat = d.groupby(level="material").mean()  # (materials, metrics): views averaged
        n = len(per_mat)
        draw = rng.integers(0, n, (n_boot, n))
        boot = per_mat.to_numpy()[draw].mean(1)  # (n_boot, metrics)
        pval = sign_flip_p(per_mat.to_numpy(), flip_rng, n_mc)
        for j, k in enumerate(METRICS):
            sign = 1 if HIGHER_IS_BETTER[k] else -1
            lo, hi = np.quantile(boot[:, j], [0.025, 0.975])
            verdict = (TOO_FEW if min_p(n) >= ALPHA
                       else bool(pval[j] < ALPHA and sign * float(per_mat[k].mean()) > 0))
            rows.append({"cell": f"{t} {k}", "mean difference": float(d[k].mean()),
                         "pairs won": f"{int((sign * d[k] > 0).sum())}/{len(d)}",
                         "95 % interval": f"[{lo:.4g}, {hi:.4g}]", "materials": n,
                         "p (sign-flip)": float(pval[j]), "beyond noise": verdict})
    return pd.DataFrame(rows)
