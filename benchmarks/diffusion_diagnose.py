"""Why `ours` samples sit off the training manifold, and what the clamp-aware sampling
constraint (diffusion.sample.negative_step) does: cheap measurements on a trained model, CPU.

  loss   : the model's x0-MSE at a fixed grid of t on train-split and held-out test-split weights
           (same noise), next to three reference denoisers on the same x_t:
             gauss  - the linear MMSE denoiser of a Gaussian with the training covariance
                      (what a model that learned only second-order statistics reaches),
             memo   - the exact posterior mean of the empirical training distribution (a model
                      that memorised every training item; on test items it shows the cost of
                      memorising), also for a 100-item subset (MERL100-sized),
             zero   - predict the mean (x0_hat = 0).
           And in function space: the training loss's field term for the model's x0 and the
           share of bins its BRDF clamps, next to the clean weights' own share.
           Plus the covariance spectrum of the standardised weights and the per-coordinate
           variance of the test split in the training standardisation.
  roundtrip: one denoising pass of real materials (train and test split) at small t: the
           BRDF-L1 from the model's x0 prediction to the material itself, and the x0-MSE per
           NBRDF tensor (a denoiser should be near the identity at t = 0).
  sample : for each sampling setting (steps, eta, clip, negative_step) and seed: the share of
           samples with a clamped-negative bin, the mean share of such bins (plausibility.py,
           same bins and seed as the workflow) and the median BRDF-L1 to the nearest training
           material (diffusion_nearest: same bins and seed), next to the real fits' figures
           (--real). Setting keys: steps, eta, clip, negative_step, and gauss_below (the
           Gaussian MMSE denoiser replaces the model below that t: an experiment). Where the
           run has metrics/reference.pt: dark_share, the share of samples whose metric render
           is as dark as the references' darkest fifth (20 % would match them; kinds --by
           brightness), and dark_any_negative, the share of those that clamp a bin.
  kinds  : where Table 2's image rows are won and lost: for every column of a finished run
           (its samples/<column>/ files, cut into the run's draws) the terms of MMD and COV
           under render RMSE, i.e. each reference's distance to its nearest sample and whether
           it is some sample's nearest reference, averaged per kind of reference (--by
           operation: the AugMERL operation that made it, original, permutation,
           interpolation; --by type: its material type), mean and std over draws. The
           references' renders come from the run's metrics/reference.pt; no model.
           --exposure E1 E2 ...: the samples also rendered E stops brighter (negative: darker)
           than the metric view, as rows "<column> <E:+g>": does a global exposure offset
           explain a column's loss?
           --by brightness: the references in fifths by the mean sRGB of their metric render
           (Q1 darkest), with each column's share of samples whose render falls in each fifth
           ("samples %": 20 % each would match the references).
           --linear: MMD RMSE also on the renders decoded to linear light (the inverse sRGB
           curve), where an error near black weighs up to 12.92x less than in sRGB.

The model is a workflow model.pt or a train_diffusion checkpoint.pt (its EMA weights; the
normaliser is refitted on the training rows, exactly as train() does).

  python benchmarks/diffusion_diagnose.py loss --model M --results R
  python benchmarks/diffusion_diagnose.py roundtrip --model M --results R --n 256
  python benchmarks/diffusion_diagnose.py sample --model M --results R --n 128 --seeds 0 1 \
      --grid steps=100,eta=0,negative_step=0 --grid steps=100,eta=0,negative_step=1
  python benchmarks/diffusion_diagnose.py kinds --results R --draws 3
  python benchmarks/diffusion_diagnose.py kinds --results R --draws 1 --by type --exposure -0.15 -0.5
  python benchmarks/diffusion_diagnose.py kinds --results R --draws 3 --by brightness --linear
"""

import argparse
import itertools
import os
import time

import numpy as np
import pandas as pd
import torch

