"""Image-conditioned sampling from noise against starting from the retrieved training material
(`conditions.image.strength` < 1, SDEdit), on a finished workflow run: its multimodal model, its
conditioning images and embeddings (`samples/image/`), its image embeddings and NeuMERL fits.

Per strength: mean PSNR / SSIM of each image's samples against it (metric view, as
conditions_eval), how many images beat retrieval, the median BRDF-L1 to the nearest training
material and to the start, and the share of samples clamping negative values.

    python benchmarks/conditions_strength.py --results results/<run> --strengths 1 0.5 0.3
"""

import argparse
import time

import numpy as np
import torch

from neumat import machine
from neumat.conditions import evaluate as ev
from neumat.conditions import image
from neumat.diffusion import Sampler, dataset
from neumat.diffusion.sample import sample
from neumat.metrics import distances
from neumat.seeds import seed_for


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", required=True, help="results/<run> of a finished conditioning stage")
    ap.add_argument("--strengths", type=float, nargs="+", default=[1.0, 0.5, 0.3])
    ap.add_argument("--per-image", type=int, default=8)
    ap.add_argument("--guidance", type=float, default=2.0)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--negative-step", type=float, default=30.0)
    ap.add_argument("--resolution", type=int, default=128, help="report.sphere_resolution of the run")
    ap.add_argument("--bins", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    R, k = a.results, a.per_image
    print(f"machine: {machine.describe()}; torch threads {torch.get_num_threads()}", flush=True)
    weights = np.load(f"{R}/neumerl/weights.npy")
    man = dataset.read_manifest(f"{R}/neumerl/manifest.tsv", len(weights))
    emb = np.load(f"{R}/samples/image/conditioning_embeddings.npy")
    cond = torch.as_tensor(np.load(f"{R}/samples/image/conditioning.npy"))
    ts = ev.TrainingSet(weights, man, distances.brdf_sample(a.bins, a.seed), "relu")
    got = image.retrieve(emb, np.load(f"{R}/conditions/image.npy")[ts.rows, 0], ts.rows)
    ret = ev.image_scores(weights[got], cond, a.resolution, "relu")
    print(f"retrieval: PSNR {ret.psnr.mean():.2f} dB, SSIM {ret.ssim.mean():.4f} ({len(emb)} images)")
    sampler = Sampler(f"{R}/diffusion/multimodal/model.pt", "cpu")
    f_start = np.repeat(ts.fv(weights[got]), k, 0)
    for st in a.strengths:
        t0 = time.perf_counter()
        w = sample(sampler, len(emb) * k, a.seed, {"image": np.repeat(emb, k, 0)},
                   {"image": a.guidance}, a.steps, 0.0, 256, None, negative_step=a.negative_step,
                   start=weights[np.repeat(got, k)], strength=st)
        dt = time.perf_counter() - t0
        sc = ev.image_scores(w, cond.repeat_interleave(k, 0), a.resolution, "relu")
        per = sc.groupby(np.repeat(np.arange(len(emb)), k)).mean()
        to_start = np.abs(ts.fv(w) - f_start).mean(1)
        neg = ev.negative_share(w, a.bins, seed_for(a.seed, "negative_share"), "relu").mean()
        print(f"strength {st:g}: PSNR {per.psnr.mean():.2f} dB, SSIM {per.ssim.mean():.4f}; "
              f"beats retrieval on {(per.psnr.to_numpy() > ret.psnr.to_numpy()).sum()}/{len(emb)}; "
              f"median BRDF-L1 to nearest training {ts.nearest(w).brdf_l1.median():.3f}, "
              f"to its start {np.median(to_start):.3f}; clamping {neg:.3f}; sampling {dt:.0f} s",
              flush=True)


if __name__ == "__main__":
    main()
