"""Builds of the fused BTF query kernel (`neumat/btf/query_kernel.c`) against each other, in
alternating rounds: the working tree's kernel and the kernel at each git revision (or C file)
given, each timed on the plain query and with HPB / hex-tiling inside it, on one 1920 x 1080
frame of queries (random 400 x 400 Triple Plane, u float64 uniform over a x15 area, or with
--coherent a x15 plane in pixel order, as a render queries it: `btf_synthesis.frame`). Per build: ms per frame (CPU time of this process, best of --repeat),
each method's overhead over the same build's plain query, the plain query's fraction of this
machine's FLOP bound (`btf_query.flops_per_query` over the build's fp32 FMA rate on one thread,
`neumat.btf.query.fma_peak`), and whether its outputs on 4096 queries (log(1 + RGB), before the clamp at 0) equal the first
build's to the bit.

A change to the kernel that must not change results shows "same" on every row. On a shared
machine, one thread and alternating rounds are what make builds comparable: a load spike then
hits one round of every build rather than every round of one.

    OMP_NUM_THREADS=1 python benchmarks/btf_kernel_ab.py --rev HEAD~1 [--march x86-64-v3]
                                                        [--methods hpb hextile] [--repeat 9]
                                                        [--coherent] [--tap-prefetch both]
                                                        [--processes 5] [--control]

--processes N repeats the whole comparison in N fresh processes and reports the medians, with the
[min, max] between processes: a process's allocations, stack and libraries' addresses move its
figures by more than its rounds do, so one process's best-of is not the build's figure (identical
code in two libraries differed by up to 16.5 CPU-ms a frame, 7 %, in one process; docs/stages.md).
--control adds a build of the working tree's own code as a library of its own; its row against
the working tree's is the noise floor a change must clear.

--tap-prefetch both times every build twice, with HPB's and hex-tiling's tap prefetch on and
off (NEUMAT_TAP_PREFETCH, `neumat.btf.query.tap_prefetch`); the default, auto, leaves it to
this machine's choice.
"""

from __future__ import annotations

import argparse
import statistics
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fresh_processes  # noqa: E402
from btf_query import flops_per_query  # noqa: E402
from btf_synthesis import FRAME, frame  # noqa: E402

import neumat.btf.synthesis as syn  # noqa: E402
from neumat import machine  # noqa: E402
from neumat.btf import models, query  # noqa: E402

CHUNK = 259200  # as btf_synthesis.py on the CPU
KERNEL = "src/neumat/btf/query_kernel.c"


def kernel_source(ref: str, tmp: Path) -> Path:
    """A C file as given, or the kernel at git revision `ref`, written under tmp."""
    if Path(ref).is_file():
        return Path(ref)
    root = Path(__file__).resolve().parents[1]
    try:
        text = subprocess.run(["git", "show", f"{ref}:{KERNEL}"], cwd=root, check=True,
                              capture_output=True, text=True).stdout
    except subprocess.CalledProcessError as e:
        sys.exit(f"--rev {ref}: neither a file nor a git revision with {KERNEL}: {e.stderr.strip()}")
    out = tmp / f"query_kernel_{ref.replace('/', '_').replace('~', '_')}.c"
    out.write_text(text)
    return out


def build(source: Path, march: str):
    """The ctypes library of `source` for `march`, built as neumat.btf.query builds its own."""
    saved = query.SOURCE
    try:
        query.SOURCE = source
        lib = query._library.__wrapped__(march)
    finally:
        query.SOURCE = saved
    if lib is None:
        sys.exit(f"{source}: the kernel did not build for -march={march} (see the log above)")
    return lib


def measure(a) -> tuple[dict, str]:
    """One process's alternating rounds: best CPU-s per (build, kind), whether each build's
    outputs equal the first build's, and the machine line."""
    tmp = Path(tempfile.mkdtemp(prefix="btf_kernel_ab_"))
    tree = Path(__file__).resolve().parents[1] / KERNEL
    sources = {"working tree": tree}
    if a.control:  # the same code in a library of its own: the noise floor of a comparison
        copy = tmp / "query_kernel_control.c"
        copy.write_text(tree.read_text() + "\n/* btf_kernel_ab.py --control: the working tree's code */\n")
        sources["working tree (control)"] = copy
    sources.update({r: kernel_source(r, tmp) for r in a.rev})
    built = {name: build(src, a.march) for name, src in sources.items()}
    # label -> (library, NEUMAT_TAP_PREFETCH or None for this machine's choice)
    if a.tap_prefetch == "both":
        libs = {f"{name}, pf {'on' if pf == '1' else 'off'}": (lib, pf)
                for name, lib in built.items() for pf in ("1", "0")}
    else:
        libs = {name: (lib, None) for name, lib in built.items()}
    env0 = os.environ.get("NEUMAT_TAP_PREFETCH")

    torch.manual_seed(0)  # the random model
    m = models.TriplePlane(400, 400).eval()
    m.requires_grad_(False)
    u, u32, w = frame(a.coherent)
    synth = {me: syn.build(m, me, 1, {}) for me in a.methods}
    kinds = ["plain", *a.methods]

    def call(kind, s, raw=False):
        if kind == "plain":
            return query.query(m, u32[s], w[s], w[s], raw=raw, march=a.march)
        return query.query(m, u[s], w[s], w[s], features_u=synth[kind], raw=raw, march=a.march)

    def use(name):  # query.query looks its library up through _library
        lib, pf = libs[name]
        query._library = lambda march="native", lib=lib: lib
        if pf is not None:
            os.environ["NEUMAT_TAP_PREFETCH"] = pf

    saved = query._library
    outs, best = {}, {}
    try:
        with torch.no_grad():
            for name in libs:  # warm-up and the outputs compared
                use(name)
                # raw: log(1 + RGB) before the clamp at 0, which would hide differences
                outs[name] = {k: call(k, slice(0, 4096), raw=True) for k in kinds}
            for _ in range(a.repeat):
                for name in libs:
                    use(name)
                    for k in kinds:
                        c0 = time.process_time()
                        for s0 in range(0, FRAME, CHUNK):
                            call(k, slice(s0, s0 + CHUNK))
                        dt = time.process_time() - c0
                        best[name, k] = min(best.get((name, k), float("inf")), dt)
    finally:
        query._library = saved
        if env0 is None:
            os.environ.pop("NEUMAT_TAP_PREFETCH", None)
        else:
            os.environ["NEUMAT_TAP_PREFETCH"] = env0

    peak_cpu = query.fma_peak(a.march)  # this build's fp32 FMA rate, one thread
    bound = FRAME * flops_per_query(m) / peak_cpu  # CPU-s per frame at the FLOP bound
    first = next(iter(libs))
    times = {name: {k: best[name, k] for k in kinds} for name in libs}
    same = {name: all(torch.equal(outs[name][k], outs[first][k]) for k in kinds) for name in libs}
    where = (f"machine: {machine.describe(a.march)}; torch threads {torch.get_num_threads()}; "
             f"fp32 FMA peak {peak_cpu / 1e9:.1f} GFLOP/CPU-s; FLOP bound {bound * 1e3:.1f} "
             f"CPU-ms/frame; u {'coherent (a x15 plane in pixel order)' if a.coherent else 'uniform random'}")
    return {"times": times, "same": same, "bound": bound}, where