from neumat import machine, nbrdf
from neumat.diffusion import DenoiserConfig, Sampler, ScheduleConfig, dataset, plausibility
from neumat.diffusion.constraints import constraint_directions
from neumat.diffusion.field_loss import field_error
from neumat.diffusion.model import Normalizer
from neumat.diffusion.schedule import RowNoise
from neumat.io import modelfile
from neumat.metrics import distances, evaluate, materials
from neumat.render import sphere
from neumat.seeds import seed_for

T_GRID = [0, 25, 50, 100, 200, 300, 400, 500, 600, 700, 800, 900, 999]


def load(model_path, results, model="ours", width=256, depth=4, heads=8, n_classes=48,
         timesteps=1000, kind="cosine", prediction="x0"):
    weights = np.load(f"{results}/neumerl/weights.npy")
    man = dataset.read_manifest(f"{results}/neumerl/manifest.tsv", len(weights))
    rows = dataset.training_rows(man, model)
    b = modelfile.load(model_path)
    if "normalizer" not in b:  # a checkpoint: rebuild the bundle the way train() writes it
        norm = Normalizer.fit(torch.from_numpy(weights[rows]))
        # the tokenisation from the input maps: 6 = one token per tensor, else the widest piece
        ins = [v.shape[1] for k, v in b["ema"].items() if k.startswith("embed_in.") and
               k.endswith(".weight")]
        b = {"model_cfg": DenoiserConfig(width=width, depth=depth, heads=heads,
                                         n_classes=n_classes,
                                         token_values=0 if len(ins) == 6 else max(ins)).to_dict(),
             "sched_cfg": ScheduleConfig(timesteps=timesteps, kind=kind,
                                         prediction=prediction).to_dict(),
             "class_names": [f"c{i}" for i in range(n_classes)], "ema": b["ema"],
             "normalizer": {k: v for k, v in norm.state_dict().items()},
             "step": b["step"]}
    print(f"model {model_path}: step {b.get('step', 'final')}", flush=True)
    return Sampler(b, "cpu"), weights, man, rows


def x0_hat(sampler, xt, tb):
    """The model's x0 prediction at x_t, whatever it predicts (x0, eps or v)."""
    ab = sampler.diffusion.alpha_bar[tb].to(xt.dtype)[:, None]
    return sampler.diffusion.split(sampler.model(xt, tb, None), xt, ab)[0]


@torch.no_grad()
def loss_table(sampler, x_train, x_test, live, seed=0, n=480):
    """Per-t x0-MSE (standardised units) of the model and the reference denoisers, over the
    `live` coordinates (bool (675,)); 'model_frozen' is the model's over the others. 'field':
    the training loss's field term for the model's x0 (neumat.diffusion.field_loss, eps 3e-3,
    1024 valid MERL bins, unweighted); 'clamped': the share of those bins (x 3 channels) where
    the predicted x0's BRDF is clamped, 'clamped_x0' the clean weights' own."""
    d = sampler.diffusion
    dirs = constraint_directions(0, 1024)
    g = torch.Generator().manual_seed(seed)
    tr = x_train[torch.randperm(len(x_train), generator=g)[:n]]
    te = x_test[:n]
    cov = torch.cov(x_train.T.double())
    lam, vec = torch.linalg.eigh(cov)
    lam = lam.clamp_min(0)
    sub = x_train[torch.randperm(len(x_train), generator=g)[:100]]
    rows = []
    for t in T_GRID:
        ab = d.alpha_bar[t].item()
        a, s = ab ** 0.5, (1 - ab) ** 0.5
        for split, x0 in (("train", tr), ("test", te)):
            eps = torch.randn(x0.shape, generator=g)
            xt = a * x0 + s * eps
            tb = torch.full((len(x0),), t, dtype=torch.long)
            pred = x0_hat(sampler, xt, tb)
            w_hat, w0 = sampler.norm.decode(pred), sampler.norm.decode(x0)
            field = {"field": float(field_error(w_hat, w0, dirs, 3e-3).mean()),
                     "clamped": float((nbrdf.forward_raw(w_hat, dirs) < 0).float().mean()),
                     "clamped_x0": float((nbrdf.forward_raw(w0, dirs) < 0).float().mean())}
            frozen = mse(pred[:, ~live], x0[:, ~live]) if (~live).any() else float("nan")
            pred, x0, xt_all = pred[:, live], x0[:, live], xt
            # Gaussian MMSE: Sigma a (a^2 Sigma + s^2 I)^-1 x_t, in the eigenbasis
            c = (xt_all.double() @ vec) * (a * lam / (a * a * lam + s * s))
            gauss = (c @ vec.T).float()[:, live]
            row = {"t": t, "alpha_bar": ab, "split": split,
                   "model": mse(pred, x0), "gauss": mse(gauss, x0), "zero": mse(0 * x0, x0),
                   "memo": mse(memorised(xt_all, x_train, a, s)[:, live], x0),
                   "model_frozen": frozen, **field}
            if split == "train":  # the 100-item memoriser on its own items
                m = memorised(a * sub + s * eps[:len(sub)], sub, a, s)
                row["memo100"] = mse(m[:, live], sub[:, live])
            rows.append(row)
    return pd.DataFrame(rows)


