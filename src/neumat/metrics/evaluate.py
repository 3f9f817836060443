"""The Table-2 evaluation of one synthesized set against a reference set, and the table writer.

`evaluate_sets` computes the 12 set metrics (MMD, COV, 1-NNA x BRDF-L1, RMSE, NegPSNR,
NegSSIM) and FID (2048-d and 64-d), as a long table with columns metric, distance, value,
note; `evaluate_draws` does so for several sample draws (a `draw` column). `table2` lays
several such tables out like M3ashy Table 2 (models as columns, display units as in the
paper but for MMD BRDF-L1, shown unscaled; mean ± std over draws, in fixed notation). Samples
with NaN or infinite values, and rows finite in fewer draws than the table has, are refused.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import pandas as pd
import torch

from neumat.io.atomic import save_torch
from neumat.metrics import MetricsInputError
from neumat.metrics import distances as D
from neumat.metrics import sets

log = logging.getLogger(__name__)
COLUMNS = ["metric", "distance", "value", "note"]
SET_METRICS = ("MMD", "COV", "1-NNA")


def self_distances(values, images) -> dict[str, torch.Tensor]:
    """{distance: d_xx} of one set: BRDF-L1 on BRDF values, the image distances on renders."""
    out = {"BRDF-L1": D.pairwise_l1(values, values)}
    out.update({name: fn(images) for name, fn in D.IMAGE_DISTANCES.items()})
    return out


def distance_matrices(ref_values, smp_values, ref_images, smp_images,
                      ref_self: dict | None = None) -> dict[str, tuple]:
    """{distance: (d_rr, d_ss, d_rs)} for BRDF-L1 (BRDF values) and the image distances;
    `ref_self`: the references' `self_distances`, when already computed (shared by draws)."""
    rr = ref_self or self_distances(ref_values, ref_images)
    ss = self_distances(smp_values, smp_images)
    rs = {"BRDF-L1": D.pairwise_l1(ref_values, smp_values)}
    rs.update({name: fn(ref_images, smp_images) for name, fn in D.IMAGE_DISTANCES.items()})
    return {name: (rr[name], ss[name], rs[name]) for name in rs}


def set_metric_rows(matrices: dict[str, tuple]) -> pd.DataFrame:
    rows = []
    for name, (d_rr, d_ss, d_rs) in matrices.items():
        for metric, value in sets.set_metrics(d_rr, d_ss, d_rs).items():
            rows.append((metric, name, value, ""))
    return pd.DataFrame(rows, columns=COLUMNS)


FID_DIMS = {2048: "Inception-v3", 64: "Inception-64"}  # rows of the FID block


def fid_rows(fid_model, ref_images, smp_images, unavailable: str = "", device="cpu",
             ref_features=None, smp_features=None) -> pd.DataFrame:
    """FID on the standard 2048-d pool3 features and on the 64-d first max-pool features
    (`pytorch_fid --dims 64`, what the released M3ashy code reports). `ref_features`,
    `smp_features`: a set's {dims: features} when already computed (the reference's, shared
    by the draws; both, for the reference halves)."""
    if fid_model is None:
        note = f"unavailable: {unavailable or 'no Inception-v3 weights'}"
        return pd.DataFrame([("FID", d, np.nan, note) for d in FID_DIMS.values()], columns=COLUMNS)
    from neumat.metrics import fid as fidlib
    fr = ref_features or fidlib.features(fid_model, ref_images, device=device)
    fs = smp_features or fidlib.features(fid_model, smp_images, device=device)
    return _fid_table(fr, fs)


def _fid_table(ref_features: dict, smp_features: dict) -> pd.DataFrame:
    from neumat.metrics import fid as fidlib
    return pd.DataFrame([("FID", name, fidlib.fid_from_features(ref_features[d], smp_features[d]),
                          f"Inception-v3 {d}-d features, sRGB sphere renders")
                         for d, name in FID_DIMS.items()], columns=COLUMNS)


