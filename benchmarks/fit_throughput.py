"""Batched NBRDF fitter vs a per-material loop, same data, same minibatches, same steps.

The loop is the usual PyTorch way: one nn.Sequential 6-21-21-3 and one torch.optim.Adam per
material, autograd, the same eq. 2 loss, lr schedule, 80/20 split and minibatch order as the
batched fitter (`neumat.fit`). Prints material-samples per second for both, the ratio and both
final validation losses (mean over materials, all validation bins), and the batched fitter's
matmul FLOP rate as a fraction of this machine's fp32 sgemm peak (a 2048^3 torch.mm with the
same threads, measured in the same run). Every figure line names the CPU and the ISA.

    OMP_NUM_THREADS=2 python benchmarks/fit_throughput.py [--tables DIR] [--materials 50]
                                                          [--march x86-64-v3]

--tables DIR fits MERL .binary tables from DIR (e.g. decoded real materials); without it the
materials are random NBRDF fields (deterministic). --kernel torch times the batched fitter's
torch path instead of the C kernel (`neumat.fit_kernel`), e.g. to see what the kernel adds.
--march builds and times the C kernel for another target, e.g. x86-64-v3 (AVX2) or x86-64-v2
(SSE4.2) on an AVX-512 host.
"""
import argparse
import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import torch

from neumat import fit, fit_kernel, machine, nbrdf
from neumat.io import merl


def load_data(args):
    rng = np.random.default_rng(0)
    if args.tables:
        paths = sorted(Path(args.tables).glob("*.binary"))[:args.materials]
        if len(paths) < args.materials:
            raise SystemExit(f"{args.tables}: {len(paths)} .binary files, need {args.materials}")
        tabs = np.stack([merl.read_merl(p).reshape(3, -1) for p in paths])
        ok = np.flatnonzero(merl.valid_mask() & (tabs >= 0).all((0, 1)))
        bins = np.sort(rng.choice(ok, args.bins, replace=False))
        return bins, tabs[:, :, bins].astype(np.float32)
    bins = np.sort(rng.choice(np.flatnonzero(merl.valid_mask()), args.bins, replace=False))
    teach = nbrdf.init_weights(args.materials, torch.Generator().manual_seed(1)) * 2
    return bins, nbrdf.forward(teach, fit.bin_inputs(bins)[0]).transpose(1, 2).numpy()


def loop_fit(values, bins, ids, init, s: fit.FitSettings, seed):
    """Per-material baseline; returns final weights (M, 675) and val losses (M,)."""
    x_all, cos_all = fit.bin_inputs(bins)
    target_all = fit.log_target(values, cos_all)
    weights, val = [], []
    for m, i in enumerate(ids):
        net = torch.nn.Sequential(torch.nn.Linear(6, 21), torch.nn.ReLU(), torch.nn.Linear(21, 21),
                                  torch.nn.ReLU(), torch.nn.Linear(21, 3))
        with torch.no_grad():
            for p, v in zip(net.parameters(), nbrdf.unflatten(torch.as_tensor(init)[None])):
                p.copy_(v[0])
        opt = torch.optim.Adam(net.parameters(), lr=s.lr)
        train, va = fit.split_bins(len(bins), seed, s.val_fraction)
        spe = len(train) // s.batch
        for step in range(s.steps):
            epoch, k = divmod(step, spe)
            if k == 0:
                order, mirror = fit.epoch_order(len(train), seed, epoch)
            sl = slice(k * s.batch, (k + 1) * s.batch)
            idx = train[order[sl]]
            x, t, c = x_all[idx], target_all[m, idx], cos_all[idx, None]
            if s.mirror_phi_d:
                x = fit.mirror_phi_d(x, mirror[sl])
            loss = (torch.log1p(torch.expm1(net(x)) * c) - t).abs().mean()
            for g in opt.param_groups:
                g["lr"] = s.lr_at(step)
            opt.zero_grad()
            loss.backward()
            opt.step()
        w = nbrdf.flatten([p.detach()[None] for p in net.parameters()])
        weights.append(w[0])
        val.append(fit.field_loss(w, x_all[va], target_all[m, va][None], cos_all[va, None]).item())
    return torch.stack(weights).numpy(), np.array(val)