def mse(p, x):
    return float(((p - x) ** 2).mean())


def memorised(xt, items, a, s):
    """E[x0 | x_t] when x0 is uniform over `items`: a softmax-weighted mean of the items."""
    if s == 0:
        s = 1e-6
    d2 = torch.cdist(xt.double(), a * items.double()) ** 2
    w = torch.softmax(-d2 / (2 * s * s), 1)
    return (w @ items.double()).float()


def uniform_t_mean(df, col, split, timesteps=1000):
    """Mean over t uniform in [0, T) (the training loss's t distribution), by interpolating the
    per-t values on the grid."""
    s = df[df["split"] == split]
    return float(np.interp(np.arange(timesteps), s["t"], s[col]).mean())


def cmd_loss(a):
    sampler, weights, man, rows = load(a.model, a.results, a.which)
    norm = sampler.norm
    x_train = norm.encode(torch.from_numpy(weights[rows]))
    x_test = norm.encode(torch.from_numpy(weights[dataset.reference_rows(man)]))
    raw_std = torch.from_numpy(weights[rows]).std(0)
    live = raw_std > a.frozen_std
    print(f"{int((~live).sum())} of {len(live)} coordinates are frozen (training std <= "
          f"{a.frozen_std:g}: dead units of the shared fit template); their standardised values "
          f"are float32 noise: {int(((raw_std > 1e-6) & ~live).sum())} have std in (1e-6, "
          f"{a.frozen_std:g}] and become unit-variance noise. Losses below: live coordinates.")
    t0 = time.perf_counter()
    df = loss_table(sampler, x_train, x_test, live)
    pd.set_option("display.width", 200)
    print(df.to_string(index=False, float_format="%.4f"))
    print("\nmean over uniform t (the training loss's weighting):")
    for col in ("model", "gauss", "memo", "zero", "model_frozen", "field", "clamped"):
        print(f"  {col:6s} train {uniform_t_mean(df, col, 'train'):.4f}   "
              f"test {uniform_t_mean(df, col, 'test'):.4f}")
    print(f"  memo100 (100-item memoriser on its items) {uniform_t_mean(df, 'memo100', 'train'):.4f}")
    k = float(live.float().mean())  # the training loss averages all coordinates; frozen ones ~0
    print(f"on all {len(live)} coordinates (the logged training loss's scale, x {k:.3f}): model "
          f"train {k * uniform_t_mean(df, 'model', 'train'):.4f}, gauss "
          f"{k * uniform_t_mean(df, 'gauss', 'train'):.4f}, memo {k * uniform_t_mean(df, 'memo', 'train'):.4f}, "
          f"memo100 {k * uniform_t_mean(df, 'memo100', 'train'):.4f}, zero "
          f"{k * uniform_t_mean(df, 'zero', 'train'):.4f}")
    lam = torch.linalg.eigvalsh(torch.cov(x_train.T.double())).flip(0).numpy()
    share = np.cumsum(lam) / lam.sum()
    print(f"\nstandardised training weights: {len(x_train)} x {x_train.shape[1]}; covariance "
          f"eigenvalues {lam[0]:.1f}, {lam[1]:.1f}, {lam[2]:.1f}, ...; components for 50/90/99 % of "
          f"the variance: {[int(np.searchsorted(share, q)) + 1 for q in (0.5, 0.9, 0.99)]}")
    var_te = x_test[:, live].var(0).numpy()
    std = norm.std.numpy()
    print(f"test split in the training standardisation (live coordinates): per-coordinate variance median "
          f"{np.median(var_te):.3f}, 5-95 % {np.percentile(var_te, 5):.3f}-"
          f"{np.percentile(var_te, 95):.3f}, max {var_te.max():.1f}; training std min "
          f"{std.min():.2e}, coordinates with std < 1e-3: {(std < 1e-3).sum()}")
    print(f"[{time.perf_counter() - t0:.1f} s; {machine.describe()}]")