def report(a, runs: list[dict], where: str) -> None:
    """The table of one process's figures, or of the medians over several (each process's own
    best of --repeat), with the spread between processes."""
    med = statistics.median
    names = list(runs[0]["times"])
    first = names[0]
    n = len(runs)
    bound = med(r["bound"] for r in runs)
    t = lambda name, k: [r["times"][name][k] for r in runs]
    ov = lambda name, k: [r["times"][name][k] / r["times"][name]["plain"] - 1 for r in runs]
    span = lambda xs, f: "" if n == 1 else f" [{f(min(xs))}, {f(max(xs))}]"
    print(where + (f"; median of {n} processes, [min, max] between them" if n > 1 else ""))
    print(f"{'build':28s} {'plain CPU-ms':>12s} {'of bound':>8s}  "
          + "  ".join(f"{k + ' CPU-ms (overhead)':>26s}" for k in a.methods) + "  outputs")
    for name in names:
        p = med(t(name, "plain"))
        cells = "  ".join(f"{med(t(name, k)) * 1e3:12.1f} ({med(ov(name, k)) * 100:+6.1f} %)"
                          + span(ov(name, k), lambda x: f"{x * 100:+.1f}") for k in a.methods)
        same = all(r["same"][name] for r in runs)
        print(f"{name:28s} {p * 1e3:12.1f} {bound / p:8.3f}  {cells}  "
              f"{'same' if same else 'DIFFER'} as {first}")
    for k in a.methods:
        for other in names[1:]:
            d = [x - y for x, y in zip(t(first, k), t(other, k))]
            rel = med([x / y - 1 for x, y in zip(t(first, k), t(other, k))])
            print(f"{k}: {first} against {other}: {med(d) * 1e3:+.1f} CPU-ms a frame "
                  f"({rel * 100:+.1f} %)" + span(d, lambda x: f"{x * 1e3:+.1f}"))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rev", nargs="+", default=["HEAD"],
                    help="git revisions (or C files) of query_kernel.c to compare with the "
                         "working tree's (default: HEAD)")
    ap.add_argument("--methods", nargs="+", default=["hpb", "hextile"], choices=["hpb", "hextile"])
    ap.add_argument("--march", default="native", help="-march of every build (x86-64-v3: AVX2)")
    ap.add_argument("--repeat", type=int, default=9, help="alternating rounds (best kept)")
    ap.add_argument("--tap-prefetch", choices=["auto", "both"], default="auto",
                    help="both: time each build with the synthesis kernels' tap prefetch on and off")
    ap.add_argument("--coherent", action="store_true",
                    help="u of a x15 plane in pixel order (a rendered frame), not uniform random u")
    ap.add_argument("--processes", type=int, default=1,
                    help="repeat the whole comparison in this many fresh processes and report "
                         "medians, with the spread between processes")
    ap.add_argument("--control", action="store_true",
                    help="add a build of the working tree's own code as a library of its own: its "
                         "row against the working tree's is the comparison's noise floor")
    ap.add_argument(fresh_processes.FLAG, action="store_true", help=argparse.SUPPRESS)  # a child
    a = ap.parse_args()
    if a.repeat < 1 or a.processes < 1:
        ap.error("--repeat and --processes must be at least 1")
    if a.processes == 1 or a.one_process:
        result, where = measure(a)
        if a.one_process:  # a child of --processes: its figures to the parent
            fresh_processes.emit({"where": where, **result})
        else:
            report(a, [result], where)
        return
    runs = fresh_processes.gather(__file__, a.processes)
    report(a, runs, runs[0]["where"])

if __name__ == "__main__":
    main()
