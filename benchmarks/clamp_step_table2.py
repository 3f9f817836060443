"""Table 2 against the clamp step (`diffusion.sample.negative_step`, lambda), on a finished run.

With `--refit N ...`, each lambda is also sampled with the clamp-aware refit of N Adam steps
(`diffusion.sample.refit_steps`, neumat.diffusion.refit) as its own column. With
`--rgb-permute`, each variant's samples are scored a second time, each in a random RGB channel
order drawn as rule sample_uncond draws it (`diffusion.sample.rgb_permute`,
neumat.diffusion.symmetry): a column "+ rgb" of the same draws. With `--type-prior`, each
variant is also sampled with a type per sample drawn from the training split's types (untyped
interpolations: the null class) and no guidance (`diffusion.sample.type_prior`,
neumat.diffusion.dataset.prior_types): a column "+ types", the same seeds. Without it, each
variant is sampled as the run's setting says.

`ours` is sampled again at each lambda with the run's model, sampling settings and draw seeds
(what rule sample_uncond does), and scored as rule metrics scores it (the run's prepared
reference, metrics/reference.pt). It is set beside the run's other generative columns
(metrics/<model>.csv). Per lambda the script prints:
- each Table 2 row, mean +- std over the draws;
- the rows where `ours` is best of the generative columns, or tied within one std (the larger
  of the two), as the Table 2 tables of docs/results.md count them;
- the share of samples with a clamped negative bin (rule diffusion_plausibility's measure);
- the brightness of the first draw's metric-view renders (mean sRGB over the sphere, per
  material: median and 10th / 90th percentiles), beside the reference set's and the other
  columns': the step lifts the NBRDF's output, and dark renders go missing first.

The baseline is the run's own `ours` (metrics/ours.csv) at the run's lambda. A line checks that
lambda's resampled draws reproduce that file (with `--rgb-permute`, a line per channel order:
the one that matches is the run's setting, whatever `--config` says). `--model M` samples
another model.pt (e.g. one trained on the run's rows in another way) in `ours`' place, with the
same settings and seeds; the check is then skipped.

    OMP_NUM_THREADS=2 python benchmarks/clamp_step_table2.py --results results/default --steps 0 10 30
        [--refit 0 300]   # per lambda: without the refit, and with 300 steps of it
        [--config C]   # settings: the run's recorded config (report/index.md), else the schema
        [--model M]    # another model.pt in ours' place
        [--rgb-permute]  # each variant also with its samples in random channel orders
        [--type-prior]   # each variant also sampled with types drawn as in training
        [--keep-look 25]  # each lambda > 0 also mixed with lambda 0's draws (below)
        [--particle-step 0 0.1]  # each variant at each particle guidance step (below)
        [--temperature 1 1.1]    # each variant at each DDIM start temperature (below)

`--keep-look X ...` (dB): per lambda > 0, a column per X that keeps each sample's clamp-step
draw unless the step changed its look: where the PSNR between the metric-view renders (sRGB)
of its draw at lambda and at lambda 0 from the same seed is below X dB, the lambda-0 draw is
kept (fields that clamp by nature, e.g. mirrors, which the step pulls to another look;
`diffusion.sample.keep_look`, neumat.diffusion.sample.keep_look). The column says the share of
samples so kept.

`--particle-step X ...`: each variant is sampled at each particle guidance step
(`diffusion.sample.particle_step`, neumat.diffusion.constraints.ParticleGuidance; 0 = off), a
column " + particles X" where X > 0. Without it, at the run's setting.

`--temperature X ...`: each variant is sampled with its DDIM start x_T scaled by X
(`diffusion.sample.temperature`, neumat.diffusion.schedule.RowNoise; 1 = off), a column
" + temperature X" where X != 1. Without it, at the run's setting.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from neumat import cli, machine, seeds
from neumat.diffusion import Sampler, dataset, plausibility, symmetry
from neumat.diffusion.sample import keep_look
from neumat.metrics import distances, evaluate, inception, materials

ROWS = ["FID", "MMD", "COV", "1-NNA"]
HIGHER = {"COV"}  # better when higher
HALF = {"1-NNA"}  # better the nearer 50 % (a fraction 0.5); the others (NegPSNR, NegSSIM too) lower
OTHERS = ["pca_a", "pca_n", "vae_a", "vae_n", "merl100"]  # the generative columns beside ours
SAMPLES = {"pca_a": "samples/pca_a/tables.npz", "training_set": "samples/training/weights.npy"}
# (the others: samples/<model>/weights.npy; workflow/rules/common.smk MODEL_WEIGHTS)


def brightness(s, resolution: int, activation: str) -> str:
    """Median [10th, 90th percentile] over materials of the mean sRGB of the metric render."""
    lum = materials.renders(s, resolution, activation).mean(dim=(1, 2, 3)).numpy()
    q10, q50, q90 = np.quantile(lum, [0.1, 0.5, 0.9])
    return f"{q50:.3f} [{q10:.3f}, {q90:.3f}]"


def stats(table: pd.DataFrame) -> pd.DataFrame:
    t = table[table["metric"].isin(ROWS)]
    return t.groupby(["metric", "distance"], sort=False)["value"].agg(["mean", "std"])


def badness(metric: str, mean: float) -> float:
    """What ranks a row's columns, lower is better: the mean, negated where higher is better
    (COV), its distance from 50 % for 1-NNA (0.5 is ideal: 30 % is as far off as 70 %)."""
    if metric in HALF:
        return abs(mean - 0.5)
    return -mean if metric in HIGHER else mean


def best_or_tied(ours: pd.DataFrame, others: dict[str, pd.DataFrame]) -> pd.Series:
    """Per row: ours is best of the generative columns (by `badness`), or within one std (the
    larger of ours' and the best's; a single draw's missing std counts as none) of the best."""
    out = {}
    for row, (m, s) in ours[["mean", "std"]].iterrows():
        best = min(((badness(row[0], o.loc[row, "mean"]), o.loc[row, "std"]) for o in others.values()),
                   key=lambda b: b[0])
        stds = np.array([s, best[1]], dtype=float)
        tol = np.nanmax(stds) if np.isfinite(stds).any() else 0.0
        mine = badness(row[0], m)
        out[row] = mine <= best[0] or mine - best[0] <= tol
    return pd.Series(out)


def name(lam: float, refit: int) -> str:
    """A variant's column: the clamp step, and the refit's steps when on."""
    return f"{lam:g}" + (f" + refit {refit}" if refit else "")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", required=True, help="a finished run: results/<run>")
    ap.add_argument("--steps", type=float, nargs="+", default=[0.0, 10.0, 30.0],
                    help="clamp steps (lambda) to sample and score")
    ap.add_argument("--refit", type=int, nargs="+", default=[0],
                    help="clamp-aware refit steps (diffusion.sample.refit_steps) per lambda; 0 = none")
    ap.add_argument("--config", help="a config whose keys override the run's recorded config "
                                     "(default: that, or the schema's defaults)")
    ap.add_argument("--model", help="a model.pt to sample in ours' place (default: the run's "
                                    "diffusion/ours/model.pt)")
    ap.add_argument("--rgb-permute", action="store_true",
                    help="score each variant also with its samples in random RGB channel orders "
                         "(diffusion.sample.rgb_permute)")
    ap.add_argument("--type-prior", action="store_true",
                    help="sample each variant also with per-sample types drawn as in training, "
                         "unguided (diffusion.sample.type_prior)")
    ap.add_argument("--particle-step", type=float, nargs="+", default=None,
                    help="particle guidance steps (diffusion.sample.particle_step) per variant; "
                         "default: the run's")
    ap.add_argument("--temperature", type=float, nargs="+", default=None,
                    help="DDIM start temperatures (diffusion.sample.temperature) per variant; "
                         "default: the run's")
    ap.add_argument("--keep-look", type=float, nargs="+", default=[],
                    help="dB: per lambda > 0, also a column keeping the lambda-0 draw of every "
                         "sample whose look the step changed by more (render PSNR below X)")
    a = ap.parse_args()
    run = Path(a.results)
    model = Path(a.model) if a.model else run / "diffusion/ours/model.pt"
    # the run's config as `report` recorded it, else the schema defaults; --config's keys first
    setting = cli.Run(run, yaml.safe_load(Path(a.config).read_text()) if a.config else None).setting

    seed, draws = setting("seed"), setting("metrics", "draws")
    s = {k: setting("diffusion", "sample", k)
         for k in ("steps", "eta", "batch_size", "clip", "negative_step")}
    activation = setting("fit", "activation")
    run_variant = (s["negative_step"], setting("diffusion", "sample", "refit_steps"))
    run_rgb = bool(setting("diffusion", "sample", "rgb_permute"))
    run_tp = bool(setting("diffusion", "sample", "type_prior"))
    run_ps = float(setting("diffusion", "sample", "particle_step"))
    run_tau = float(setting("diffusion", "sample", "temperature"))
    variants = [(lam, r, tp, ps, tau) for lam in a.steps for r in a.refit
                for tp in ([False, True] if a.type_prior else [run_tp])
                for ps in (a.particle_step if a.particle_step is not None else [run_ps])
                for tau in (a.temperature if a.temperature is not None else [run_tau])]
    kw = dict(resolution=setting("render", "resolution"), activation=activation,
              bins=distances.brdf_sample(setting("metrics", "brdf_samples"),
                                         seeds.seed_for(seed, "metrics")),
              fid_model=inception.fid_network(setting("metrics", "inception_weights"))[0])
    ref = materials.load(run / "samples/reference/weights.npy")
    prepared = evaluate.load_reference(run / "metrics/reference.pt")
    man = dataset.read_manifest(run / "neumerl/manifest.tsv")
    n_ref = len(dataset.reference_rows(man))
    draw_seeds = [seeds.seed_for(seed, "sample", "ours", d) for d in range(draws)]
    sampler = Sampler(str(model), "cpu")
    # columns the run has not scored yet are left out of the comparison, and named
    others = {m: stats(pd.read_csv(run / f"metrics/{m}.csv")) for m in OTHERS
              if (run / f"metrics/{m}.csv").exists()}
    missing = [m for m in OTHERS if m not in others]
    baseline = pd.read_csv(run / "metrics/ours.csv") if (run / "metrics/ours.csv").exists() else None
    print(f"machine: {machine.describe()}; {run}: {draws} draws x {n_ref} samples, "
          f"{len(ref)} references, run's lambda {s['negative_step']}; ours sampled from {model}")
    print("render brightness, median [10th, 90th percentile] of the mean sRGB per material, first "
          "draw: reference " + brightness(ref, kw["resolution"], activation) + "; " + "; ".join(
              f"{m} " + brightness(materials.rows(materials.load(run / SAMPLES.get(
                  m, f"samples/{m}/weights.npy")), slice(0, n_ref)), kw["resolution"], activation)
              for m in ["training_set", *others]))
    cols, clamp = {}, {}
    drawn_at = {}  # (lambda, refit, types, particles, temperature) -> draws: lambda 0's reused

    def draw(*v):  # v: a variant
        lam, r, tp, ps, tau = v
        if v not in drawn_at:  # as rule sample_uncond: each draw's types from its own stream
            drawn_at[v] = [sampler.sample(
                n_ref, d, dataset.prior_types(man, n_ref, seeds.seed_for(d, "type_prior"))
                if tp else None, s["steps"], s["eta"], 1.0, s["batch_size"], s["clip"], lam,
                activation, refit_steps=r, particle_step=ps, temperature=tau) for d in draw_seeds]
        return drawn_at[v]

    def sampled_variants():
        """(column, draws, seconds, is the run's own setting) per variant, with the --keep-look
        mixtures after their lambda."""
        for lam, r, tp, ps, tau in variants:
            t0 = time.perf_counter()
            drawn = draw(lam, r, tp, ps, tau)
            col = name(lam, r) + (" + types" if tp else "") + (f" + particles {ps:g}" if ps else "") \
                + (f" + temperature {tau:g}" if tau != 1.0 else "")
            yield col, drawn, time.perf_counter() - t0, \
                (lam, r, tp, ps, tau) == (*run_variant, run_tp, run_ps, run_tau)
            if not (a.keep_look and lam > 0):
                continue
            base = draw(0.0, r, tp, ps, tau)
            for x in a.keep_look:  # as rule sample_uncond with diffusion.sample.keep_look x
                mixed, kept = zip(*[keep_look(z, y, x, kw["resolution"], activation)
                                    for z, y in zip(drawn, base)])
                yield (f"{col} keep look {x:g} dB ({np.mean(kept):.3f} at lambda 0)", list(mixed),
                       time.perf_counter() - t0, False)

    for lam0, drawn, sampled, at_run in sampled_variants():
        for rgb in [False, True] if a.rgb_permute else [run_rgb]:
            # as rule sample_uncond: each draw's samples in channel orders from its own stream
            w = np.concatenate([symmetry.random_channels(x, seeds.seed_for(d, "rgb_permute"))
                                if rgb else x for x, d in zip(drawn, draw_seeds)])
            lam = lam0 + (" + rgb" if rgb else "")
            t1 = time.perf_counter()
            table = evaluate.evaluate_draws(ref, [w[i * n_ref:(i + 1) * n_ref] for i in range(draws)],
                                            **kw, reference=prepared)
            pl = plausibility.plausibility(w, n_angles=setting("diffusion", "plausibility_angles"),
                                           seed=seeds.seed_for(seed, "diffusion_plausibility"),
                                           activation=activation)
            summary = plausibility.summarize(pl)
            clamp[lam] = summary["share_any_negative"]
            cols[lam] = stats(table)
            print(f"lambda {lam}: sampled in {sampled:.0f} s, scored in {time.perf_counter() - t1:.0f} s; "
                  f"samples clamping a negative bin {clamp[lam]:.3f} (mean clamped share "
                  f"{summary['mean_negative_share']:.4f}); render brightness "
                  f"{brightness(w[:n_ref], kw['resolution'], activation)}")
            # at the run's lambda, both orders with --rgb-permute: a --config may say other than
            # the run was built with, and the order that matches says which it was
            if at_run and not a.model and baseline is not None \
                    and (a.rgb_permute or rgb == run_rgb):
                got = table.merge(baseline, on=["draw", "metric", "distance"], suffixes=("", "_run"))
                rel = ((got["value"] - got["value_run"]).abs() / got["value_run"].abs().clip(lower=1e-12))
                print(f"  check of lambda {lam} against the run's metrics/ours.csv: {len(got)} "
                      f"values, max relative difference {rel.max():.2g}"
                      + ("" if rgb == run_rgb else " (not the setting the config gives)"))
    if missing:
        print(f"not scored in this run, left out of the comparison: {', '.join(missing)}")
    if not others:
        for lam, c in cols.items():
            print(f"lambda {lam}:\n{c.to_string()}")
        return
    wins = pd.DataFrame({lam: best_or_tied(c, others) for lam, c in cols.items()})
    rows = []
    for row in next(iter(cols.values())).index:
        rows.append({"metric": row[0], "distance": row[1],
                     **{f"lambda {lam}": f"{c.loc[row, 'mean']:.4g} ± {c.loc[row, 'std']:.2g}"
                        + (" *" if wins.loc[row, lam] else "") for lam, c in cols.items()},
                     **{m: f"{o.loc[row, 'mean']:.4g} ± {o.loc[row, 'std']:.2g}" for m, o in others.items()}})
    print(pd.DataFrame(rows).to_string(index=False))
    print("* best of the generative columns or tied within one std (COV: higher is better; "
          "1-NNA: nearer 50 % is better, ranked by |1-NNA - 50 %|; the others: lower is better)")
    for lam in cols:
        print(f"lambda {lam}: ours best or tied on {int(wins[lam].sum())} of {len(wins)} rows; "
              f"clamping {clamp[lam]:.3f}")


if __name__ == "__main__":
    main()
