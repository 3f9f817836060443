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

--device cuda fits on a GPU (the batched fitter's torch path; the loop runs there too, as the
released M3ashy code fits) and takes the peak from an 8192^3 fp32 torch.mm on that GPU. With
--loop-materials N the loop fits only the first N materials and its time is scaled to all of
them (per-material fits are independent), e.g. for paper.yaml's 2400:

    python benchmarks/fit_throughput.py --device cuda --materials 2400 --loop-materials 20
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


def loop_fit(values, bins, ids, init, s: fit.FitSettings, seed, device="cpu"):
    """Per-material baseline; returns final weights (M, 675) and val losses (M,)."""
    x_all, cos_all = fit.bin_inputs(bins)
    target_all = fit.log_target(values, cos_all)
    x_all, cos_all, target_all = x_all.to(device), cos_all.to(device), target_all.to(device)
    weights, val = [], []
    for m, i in enumerate(ids):
        net = torch.nn.Sequential(torch.nn.Linear(6, 21), torch.nn.ReLU(), torch.nn.Linear(21, 21),
                                  torch.nn.ReLU(), torch.nn.Linear(21, 3)).to(device)
        with torch.no_grad():
            for p, v in zip(net.parameters(), nbrdf.unflatten(torch.as_tensor(init)[None])):
                p.copy_(v[0])
        opt = torch.optim.Adam(net.parameters(), lr=s.lr)
        train, va = (i.to(device) for i in fit.split_bins(len(bins), seed, s.val_fraction))
        spe = len(train) // s.batch
        for step in range(s.steps):
            epoch, k = divmod(step, spe)
            if k == 0:
                order, mirror = (i.to(device) for i in fit.epoch_order(len(train), seed, epoch))
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
        weights.append(w[0].cpu())
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
    ap.add_argument("--device", default="cpu", help="cpu | cuda")
    ap.add_argument("--loop-materials", type=int, default=None,
                    help="fit only this many materials in the loop and scale its time")
    args = ap.parse_args()
    dev = torch.device(args.device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
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
    n_loop = min(args.loop_materials or args.materials, args.materials)
    scale = args.materials / n_loop  # the loop's time for all materials, from the first n_loop
    sync()
    t0, c0 = time.perf_counter(), time.process_time()
    w_loop, val_loop = loop_fit(values[:n_loop], bins, ids[:n_loop], init, s, seed=0, device=dev)
    sync()
    t_loop, c_loop = scale * (time.perf_counter() - t0), scale * (time.process_time() - c0)
    t0, c0 = time.perf_counter(), time.process_time()
    x, cos = fit.bin_inputs(bins)
    f = fit.BatchFitter(x, cos, fit.log_target(values, cos), ids,
                        torch.as_tensor(init).expand(len(ids), -1), s, seed=0, device=dev).train()
    val_batch, w_batch = f.eval_loss("val"), f.w.cpu().numpy()  # the loop evaluates val only
    sync()
    t_batch, c_batch = time.perf_counter() - t0, time.process_time() - c0

    if dev.type == "cuda":  # the host's CPU time means nothing for a GPU fit: wall only
        peak = peak_cpu = machine.gpu_matmul_rate(dev)
    else:
        peak, peak_cpu = machine.sgemm_peak(args.threads)
    vl, vb = val_loop.mean(), val_batch[:n_loop].mean()
    where = machine.describe(march if f.kernel == "c" else None)
    if dev.type == "cuda":
        where += f"; GPU {torch.cuda.get_device_name(dev)}, torch {torch.__version__}"
    print(f"machine: {where}")
    if n_loop < args.materials:
        print(f"loop: fitted the first {n_loop} materials, time scaled x{scale:g}; its val loss "
              f"and the weight difference are over those {n_loop}")
    print(f"{args.materials} materials x {args.steps} steps x batch {s.batch}, {len(bins)} bins, "
          f"{args.threads} threads, kernel {f.kernel}, data: {args.tables or 'random NBRDF fields'}")
    for what, t, c, v in (("per-material loop", t_loop, c_loop, vl),
                          ("batched fitter   ", t_batch, c_batch, val_batch.mean())):
        print(f"{what}: wall {t:8.2f} s ({samples / t:10.4g} material-samples/s), "
              f"CPU {c:8.2f} s ({samples / c:10.4g} material-samples/CPU-s), final val loss {v:.5f}")
    print(f"speed-up: wall {t_loop / t_batch:.1f}x, CPU {c_loop / c_batch:.1f}x; "
          f"val loss batched/loop {vb / vl:.4f}; "
          f"max |w_batched - w_loop| {np.abs(w_batch[:n_loop] - w_loop).max():.2e}  [{where}]")
    print(f"per material-step: batched {1e6 * t_batch / (args.materials * args.steps):.3g} us, "
          f"loop {1e6 * t_loop / (args.materials * args.steps):.4g} us (wall)  [{where}]")
    rate, rate_cpu = samples * STEP_FLOPS / t_batch, samples * STEP_FLOPS / c_batch
    print(f"batched fitter: {rate / 1e9:.1f} GFLOP/s wall = {100 * rate / peak:.1f} % of the fp32 "
          f"sgemm peak {peak / 1e9:.1f} GFLOP/s; {rate_cpu / 1e9:.1f} GFLOP/CPU-s = "
          f"{100 * rate_cpu / peak_cpu:.1f} % of sgemm's {peak_cpu / 1e9:.1f} GFLOP/CPU-s "
          f"({STEP_FLOPS} matmul FLOP per material-sample; 2048^3 torch.mm, {args.threads} "
          f"threads)  [{where}]")

if __name__ == "__main__":
    main()