@torch.no_grad()
def cmd_roundtrip(a):
    """How far one denoising pass moves a real material: x0 -> x_t -> model x0_hat, as BRDF-L1
    to the material itself, and the x0-MSE per NBRDF tensor (standardised, live coordinates)."""
    sampler, weights, man, rows = load(a.model, a.results, a.which)
    norm, d = sampler.norm, sampler.diffusion
    bins = distances.brdf_sample(a.nn_bins, seed_for(a.seed, "diffusion_nearest"))
    fv = lambda w: distances.field_values(w, bins, a.activation)  # noqa: E731
    live = torch.from_numpy(weights[rows]).std(0) > a.frozen_std
    g = torch.Generator().manual_seed(0)
    sets = {"train": weights[rows][torch.randperm(len(rows), generator=g)[:a.n].numpy()],
            "test": weights[dataset.reference_rows(man)][:a.n]}
    sizes = [int(np.prod(s)) for s in nbrdf.PARAM_SHAPES]  # per NBRDF tensor, not per token
    out = []
    for split, w in sets.items():
        x0 = norm.encode(torch.from_numpy(w))
        f0 = fv(w)
        for t in (0, 10, 50, 100, 300):
            ab = d.alpha_bar[t].item()
            xt = ab ** 0.5 * x0 + (1 - ab) ** 0.5 * torch.randn(x0.shape, generator=g)
            pred = x0_hat(sampler, xt, torch.full((len(x0),), t, dtype=torch.long))
            l1 = torch.diagonal(distances.pairwise_l1(fv(norm.decode(pred).numpy()), f0)).numpy()
            l1_xt = torch.diagonal(distances.pairwise_l1(fv(norm.decode(xt / ab ** 0.5).numpy()),
                                                         f0)).numpy()
            row = {"split": split, "t": t, "median_l1_x0hat": float(np.median(l1)),
                   "median_l1_xt_rescaled": float(np.median(l1_xt))}
            err = ((pred - x0) ** 2) * live
            k = 0
            for name, n in zip(nbrdf.PARAM_NAMES, sizes):
                m = live[k:k + n]
                row[f"mse_{name}"] = float(err[:, k:k + n][:, m].mean()) if m.any() else float("nan")
                k += n
            out.append(row)
            print(pd.DataFrame(out[-1:]).to_string(index=False, header=len(out) == 1,
                                                   float_format="%.4f"), flush=True)
    print(f"live coordinates per tensor: "
          f"{dict(zip(nbrdf.PARAM_NAMES, [int(m.sum()) for m in torch.split(live, sizes)]))}; "
          f"token width {sampler.model.cfg.width}")
    print(f"[{machine.describe()}]")


