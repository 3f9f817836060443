"""Triple Plane query throughput for one 1920 x 1080 frame (2,073,600 queries): the fused C
query (`neumat.btf.query`, CPU) and the batched torch path (`model(u, wi, wo)` in chunks),
against (a) a plain unbatched torch implementation of the same model (one query per call, timed
on a subset and extrapolated) and (b) the FLOP bound of this machine (FLOPs per query vs a
float32 matmul measured in the same run). Wall and CPU time both: on a shared machine the
fraction of the bound per CPU-second is the load-independent one. Each figure line names the
CPU and ISA. Paper anchor: 2.0 ms per frame on an RTX 4090.

    OMP_NUM_THREADS=2 python benchmarks/btf_query.py [--model results/<run>/btf/models/<m>/triple_plane.pt]
                                                      [--march x86-64-v3]

--march builds the fused query for another target (e.g. x86-64-v3: AVX2 on an AVX-512 host).
With --device cuda (the default where a GPU is visible) the fused row is the Triton kernel
(`neumat.btf.query_triton`, where Triton is installed) and its goal is <= 1.0 ms per frame.
"""

from __future__ import annotations

import argparse
import time

import torch

from neumat import machine
from neumat.btf import models, query, query_triton
from neumat.btf.directions import half_diff
from neumat.btf.neural import fetch

FRAME = 1920 * 1080
GPU_GOAL_MS = 1.0


def random_queries(n, gen, device):
    u = torch.rand(n, 2, generator=gen)
    def hemi():
        w = torch.randn(n, 3, generator=gen)
        w[:, 2] = w[:, 2].abs() + 0.05
        return torch.nn.functional.normalize(w, dim=-1)
    return u.to(device), hemi().to(device), hemi().to(device)


def flops_per_query(m) -> int:
    """Multiply-adds x 2 of the MLP, the three 4-tap bilinear fetches and the half/diff frame."""
    lin = [l for l in m.net if isinstance(l, torch.nn.Linear)]
    mlp = sum(2 * l.in_features * l.out_features + l.out_features for l in lin)
    relu = sum(l.out_features for l in lin[:-1])
    fetch = 3 * 4 * 2 * max(m.kwargs["u_channels"], m.kwargs["dir_channels"])
    return mlp + relu + fetch + 60 + 3  # ~60 for half_diff (normalise, rotations), expm1 + relu


def timed(fn, repeat=3, sync=lambda: None):
    """Best wall and best process CPU seconds of `repeat` calls."""
    wall = cpu = float("inf")
    for _ in range(repeat):
        sync()
        t, c = time.perf_counter(), time.process_time()
        fn()
        sync()
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
    return wall, cpu


@torch.no_grad()
def batched(m, u, wi, wo, chunk):
    return torch.cat([m(u[s:s + chunk], wi[s:s + chunk], wo[s:s + chunk])
                      for s in range(0, len(u), chunk)])


