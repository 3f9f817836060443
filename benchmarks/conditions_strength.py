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
    if mode != "image" and a.render_steps != [0.0]:
        raise SystemExit("--render-steps needs --mode image (render guidance follows an image)")
    tgt = None if cond is None else cond.repeat_interleave(k, 0)
    for st, rs in [(st, rs) for st in a.strengths for rs in a.render_steps]:
        t0 = time.perf_counter()
        w = sample(sampler, len(emb) * k, a.seed, c, {mode: a.guidance} if c else None, a.steps,
                   0.0, 256, None,
                   negative_step=a.negative_step, start=weights[np.repeat(got, k)], strength=st,
                   render_targets=tgt if rs else None, render_step=rs)
        dt = time.perf_counter() - t0
        near = ts.nearest(w)
        hits = (near.nearest_type.to_numpy() == asked)[scorable].mean()
        line = f"strength {st:g}{f', render step {rs:g}' if rs else ''}: type hits {hits:.3f} ({scorable.sum()} samples)"
        if cond is not None:
            sc = ev.image_scores(w, cond.repeat_interleave(k, 0), a.resolution, "relu")
            per = sc.groupby(np.repeat(np.arange(len(emb)), k)).mean()
            line += (f", PSNR {per.psnr.mean():.2f} dB, SSIM {per.ssim.mean():.4f}; beats "
                     f"retrieval on {(per.psnr.to_numpy() > rsc.psnr.to_numpy()).sum()}/{len(emb)}")
        to_start = np.abs(np.asarray(ts.fv(w)) - np.asarray(f_start)).mean(1)
        neg = ev.negative_share(w, a.bins, seed_for(a.seed, "negative_share"), "relu").mean()
        print(f"{line}; median BRDF-L1 to nearest training {near.brdf_l1.median():.3f}, "
              f"to its start {np.median(to_start):.3f}; clamping {neg:.3f}; sampling {dt:.0f} s",
              flush=True)


if __name__ == "__main__":
    main()
