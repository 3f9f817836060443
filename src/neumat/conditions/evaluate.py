"""Measures of conditioned samples (M3ashy §4.4): type hits against the nearest typed training
material, colour-word chromaticity, image agreement in the conditioning view, the distance to
the nearest training material and the share of samples whose output clamps negative values.

Colour match: a render's mean linear RGB over the sphere -> hue angle (HSV) and saturation; a
chromatic colour word matches when the hue lies within `HUE_TOLERANCE` degrees of the word's
hue and the saturation is at least `MIN_SATURATION`; achromatic words (white, black, gray,
silver) match when the saturation is below it. Words with no fixed chromaticity (dark, light,
beige, maroon...) are not scored.
"""

from __future__ import annotations

import colorsys

import numpy as np
import pandas as pd
import torch

from neumat.diffusion import dataset
from neumat.diffusion.plausibility import plausibility
from neumat.metrics import distances
from neumat.render import sphere

HUES = {"red": 0.0, "orange": 30.0, "gold": 45.0, "yellow": 55.0, "green": 120.0,
        "blue": 225.0, "violet": 275.0, "purple": 285.0, "pink": 330.0}
ACHROMATIC = {"white", "black", "gray", "silver"}
HUE_TOLERANCE = 40.0
MIN_SATURATION = 0.15


def colour_of(prompt: str) -> str:
    """The first scorable colour word of a prompt, or ''."""
    for w in prompt.lower().replace(",", " ").split():
        if w in HUES or w in ACHROMATIC:
            return w
    return ""


def mean_colour(renders: torch.Tensor) -> np.ndarray:
    """(B, H, W, 3) linear renders -> (B, 3) mean RGB over the sphere's pixels."""
    mask = sphere.sphere_view(renders.shape[1]).mask.cpu()
    return renders[:, mask].mean(1).numpy()


# the hue words a measured colour is named by (colour_word): one per hue region, no material
# words (gold) and no near-duplicates (violet ~ purple)
NAMING = ("red", "orange", "yellow", "green", "blue", "purple", "pink")


def colour_word(rgb: np.ndarray) -> str:
    """The hue word of a mean linear RGB: the `NAMING` hue nearest its HSV hue, the word that
    `colour_matches` accepts for it; '' when none does (saturation below `MIN_SATURATION`, or a
    hue more than `HUE_TOLERANCE` from every word, e.g. cyan)."""
    r, g, b = np.clip(rgb, 0, None) / max(float(np.max(rgb)), 1e-12)
    h, s, _ = colorsys.rgb_to_hsv(r, g, b)
    if s < MIN_SATURATION:
        return ""
    gap = {w: abs((h * 360.0 - HUES[w] + 180.0) % 360.0 - 180.0) for w in NAMING}
    word = min(gap, key=gap.get)
    return word if gap[word] <= HUE_TOLERANCE else ""


def colour_matches(rgb: np.ndarray, colour: str) -> bool:
    r, g, b = np.clip(rgb, 0, None) / max(float(np.max(rgb)), 1e-12)
    h, s, _ = colorsys.rgb_to_hsv(r, g, b)
    if colour in ACHROMATIC:
        return s < MIN_SATURATION
    d = abs((h * 360.0 - HUES[colour] + 180.0) % 360.0 - 180.0)
    return s >= MIN_SATURATION and d <= HUE_TOLERANCE


