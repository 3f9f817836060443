"""Weight-space baselines and the off-manifold question on realistic weights: the 100 published
NBRDF fits of MERL and their exact RGB permutations (as benchmarks/diffusion_realistic.py), split
by source with 20 test sources (the default test_fraction 0.2).

For each set - reference (test split), a training subset, PCA-N, VAE-N and, if given, the
samples of a diffusion model (`--samples name=path.npy`) - it prints the share of materials with
clamped (negative) bins, the mean clamped share, and the median BRDF-L1 distance to the nearest
training field, so "how far off the training manifold" is measured the same way for all.
`--table` adds Table 2 (mean ± std over 3 draws, FID included) - slow on 2 cores.
Also prints each baseline's fit time on this machine (wall), and the CPU time per VAE training
step at the default config's sizes (`cost`; 1 thread).

`floor`: the training loss of the *ideal* x0 denoiser for a training set - the posterior mean
E[x0 | x_t] under the empirical distribution of the set, in the workflow's per-coordinate
standardised space with the default cosine schedule (T = 1000) - averaged over uniform t like
`Diffusion.loss`. That is the lowest loss any network can reach; the gap between two training
sets' floors says how much of a loss gap is the data, not the model.

  python benchmarks/baselines_realistic.py run [--vae-steps 2000] [--table]
  python benchmarks/baselines_realistic.py cost
  python benchmarks/baselines_realistic.py floor
"""

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diffusion_realistic import build  # noqa: E402

from neumat.baselines import pca, vae  # noqa: E402
from neumat.diffusion import dataset, plausibility  # noqa: E402
from neumat.io import merl  # noqa: E402
from neumat.machine import describe as host_line  # noqa: E402
from neumat.metrics import distances, evaluate  # noqa: E402


def machine():
    """The CPU line every benchmark prints (neumat.machine), with the torch threads."""
    return f"{host_line()}, torch threads {torch.get_num_threads()}"


def split_20(seed=0, n_test=20):
    man, w = build(seed)
    test = set(np.random.default_rng(seed).choice(100, n_test, replace=False).tolist())
    man["split"] = ["test" if s in test else "train" for s in man["src"]]
    return man, w


def describe(name, w, train_vals, bins):
    p = plausibility.summarize(plausibility.plausibility(w, n_angles=5000))
    _, dist = dataset.nearest(distances.field_values(np.nan_to_num(w), bins), train_vals)
    return {"set": name, "n": len(w), "share_any_negative": p["share_any_negative"],
            "mean_negative_share": p["mean_negative_share"], "nearest_train_L1_median": float(np.median(dist))}