@torch.no_grad()
def hybrid_sample(sampler, train_w, n, seed, cfg, activation):
    """DDIM where the x0 prediction for t < cfg['gauss_below'] comes from the linear MMSE
    (Gaussian) denoiser of the training weights instead of the model (an experiment: the model's
    low-t error floor vs a denoiser that is exact at low noise)."""
    from neumat.diffusion.constraints import constraint_for

    x = sampler.norm.encode(torch.from_numpy(train_w)).double()
    lam, vec = torch.linalg.eigh(torch.cov(x.T))
    lam = lam.clamp_min(0)
    alpha_bar, cut = sampler.diffusion.alpha_bar, int(cfg["gauss_below"])

    def predict(xt, tb):
        t = int(tb[0])
        if t >= cut:
            return sampler.model(xt, tb, None)
        ab = alpha_bar[t].item()
        a_, s2 = ab ** 0.5, 1 - ab
        c = (xt.double() @ vec) * (a_ * lam / (ab * lam + s2))
        x0 = (c @ vec.T).to(xt.dtype)
        kind = sampler.diffusion.cfg.prediction  # the Gaussian x0 as the model's output kind
        eps = (xt - a_ * x0) / s2 ** 0.5
        return {"x0": x0, "eps": eps, "v": a_ * eps - s2 ** 0.5 * x0}[kind]

    rows = RowNoise(seed_for(seed, "ddim"), nbrdf.N_PARAMS)  # Sampler.sample's noise
    z = sampler.diffusion.ddim_sample(predict, (n, nbrdf.N_PARAMS), cfg["steps"], cfg["eta"], None,
                                      "cpu", clip=cfg["clip"], noise=rows.batch(0, n),
                                      constrain=constraint_for(sampler, cfg["negative_step"],
                                                               seed, activation))
    return sampler.norm.decode(z).float().numpy()


def nearest_quantiles(f, f_train):
    """Quartiles of the BRDF-L1 to the nearest training material (the median is the report's
    novelty figure; the quartiles show how stable it is)."""
    q = np.percentile(dataset.nearest(f, f_train)[1], [25, 50, 75])
    return {"nearest_l1_q25": q[0], "median_nearest_l1": q[1], "nearest_l1_q75": q[2]}


def cmd_sample(a):
    sampler, weights, man, rows = load(a.model, a.results, a.which)
    bins = distances.brdf_sample(a.nn_bins, seed_for(a.seed, "diffusion_nearest"))
    fv = lambda w: distances.field_values(np.nan_to_num(w), bins, a.activation)  # noqa: E731
    f_train = fv(weights[rows])
    kw = dict(n_angles=a.angles, seed=seed_for(a.seed, "diffusion_plausibility"),
              activation=a.activation, albedo_kw=dict(n_theta_o=4, n_theta_h=32, n_phi_h=32))
    out = []
    # the darkest fifth of the references by render brightness (kinds --by brightness), where
    # the run's metrics/reference.pt exists: how many samples land there, and how many of those
    # clamp a bin
    ref_path = f"{a.results}/metrics/reference.pt"
    ri = evaluate.load_reference(ref_path)["images"] if os.path.exists(ref_path) else None
    dark_edge = np.quantile(brightness(ri), BRIGHTNESS_FIFTHS[0]) if ri is not None else None

    def darkness(w, pl):
        if ri is None:
            return {}
        dark = brightness(materials.renders(np.nan_to_num(w), ri.shape[1], a.activation)) < dark_edge
        return {"dark_share": dark.mean(),
                "dark_any_negative": (pl["negative_share"][dark] > 0).mean() if dark.any() else np.nan}

    def row(name, w, seconds=float("nan"), nearest=True, **extra):
        pl = plausibility.plausibility(w, **kw)
        s = plausibility.summarize(pl)
        out.append({"set": name, **extra, "n": len(w),
                    "share_any_negative": s["share_any_negative"],
                    "mean_negative_share": s["mean_negative_share"],
                    "median_max_albedo": s["median_max_albedo"],
                    "share_passivity_violation": s["share_passivity_violation"],
                    **(nearest_quantiles(fv(w), f_train) if nearest else {}),
                    **darkness(w, pl),
                    "seconds": seconds})
        print(pd.DataFrame(out[-1:]).to_string(index=False, header=len(out) == 1,
                                               float_format="%.4f"), flush=True)

    ref = weights[dataset.reference_rows(man)]
    if a.real:  # the training split is its own nearest neighbour: no distance
        row("real: NeuMERL train split", weights[rows], nearest=False)
        row("real: test split (reference)", ref)
    for spec in a.grid:
        cfg = dict(steps=100, eta=0.0, clip=None, negative_step=0.0, gauss_below=0)
        for kv in spec.split(","):
            k, v = kv.split("=")
            cfg[k] = None if v == "none" else (int(v) if k == "steps" else float(v))
        for seed in a.seeds:
            t0 = time.perf_counter()
            if cfg.get("gauss_below"):  # hybrid denoiser: Gaussian MMSE below that t
                w = hybrid_sample(sampler, weights[rows], a.n, seed, cfg, a.activation)
            else:
                w = sampler.sample(a.n, seed, None, cfg["steps"], cfg["eta"], 1.0, 256,
                                   cfg["clip"], cfg["negative_step"], a.activation)
            row("ours", w, time.perf_counter() - t0, **cfg, seed=seed)
    df = pd.DataFrame(out)
    if a.csv:
        df.to_csv(a.csv, sep="\t", index=False, float_format="%.6g")
    keys = ["steps", "eta", "clip", "negative_step", "gauss_below"]
    agg = df[df["set"] == "ours"].fillna({"clip": -1}).groupby(keys)[
        ["share_any_negative", "mean_negative_share", "share_passivity_violation",
         "median_nearest_l1", *(["dark_share", "dark_any_negative"] if ri is not None else [])]
    ].agg(["mean", "std"])
    print("\nmean (std) over seeds; clip -1 = none\n" + agg.to_string(float_format="%.4f"))
    print(f"[{machine.describe()}]")