# matmul FLOPs per material-sample of one training step: forward 6-21-21-3 (630 multiply-adds),
# weight gradients (630) and input gradients of layers 2 and 3 (504); 2 FLOPs per multiply-add
STEP_FLOPS = 2 * (630 + 630 + 504)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--tables", help="directory of MERL .binary tables (default: random fields)")
    ap.add_argument("--materials", type=int, default=50, help="materials (= one batched model)")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--bins", type=int, default=65536, help="stored bins per material")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--kernel", choices=fit.KERNELS, default="auto", help="batched fitter's step")
    ap.add_argument("--march", default=None,
                    help="-march of the C kernel (default: native, or $NEUMAT_FIT_MARCH)")
    args = ap.parse_args()
    if args.march:  # before the first library load: the fitter builds for this target
        os.environ["NEUMAT_FIT_MARCH"] = args.march
    march = fit_kernel.default_march()
    torch.set_num_threads(args.threads)
    bins, values = load_data(args)
    ids = np.arange(args.materials)
    init = nbrdf.init_weights(1, torch.Generator().manual_seed(0))[0].numpy()
    s = dataclasses.replace(fit.FitSettings(), steps=args.steps, materials_per_batch=args.materials,
                            eval_every=10 ** 9, kernel=args.kernel)
    samples = args.materials * args.steps * s.batch
    fit_kernel.available()  # compiles fit_step.c on a machine's first use: not part of a fit

    # wall and CPU time of the process: on a shared machine, CPU time (one thread) is the
    # load-independent measure; wall time is what a user waits
    t0, c0 = time.perf_counter(), time.process_time()
    w_loop, val_loop = loop_fit(values, bins, ids, init, s, seed=0)
    t_loop, c_loop = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    x, cos = fit.bin_inputs(bins)
    f = fit.BatchFitter(x, cos, fit.log_target(values, cos), ids,
                        torch.as_tensor(init).expand(len(ids), -1), s, seed=0).train()
    val_batch, w_batch = f.eval_loss("val"), f.w.numpy()  # the loop also evaluates val only
    t_batch, c_batch = time.perf_counter() - t0, time.process_time() - c0

    peak, peak_cpu = machine.sgemm_peak(args.threads)
    vl, vb = val_loop.mean(), val_batch.mean()
    where = machine.describe(march if f.kernel == "c" else None)
    print(f"machine: {where}")
    print(f"{args.materials} materials x {args.steps} steps x batch {s.batch}, {len(bins)} bins, "
          f"{args.threads} threads, kernel {f.kernel}, data: {args.tables or 'random NBRDF fields'}")
    for what, t, c, v in (("per-material loop", t_loop, c_loop, vl),
                          ("batched fitter   ", t_batch, c_batch, vb)):
        print(f"{what}: wall {t:8.2f} s ({samples / t:10.4g} material-samples/s), "
              f"CPU {c:8.2f} s ({samples / c:10.4g} material-samples/CPU-s), final val loss {v:.5f}")
    print(f"speed-up: wall {t_loop / t_batch:.1f}x, CPU {c_loop / c_batch:.1f}x; "
          f"val loss batched/loop {vb / vl:.4f}; "
          f"max |w_batched - w_loop| {np.abs(w_batch - w_loop).max():.2e}  [{where}]")
    rate, rate_cpu = samples * STEP_FLOPS / t_batch, samples * STEP_FLOPS / c_batch
    print(f"batched fitter: {rate / 1e9:.1f} GFLOP/s wall = {100 * rate / peak:.1f} % of the fp32 "
          f"sgemm peak {peak / 1e9:.1f} GFLOP/s; {rate_cpu / 1e9:.1f} GFLOP/CPU-s = "
          f"{100 * rate_cpu / peak_cpu:.1f} % of sgemm's {peak_cpu / 1e9:.1f} GFLOP/CPU-s "
          f"({STEP_FLOPS} matmul FLOP per material-sample; 2048^3 torch.mm, {args.threads} "
          f"threads)  [{where}]")

if __name__ == "__main__":
    main()
