"""Constrained synthesis (M3ashy §4.5, Fig. 6): seven reflectance categories and rejection
sampling of a diffusion model into them.

Every rule reads a handful of statistics of a BRDF over the MERL grid (90 x 90 x 180 bin
centres, above-horizon bins only), all in physical units (1/sr):
    mean_c, max_c   per-channel mean and max reflectance (c = R, G, B)
    n_above         number of bins whose max-channel reflectance ||f||_inf exceeds f_diffuse
    n_valid         number of above-horizon bins (1,096,216 on the full grid)

Paper eqs. 7-10 fix two categories: f_diffuse = 1/pi (a constant BRDF reflecting all incident
energy), *diffuse* = fewer than e = 8e4 bins above f_diffuse (eq. 9), *metallic* = every bin
above it (eq. 10). The other five rules (supplement D.4) are not published; ours are formulas
over the same statistics with thresholds computed from the source materials' per-type medians
(`derive_thresholds`), written out in docs/stages.md ("Constrained synthesis"). Rules are checked in a fixed order and the
first that holds names the category, so every material has exactly one:

    metallic        n_above >= n_valid - metallic_exceptions                        (eq. 10)
    diffuse         n_above < e                                                      (eq. 9)
    mirror          peak >= mirror_peak  and  body >= mirror_body
    plastic         sharpness >= plastic_sharpness
    high-specular   peak >= high_peak
    medium-specular peak >= medium_peak
    low-specular    otherwise
with peak = max_c max_c (the highlight), body = max_c mean_c (the average level),
sharpness = peak / body (how much of the lobe is a spike). `features` also gives tint_peak =
(max_c max_c - min_c max_c) / max_c max_c, reported beside the categories, not used by a rule.
Thresholds a config sets (constrained.thresholds) replace the derived ones (`in_use`).

When a grid is subsampled (`bins` < all), n_above and n_valid are scaled to the full grid, so
e keeps its meaning.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import asdict, dataclass, fields

import numpy as np
import pandas as pd
import torch

from neumat import nbrdf
from neumat.io import merl
from neumat.seeds import seed_for

log = logging.getLogger(__name__)

F_DIFFUSE = 1.0 / np.pi  # eq. 8: a constant BRDF reflecting all incident energy
CATEGORIES = ["diffuse", "metallic", "low-specular", "medium-specular", "high-specular",
              "plastic", "mirror"]
# The rules in the order they are checked (first that holds wins): each category, the rule as
# the report states it (constrained_section) and its test on the per-row counts, the features
# and the thresholds. One table for both, so the report cannot describe other rules than
# `classify` applies.
RULES = [
    ("metallic", "n_above >= n_valid - metallic_exceptions (paper eq. 10)",
     lambda n_above, n_valid, f, th: n_above >= n_valid - th.metallic_exceptions),
    ("diffuse", "n_above < e (paper eq. 9)",
     lambda n_above, n_valid, f, th: n_above < th.e),
    ("mirror", "peak >= mirror_peak and body >= mirror_body",
     lambda n_above, n_valid, f, th: (f["peak"] >= th.mirror_peak).to_numpy()
     & (f["body"] >= th.mirror_body).to_numpy()),
    ("plastic", "sharpness >= plastic_sharpness",
     lambda n_above, n_valid, f, th: (f["sharpness"] >= th.plastic_sharpness).to_numpy()),
    ("high-specular", "peak >= high_peak",
     lambda n_above, n_valid, f, th: (f["peak"] >= th.high_peak).to_numpy()),
    ("medium-specular", "peak >= medium_peak",
     lambda n_above, n_valid, f, th: (f["peak"] >= th.medium_peak).to_numpy()),
    ("low-specular", "otherwise",
     lambda n_above, n_valid, f, th: np.ones(len(n_above), bool)),
]
ORDER = [cat for cat, _, _ in RULES]
# what the rules' quantities are (the report prints it under the rules)
RULE_TERMS = ("n_above = bins of the 90 x 90 x 180 grid with max-channel reflectance > "
              "f_diffuse = 1/pi; peak = max over channels of the per-channel max; body = max over "
              "channels of the per-channel mean; sharpness = peak / body (all over the valid "
              "bins, physical units)")
STAT_COLUMNS = ["mean_r", "mean_g", "mean_b", "max_r", "max_g", "max_b", "n_above", "n_valid"]


# ----------------------------------------------------------------------------- statistics


@functools.lru_cache(maxsize=4)
def _inputs(key: bytes) -> torch.Tensor:
    bins = np.frombuffer(key, dtype=np.int64)
    return torch.as_tensor(merl.half_diff_cartesian(*(a[bins] for a in merl.grid_angles())),
                           dtype=torch.float32)


def n_peak_bins() -> int:
    """Above-horizon bins at theta_h bin 0, where highlights (mirrors') peak: 16,200. Every
    subsample keeps them (`grid_bins`), so it is also the fewest bins a subsample may have."""
    return int(merl.valid_mask()[: merl.N_TD * merl.N_PD].sum())


def grid_bins(bins: int | None = None, seed: int = 0) -> np.ndarray:
    """Flat indices of the above-horizon MERL bins used for the statistics: all of them, or
    `bins` drawn without replacement (sorted) with `seed`. The highlight bins (theta_h bin 0,
    where mirrors put their peak) are always kept, so a subsample still sees the peak."""
    valid = np.flatnonzero(merl.valid_mask())
    if bins is None or bins >= len(valid):
        return valid
    n_peak = n_peak_bins()  # theta_h bin 0: a prefix of the sorted valid bins
    peak, rest = valid[:n_peak], valid[n_peak:]  # (valid is sorted: no set difference needed)
    rng = np.random.default_rng(seed)
    pick = rng.choice(rest, size=max(bins - len(peak), 0), replace=False)
    return np.sort(np.concatenate([peak, pick]))


class _Accumulator:
    """Running per-channel sums, maxima and counts above f_diffuse over chunks of bins."""

    def __init__(self, b: int, n_valid_full: int, n_used: int, weights_per_bin: np.ndarray):
        self.sum = np.zeros((b, 3))
        self.max = np.full((b, 3), -np.inf)
        self.above = np.zeros(b)
        self.scale = n_valid_full / n_used
        self.w = weights_per_bin  # stratification weight of each used bin (sums to n_used)
        self.n_valid_full = n_valid_full

    def add(self, f: torch.Tensor | np.ndarray, sl: slice) -> None:
        """f (B, n, 3) physical BRDF at bins[sl], float32 or float64. Reduced in torch: numpy's
        reductions over the short strided axes cost nearly as much as the NBRDF pass. Maxima
        are exact in either precision; sums are taken in float64."""
        f = torch.as_tensor(f)
        w = torch.from_numpy(self.w[sl])
        self.sum += torch.einsum("bnc,n->bc", f.double(), w).numpy()
        self.max = np.maximum(self.max, f.amax(1).double().numpy())
        self.above += ((f.amax(2).double() > F_DIFFUSE).double() @ w).numpy()

    def frame(self, names) -> pd.DataFrame:
        n = self.n_valid_full / self.scale
        df = pd.DataFrame(np.concatenate([self.sum / n, self.max], 1), columns=STAT_COLUMNS[:6])
        df["n_above"] = np.round(self.above * self.scale).astype(np.int64)
        df["n_valid"] = self.n_valid_full
        df.insert(0, "name", list(names))
        return df


def _stratified_weights(bins: np.ndarray) -> np.ndarray:
    """Weights that make a subsample with all theta_h-bin-0 bins kept unbiased for the full
    grid: the kept peak bins count once, the random rest counts for the bins it stands for."""
    valid = merl.valid_mask()
    n_peak = n_peak_bins()
    n_rest_full = int(valid.sum()) - n_peak
    is_peak = bins < merl.N_TD * merl.N_PD
    n_rest = int((~is_peak).sum())
    if n_rest == 0 and n_rest_full:  # the peak bins alone would stand for the whole grid
        raise ValueError(f"constrained.bins: {len(bins)} bins hold no bin beyond the "
                         f"{n_peak} theta_h-bin-0 ones; give more than {n_peak}, or null (all)")
    w = np.ones(len(bins))
    if n_rest and n_rest < n_rest_full:
        w[~is_peak] = n_rest_full / n_rest
    return w * len(bins) / w.sum()


def field_stats(weights: np.ndarray, names=None, activation: str = "relu", bins: np.ndarray | None = None,
                device: str = "cpu", progress=None, points_per_pass: int | None = None) -> pd.DataFrame:
    """Statistics (STAT_COLUMNS) of neural fields (N, 675) over `bins` (default: all valid).

    A block of fields goes through a chunk of bins a pass, about `points_per_pass` field-bin
    pairs in all (on the CPU 2^15, as nbrdf.materials_per_pass; on a GPU 2^22). Passes of 2^22
    pairs mapped and zeroed fresh pages for their ~0.35 GB of activations every time: 64 fields
    at 65,536 bins took 4.38x as long (`OMP_NUM_THREADS=1 python benchmarks/plausibility.py`;
    AMD EPYC AVX-512, 2026-11-26; README "Benchmarks"); 2400 fields at 65,536 bins in one pass took 21 GB and were
    OOM-killed in the default-config run. Non-finite weights give NaN statistics (no category)."""
    weights = np.asarray(weights, dtype=np.float32).reshape(-1, nbrdf.N_PARAMS)
    names = names if names is not None else [str(i) for i in range(len(weights))]
    bins = grid_bins() if bins is None else bins
    pairs = points_per_pass or (1 << 22 if torch.device(device).type == "cuda" else 1 << 15)
    chunk = max(min(4096, pairs), pairs // max(len(weights), 1))  # bins a pass
    per = max(1, pairs // chunk)  # fields a pass
    x = _inputs(np.ascontiguousarray(bins, dtype=np.int64).tobytes()).to(device)
    n_valid, sw = int(merl.valid_mask().sum()), _stratified_weights(bins)
    w = torch.as_tensor(np.nan_to_num(weights, nan=0.0, posinf=0.0, neginf=0.0), device=device)
    frames, total = [], len(weights) * len(bins)
    with torch.no_grad():
        for m in range(0, len(weights), per):
            acc = _Accumulator(min(per, len(w) - m), n_valid, len(bins), sw)
            for s in range(0, len(bins), chunk):
                f = nbrdf.forward(w[m:m + per], x[s:s + chunk], activation).cpu()
                acc.add(torch.nan_to_num(f, nan=np.inf, posinf=np.inf), slice(s, s + chunk))
                if progress:
                    progress(m * len(bins) + len(f) * min(s + chunk, len(bins)), total)
            frames.append(acc.frame(names[m:m + per]))
    df = pd.concat(frames, ignore_index=True) if frames else _Accumulator(
        0, n_valid, len(bins), sw).frame([])
    bad = ~np.isfinite(weights).all(1)
    if bad.any():  # no statistics; the counts stay whole numbers (Int64 with NA), not floats
        df[["n_above", "n_valid"]] = df[["n_above", "n_valid"]].astype("Int64")  # that a TSV's
        df.loc[bad, STAT_COLUMNS] = np.nan  # %.6g would round (1,096,216 -> 1.09622e+06)
    return df


def table_stats(tables, names=None, bins: np.ndarray | None = None) -> pd.DataFrame:
    """Statistics of MERL tables (each (3, 90, 90, 180) physical BRDF, or a .binary path)."""
    tables = list(tables)
    names = names if names is not None else [str(i) for i in range(len(tables))]
    bins = grid_bins() if bins is None else bins
    n_valid, sw = int(merl.valid_mask().sum()), _stratified_weights(bins)
    frames = []
    for name, t in zip(names, tables):  # one at a time: a table is 35 MB
        t = merl.read_merl(t) if not isinstance(t, np.ndarray) else t
        acc = _Accumulator(1, n_valid, len(bins), sw)
        acc.add(np.clip(t.reshape(3, -1)[:, bins].T, 0, None)[None], slice(0, len(bins)))
        frames.append(acc.frame([name]))
    return pd.concat(frames, ignore_index=True)


def _num(col: pd.Series) -> np.ndarray:
    """A count column as float, NaN where missing (int64, nullable Int64 or float)."""
    return col.astype(float).to_numpy()


def features(stats: pd.DataFrame) -> pd.DataFrame:
    """peak, body, sharpness, tint_peak and share_above of each row of a statistics frame."""
    mean = stats[["mean_r", "mean_g", "mean_b"]].to_numpy(float)
    mx = stats[["max_r", "max_g", "max_b"]].to_numpy(float)
    peak, body = mx.max(1), mean.max(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return pd.DataFrame({  # a black material (all zero) has sharpness and tint 0
            "peak": peak, "body": body, "sharpness": np.where(peak > 0, peak / body, 0.0),
            "tint_peak": np.where(peak > 0, (peak - mx.min(1)) / peak, 0.0),
            "share_above": _num(stats["n_above"]) / _num(stats["n_valid"]),
        }, index=stats.index)


# ----------------------------------------------------------------------------- rules


@dataclass
class Thresholds:
    """Named thresholds of the seven rules (module docstring). Units: 1/sr, counts of bins."""
    e: float = 8e4  # eq. 9: exceptions a diffuse material may have
    metallic_exceptions: float = 0  # eq. 10 says none
    mirror_peak: float = np.inf
    mirror_body: float = np.inf
    plastic_sharpness: float = np.inf
    high_peak: float = np.inf
    medium_peak: float = np.inf

    @classmethod
    def from_tsv(cls, path, overrides: dict | None = None) -> "Thresholds":
        """Read rules.tsv (columns threshold, value); non-null `overrides` win."""
        df = pd.read_csv(path, sep="\t")
        known = {f.name for f in fields(cls)}
        unknown = set(df["threshold"]) - known
        if unknown:
            raise ValueError(f"{path}: unknown thresholds {sorted(unknown)}; known: {sorted(known)}")
        values = dict(zip(df["threshold"], df["value"].astype(float)))
        for k, v in (overrides or {}).items():
            if k not in known:
                raise ValueError(f"constrained.thresholds.{k}: unknown threshold; known: {sorted(known)}")
            if v is not None:
                values[k] = float(v)
        return cls(**values)

    def to_frame(self, how: dict | None = None) -> pd.DataFrame:
        how = how or {}
        return pd.DataFrame([{"threshold": k, "value": v, "derived_from": how.get(k, "")}
                             for k, v in asdict(self).items()])


def rules_markdown() -> str:
    """The rules as the report shows them: a table in check order, then what the terms are."""
    rows = "\n".join(f"| {cat} | {text} |" for cat, text, _ in RULES)
    return ("| category | rule (first that holds, in this order) |\n| --- | --- |\n" + rows
            + "\n\n" + RULE_TERMS + ".")


def classify(stats: pd.DataFrame, th: Thresholds) -> np.ndarray:
    """Category of each row of a statistics frame (first rule in RULES that holds; '' when the
    statistics are not finite, e.g. a sample with NaN weights)."""
    f = features(stats)
    n_above, n_valid = _num(stats["n_above"]), _num(stats["n_valid"])
    out = np.full(len(stats), "", dtype=object)
    for cat, _, holds in reversed(RULES):  # earlier rules overwrite later ones
        out[holds(n_above, n_valid, f, th)] = cat
    finite = np.isfinite(stats[STAT_COLUMNS].astype(float).to_numpy()).all(1) & np.isfinite(f["sharpness"].to_numpy())
    out[~finite] = ""
    return out


def derive_thresholds(stats: pd.DataFrame, types, mirror_quantile: float = 0.9,
                      plastic_quantile: float = 0.75, specular_quantiles=(1 / 3, 2 / 3),
                      e: float = 8e4, metallic_exceptions: float = 0) -> tuple[Thresholds, dict]:
    """Thresholds of the five unpublished rules from per-type medians of the source materials.

    Each type (e.g. 'fabric', 'metallic-paint') is summarised by the median of its materials'
    peak, body and sharpness. Types whose median material is already diffuse or metallic by
    eqs. 9-10 are left out; over the remaining types:
        mirror_peak, mirror_body = mirror_quantile quantile of the type medians of peak, body
        plastic_sharpness        = plastic_quantile quantile of the type medians of sharpness
        medium_peak, high_peak   = specular_quantiles quantiles of the type medians of peak
    (quantiles of log values, i.e. geometric interpolation). Returns the thresholds and, per
    threshold, a sentence saying where it came from."""
    f = features(stats).assign(type=list(types), n_above=_num(stats["n_above"]),
                                n_valid=_num(stats["n_valid"]))
    f = f[np.isfinite(f[["peak", "body", "sharpness"]]).all(axis=1) & (f["type"] != "")]
    med = f.groupby("type")[["peak", "body", "sharpness", "n_above", "n_valid"]].median()
    keep = (med["n_above"] >= e) & (med["n_above"] < med["n_valid"] - metallic_exceptions)
    med = med[keep]
    if len(med) < 2:
        raise ValueError(f"deriving the category thresholds needs >= 2 material types that are "
                         f"neither diffuse nor metallic by eqs. 9-10; the source materials have "
                         f"{len(med)}: use more source materials (merl.subset / merl.synthetic.count) "
                         f"or set constrained.thresholds {', '.join(DERIVED)} in the config")

    def q(col, p):
        return float(np.exp(np.quantile(np.log(med[col]), p)))

    lo, hi = specular_quantiles
    th = Thresholds(e=e, metallic_exceptions=metallic_exceptions,
                    mirror_peak=q("peak", mirror_quantile), mirror_body=q("body", mirror_quantile),
                    plastic_sharpness=q("sharpness", plastic_quantile),
                    high_peak=q("peak", hi), medium_peak=q("peak", lo))
    n = f"{len(med)} non-diffuse, non-metallic types"
    how = {"e": "paper eq. 9", "metallic_exceptions": "paper eq. 10 (all directions)",
           "mirror_peak": f"{mirror_quantile:g} quantile of type-median peak over {n}",
           "mirror_body": f"{mirror_quantile:g} quantile of type-median body over {n}",
           "plastic_sharpness": f"{plastic_quantile:g} quantile of type-median sharpness over {n}",
           "high_peak": f"{hi:g} quantile of type-median peak over {n}",
           "medium_peak": f"{lo:g} quantile of type-median peak over {n}"}
    return th, how


DERIVED = ("mirror_peak", "mirror_body", "plastic_sharpness", "high_peak", "medium_peak")


def in_use(stats: pd.DataFrame, types, derive: dict, overrides: dict) -> tuple[Thresholds, dict]:
    """The thresholds the rules use, and where each came from: every non-null value of
    `overrides` (config constrained.thresholds; e and metallic_exceptions always), the rest
    derived from the source materials (`derive_thresholds` with `derive`'s quantiles); nothing
    is derived when the config sets all five, so a source set too small to derive from works."""
    given = {k: float(v) for k, v in overrides.items() if v is not None}
    if all(k in given for k in DERIVED):
        return Thresholds(**given), {k: "config constrained.thresholds" for k in given}
    th, how = derive_thresholds(stats, types, derive["mirror_quantile"], derive["plastic_quantile"],
                                derive["specular_quantiles"], given.get("e", 8e4),
                                given.get("metallic_exceptions", 0))
    for k in set(given) & set(DERIVED):
        setattr(th, k, given[k])
        how[k] = "config constrained.thresholds"
    return th, how


def type_purity(types, categories) -> pd.DataFrame:
    """Per type: materials, its most common category and the share of its materials in it
    (1.0 = the type falls cleanly into one category)."""
    df = pd.DataFrame({"type": list(types), "category": list(categories)})
    df = df[df["type"] != ""]
    rows = []
    for t, g in df.groupby("type"):
        counts = g["category"].value_counts()
        rows.append({"type": t, "materials": len(g), "category": counts.index[0],
                     "purity": counts.iloc[0] / len(g),
                     "categories": ", ".join(f"{c} {n}" for c, n in counts.items())})
    return pd.DataFrame(rows, columns=["type", "materials", "category", "purity", "categories"])


def category_types(types, categories) -> dict[str, list[str]]:
    """Per category, the types whose most common category it is (what type guidance asks for)."""
    pur = type_purity(types, categories)
    return {c: sorted(pur.loc[pur["category"] == c, "type"]) for c in CATEGORIES}


# ----------------------------------------------------------------------------- sampling


@dataclass
class CategoryResult:
    category: str
    weights: np.ndarray  # (accepted, 675)
    stats: pd.DataFrame  # statistics of the accepted samples, and the mode that drew each (guide)
    drawn: int
    guide: str  # the sampling mode drawn in after the pilot (`sampling_modes`)
    pilot: dict  # acceptance of each mode in the pilot batch
    hits: int = 0  # draws that fell into the category (>= len(weights): the last batch may overshoot)


def _draw(sampler, n, seed, mode, sample_cfg, activation="relu"):
    """n draws in one mode: {'types': list or None, 'category': str or None, 'step': float}."""
    types = mode["types"]
    guidance = sample_cfg["guidance"] if types else 1.0
    ts = [types[i % len(types)] for i in range(n)] if types else None
    extra = {"category": mode["category"], "category_step": mode["step"]} if mode["category"] else {}
    return sampler.sample(n, seed, ts, sample_cfg["steps"], sample_cfg["eta"], guidance,
                          sample_cfg["batch_size"], sample_cfg["clip"],
                          sample_cfg["negative_step"], activation,
                          refit_steps=sample_cfg.get("refit_steps", 0), **extra)


def sampling_modes(category: str, guide_types: list[str] | None = None,
                   guidance_step: float = 0.0) -> dict[str, dict]:
    """The ways `sample_category` may draw for `category`, by name, in pilot order:
    unconditionally; with category guidance (`guidance_step` > 0, diffuse and metallic only:
    `neumat.diffusion.constraints.CategoryConstraint`); guided by `guide_types`."""
    # here, not at the top: the rules and section jobs import this module without sampling
    from neumat.diffusion.constraints import GUIDED_CATEGORIES

    modes = {"unconditional": {"types": None, "category": None, "step": 0.0}}
    # before type guidance, so that a budget of two batches still pilots it
    if guidance_step > 0 and category in GUIDED_CATEGORIES:
        eq = {"diffuse": 9, "metallic": 10}[category]
        modes[f"category guidance: eq. {eq}, step {guidance_step:g}"] = {
            "types": None, "category": category, "step": float(guidance_step)}
    if guide_types:
        modes[f"type: {', '.join(guide_types)}"] = {"types": list(guide_types), "category": None,
                                                   "step": 0.0}
    return modes


def sample_category(sampler, category: str, th: Thresholds, n: int, budget: int, batch: int,
                    seed: int, sample_cfg: dict, guide_types: list[str] | None = None,
                    bins: np.ndarray | None = None, activation: str = "relu",
                    progress=None, guidance_step: float = 10.0,
                    pilot_every_mode: bool = True) -> CategoryResult:
    """Draw from `sampler` in batches until `n` samples fall into `category` or `budget`
    samples were drawn. The first batch is drawn in each of `sampling_modes` (unconditional;
    category guidance when `guidance_step` > 0; guided by `guide_types`, cycling), and the rest
    in whichever accepted more (ties: unconditional, the paper's setting). Every draw is judged
    by the exact rule (`classify`). Seeds: the named stream (seed, mode, batch index), the
    pilot batch 0, so a category's draws do not depend on the others. `pilot_every_mode` False
    stops as soon as `n` samples are accepted, even in the pilots (the CLI: four samples asked
    for should not cost a pilot batch of every mode; the workflow reports every mode's pilot)."""
    modes = sampling_modes(category, guide_types, guidance_step)
    acc_w, acc_s, drawn, pilot = [], [], 0, {}
    chosen = "unconditional"
    for k, (name, mode) in enumerate(modes.items()):  # pilot batch of each mode
        b = min(batch, budget - drawn)
        if b <= 0 or (not pilot_every_mode and sum(map(len, acc_w)) >= n):
            break
        w = _draw(sampler, b, seed_for(seed, name, 0), mode, sample_cfg, activation)
        s = field_stats(w, activation=activation, bins=bins)
        ok = classify(s, th) == category
        pilot[name] = float(ok.mean())
        acc_w.append(w[ok]), acc_s.append(s[ok].assign(guide=name))  # each hit's own mode
        drawn += b
        if progress:
            progress(drawn, int(sum(map(len, acc_w))))
    chosen = max(pilot, key=lambda m: (pilot[m], m == "unconditional")) if pilot else chosen
    i = 1
    while sum(map(len, acc_w)) < n and drawn < budget:
        b = min(batch, budget - drawn)
        w = _draw(sampler, b, seed_for(seed, chosen, i), modes[chosen], sample_cfg, activation)
        s = field_stats(w, activation=activation, bins=bins)
        ok = classify(s, th) == category
        acc_w.append(w[ok]), acc_s.append(s[ok].assign(guide=chosen))
        drawn += b
        i += 1
        if progress:
            progress(drawn, int(sum(map(len, acc_w))))
    hits = int(sum(map(len, acc_w)))
    w = np.concatenate(acc_w)[:n] if acc_w else np.zeros((0, nbrdf.N_PARAMS), np.float32)
    s = (pd.concat(acc_s, ignore_index=True).iloc[:n] if acc_s
         else pd.DataFrame(columns=["name", *STAT_COLUMNS, "guide"]))
    return CategoryResult(category, w.astype(np.float32), s, drawn, chosen, pilot, hits)


def acceptance_row(r: CategoryResult, n: int) -> dict:
    """One row of acceptance.tsv: acceptance = hits / drawn over every draw, pilots included."""
    return {"category": r.category, "accepted": len(r.weights), "requested": n, "drawn": r.drawn,
            "hits": r.hits, "acceptance": r.hits / r.drawn if r.drawn else float("nan"),
            "complete": len(r.weights) >= n, "guide": r.guide,
            "pilot": "; ".join(f"{k}: {v:.3f}" for k, v in r.pilot.items())}