@torch.no_grad()
def unbatched(m, u, wi, wo):
    """The same model evaluated one query at a time with plain tensor ops (no batching)."""
    W = [(l.weight, l.bias) for l in m.net if isinstance(l, torch.nn.Linear)]
    out = []
    for k in range(len(u)):
        h, d = half_diff(wi[k:k + 1], wo[k:k + 1])
        x = torch.cat([m.features_u(u[k:k + 1]),
                       fetch(m.f_h, (h[:, :2] + 1) / 2, False),
                       fetch(m.f_d, (d[:, :2] + 1) / 2, False)], -1)
        for i, (w, b) in enumerate(W):
            x = x @ w.T + b
            if i < len(W) - 1:
                x = torch.relu(x)
        out.append(torch.relu(torch.expm1(x)))
    return torch.cat(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", help="trained triple_plane.pt (default: random 400x400 model)")
    ap.add_argument("--chunk", type=int, default=1 << 18)
    ap.add_argument("--unbatched", type=int, default=2000, help="queries timed one by one")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--march", default="native", help="-march of the fused C query")
    ap.add_argument("--sweep", action="store_true",
                    help="GPU: time the Triton query, plain, with HPB and with hex-tiling, for "
                         "each queries-per-program and warps-per-program launch shape")
    a = ap.parse_args()
    dev = torch.device(a.device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    m = models.load(a.model) if a.model else models.TriplePlane(400, 400)
    m = m.to(dev).eval()
    gen = torch.Generator().manual_seed(0)
    u, wi, wo = random_queries(FRAME, gen, dev)
    print(f"device {dev}, torch threads {torch.get_num_threads()}, model {m.kwargs}, "
          f"{m.n_params()} parameters")

    m.requires_grad_(False)  # inference: the fused query needs no autograd
    fused = dev.type == "cpu" and query.supported(m, u, march=a.march)
    where = machine.describe(a.march if fused else None)
    if dev.type == "cuda":
        where += f"; GPU {torch.cuda.get_device_name(dev)}"
    print(f"machine: {where}")

    batched(m, u[:4096], wi[:4096], wo[:4096], a.chunk)                 # warm-up
    t_b, c_b = timed(lambda: batched(m, u, wi, wo, a.chunk), sync=sync)
    n1 = min(a.unbatched, FRAME)
    ref = batched(m, u[:n1], wi[:n1], wo[:n1], a.chunk)
    t1, _ = timed(lambda: unbatched(m, u[:n1], wi[:n1], wo[:n1]), repeat=1, sync=sync)
    assert torch.allclose(unbatched(m, u[:50], wi[:50], wo[:50]), ref[:50], rtol=1e-4, atol=1e-5)
    t_u = t1 * FRAME / n1
    if fused:
        with torch.no_grad():
            fq_ = lambda *q: query.query(m, *q, march=a.march)
            fq_(u[:4096], wi[:4096], wo[:4096])                             # warm-up, build
            t_f, c_f = timed(lambda: fq_(u, wi, wo))
            diff = (fq_(u[:n1], wi[:n1], wo[:n1]) - ref).abs().max().item()
    triton_ = dev.type == "cuda" and query_triton.supported(m, u, wi, wo)
    if triton_:
        with torch.no_grad():
            query.query(m, u[:4096], wi[:4096], wo[:4096])                  # warm-up, compile
            t_t, _ = timed(lambda: query.query(m, u, wi, wo), repeat=10, sync=sync)
            diff_t = (query.query(m, u[:n1], wi[:n1], wo[:n1]) - ref).abs().max().item()
            # the log-space output too: a random model's RGB is often clamped to 0
            raw_ref = m.raw(u[:n1], wi[:n1], wo[:n1])
            diff_r = (query.query(m, u[:n1], wi[:n1], wo[:n1], raw=True) - raw_ref).abs().max()
            diff_t = f"{diff_t:.2e} (raw {diff_r.item():.2e} of max |raw| {raw_ref.abs().max():.2f})"

    if triton_ and a.sweep:
        sweep(m, u, wi, wo, sync)
    fq = flops_per_query(m)
    n = 4096 if dev.type == "cuda" else 2048
    A = torch.randn(n, n, device=dev)
    t_mm, c_mm = timed(lambda: A @ A, sync=sync)
    peak, peak_cpu = 2 * n ** 3 / t_mm, 2 * n ** 3 / c_mm
    bound, bound_cpu = peak / fq, peak_cpu / fq  # queries per wall s, per CPU-s

    qps_b, qps_u = FRAME / t_b, FRAME / t_u
    print(f"batched   : {t_b * 1e3:10.1f} ms/frame  {qps_b:12.4g} queries/s, "
          f"{c_b * 1e3:.1f} CPU-ms/frame  [{where}]")
    if fused:
        print(f"fused C   : {t_f * 1e3:10.1f} ms/frame  {FRAME / t_f:12.4g} queries/s, "
              f"{c_f * 1e3:.1f} CPU-ms/frame, max |fused - batched| {diff:.2e}  [{where}]")
    if triton_:
        print(f"Triton    : {t_t * 1e3:10.3f} ms/frame  {FRAME / t_t:12.4g} queries/s, "
              f"max |Triton - batched| {diff_t}; fused/bound {FRAME / t_t / bound:.3f}, "
              f"Triton/batched {t_b / t_t:.1f}x; goal <= {GPU_GOAL_MS} ms/frame: "
              f"{'met' if t_t * 1e3 <= GPU_GOAL_MS else 'not met'}  [{where}]")
    elif dev.type == "cuda":
        print(f"Triton    : not available (Triton not installed: the torch path runs)  [{where}]")
    print(f"unbatched : {t_u * 1e3:10.1f} ms/frame  {qps_u:12.4g} queries/s "
          f"(extrapolated from {n1} queries)")
    print(f"FLOP bound: {FRAME / bound * 1e3:10.1f} ms/frame  {bound:12.4g} queries/s "
          f"({fq} FLOP/query, {n}^3 matmul {peak / 1e9:.1f} GFLOP/s, "
          f"{peak_cpu / 1e9:.1f} GFLOP/CPU-s)  [{where}]")
    print(f"ratios    : batched/unbatched {qps_b / qps_u:.1f}x, batched/bound {qps_b / bound:.3f} "
          f"(per CPU-s {FRAME / c_b / bound_cpu:.3f}), "
          f"paper anchor (RTX 4090, 2.0 ms/frame) / batched {t_b / 2.0e-3:.1f}x slower  [{where}]")
    if fused:
        print(f"ratios    : fused/bound {FRAME / t_f / bound:.3f} (per CPU-s "
              f"{FRAME / c_f / bound_cpu:.3f}), fused/batched {t_b / t_f:.1f}x wall, "
              f"{c_b / c_f:.1f}x CPU  [{where}]")
        # the matmul rate is not the fused query's bound: its MLP can beat MKL's sgemm (AMD
        # Zen 5: about 200 against 100 GFLOP/CPU-s); the build's FMA rate is
        fpk = query.fma_peak(a.march)
        print(f"FMA bound : {FRAME * fq / fpk * 1e3:10.1f} CPU-ms/frame (the fused build's fp32 FMA "
              f"peak {fpk / 1e9:.1f} GFLOP/CPU-s, one thread): fused {FRAME * fq / fpk / c_f:.3f} "
              f"of it per CPU-s  [{where}]")

SHAPES = ((32, 1), (32, 4), (64, 2), (64, 4), (128, 4), (128, 8), (256, 8))


@torch.no_grad()
def sweep(m, u, wi, wo, sync, rounds=10):
    """ms/frame of the plain, the HPB and the hex-tiling Triton query (the syntheses reading
    their planes as float16, the default, and as float32) per launch shape (queries and warps
    per program; query_triton.LAUNCH holds each kernel's default), best of `rounds` rounds that
    each time every variant once, so a slow spell of the shared GPU host hits all alike."""
    from neumat.btf import synthesis as syn
    h, x = syn.build(m, "hpb", 1, {}), syn.build(m, "hextile", 1, {})
    variants = {"plain": (None, query_triton.packed(m)),
                "HPB": (h, query_triton._pack(m, h)),
                "HPB fp32": (h, query_triton._pack(m, h, half=False)),
                "hex-tiling": (x, query_triton._pack(m, x)),
                "hex-tiling fp32": (x, query_triton._pack(m, x, half=False))}
    u64 = (u.double() - 0.5) * 2e3
    runs = {}
    for block, warps in SHAPES:
        for name, (s, p) in variants.items():
            def f(uu=u if s is None else u64, p=p, s=s, shape=dict(BLOCK=block, num_warps=warps)):
                return query_triton.query(m, uu, wi, wo, packed=p, synth=s, launch=shape)
            f()  # compile
            runs[block, warps, name] = f
    best = {k: float("inf") for k in runs}
    for _ in range(rounds):
        for k, f in runs.items():
            best[k] = min(best[k], timed(f, repeat=1, sync=sync)[0] * 1e3)
    print(f"sweep, ms/frame (best of {rounds} interleaved rounds; overhead against plain at the "
          f"same shape), defaults {query_triton.LAUNCH}:")
    for block, warps in SHAPES:
        pl = best[block, warps, "plain"]
        print(f"  BLOCK {block:4d} warps {warps}: plain {pl:.3f}" + "".join(
            f"; {n} {best[block, warps, n]:.3f} ({100 * (best[block, warps, n] / pl - 1):+.1f} %)"
            for n in variants if n != "plain"))
    fastest = {n: min((v, k[:2]) for k, v in best.items() if k[2] == n) for n in variants}
    bound = FRAME * flops_per_query(m) / machine.gpu_matmul_rate(u.device) * 1e3
    print(f"FLOP bound {bound:.3f} ms/frame (fp32 torch.mm rate in this run): the fastest plain "
          f"{bound / fastest['plain'][0]:.3f} of it")
    for n in variants:
        v, shape = fastest[n]
        line = f"fastest {n} {v:.3f} ms at {shape}"
        if n != "plain":
            line += (f": overhead {100 * (v / fastest['plain'][0] - 1):+.1f} % against the "
                     f"fastest plain (goal <= 10 %)")
        print(line)


if __name__ == "__main__":
    main()