class TrainingSet:
    """BRDF values of the training materials at a fixed bin sample, for nearest look-ups."""

    def __init__(self, weights: np.ndarray, man: pd.DataFrame, bins: np.ndarray, activation: str):
        self.rows = dataset.training_rows(man, "ours")
        self.typed = self.rows[man["type"].iloc[self.rows].to_numpy() != ""]
        self.types = man["type"].iloc[self.typed].to_numpy()
        self.bins, self.activation = bins, activation
        self.values = self.fv(weights[self.rows])
        self.typed_values = self.values[np.searchsorted(self.rows, self.typed)]

    def scorable(self, types) -> np.ndarray:
        """Which asked types can score a hit: non-empty and present among the typed training
        materials (a test-split source may have a type no training material has)."""
        have = set(self.types)
        return np.array([t != "" and t in have for t in types], dtype=bool)

    def fv(self, w):
        return distances.field_values(np.nan_to_num(w), self.bins, self.activation)

    def nearest(self, samples: np.ndarray) -> pd.DataFrame:
        """Per sample: BRDF-L1 to the nearest training material and the nearest typed one's type."""
        f = self.fv(samples)
        _, dist = dataset.nearest(f, self.values)
        tidx, _ = dataset.nearest(f, self.typed_values)
        return pd.DataFrame({"brdf_l1": dist, "nearest_type": self.types[tidx]})


def negative_share(samples: np.ndarray, angles: int, seed: int, activation: str) -> np.ndarray:
    """Per sample: does the field produce any negative value (clamped to 0) on `angles` bins."""
    df = plausibility(samples, n_angles=angles, seed=seed, activation=activation,
                      albedo_kw={"n_theta_o": 1, "n_theta_h": 2, "n_phi_h": 2})
    return (df["negative_share"] > 0).to_numpy()


def _srgb_pair(samples, targets, resolution: int, activation: str):
    a = sphere.to_srgb(sphere.render_fields(np.nan_to_num(samples), resolution, activation))
    return a, sphere.to_srgb(torch.as_tensor(targets))