def evaluate_sets(ref, smp, *, resolution: int, bins, activation="relu", fid_model=None,
                  fid_unavailable: str = "", device="cpu") -> pd.DataFrame:
    """All Table-2 metrics of material set `smp` against `ref` (field or table sets, see
    `neumat.metrics.materials`). `fid_model`: an `inception.FIDInception` (or None, with the
    reason in `fid_unavailable`)."""
    return evaluate_draws(ref, [smp], resolution=resolution, bins=bins, activation=activation,
                          fid_model=fid_model, fid_unavailable=fid_unavailable,
                          device=device).drop(columns="draw")


def evaluate_fields(ref_weights, smp_weights, **kw) -> pd.DataFrame:
    """`evaluate_sets` for two neural-field sets (N, 675)."""
    return evaluate_sets(np.asarray(ref_weights), np.asarray(smp_weights), **kw)


def _prepare(s, resolution, bins, activation, device, where="material set"):
    """BRDF values and renders of set `s`, refused (MetricsInputError naming `where` and the
    rows) where not finite: fields whose weights are finite can still overflow exp."""
    from neumat.metrics import materials as M
    values = M.brdf_values(s, bins, activation)
    M.require_finite(values, where, "non-finite BRDF values (NaN, or inf where the field's "
                                    "output overflows exp)")
    images = M.renders(s, resolution, activation, device)
    M.require_finite(images, where, "non-finite renders")
    return values, images


REFERENCE_SETTINGS = ("bins", "activation", "resolution")  # stored in reference.pt, compared


def prepare_reference(ref, *, resolution: int, bins, activation="relu", fid_model=None,
                      device="cpu") -> dict:
    """What every model's metrics share about the reference set: its BRDF values, renders,
    self-distance matrices and (with `fid_model`) Inception features. Rule metrics_reference
    computes it once (`save_reference`) for all the metrics jobs (`evaluate_draws(...,
    reference=)`). On the realistic run (480 references, 128 px) it takes 50 s, which every job
    spent before: the metrics stage 1636 -> 1318 s, tables equal (2-core AMD EPYC, AVX-512, idle;
    `OMP_NUM_THREADS=2 python benchmarks/metrics_reference.py --results R --config C`)."""
    values, images = _prepare(ref, resolution, bins, activation, device, "reference set")
    out = {"values": values, "images": images, "self": self_distances(values, images),
           # the settings it was made for, checked by every job that reads it (_check_reference)
           "bins": torch.as_tensor(np.asarray(bins, dtype=np.int64)),
           "activation": str(activation), "resolution": int(resolution)}
    if fid_model is not None:
        from neumat.metrics import fid as fidlib
        out["fid"] = {d: torch.from_numpy(f) for d, f in
                      fidlib.features(fid_model, images, device=device).items()}
    return out


def save_reference(prepared: dict, path) -> None:
    save_torch(path, prepared)  # tensors and plain containers: loads with weights_only


def load_reference(path) -> dict:
    """A prepared reference file (rule metrics_reference), with its path under "source" for
    the errors of `_check_reference`."""
    from neumat.io import modelfile
    bundle = modelfile.require(modelfile.load(path), ("values", "images", "self"), path,
                               "a prepared reference (rule metrics_reference)")
    return {**bundle, "source": str(path)}


REBUILD_REFERENCE = ("rebuild it with its rule: snakemake <your usual options> --forcerun "
                     "metrics_reference")