def cmd_run(a):
    man, w = split_20()
    train, ref_rows = dataset.training_rows(man, "ours"), dataset.reference_rows(man)
    n = len(ref_rows)
    seeds = [11, 12, 13]
    sets = {"reference": w[ref_rows],
            "training_set": w[dataset.training_subset(man, 5, draws=3)]}
    cost = {}
    t0 = time.perf_counter()
    fitted = pca.WeightPCA(a.pca_components).fit(w[train])
    sets["pca_n"] = np.concatenate([fitted.sample(n, s) for s in seeds])
    cost["pca_n fit+sample s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    net, hist = vae.train_weight_vae(w[train], latent=32, hidden=256, steps=a.vae_steps,
                                     batch_size=128, lr=1e-3, beta=1.0, seed=0)
    sets["vae_n"] = np.concatenate([vae.prior_samples(net, n, s) for s in seeds])
    cost[f"vae_n train ({a.vae_steps} steps)+sample s"] = time.perf_counter() - t0
    cost["vae_n final rec"] = hist[-1]["rec"]
    for spec in a.samples:
        k, path = spec.split("=", 1)
        sets[k] = np.load(path)
    bins = distances.brdf_sample(a.bins, 0)
    train_vals = distances.field_values(w[train], bins)
    rows = [describe(k, v, train_vals, bins) for k, v in sets.items()]
    print(machine())
    print(f"{len(train)} training fields ({len(set(man['src'][train]))} sources), {n} references")
    print(pd.DataFrame(rows).to_markdown(index=False, floatfmt=".4g"))
    print(pd.Series(cost).to_string())
    if a.table:
        res = {}
        for k, v in sets.items():
            if k == "reference":
                continue
            draws = [v[i * n:(i + 1) * n] for i in range(len(v) // n)] or [v]
            res[k] = evaluate.evaluate_draws(w[ref_rows], draws, resolution=a.resolution, bins=bins)
        print(evaluate.table2(res).reset_index().to_markdown(index=False))


def cmd_cost(a):
    """Seconds per VAE-A step at the default sizes (batch 16, 1024 context, 2048 queries,
    latent 40, hidden 128) and per VAE-N step (batch 128, hidden 256), on random data."""
    rng = np.random.default_rng(0)
    bins = np.sort(rng.choice(np.flatnonzero(merl.valid_mask()), 8192, replace=False))
    th, td, pd_ = (x[bins] for x in merl.grid_angles())
    vals = rng.gamma(1.0, 0.1, (64, 3, len(bins))).astype(np.float32)
    out = {}
    # CPU time of the process (this machine is shared: wall time would measure the neighbours),
    # difference of two runs to remove the set-up cost
    for steps in (5, 45):
        t0 = time.process_time()
        vae.train_set_vae(vals, merl.half_diff_cartesian(th, td, pd_), merl.cos_theta_i(th, td, pd_),
                          latent=40, hidden=128, steps=steps, batch_size=16, context=1024,
                          queries=2048, lr=5e-4, beta=1.0, seed=0)
        out[steps] = time.process_time() - t0
    per_a = (out[45] - out[5]) / 40
    w = rng.standard_normal((1000, 675)).astype(np.float32)
    for steps in (2, 52):
        t0 = time.process_time()
        vae.train_weight_vae(w, latent=32, hidden=256, steps=steps, batch_size=128, lr=1e-3,
                             beta=1.0, seed=0)
        out[f"n{steps}"] = time.process_time() - t0
    per_n = (out["n52"] - out["n2"]) / 50
    print(machine())
    print(f"VAE-A: {per_a * 1e3:.1f} CPU-ms/step -> default 3000 steps ~ {per_a * 3000 / 60:.1f} CPU-min")
    print(f"VAE-N: {per_n * 1e3:.2f} CPU-ms/step -> default 5000 steps ~ {per_n * 5000 / 60:.1f} CPU-min")
    print("load average:", open("/proc/loadavg").read().split()[:3])


def ideal_x0_loss(x, diffusion, n_draws=4096, seed=0, chunk=256):
    """Mean over (x0 from the set, t uniform, noise) of |E[x0 | x_t] - x0|^2 / dims, with the
    posterior mean a softmax over the set: log w_j = -|x_t - sqrt(ab) x_j|^2 / (2 (1 - ab))."""
    g = torch.Generator().manual_seed(seed)
    x = x.double()
    idx = torch.randint(len(x), (n_draws,), generator=g)
    t = torch.randint(diffusion.T, (n_draws,), generator=g)
    noise = torch.randn(n_draws, x.shape[1], generator=g, dtype=torch.float64)
    ab = diffusion.alpha_bar[t][:, None]
    xt = ab.sqrt() * x[idx] + (1 - ab).sqrt() * noise
    err = torch.empty(n_draws, dtype=torch.float64)
    for s in range(0, n_draws, chunk):
        sl = slice(s, s + chunk)
        r = ab[sl].sqrt()  # (c, 1): each draw scales the set by its own sqrt(alpha_bar)
        d2 = (xt[sl] ** 2).sum(1, keepdim=True) - 2 * r * (xt[sl] @ x.T) + r ** 2 * (x ** 2).sum(1)
        w = torch.softmax(-d2 / (2 * (1 - ab[sl])), 1)
        err[sl] = ((w @ x - x[idx[sl]]) ** 2).mean(1)
    return err, t


def cmd_floor(a):
    from neumat.diffusion import Diffusion, Normalizer, ScheduleConfig
    man, w = split_20()
    diff = Diffusion(ScheduleConfig())
    rows = []
    for model in ("ours", "merl100"):
        tr = torch.as_tensor(w[dataset.training_rows(man, model)])
        x = Normalizer.fit(tr).encode(tr)
        err, t = ideal_x0_loss(x, diff)
        buckets = {f"t<{b}": float(err[(t >= lo) & (t < b)].mean())
                   for lo, b in ((0, 250), (250, 500), (500, 750), (750, 1000))}
        rows.append({"training set": model, "fields": len(tr), "ideal x0 loss": float(err.mean()), **buckets})
    print(machine())
    print(pd.DataFrame(rows).to_markdown(index=False, floatfmt=".4f"))


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd", choices=["run", "cost", "floor"])
    ap.add_argument("--vae-steps", type=int, default=2000)
    ap.add_argument("--pca-components", type=int, default=64)
    ap.add_argument("--bins", type=int, default=20000)
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--samples", nargs="*", default=[], help="name=path.npy sets to describe too")
    ap.add_argument("--table", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    {"run": cmd_run, "cost": cmd_cost, "floor": cmd_floor}[a.cmd](a)
