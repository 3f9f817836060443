"""Render guidance (`diffusion.constraints.RenderConstraint`) on a finished run: samples of its
`ours` model pulled toward held-out materials' metric-view renders, against retrieval.

Targets: the metric-view renders (linear HDR, `--resolution` px) of the run's test-split
original materials (held out by source: no variant of them is in training). Per render step
(0 = the unguided model), `--per-image` samples per target, unconditional apart from the
guidance, `negative_step` as the run's default. Scores as conditions_eval: PSNR / SSIM (sRGB)
of each sample's render against its target, mean per target; the median BRDF-L1 from each
sample to the nearest training material and to its target (real held-out materials sit at the
first for themselves); the share of samples clamping negative values. Baseline in the same
run: the best training material for each target by PSNR over all training renders (oracle
retrieval, an upper bound of any embedding retrieval).

    python benchmarks/render_guidance.py --results results/<run> --steps 0 1 3 10
    python benchmarks/render_guidance.py --results results/<run> --strengths 1 0.3 --steps 0 3
"""
import argparse
import time

import numpy as np
import torch

from neumat import machine
from neumat.conditions import evaluate as ev
from neumat.diffusion import Sampler, dataset
from neumat.diffusion.sample import sample
from neumat.metrics import distances
from neumat.render import sphere
from neumat.seeds import seed_for


def psnr_matrix(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(A, H, W, 3) x (B, H, W, 3) linear HDR -> (A, B) PSNR in sRGB, as image_scores."""
    mse = distances.pairwise_mse(sphere.to_srgb(a), sphere.to_srgb(b))
    return -10 * torch.log10(mse.clamp_min(distances.PSNR_FLOOR_MSE))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", required=True, help="results/<run> with neumerl/ and diffusion/ours")
    ap.add_argument("--steps", type=float, nargs="+", default=[0.0, 1.0, 3.0, 10.0],
                    help="render steps (lambda) to compare")
    ap.add_argument("--strengths", type=float, nargs="+", default=[1.0],
                    help="1 = from noise; < 1: from the oracle-retrieved material noised to it "
                         "(SDEdit, as conditions.image.strength)")
    ap.add_argument("--targets", type=int, default=24, help="held-out originals used as targets")
    ap.add_argument("--per-image", type=int, default=8)
    ap.add_argument("--ddim-steps", type=int, default=100)
    ap.add_argument("--negative-step", type=float, default=30.0)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--bins", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    R, k = a.results, a.per_image
    print(f"machine: {machine.describe()}; torch threads {torch.get_num_threads()}", flush=True)
    weights = np.load(f"{R}/neumerl/weights.npy")
    man = dataset.read_manifest(f"{R}/neumerl/manifest.tsv", len(weights))
    train = np.flatnonzero((man["split"] == "train").to_numpy())
    test = np.flatnonzero(((man["split"] == "test") & (man["operation"] == "original")).to_numpy())
    test = test[:a.targets]
    ts = ev.TrainingSet(weights, man, distances.brdf_sample(a.bins, a.seed), "relu")
    targets = sphere.render_fields(weights[test], a.resolution)
    t0 = time.perf_counter()
    best = torch.full((len(test),), -np.inf, dtype=torch.float64)
    arg = torch.zeros(len(test), dtype=torch.long)
    for s in range(0, len(train), 256):
        p = psnr_matrix(sphere.render_fields(weights[train[s:s + 256]], a.resolution), targets)
        m, i = p.max(0)
        arg = torch.where(m > best, i + s, arg)
        best = torch.maximum(best, m)
    ret = weights[train[arg.numpy()]]
    rsc = ev.image_scores(ret, targets, a.resolution, "relu")
    print(f"{len(test)} held-out originals ({', '.join(man['name'].iloc[test[:6]])}, ...), "
          f"{len(train)} training rows; oracle retrieval (best training PSNR): PSNR "
          f"{rsc.psnr.mean():.2f} dB, SSIM {rsc.ssim.mean():.4f} ({time.perf_counter() - t0:.0f} s)",
          flush=True)
    ref_neg = ev.negative_share(weights[test], a.bins, seed_for(a.seed, "negative_share"), "relu")
    print(f"the held-out materials themselves: clamping {ref_neg.mean():.3f}", flush=True)
    sampler = Sampler(f"{R}/diffusion/ours/model.pt", "cpu")
    tgt = targets.repeat_interleave(k, 0)
    f_tgt = np.repeat(np.asarray(ts.fv(weights[test])), k, 0)
    for strength, step in [(st, sp) for st in a.strengths for sp in a.steps]:
        t0 = time.perf_counter()
        w = sample(sampler, len(test) * k, a.seed, None, None, a.ddim_steps, 0.0, 256, None,
                   negative_step=a.negative_step, render_targets=tgt, render_step=step,
                   start=np.repeat(ret, k, 0) if strength < 1 else None, strength=strength)
        dt = time.perf_counter() - t0
        sc = ev.image_scores(w, tgt, a.resolution, "relu")
        per = sc.groupby(np.repeat(np.arange(len(test)), k)).mean()
        near = ts.nearest(w)
        to_t = np.abs(np.asarray(ts.fv(w)) - f_tgt).mean(1)
        neg = ev.negative_share(w, a.bins, seed_for(a.seed, "negative_share"), "relu").mean()
        print(f"strength {strength:g}, render step {step:g}: PSNR {per.psnr.mean():.2f} dB, SSIM {per.ssim.mean():.4f}; "
              f"beats oracle retrieval on {(per.psnr.to_numpy() > rsc.psnr.to_numpy()).sum()}/"
              f"{len(test)} targets; median BRDF-L1 to nearest training {near.brdf_l1.median():.3f}, "
              f"to the target material {np.median(to_t):.3f}; clamping {neg:.3f}; sampling {dt:.0f} s",
              flush=True)


if __name__ == "__main__":
    main()