def _check_reference(reference: dict, ref, resolution: int, bins, activation: str) -> None:
    """A prepared reference made for another set or other settings would score silently wrong:
    its material count, render resolution, activation and BRDF-L1 bins must be those asked
    for. A file without the settings (written before they were stored) is refused."""
    where = reference.get("source", "metrics/reference.pt")
    missing = [k for k in REFERENCE_SETTINGS if k not in reference]
    if missing:
        raise MetricsInputError(
            f"{where}: prepared reference without {', '.join(missing)} (written by an older "
            f"neumat), so whether it matches these metrics' settings cannot be checked; "
            f"{REBUILD_REFERENCE}")
    n = len(reference["values"])
    have, want = np.asarray(reference["bins"]), np.asarray(bins, dtype=np.int64)
    diffs = []
    if ref is not None and len(ref) != n:
        diffs.append(f"{n} reference materials there, {len(ref)} here")
    if int(reference["resolution"]) != resolution:
        diffs.append(f"renders of {int(reference['resolution'])} px there, {resolution} px here")
    if reference["activation"] != activation:
        diffs.append(f"activation {reference['activation']!r} there, {activation!r} here")
    if not np.array_equal(have, want):
        diffs.append(f"BRDF-L1 bins: {len(have)} there, {len(want)} here" + (
            f", {int((have != want).sum())} of them differ" if len(have) == len(want) else ""))
    if diffs:
        raise MetricsInputError(f"{where} was prepared for other settings than these metrics "
                                f"(render.resolution, fit.activation, metrics.brdf_samples, seed, "
                                f"the reference set): {'; '.join(diffs)}; {REBUILD_REFERENCE}")
    shapes = (tuple(reference["values"].shape), tuple(reference["images"].shape[:3]))
    if shapes != ((n, 3 * len(have)), (n, resolution, resolution)):
        raise MetricsInputError(f"{where}: values {shapes[0]} and renders {shapes[1]} do not fit "
                                f"its {len(have)} bins and {resolution} px: the file is damaged; "
                                f"{REBUILD_REFERENCE}")


def split_draws(smp, k: int, n_ref: int, source: str = "samples") -> list:
    """The k draws of a sample set the samplers write draw-major: k consecutive blocks of n_ref
    materials (a draw as large as the reference set, so COV and 1-NNA mean what Table 2 says).
    MetricsInputError naming `source` for any other count: it had been cut into k blocks of
    len // k with the remainder dropped and a warning in the job's log."""
    if len(smp) != k * n_ref:
        raise MetricsInputError(
            f"{source}: {len(smp)} samples, not metrics.draws {k} x the {n_ref} references: a "
            f"sample set from another config or an interrupted job; delete it and rerun its "
            f"rule (Snakemake rebuilds it)")
    from neumat.metrics import materials
    return [materials.rows(smp, slice(i * n_ref, (i + 1) * n_ref)) for i in range(k)]


def evaluate_draws(ref, draws, *, resolution: int, bins, activation="relu", fid_model=None,
                   fid_unavailable: str = "", device="cpu", refs=None,
                   reference: dict | None = None, source: str = "samples") -> pd.DataFrame:
    """Metrics of several sample draws (each a material set) against `ref`, or against
    `refs[i]` per draw when given (the reference-vs-itself sanity row). Long table with a
    `draw` column; references are rendered once when shared, or come from `reference`
    (`prepare_reference` of the same `ref` and settings), with the same results. A draw with
    non-finite BRDF values or renders is refused, naming `source` (the samples' file)."""
    t0 = time.time()

    def prepare(s, where):
        return _prepare(s, resolution, bins, activation, device, where)

    shared = shared_self = shared_fid = None
    if reference is not None:
        _check_reference(reference, ref, resolution, bins, activation)
        shared, shared_self = (reference["values"], reference["images"]), reference["self"]
        if fid_model is not None and "fid" in reference:
            shared_fid = {d: f.numpy() for d, f in reference["fid"].items()}
    elif refs is None:
        shared = prepare(ref, "reference set")
        shared_self = self_distances(*shared)  # once for every draw
    out = []
    for i, smp in enumerate(draws):
        rv, ri = shared if refs is None else prepare(refs[i], f"reference set of draw {i}")
        sv, si = prepare(smp, f"{source}, draw {i} (rows counted within the draw)")
        if fid_model is not None and refs is None and shared_fid is None:
            from neumat.metrics import fid as fidlib
            shared_fid = fidlib.features(fid_model, ri, device=device)
        table = pd.concat([fid_rows(fid_model, ri, si, fid_unavailable, device, shared_fid),
                           set_metric_rows(distance_matrices(rv, sv, ri, si, shared_self))],
                          ignore_index=True)
        out.append(table.assign(draw=i))
        log.info("draw %d: %d vs %d materials, %.1fs so far", i, len(sv), len(rv), time.time() - t0)
    return pd.concat(out, ignore_index=True)[["draw", *COLUMNS]]


