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


def paired(scores: pd.DataFrame, better: str, worse: str, tasks: list[str], seed: int,
           n_boot: int = 2000) -> pd.DataFrame:
    """How firmly method `better` beats `worse`, per Table 3 cell, on the same materials and
    views: the mean difference (better - worse; positive = better wins for PSNR and SSIM,
    negative for dE), the share of (material, view) pairs it wins, and a 95 % bootstrap interval
    of the mean difference, resampling materials (both views of a material together, since they
    are not independent). A cell whose interval excludes 0 is a win beyond material-to-material
    noise; one that straddles 0 is not."""
    rng = np.random.default_rng(seed)
    rows = []
    for t in tasks:
        a = scores[(scores["method"] == better) & (scores["task"] == t)]
        b = scores[(scores["method"] == worse) & (scores["task"] == t)]
        d = (a.set_index(["material", "view"])[list(METRICS)]
             - b.set_index(["material", "view"])[list(METRICS)])
        if d.isna().any().any() or len(d) == 0:
            raise ValueError(f"task {t!r}: {better!r} and {worse!r} are not scored on the same "
                             "materials and views")
        per_mat = d.groupby(level="material").mean()  # (materials, metrics): views averaged
        draw = rng.integers(0, len(per_mat), (n_boot, len(per_mat)))
        boot = per_mat.to_numpy()[draw].mean(1)  # (n_boot, metrics)
        for j, k in enumerate(METRICS):
            sign = 1 if HIGHER_IS_BETTER[k] else -1
            lo, hi = np.quantile(boot[:, j], [0.025, 0.975])
            rows.append({"cell": f"{t} {k}", "mean difference": float(d[k].mean()),
                         "pairs won": f"{int((sign * d[k] > 0).sum())}/{len(d)}",
                         "95 % interval": f"[{lo:.4g}, {hi:.4g}]",
                         "beyond noise": bool(sign * lo > 0 and sign * hi > 0)})
    return pd.DataFrame(rows)
