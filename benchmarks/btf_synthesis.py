"""Synthesis overhead per 1920 x 1080 frame of BTF queries (2,073,600 queries, u uniform over a
x15 area, float64) against the plain Triple Plane query of the same frame, in the same run.
Overhead = (t(query with synthesis) - t(plain query)) / t(plain query), in wall time and in
CPU time of this process (the load-independent one on a shared machine); goal <= 10 % (paper:
< 0.2 ms synthesis vs 2.0 ms query on an RTX 4090).

Rows, each against the plain query of the same path:
  fused C   `Synthesized(model, synth)(u, wi, wo)` on the CPU: HPB and hex-tiling run inside
            the query kernel (`neumat/btf/query_kernel.c`, btf_triple_plane_hpb and _hex),
            other methods feed their features to it; against the fused plain query
            `query.query(model, u, wi, wo)`.
  hook      HPB's features computed first (its C `hpb_features`) and fed to the fused query
            through `features_u` (what the fused query did before HPB ran inside it).
  torch     `Synthesized.torch_forward`, synthesis on its torch path; against eager
            `model(u, wi, wo)`, and the plane fetch alone.
--compile adds rows whose torch synthesis is torch.compile'd.
--device cuda: the same frame on a GPU, where the plain query, HPB and hex-tiling run as Triton
kernels (neumat.btf.query_triton) and the other methods on their torch paths; wall time only,
one launch per frame by default. The "(GPU)" rows go through `query.query` as a renderer does;
the "(GPU kernel)" rows call the kernels with their tables packed once, and the overhead verdict
compares those (query.query's dispatch is host time). HPB and hex-tiling also get a
"(GPU kernel, fp32 plane)" row: the same kernel reading its synthesised plane as float32 (the
layout before the float16 planes), the baseline of that change.

    OMP_NUM_THREADS=2 python benchmarks/btf_synthesis.py [--methods hpb] [--repeat 3] [--coherent]
                                                          [--processes 5]
                                                          [--model results/<run>/btf/models/<m>/triple_plane.pt]
                                                          [--march x86-64-v3] [--size 200]
    python benchmarks/btf_synthesis.py --device cuda --no-torch --methods hpb hextile
                                       [--repeat 20] [--launch hextile=128x4]
--march builds the fused query for another target (x86-64-v3: the AVX2 kernel on an AVX-512
host); "synthesis alone" stays native.

On a shared host, compare builds with OMP_NUM_THREADS=1 and --repeat 15: one thread's CPU time
is the steady figure. On 2026-11-25 (AMD EPYC, 2 cores, load ~1 from other tenants) the plain
query's best over 5 two-thread rounds ranged 111-137 ms between runs and HPB's overhead +4.9 to
+16.9 %; on one thread, best of 15, the plain query took 215-224 ms and HPB +9.9 to +11.1 %;
with the fetch coordinate in fixed point (query_kernel.c grid_prepare; idle, same day) +9.1 %
(AVX2 build +18.7 %) against +11.3 % (+20.6 %) for the build before, run in turn; AVX2 build
with the LUT read by scalar loads (lut_fetch, best of 9, in turn) +15.4 and +16.4 % against
+17.7 and +18.2 %. Hex-tiling,
one thread, best of 9 (`--methods hpb hextile --no-torch --repeat 9`, same host, idle,
2026-11-25): +41.2 % (AVX2 build +53.6 %); with its blend folded into the bilinear weights as
HPB's (f5f8541) +30.9 % (+39.1 %); with its rotated fetch coordinate in fixed point too +26.9 %
(+34.7 %); with Gain3's power by polynomials (query_kernel.c powk) +24.9 % (+33.8 %).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import fresh_processes
import neumat.btf.synthesis as syn
from btf_query import flops_per_query
from neumat import machine
from neumat.btf import models, query, query_triton
from neumat.btf.neural import fetch

FRAME = 1920 * 1080
GOAL = 0.10


@torch.no_grad()
def chunked(fn, n, chunk):
    return [fn(slice(s, s + chunk)) for s in range(0, n, chunk)]


class _Fn:
    """A function of u in the place of the synthesis object (the features hook, compiled)."""

    method, dynamic = "function", True

    def __init__(self, fn):
        self.fn = fn

    def __call__(self, u):
        return self.fn(u)


def timed(runs: dict, repeat: int, sync) -> tuple[dict, dict]:
    """Best wall and CPU seconds of each run over `repeat` rounds, after a warm-up (kernel build
    or load, first touch). Rounds interleave all variants: on a shared machine a load spike then
    hits one round of every variant rather than all rounds of one."""
    wall = {k: float("inf") for k in runs}
    cpu = dict(wall)
    for fn in runs.values():
        fn(4096)
    for _ in range(repeat):
        for k, fn in runs.items():
            sync()
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            sync()
            wall[k] = min(wall[k], time.perf_counter() - t0)
            cpu[k] = min(cpu[k], time.process_time() - c0)
    return wall, cpu


def frame(coherent: bool = False):
    """One frame of queries: u (FRAME, 2) float64, uniform over a x15 area or, `coherent`, a x15
    plane in pixel order; u32 its float32 remainder (the plain query's coordinates); w (FRAME, 3)
    unit directions about the normal. Seeded: the same frame in every run."""
    g = torch.Generator().manual_seed(0)
    u = torch.rand(FRAME, 2, generator=g, dtype=torch.float64) * 15
    if coherent:  # neighbouring pixels, neighbouring u: 128 pixels per unit of u
        ys, xs = torch.meshgrid(torch.arange(1080.0, dtype=torch.float64),
                                torch.arange(1920.0, dtype=torch.float64), indexing="ij")
        u = torch.stack([(xs + 0.5) / 128, (ys + 0.5) / 128], -1).reshape(-1, 2) + 1234.5
    u32 = torch.remainder(u, 1.0).float()
    w = torch.nn.functional.normalize(torch.randn(FRAME, 3, generator=g) * torch.tensor([1, 1, 0.5])
                                      + torch.tensor([0, 0, 0.8]), dim=-1)
    return u, u32, w


def timed_runs(a, m, u, u32, w, c, dev, fused, K):
    """The timed functions of a frame by name, and for each synthesis row the plain query it
    is measured against."""
    run = lambda f: lambda n=FRAME: chunked(f, n, c)
    runs, refs = {}, {}   # name -> timed function; name -> the plain query it is measured against
    if fused:
        runs[f"plain ({K})"] = run(lambda s: query.query(m, u32[s], w[s], w[s], march=a.march))
    if dev.type == "cuda":
        p0 = query_triton.packed(m)
        runs["plain (GPU kernel)"] = run(lambda s: query_triton.query(m, u32[s], w[s], w[s],
                                                                      packed=p0))
    if not a.no_torch:
        runs["plain (torch)"] = run(lambda s: m(u32[s], w[s], w[s]))
        runs["plain f_U fetch (torch)"] = run(lambda s: fetch(m.f_u, u32[s], True))
    for method in a.methods:
        st = {"scale": a.quilt_scale} if method == "quilting" else {}
        wr = syn.Synthesized(m, syn.build(m, method, 1, st))
        if fused:
            # Synthesized.forward, with the build chosen: query.query with the synthesis as f_U
            runs[f"{method} ({K})"] = run(lambda s, wr=wr: query.query(
                m, u[s], w[s], w[s], features_u=wr.synth, march=a.march))
            refs[f"{method} ({K})"] = f"plain ({K})"
            if dev.type == "cuda" and method in query_triton.METHODS:
                # the kernels alone, packed once (no dispatch in query.query), and the baseline
                # of the float16 planes: the same kernel reading its plane as float32
                for name, half in (("kernel", True), ("kernel, fp32 plane", False)):
                    p = query_triton._pack(m, wr.synth, half=half)
                    runs[f"{method} (GPU {name})"] = run(
                        lambda s, wr=wr, p=p: query_triton.query(m, u[s], w[s], w[s], packed=p,
                                                                 synth=wr.synth))
                    refs[f"{method} (GPU {name})"] = "plain (GPU kernel)"
            if method == "hpb" and dev.type == "cpu":
                hook = _Fn(wr.synth)  # not an HPB object: its features are fed to the kernel
                runs[f"hpb (hook, {K})"] = run(
                    lambda s, h=hook: query.query(m, u[s], w[s], w[s], features_u=h, march=a.march))
                refs[f"hpb (hook, {K})"] = f"plain ({K})"
        runs[f"{method} synthesis alone"] = run(lambda s, wr=wr: wr.synth(u[s]))
        if not a.no_torch:
            tf = _Fn(wr.synth.torch_features) if method == "hpb" else wr.synth
            wt = syn.Synthesized(m, tf)
            runs[f"{method} (torch)"] = run(lambda s, wt=wt: wt.torch_forward(u[s], w[s], w[s]))
            refs[f"{method} (torch)"] = "plain (torch)"
        if a.compile:
            fast = torch.compile(wr.synth.__call__, dynamic=False)
            t0 = time.perf_counter()
            fast(u[:c])
            print(f"{method}: torch.compile {time.perf_counter() - t0:.0f} s", flush=True)
            wc = syn.Synthesized(m, _Fn(fast))
            runs[f"{method} (compiled torch)"] = run(lambda s, wc=wc: wc.torch_forward(u[s], w[s], w[s]))
            refs[f"{method} (compiled torch)"] = "plain (torch)"
    return runs, refs


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", help="trained triple_plane.pt (default: random --size model)")
    ap.add_argument("--size", type=int, default=400,
                    help="the random model's plane side (400: UBO2014's; 200: HPB's and "
                         "hex-tiling's float16 planes fit a 2 MB L2)")
    ap.add_argument("--methods", nargs="+", default=["linear", "hpb", "hextile"])
    ap.add_argument("--quilt-scale", type=int, default=2,
                    help="quilting (if in --methods) is built at this scale first (not timed)")
    ap.add_argument("--chunk", type=int,
                    help="divides the frame: one compiled shape (default: 259200 on the CPU, the "
                         "whole frame, one launch, on a GPU)")
    ap.add_argument("--compile", action="store_true", help="also time torch.compile'd synthesis")
    ap.add_argument("--repeat", type=int, default=5, help="interleaved rounds (best kept)")
    ap.add_argument("--no-torch", action="store_true", help="skip the (slow) torch-path rows")
    ap.add_argument("--device", default="cpu", help="cpu | cuda")
    ap.add_argument("--march", default="native", help="-march of the fused C query")
    ap.add_argument("--launch", nargs="+", default=[], metavar="METHOD=BxW",
                    help="GPU: a synthesis kernel's launch shape in place of query_triton.LAUNCH's, "
                         "e.g. hextile=128x4 (queries and warps per program)")
    ap.add_argument("--coherent", action="store_true",
                    help="u of a x15 plane across the frame in pixel order (a rendered frame), "
                         "not uniform random u")
    ap.add_argument("--processes", type=int, default=1,
                    help="CPU: the whole run in this many fresh processes, the medians reported "
                         "with the [min, max] of the CPU overhead between them (a process's figures "
                         "move by more than its rounds do: fresh_processes.py)")
    ap.add_argument(fresh_processes.FLAG, action="store_true", help=argparse.SUPPRESS)  # a child
    a = ap.parse_args()
    if a.processes < 1 or (a.processes > 1 and a.device != "cpu"):
        ap.error("--processes must be at least 1, and above 1 only with --device cpu")
    for item in a.launch:  # the kernels read query_triton.LAUNCH at each launch
        method, _, shape = item.partition("=")
        b, _, w = shape.partition("x")
        if method not in query_triton.METHODS or not (b.isdigit() and w.isdigit()):
            ap.error(f"--launch {item}: give METHOD=BxW, METHOD one of {query_triton.METHODS}")
        query_triton.LAUNCH[method] = {"BLOCK": int(b), "num_warps": int(w)}
    m = (models.load(a.model) if a.model else models.TriplePlane(a.size, a.size)).eval()
    m.requires_grad_(False)
    u, u32, w = frame(a.coherent)
    dev = torch.device(a.device)
    m, u, u32, w = m.to(dev), u.to(dev), u32.to(dev), w.to(dev)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    fused = dev.type == "cuda" or query.supported(m, u32[:8], w[:8], w[:8], march=a.march)
    where = machine.describe(a.march if dev.type == "cpu" and fused else None)
    if dev.type == "cuda":
        where += f"; GPU {torch.cuda.get_device_name(dev)}, Triton " + (
            "on" if query_triton.supported(m, u32[:8], w[:8], w[:8]) else "not available")
    c = a.chunk or (FRAME if dev.type == "cuda" else 259200)
    print(f"machine: {where}; torch ISA {torch.backends.cpu.get_cpu_capability()}, "
          f"torch threads {torch.get_num_threads()}, torch {torch.__version__}")
    print(f"model {m.method} {m.kwargs}, frame {FRAME} queries "
          f"({'coherent: a x15 plane in pixel order' if a.coherent else 'uniform random u'}), "
          f"chunk {c}" + (f"; launch shapes {query_triton.LAUNCH}" if dev.type == "cuda" else ""))
    K = "fused C" if dev.type == "cpu" else "GPU"  # the fused path of this device
    parent = a.processes > 1 and not a.one_process
    # the parent of --processes builds no synthesis (nor torch.compile's): its children time them
    runs, refs = ({}, {}) if parent else timed_runs(a, m, u, u32, w, c, dev, fused, K)
    spread, how = {}, "one process"
    if parent:
        per = fresh_processes.gather(__file__, a.processes)
        runs, refs = dict.fromkeys(per[0]["cpu"]), per[0]["refs"]
        med = statistics.median
        wall = {k: med(r["wall"][k] for r in per) for k in runs}
        cpu = {k: med(r["cpu"][k] for r in per) for k in runs}
        spread = {k: [r["cpu"][k] / r["cpu"][refs[k]] - 1 for r in per] for k in refs}
        how = f"median of {a.processes} processes"
        print(f"{how}, each its best of {a.repeat} rounds; [min, max] of the CPU overhead "
              f"between processes")
    else:
        wall, cpu = timed(runs, a.repeat, sync)
        if a.one_process:  # a child of --processes: its figures to the parent
            fresh_processes.emit({"wall": wall, "cpu": cpu, "refs": refs})
            return
    print(f"{'':28s} {'wall ms/frame':>14s} {'CPU ms/frame':>13s}   overhead vs plain (wall, CPU)")
    for k in runs:
        line = f"{k:28s} {wall[k] * 1e3:14.1f} {cpu[k] * 1e3:13.1f}"
        if k in refs:
            r = refs[k]
            ow, oc = wall[k] / wall[r] - 1, cpu[k] / cpu[r] - 1
            line += f"   {ow * 100:+7.1f} %  {oc * 100:+7.1f} %   vs {r}"
            if k in spread:
                line += f"  [{min(spread[k]) * 100:+.1f}, {max(spread[k]) * 100:+.1f}]"
        print(line, flush=True)
    if dev.type == "cpu" and fused:  # the baseline against the machine: its FLOP bound
        peak_cpu = query.fma_peak(a.march)  # the build's fp32 FMA rate, one thread
        bound = FRAME * flops_per_query(m) / peak_cpu
        print(f"plain (fused C): {bound * 1e3:.1f} CPU-ms/frame at the FLOP bound (this build's "
              f"fp32 FMA peak {peak_cpu / 1e9:.1f} GFLOP/CPU-s in this run, one thread): "
              f"{bound / cpu['plain (fused C)']:.3f} of it")
    elif dev.type == "cuda" and "plain (GPU kernel)" in wall:
        peak = machine.gpu_matmul_rate(dev)
        bound = FRAME * flops_per_query(m) / peak
        print(f"plain (GPU kernel): {bound * 1e3:.3f} ms/frame at the FLOP bound (fp32 torch.mm "
              f"{peak / 1e12:.1f} TFLOP/s in this run): {bound / wall['plain (GPU kernel)']:.3f} "
              f"of it  [{where}]")
    for method in [x for x in ("hpb", "hextile") if fused and x in a.methods]:
        r, k = f"plain ({K})", f"{method} ({K})"
        if dev.type == "cuda":  # the kernels' own times: query.query's dispatch is host time
            r, k = "plain (GPU kernel)", f"{method} (GPU kernel)"
        ow, oc = wall[k] / wall[r] - 1, cpu[k] / cpu[r] - 1
        if dev.type == "cuda":  # the host's CPU time means nothing for a GPU frame
            verdict = "met" if ow <= GOAL else "not met"
            print(f"{syn.LABELS[method]} synthesis overhead per frame, GPU: {ow * 100:+.1f} % wall "
                  f"({(wall[k] - wall[r]) * 1e3:+.3f} ms) against {wall[r] * 1e3:.3f} ms; "
                  f"goal <= {GOAL * 100:.0f} %: {verdict}  [{where}]")
            continue
        verdict = "met" if max(ow, oc) <= GOAL else "not met"
        print(f"{syn.LABELS[method]} synthesis overhead per frame, fused C: {ow * 100:+.1f} % wall, {oc * 100:+.1f} % "
              f"CPU ({(wall[k] - wall[r]) * 1e3:+.1f} ms, {(cpu[k] - cpu[r]) * 1e3:+.1f} CPU-ms) "
              f"against {wall[r] * 1e3:.1f} ms ({how}); goal <= {GOAL * 100:.0f} %: {verdict}  "
              f"[{where}]")


if __name__ == "__main__":
    main()
