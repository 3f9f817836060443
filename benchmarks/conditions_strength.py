"""Conditioned sampling from noise against starting from a retrieved training material (SDEdit,
`conditions.image.strength` < 1), on a finished workflow run: its multimodal model, its
conditioning images and embeddings (`samples/image/`), prompts and embeddings (`conditions/`)
and NeuMERL fits. The start per condition (--mode): image - the training material with the
nearest metric-view embedding; text - the nearest description embedding; type - a training
material of that type.

Per strength: type hits (the nearest typed training material has the asked type, as
conditions_eval), for images the mean PSNR / SSIM of each image's samples against it (metric
view) and how many images beat retrieval, the median BRDF-L1 to the nearest training material
and to the start, and the share of samples clamping negative values.

    python benchmarks/conditions_strength.py --results results/<run> --strengths 1 0.5 0.3
    python benchmarks/conditions_strength.py --results results/<run> --mode type --strengths 1 0.3
    python benchmarks/conditions_strength.py --results results/<run> --strengths 1 0.3 --render-steps 0 1

--render-steps (image mode): also pull each sample toward its conditioning image's metric-view
render (`conditions.image.render_step`, RenderConstraint); every strength with every step.
--model: another model file trained on the same NeuMERL rows (e.g. a `prediction: v` one, which
keeps a start it is given); one without the mode's condition refines the start unconditionally.
--candidates / --clamp-penalties (image mode): best of n (`conditions.image.candidates`,
`clamp_penalty`): each image's samples are the best of n times as many draws by render PSNR
against it, less the penalty (dB) for a clamping draw (clamps checked on their own seed stream,
not the one the clamping column reports); n = 1 is the plain sampling of the same run.
--unconstrained-candidates m (with --candidates n): each image also draws m times its samples
without the clamp constraint (`conditions.image.unconstrained_candidates`; seed stream
"unconstrained"), and best of n + m chooses among all of them. Adds the
samples' spread: the mean pairwise PSNR between the metric-view renders of an image's samples
(higher: more alike) and their mean pairwise weight-space L2. The workflow's image sampling of
config/config.yaml:

    python benchmarks/conditions_strength.py --results results/<run> --model results/<run>/diffusion/refiner/model.pt \
        --strengths 0.05 --render-steps 0.5 --candidates 1 4 8 --clamp-penalties 0 3 10
    python benchmarks/conditions_strength.py --results results/<run> --model results/<run>/diffusion/refiner/model.pt \
        --strengths 0.05 --render-steps 0.5 --candidates 4 8 --unconstrained-candidates 0 4 8
"""

import argparse
import time

import numpy as np
import pandas as pd
import torch

from neumat import machine
from neumat.conditions import evaluate as ev
from neumat.conditions import image
from neumat.diffusion import Sampler, dataset
from neumat.diffusion.sample import sample
from neumat.metrics import distances
from neumat.seeds import seed_for


def start_rows(mode, R, ts, seed, emb):
    """The training material each condition starts from: image - nearest metric-view
    embedding (retrieval); text - nearest description embedding (cosine) among the training
    materials; type - a training material of that type, drawn with `seed` (the types no
    training material has are left out: they cannot score a hit)."""
    if mode == "image":
        return image.retrieve(emb, np.load(f"{R}/conditions/image.npy")[ts.rows, 0], ts.rows)
    if mode == "text":  # text.embed's vectors are L2-normalised: a dot product is the cosine
        return ts.rows[(emb @ np.load(f"{R}/conditions/text.npy")[ts.rows].T).argmax(1)]
    rng = np.random.default_rng(seed)
    return np.array([rng.choice(ts.typed[ts.types == t]) for t in emb])