COLUMNS = ["training", "pca_a", "pca_n", "vae_a", "vae_n", "merl100", "ours"]


BRIGHTNESS_FIFTHS = [0.2, 0.4, 0.6, 0.8]


def brightness(images: torch.Tensor) -> np.ndarray:
    """Mean sRGB of each metric render (N, H, W, 3) -> (N,)."""
    return images.flatten(1).mean(1).numpy()


def fifth_of(images: torch.Tensor, edges: np.ndarray) -> np.ndarray:
    """Each render's brightness fifth, "Q1" (darkest) to "Q5", between the references' `edges`."""
    return np.array([f"Q{q + 1}" for q in np.searchsorted(edges, brightness(images))])


def reference_kinds(results, ri, by="operation"):
    """Each reference's AugMERL operation (original, permutation, interpolation), material type
    (`by` "type"), or fifth by render brightness (`by` "brightness"; also returns the fifths'
    edges, else None)."""
    n = len(ri)
    if by == "brightness":
        edges = np.quantile(brightness(ri), BRIGHTNESS_FIFTHS)
        return fifth_of(ri, edges), edges
    man = pd.read_csv(f"{results}/augmerl/manifest.tsv", sep="\t", keep_default_na=False)
    ids = pd.read_csv(f"{results}/samples/reference/samples.tsv", sep="\t")["id"]
    kind = man.set_index("id").loc[ids, by].to_numpy()
    if len(kind) != n:
        raise SystemExit(f"{len(kind)} reference ids for {n} prepared renders: "
                         "metrics/reference.pt is not this run's reference set")
    return kind, None


def nearest_terms(ri, si):
    """Per reference: render RMSE to its nearest sample (MMD's terms) and whether it is some
    sample's nearest reference (COV's), between reference renders ri and sample renders si."""
    rs = torch.as_tensor(distances.IMAGE_DISTANCES["RMSE"](ri, si))
    covered = np.zeros(len(ri), bool)
    covered[rs.argmin(0).unique().numpy()] = True
    return rs.min(1).values.numpy(), covered