def evaluate_halves(reference: dict, splits, *, ref, resolution: int, bins, activation="relu",
                    fid_model=None, fid_unavailable: str = "", device="cpu") -> pd.DataFrame:
    """The sanity row from the prepared reference alone (`prepare_reference`): per split (a
    permutation of the reference set), its second half scored as a draw against its first.
    Every number it needs is a sub-matrix of the reference's self-distances or rows of its
    Inception features, so nothing is rendered or compared again. A reference prepared without
    an Inception network has its renders embedded here once with `fid_model` (as
    `evaluate_draws` does); without either, FID is unavailable, with `fid_unavailable`. Long
    table with a `draw` column, as `evaluate_draws`. `ref`, `resolution`, `bins`,
    `activation`: the set and settings it must have been prepared for."""
    _check_reference(reference, ref, resolution, bins, activation)
    n = len(reference["values"])
    h = n // 2
    if h < 2:
        raise ValueError(f"{n} reference materials cannot make two halves of at least 2")
    if "fid" in reference:
        feats = {d: f.numpy() for d, f in reference["fid"].items()}
    elif fid_model is not None:
        from neumat.metrics import fid as fidlib
        feats = fidlib.features(fid_model, reference["images"], device=device)
    else:
        feats = None
    out = []
    for i, order in enumerate(splits):
        a, b = (torch.as_tensor(np.asarray(order[s]), dtype=torch.long)
                for s in (slice(0, h), slice(h, 2 * h)))
        mats = {name: (d[a][:, a], d[b][:, b], d[a][:, b]) for name, d in reference["self"].items()}
        fid = (_fid_table({k: f[a.numpy()] for k, f in feats.items()},
                          {k: f[b.numpy()] for k, f in feats.items()})
               if feats is not None else fid_rows(None, None, None, fid_unavailable))
        out.append(pd.concat([fid, set_metric_rows(mats)], ignore_index=True).assign(draw=i))
    return pd.concat(out, ignore_index=True)[["draw", *COLUMNS]]


def novelty_bins(bins, n: int, seed: int) -> np.ndarray:
    """The novelty rows' bins: a sorted random subset of n of the BRDF-L1 `bins` (all when
    fewer), drawn with `seed` - a stream of its own (rule metrics' novelty_seed), not the one
    that drew `bins`."""
    bins = np.asarray(bins)
    pick = np.random.default_rng(seed).choice(len(bins), min(n, len(bins)), replace=False)
    return bins[np.sort(pick)]


def novelty_rows(smp_values, train_values, ref_values=None) -> pd.DataFrame:
    """Off-manifold check: median BRDF-L1 from each sample to its nearest training material
    ('Novelty', 'BRDF-L1'), and the same for the reference set ('Novelty', 'reference') - real
    unseen materials, the scale a good generator's samples should sit at."""
    from neumat.diffusion.dataset import nearest
    rows = [("Novelty", "BRDF-L1", float(np.median(nearest(smp_values, train_values)[1])),
             "median BRDF-L1 to the nearest training material")]
    if ref_values is not None:
        rows.append(("Novelty", "reference", float(np.median(nearest(ref_values, train_values)[1])),
                     "the same for the reference set"))
    return pd.DataFrame(rows, columns=COLUMNS)