def _psnr(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    mse = ((a - b) ** 2).flatten(1).mean(1).double().clamp_min(distances.PSNR_FLOOR_MSE)
    return (-10 * torch.log10(mse)).numpy()


def render_psnr(samples: np.ndarray, targets, resolution: int, activation: str) -> np.ndarray:
    """PSNR (sRGB, data range 1) of each sample's metric-view render against its target image
    (image_scores without SSIM)."""
    return _psnr(*_srgb_pair(samples, targets, resolution, activation))


def image_scores(samples: np.ndarray, targets: torch.Tensor, resolution: int,
                 activation: str) -> pd.DataFrame:
    """PSNR / SSIM (sRGB, data range 1, as Table 2) of each sample's metric-view render against
    its conditioning image (targets (B, H, W, 3) linear HDR in the same view)."""
    a, b = _srgb_pair(samples, targets, resolution, activation)
    ssim = torch.stack([distances.pairwise_ssim(a[i:i + 1], b[i:i + 1])[0, 0] for i in range(len(a))]) \
        if len(a) else torch.zeros(0)
    return pd.DataFrame({"psnr": _psnr(a, b), "ssim": ssim.numpy()})


# ----------------------------------------------------------------------------- sample sets

SET_COLUMNS = ("sample", "condition", "kind", "prompt", "source", "type", "colour")


def score_set(ts: TrainingSet, w: np.ndarray, table: pd.DataFrame, negative, resolution: int,
              activation: str) -> pd.DataFrame:
    """Per sample of one set (its weights and samples.tsv): the conditions asked, the nearest
    training material (BRDF-L1, its type), type hit, colour match of the metric-view render,
    and whether it clamps negatives (`negative(w)` -> bool per sample)."""
    t = table.copy()
    for col in SET_COLUMNS:
        if col not in t:
            t[col] = ""
    df = pd.concat([t[list(SET_COLUMNS)].reset_index(drop=True), ts.nearest(w)], axis=1)
    df["scorable"] = ts.scorable(df["type"])
    df["type_hit"] = (df["type"] == df["nearest_type"]) & df["scorable"]
    rgb = mean_colour(sphere.render_fields(np.nan_to_num(w), resolution, activation))
    df["colour_match"] = [bool(c) and colour_matches(x, c) for x, c in zip(rgb, df["colour"])]
    df["negative"] = negative(w)
    return df


def summarise(df: pd.DataFrame, name: str) -> dict:
    """One summary row of `score_set`'s table: type hits over the samples whose type training
    has, colour match over those naming a colour, median distance, share clamping."""
    typed, coloured = df[df["scorable"]], df[df["colour"] != ""]
    return {"set": name, "samples": len(df),
            "type hits": typed["type_hit"].mean() if len(typed) else np.nan,
            "samples with a training type": len(typed),
            "colour match": coloured["colour_match"].mean() if len(coloured) else np.nan,
            "coloured samples": len(coloured),
            "median BRDF-L1 to nearest training": df["brdf_l1"].median(),
            "share clamping negatives": df["negative"].mean()}


def reference_summaries(ts: TrainingSet, weights: np.ndarray, man: pd.DataFrame,
                        negative) -> list[dict]:
    """The yardsticks: the real test-split materials scored as a sample set would be (type hits
    of their own types, distance, clamping), and the training fits' clamping."""
    test = dataset.reference_rows(man)
    near = ts.nearest(weights[test])
    own = man["type"].iloc[test].to_numpy()
    ok = ts.scorable(own)
    return [{"set": "reference: real test-split materials", "samples": len(test),
             "type hits": (near["nearest_type"].to_numpy() == own)[ok].mean() if ok.any() else np.nan,
             "samples with a training type": int(ok.sum()),
             "median BRDF-L1 to nearest training": near["brdf_l1"].median(),
             "share clamping negatives": negative(weights[test]).mean()},
            {"set": "reference: training fits", "samples": len(ts.rows),
             "share clamping negatives": negative(weights[ts.rows]).mean()}]


def image_yardsticks(ts: TrainingSet, weights: np.ndarray, rows: np.ndarray,
                     retrieved: np.ndarray, types, negative, resolution: int,
                     activation: str) -> list[dict]:
    """Yardsticks for the image modality's type hits, one sample per conditioning image (rows:
    the manifest rows of its material, types: its type): the conditioning materials themselves,
    i.e. a sampler that gives back each image's own material, and the retrieval baseline's
    training materials (weights[retrieved]), scored as a sample set is. The first is the most
    an image-conditioned sampler can score: under the split by source, a held-out material's
    nearest typed training material often has another type (diffuse paints sit by fabrics)."""
    t = pd.DataFrame({"type": list(types)})
    return [summarise(score_set(ts, weights[w], t, negative, resolution, activation), name)
            for w, name in ((np.asarray(rows), "image: the conditioning materials themselves"),
                            (np.asarray(retrieved), "image: retrieval"))]


def image_agreement(targets: torch.Tensor, conditions: np.ndarray, w_cond: np.ndarray,
                    w_uncond: np.ndarray, retrieved: np.ndarray, weights: np.ndarray,
                    sources, names, resolution: int, activation: str) -> pd.DataFrame:
    """Per conditioning image c (targets (C, H, W, 3), the metric view): mean PSNR / SSIM of its
    conditioned samples (rows of w_cond whose `conditions` == c), of every unconditional sample,
    and of the retrieved training material (weights[retrieved[c]], named names[retrieved[c]])."""
    res = []
    for c in range(len(targets)):
        target = targets[c:c + 1]
        mine = conditions == c
        s_cond = image_scores(w_cond[mine], target.expand(int(mine.sum()), -1, -1, -1),
                              resolution, activation)
        s_unc = image_scores(w_uncond, target.expand(len(w_uncond), -1, -1, -1), resolution,
                             activation)
        s_ret = image_scores(weights[retrieved[c:c + 1]], target, resolution, activation)
        res.append({"condition": c, "source": sources[c], "psnr_conditioned": s_cond["psnr"].mean(),
                    "ssim_conditioned": s_cond["ssim"].mean(),
                    "psnr_unconditional": s_unc["psnr"].mean(), "ssim_unconditional": s_unc["ssim"].mean(),
                    "psnr_retrieval": s_ret["psnr"].iloc[0], "ssim_retrieval": s_ret["ssim"].iloc[0],
                    "retrieved": names[retrieved[c]]})
    return pd.DataFrame(res)