def cmd_kinds(a):
    ri = evaluate.load_reference(f"{a.results}/metrics/reference.pt")["images"]
    kind, edges = reference_kinds(a.results, ri, a.by)
    ri_linear = sphere.srgb_decode(ri) if a.linear else None
    out = []
    for col in COLUMNS:
        path = next((f"{a.results}/samples/{col}/{f}" for f in ("weights.npy", "tables.npz")
                     if os.path.exists(f"{a.results}/samples/{col}/{f}")), None)
        if path is None:
            print(f"{col}: no samples, skipped")
            continue
        s = materials.load(path)
        n = len(s) // a.draws
        for d, e in itertools.product(range(a.draws), [0.0, *a.exposure]):
            si = materials.renders(materials.rows(s, slice(d * n, (d + 1) * n)), ri.shape[1],
                                   a.activation, exposure=e)
            nearest, covered = nearest_terms(ri, si)
            extra = {}
            if a.linear:
                extra["MMD linear RMSE x10^2"] = nearest_terms(ri_linear, sphere.srgb_decode(si))[0]
            if edges is not None:
                fifth = fifth_of(si, edges)
            for k in [*np.unique(kind), "all"]:
                m = kind == k if k != "all" else np.ones(len(kind), bool)
                row = {"kind": f"{k or '(untyped)'} ({m.sum()})", "draw": d,
                       "column": col if e == 0 else f"{col} {e:+g}",
                       "MMD RMSE x10^2": 100 * nearest[m].mean(),
                       "COV RMSE %": 100 * covered[m].mean()}
                row.update({key: 100 * v[m].mean() for key, v in extra.items()})
                if edges is not None:
                    row["samples %"] = 100 * (np.mean(fifth == k) if k != "all" else 1.0)
                out.append(row)
        print(f"{col}: {a.draws} draws of {n}", flush=True)
    if edges is not None:
        print("reference fifths by mean sRGB of the metric render, edges "
              + ", ".join(f"{x:.3f}" for x in edges))
    stats = [c for c in out[0] if c not in ("kind", "draw", "column")]
    t = pd.DataFrame(out).groupby(["kind", "column"], sort=False)[stats].agg(["mean", "std"])
    pd.set_option("display.width", 200)
    print(t.to_string(float_format="%.2f"))
    print(f"[{machine.describe()}]")


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("command", choices=["loss", "roundtrip", "sample", "kinds"])
    p.add_argument("--model", help="model.pt or checkpoint.pt of train_diffusion (not for kinds)")
    p.add_argument("--draws", type=int, default=3, help="kinds: the run's metrics.draws")
    p.add_argument("--by", choices=["operation", "type", "brightness"], default="operation",
                   help="kinds: group the references by AugMERL operation, material type or "
                        "fifth of render brightness")
    p.add_argument("--linear", action="store_true",
                   help="kinds: MMD RMSE also on the renders decoded to linear light")
    p.add_argument("--exposure", type=float, nargs="*", default=[],
                   help="kinds: also render the samples these stops brighter (negative: darker)")
    p.add_argument("--results", required=True, help="results/<run> directory (neumerl/ inside)")
    p.add_argument("--which", default="ours", choices=dataset.MODELS)
    p.add_argument("--seed", type=int, default=0, help="config seed (named streams)")
    p.add_argument("--n", type=int, default=128, help="samples per setting and seed")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--grid", action="append", default=[],
                   help="a sampling setting, e.g. steps=100,eta=0,clip=none,negative_step=1")
    p.add_argument("--nn-bins", type=int, default=20000)
    p.add_argument("--angles", type=int, default=20000)
    p.add_argument("--activation", default="relu")
    p.add_argument("--csv")
    p.add_argument("--real", action="store_true", help="also the real fits' figures")
    p.add_argument("--frozen-std", type=float, default=1e-4,
                   help="coordinates with a training std at most this are 'frozen'")
    a = p.parse_args()
    torch.set_num_threads(1)
    if a.command != "kinds" and not a.model:
        p.error(f"{a.command} needs --model")
    if a.command == "kinds":
        cmd_kinds(a)
    elif a.command == "loss":
        cmd_loss(a)
    elif a.command == "roundtrip":
        cmd_roundtrip(a)
    else:
        if not a.grid:
            a.grid = ["steps=100,eta=0,negative_step=0"]
        cmd_sample(a)


if __name__ == "__main__":
    main()