def novelty_table(results: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """Per column: median nearest-training distance (mean ± std over draws) and its ratio to
    the reference set's (M3ashy's samples should be new but plausible: ratio near 1; a ratio
    near 0 means near-copies of training materials, far above 1 off-manifold samples)."""
    rows = []
    for model, df in results.items():
        nov = df[df["metric"] == "Novelty"]
        if nov.empty:
            continue
        bad = int((~np.isfinite(nov["value"])).sum())
        if bad:
            raise MetricsInputError(f"novelty of model {model!r}: {bad} non-finite values; "
                                    "rebuild its metrics with rule metrics (--forcerun)")
        s = nov.loc[nov["distance"] == "BRDF-L1", "value"]
        r = nov.loc[nov["distance"] == "reference", "value"]
        rows.append({"model": MODEL_NAMES.get(model, model), "median nearest BRDF-L1": s.mean(),
                     "std over draws": s.std(ddof=1) if len(s) > 1 else np.nan,
                     "reference": r.mean(), "ratio to reference": s.mean() / r.mean()})
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------- Table 2

# display factors of the row labels, shown = value x factor ("RMSE x10^2": 0.0754 -> 7.54;
# "NegSSIM x10": -0.955 -> -9.55), as in the paper. MMD BRDF-L1 is shown as it is (about 1.6
# on physical MERL values here): the paper's "x10^-3" would print 0.00164, its released code
# being on another BRDF scale.
FACTORS = {("MMD", "RMSE"): 1e2, ("MMD", "NegSSIM"): 1e1}
_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")
ARROWS = {"FID": "↓", "MMD": "↓", "COV": "↑", "1-NNA": "↓"}


ROW_ORDER = [("FID", d) for d in FID_DIMS.values()] + [(m, d) for m in SET_METRICS
                                                       for d in D.DISTANCES]


def _row_label(metric, distance):
    if metric == "FID":
        return "FID (↓)", {"Inception-v3": "2048-d", "Inception-64": "64-d (as M³ashy code)"}[distance]
    factor = FACTORS.get((metric, distance))
    exp = round(np.log10(factor)) if factor else 0
    scale = "" if not factor else " ×10" + ("" if exp == 1 else str(exp).translate(_SUPERSCRIPT))
    pct = " (%)" if metric in ("COV", "1-NNA") else ""
    return f"{metric}{pct} ({ARROWS[metric]})", f"{distance}{scale}"


def table2(results: dict[str, pd.DataFrame], sources: dict | None = None) -> pd.DataFrame:
    """{model: metrics table} -> wide table: rows (metric, distance) in paper order, one column
    per model, values x the display factors, mean ± std over the draws of a long table (rows
    repeated per draw, `_display`); FID unavailable in every draw (its note says why) is 'n/a'.
    Any other row finite in fewer draws than the table has is an error naming the model and
    the row (and its file, from `sources`): a mean over the finite draws would pass unnoticed."""
    cols = {}
    for model, df in results.items():
        missing = set(ROW_ORDER) - set(zip(df["metric"], df["distance"]))
        if missing:
            raise ValueError(f"metrics of model {model!r} lack rows {sorted(missing)}")
        where = f"model {model!r}" + (f" ({sources[model]})" if sources and model in sources else "")
        draws = df["draw"].nunique() if "draw" in df.columns else 1
        ok = df.assign(value=df["value"].where(np.isfinite(df["value"])))
        g = ok.groupby(["metric", "distance"])["value"]
        mean, std, n = g.mean(), g.std(ddof=1), g.count()
        notes = df.groupby(["metric", "distance"])["note"].agg(
            lambda x: x.astype(str).str.startswith("unavailable").all())
        for m, d in ROW_ORDER:
            if n[(m, d)] >= draws or (m == "FID" and n[(m, d)] == 0 and notes[(m, d)]):
                continue
            raise MetricsInputError(
                f"{where}: {m} {d} is finite in {n[(m, d)]} of {draws} draws (NaN or inf in the "
                "others), and a mean over fewer draws than the other cells would pass unnoticed. "
                "The metrics refuse non-finite samples, so the file was written by an older "
                "neumat or by hand: rebuild it with rule metrics (--forcerun)")
        cols[model] = [_display(m, d, mean[(m, d)], std[(m, d)] if n[(m, d)] > 1 else None)
                       for m, d in ROW_ORDER]
    index = pd.MultiIndex.from_tuples([_row_label(m, d) for m, d in ROW_ORDER],
                                      names=["metric", "distance"])
    return pd.DataFrame(cols, index=index)


def _decimals(x: float, digits: int) -> int:
    """Decimal places that give finite nonzero `x` `digits` significant digits (negative:
    round left of the point), counted after rounding (9.996 -> 10.0, not 10.00)."""
    e = int(np.floor(np.log10(abs(x))))
    k = digits - 1 - e
    r = round(x, k)
    return k - 1 if r != 0 and np.floor(np.log10(abs(r))) > e else k


def format_cell(value: float, std: float | None = None) -> str:
    """'mean ± std' in fixed notation, never scientific: the mean to 3 significant digits, the
    std to the same decimal place (1.6734 ± 0.0521 -> '1.67 ± 0.05'; 123456 -> '123000';
    a zero mean takes the std's place at 2 digits); 'n/a' when the mean is not finite."""
    if not np.isfinite(value):
        return "n/a"
    has_std = std is not None and np.isfinite(std)
    if value != 0:
        k = _decimals(value, 3)
    else:
        k = _decimals(std, 2) if has_std and std != 0 else 0

    def fixed(x):
        return f"{round(x, k) + 0.0:.{max(k, 0)}f}"  # + 0.0: no '-0'
    return fixed(value) + (f" ± {fixed(std)}" if has_std else "")


def _display(metric, distance, value, std=None):
    """Displayed cell: value x factor (x 100 for the percentages), '± std' over draws when
    there are several (`format_cell`)."""
    k = (100 if metric in ("COV", "1-NNA") else 1) * FACTORS.get((metric, distance), 1.0)
    return format_cell(value * k, None if std is None else std * k)


# column headers of the paper's Table 2 (other model keys are shown as they are)
MODEL_NAMES = {"training_set": "Training set", "pca_a": "PCA-A", "pca_n": "PCA-N",
               "vae_a": "VAE-A", "vae_n": "VAE-N", "merl100": "MERL100", "ours": "ours",
               "reference_halves": "Reference halves"}


def sanity(halves: pd.DataFrame, training: pd.DataFrame | None = None,
           band=(0.3, 0.7)) -> tuple[pd.DataFrame, list[str]]:
    """Sanity rows: 1-NNA (mean, std over draws) of reference halves against each other and
    of the Training-set column, and the problems found: the halves' 1-NNA must sit near 50 %
    (inside `band`), or the protocol cannot tell distributions apart."""
    rows, problems = [], []
    for name, df in (("reference_halves", halves), ("training_set", training)):
        if df is None:
            continue
        for d in D.DISTANCES:
            v = df.loc[(df["metric"] == "1-NNA") & (df["distance"] == d), "value"]
            if not np.isfinite(v).all():
                raise MetricsInputError(f"sanity row {name!r}: 1-NNA {d} is not finite in "
                                        f"{int((~np.isfinite(v)).sum())} of {len(v)} draws; "
                                        "rebuild its metrics with rule metrics (--forcerun)")
            rows.append((MODEL_NAMES[name], d, 100 * v.mean(), 100 * v.std(ddof=1) if len(v) > 1 else np.nan))
            if name == "reference_halves" and not band[0] <= v.mean() <= band[1]:
                problems.append(f"reference halves 1-NNA ({d}) = {100 * v.mean():.1f} %, outside "
                                f"{100 * band[0]:.0f}-{100 * band[1]:.0f} %")
    return pd.DataFrame(rows, columns=["set", "distance", "1-NNA mean (%)", "1-NNA std (%)"]), problems


def write_table2(results: dict[str, pd.DataFrame], csv, md, html,
                 sources: dict | None = None) -> pd.DataFrame:
    t = table2(results, sources).rename(columns=MODEL_NAMES)
    t.to_csv(csv)
    flat = t.reset_index()
    flat.loc[flat["metric"].duplicated(), "metric"] = ""  # paper style: label once per block
    with open(md, "w") as f:
        f.write(flat.to_markdown(index=False) + "\n")
    with open(html, "w") as f:
        f.write(t.to_html(border=0, classes="table2") + "\n")
    return t