def conditions_for(mode, R, ts):
    """(embeddings or types asked, conditioning images or None, the types asked)"""
    if mode == "image":
        emb = np.load(f"{R}/samples/image/conditioning_embeddings.npy")
        table = pd.read_csv(f"{R}/samples/image/samples.tsv", sep="\t", keep_default_na=False)
        types = table.groupby("condition")["type"].first().to_numpy()
        return emb, torch.as_tensor(np.load(f"{R}/samples/image/conditioning.npy")), types
    prompts = pd.read_csv(f"{R}/conditions/prompts.tsv", sep="\t", keep_default_na=False)
    keep = (prompts["kind"] == "test").to_numpy() & ts.scorable(prompts["type"])
    if mode == "text":
        return np.load(f"{R}/conditions/prompts.npy")[keep], None, prompts["type"][keep].to_numpy()
    return prompts["type"][keep].to_numpy(), None, prompts["type"][keep].to_numpy()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", required=True, help="results/<run> of a finished conditioning stage")
    ap.add_argument("--mode", default="image", choices=["image", "text", "type"])
    ap.add_argument("--strengths", type=float, nargs="+", default=[1.0, 0.5, 0.3])
    ap.add_argument("--per-image", type=int, default=8, help="samples per condition")
    ap.add_argument("--render-steps", type=float, nargs="+", default=[0.0],
                    help="image mode: render guidance steps (conditions.image.render_step)")
    ap.add_argument("--guidance", type=float, default=2.0)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--negative-step", type=float, default=30.0)
    ap.add_argument("--resolution", type=int, default=128, help="report.sphere_resolution of the run")
    ap.add_argument("--bins", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--model", help="model file (default: <results>/diffusion/multimodal/model.pt)")
    ap.add_argument("--candidates", type=int, nargs="+", default=[1],
                    help="image mode: best of n draws (conditions.image.candidates)")
    ap.add_argument("--clamp-penalties", type=float, nargs="+", default=[10.0],
                    help="dB off a clamping draw's score (conditions.image.clamp_penalty)")
    ap.add_argument("--unconstrained-candidates", type=int, nargs="+", default=[0],
                    help="image mode: more draws per sample without the clamp constraint "
                         "(conditions.image.unconstrained_candidates)")
    a = ap.parse_args()
    R, k, mode = a.results, a.per_image, a.mode
    print(f"machine: {machine.describe()}; torch threads {torch.get_num_threads()}; mode {mode}",
          flush=True)
    weights = np.load(f"{R}/neumerl/weights.npy")
    man = dataset.read_manifest(f"{R}/neumerl/manifest.tsv", len(weights))
    ts = ev.TrainingSet(weights, man, distances.brdf_sample(a.bins, a.seed), "relu")
    emb, cond, types = conditions_for(mode, R, ts)
    got = start_rows(mode, R, ts, a.seed, emb)
    asked = np.repeat(types, k)
    scorable = ts.scorable(asked)
    ret = weights[got]
    ret_hits = (ts.nearest(ret).nearest_type.to_numpy() == types)[ts.scorable(types)].mean()
    line = f"retrieval: type hits {ret_hits:.3f} ({len(got)} conditions)"
    if cond is not None:
        rsc = ev.image_scores(ret, cond, a.resolution, "relu")
        line += f", PSNR {rsc.psnr.mean():.2f} dB, SSIM {rsc.ssim.mean():.4f}"
    print(line, flush=True)
    sampler = Sampler(a.model or f"{R}/diffusion/multimodal/model.pt", "cpu")
    c = {mode: list(np.repeat(emb, k)) if mode == "type" else np.repeat(emb, k, 0)}
    if mode not in sampler.model.cond_names:  # refine the start without the condition
        print(f"{a.model}: no {mode} condition; the start is refined unconditionally", flush=True)
        c = {}
    f_start = np.repeat(ts.fv(ret), k, 0)
    if mode != "image" and (a.render_steps != [0.0] or a.candidates != [1]
                            or a.unconstrained_candidates != [0]):
        raise SystemExit("--render-steps and --candidates need --mode image (they follow an image)")

    def draw(n, seed, negative_step, st, rs):
        """n draws per sample of every condition (len(emb), k n, 675) and their seconds."""
        cd = {m: (list(np.repeat(v, n)) if mode == "type" else np.repeat(v, n, 0))
              for m, v in c.items()}
        tgt = None if cond is None else cond.repeat_interleave(k * n, 0)
        t0 = time.perf_counter()
        w = sample(sampler, len(emb) * k * n, seed, cd, {mode: a.guidance} if c else None,
                   a.steps, 0.0, 256, None, negative_step=negative_step,
                   start=weights[np.repeat(got, k * n)], strength=st,
                   render_targets=tgt if rs else None, render_step=rs)
        return w.reshape(len(emb), k * n, -1), time.perf_counter() - t0

    def pick(st, rs, n, m, draws, dt):
        """Report the best k of each condition's k (n + m) draws (all of them for n + m = 1)."""
        kd = k * (n + m)  # draws per condition
        draws = draws.reshape(len(emb) * kd, -1)
        if n + m == 1:
            picks = [(None, draws)]
        else:
            psnr, clamps = image.score_draws(draws, cond, a.bins, a.seed, "relu")
            picks = [(pen, draws[image.best_of(image.selection_score(psnr, clamps, pen), kd, k)])
                     for pen in a.clamp_penalties]
        for pen, w in picks:
            tag = (f", best of {n + m}{f' ({m} unconstrained)' if m else ''}, clamp penalty "
                   f"{pen:g} dB" if n + m > 1 else "")
            report(a, ts, w, k, emb, cond, rsc if cond is not None else None, asked, scorable,
                   f_start, f"strength {st:g}{f', render step {rs:g}' if rs else ''}{tag}", dt)

    for st, rs in [(st, rs) for st in a.strengths for rs in a.render_steps]:
        free = {m: draw(m, seed_for(a.seed, "unconstrained"), 0.0, st, rs)
                for m in a.unconstrained_candidates if m}
        for n in a.candidates:
            w, dt = draw(n, a.seed, a.negative_step, st, rs)  # the constrained draws first
            for m in a.unconstrained_candidates:
                if m:
                    pick(st, rs, n, m, np.concatenate([w, free[m][0]], 1), dt + free[m][1])
                else:
                    pick(st, rs, n, m, w, dt)


def spread(w, k, resolution):
    """Mean over conditions of the mean pairwise PSNR between the metric-view renders (sRGB) of
    a condition's k samples, and of their mean pairwise weight-space L2."""
    from neumat.render import sphere
    r = sphere.to_srgb(sphere.render_fields(w, resolution, "relu")).reshape(-1, k, resolution ** 2 * 3)
    iu = torch.triu_indices(k, k, 1)
    mse = torch.stack([(torch.cdist(x.double(), x.double()) ** 2)[iu[0], iu[1]] for x in r]) / r.shape[-1]
    wt = torch.as_tensor(w).double().reshape(-1, k, w.shape[1])
    l2 = torch.stack([torch.pdist(x).mean() for x in wt])
    return (-10 * torch.log10(mse.clamp_min(distances.PSNR_FLOOR_MSE))).mean().item(), l2.mean().item()


def report(a, ts, w, k, emb, cond, rsc, asked, scorable, f_start, head, dt):
    """One line of measures for the samples w (len(emb) k, 675)."""
    near = ts.nearest(w)
    hits = (near.nearest_type.to_numpy() == asked)[scorable].mean()
    line = f"{head}: type hits {hits:.3f} ({scorable.sum()} samples)"
    if cond is not None:
        sc = ev.image_scores(w, cond.repeat_interleave(k, 0), a.resolution, "relu")
        per = sc.groupby(np.repeat(np.arange(len(emb)), k)).mean()
        sp, l2 = spread(w, k, a.resolution)
        line += (f", PSNR {per.psnr.mean():.2f} dB, SSIM {per.ssim.mean():.4f}; beats "
                 f"retrieval on {(per.psnr.to_numpy() > rsc.psnr.to_numpy()).sum()}/{len(emb)} "
                 f"(SSIM {(per.ssim.to_numpy() >= rsc.ssim.to_numpy()).sum()}); spread: "
                 f"pairwise render PSNR {sp:.2f} dB, weight L2 {l2:.3f}")
    to_start = np.abs(np.asarray(ts.fv(w)) - np.asarray(f_start)).mean(1)
    neg = ev.negative_share(w, a.bins, seed_for(a.seed, "negative_share"), "relu").mean()
    print(f"{line}; median BRDF-L1 to nearest training {near.brdf_l1.median():.3f}, "
          f"to its start {np.median(to_start):.3f}; clamping {neg:.3f}; sampling {dt:.0f} s",
          flush=True)


if __name__ == "__main__":
    main()
