"""Idle OpenMP threads: libgomp's default (spin 300,000 times at every barrier) against no spin
(OMP_WAIT_POLICY=PASSIVE, which workflow/rules/common.smk sets for every job unless the
environment sets it or GOMP_SPINCOUNT) and a short spin (GOMP_SPINCOUNT=1000), on two workloads
of the workflow's 2-thread jobs, alone and beside other processes.

libgomp reads the policy once, when torch loads it, so each measurement is a fresh process.
Workloads (2 torch threads each):
  inception  Inception-v3 FID features of 2 x 32 images (32 px, resized to 299), as a `metrics`
             job computes per draw; also printed as the convolutions' FLOP per CPU second
             against this machine's fp32 matmul rate per CPU second (machine.sgemm_peak), so
             a thread that spins shows as a lower fraction.
  denoiser   training steps of config/config.yaml's denoiser (width 256, depth 4, batch 128),
             as `train_diffusion` runs them: many small parallel regions, where waking a
             sleeping thread costs most.
Beside:
  alone      nothing else runs;
  busy       one nice-0 process spinning: another job, or another program on the same cores;
  niced      two nice-19 processes alternating 2 ms of work and 2 ms of sleep: the test suite's
             tests (tests/conftest.py nices them) beside its tiny run.
Prints wall and CPU seconds per policy and their ratios to the first policy's, each the
median of --repeat fresh processes, with the machine.

    python benchmarks/omp_wait.py [--repeat 3] [--policies default spin:1000 PASSIVE] [--beside alone busy niced]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _inception() -> dict:
    import numpy as np

    from fid_features import conv_flop  # benchmarks/: the convolutions' FLOP per image
    from neumat.metrics import fid, inception
    net, reason = inception.fid_network(None, "cpu")
    if net is None:
        raise SystemExit(f"inception workload unavailable: {reason}")
    images = np.random.default_rng(0).random((32, 32, 32, 3), dtype=np.float32)
    fid.features(net, images[:2])  # warm-up: first-call allocations
    t, c = time.perf_counter(), time.process_time()
    for _ in range(2):
        fid.features(net, images)
    return {"wall": time.perf_counter() - t, "cpu": time.process_time() - c,
            "flop": 2 * len(images) * conv_flop(net)}


def _denoiser(steps: int = 30) -> dict:
    import torch
    import yaml

    from neumat.diffusion import Denoiser, DenoiserConfig, Diffusion, ScheduleConfig
    cfg = yaml.safe_load((ROOT / "config/config.yaml").read_text())["diffusion"]
    torch.manual_seed(0)
    model = Denoiser(DenoiserConfig(**cfg["model"], n_classes=48))
    diffusion = Diffusion(ScheduleConfig(**cfg["schedule"]))
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    batch = cfg["train"]["batch_size"]
    x0 = torch.randn(batch, 675)
    cond = {"type": torch.zeros(batch, dtype=torch.long)}
    drop = {"type": torch.zeros(batch, dtype=torch.bool)}  # conditioned, as most training rows

    def step():
        opt.zero_grad(set_to_none=True)
        diffusion.loss(model, x0, cond, drop).backward()
        opt.step()

    for _ in range(3):  # warm-up
        step()
    t, c = time.perf_counter(), time.process_time()
    for _ in range(steps):
        step()
    return {"wall": time.perf_counter() - t, "cpu": time.process_time() - c}


def child(workload: str) -> None:
    import torch
    torch.set_num_threads(2)
    r = {"inception": _inception, "denoiser": _denoiser}[workload]()
    if workload == "inception":
        from neumat import machine
        r["peak_per_cpu_s"] = machine.sgemm_peak(threads=1)[1]
    print(json.dumps(r))


def _others(beside: str) -> list[subprocess.Popen]:
    spin = "import time\nwhile True:\n    t = time.perf_counter()\n" \
           "    while time.perf_counter() - t < {busy}: pass\n    time.sleep({idle})\n"
    if beside == "busy":
        return [subprocess.Popen([sys.executable, "-c", "while True: pass"])]
    if beside == "niced":
        return [subprocess.Popen(["nice", "-n", "19", sys.executable, "-c",
                                  spin.format(busy=0.002, idle=0.002)]) for _ in range(2)]
    return []


def measure(workload: str, policy: str) -> dict:
    """One fresh process; `policy`: default (libgomp's), an OMP_WAIT_POLICY value, or
    spin:N (GOMP_SPINCOUNT=N: spin N iterations, then sleep)."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env.pop("OMP_NUM_THREADS", None)
    if policy.startswith("spin:"):
        env["GOMP_SPINCOUNT"] = policy.split(":", 1)[1]
    elif policy != "default":
        env["OMP_WAIT_POLICY"] = policy
    out = subprocess.run([sys.executable, __file__, "--child", workload], env=env, check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--repeat", type=int, default=3, help="fresh processes per cell, median kept")
    ap.add_argument("--workloads", nargs="+", default=["inception", "denoiser"])
    ap.add_argument("--beside", nargs="+", default=["alone", "busy", "niced"])
    ap.add_argument("--policies", nargs="+", default=["default", "spin:1000", "PASSIVE"],
                    help="default (libgomp's), an OMP_WAIT_POLICY value (the workflow's: "
                         "PASSIVE), or spin:N (GOMP_SPINCOUNT=N)")
    a = ap.parse_args()
    if a.child:
        return child(a.child)
    import torch

    from neumat import machine
    # torch's kernels may run another ISA than the host's (ATEN_CPU_CAPABILITY=avx2)
    print(f"# {machine.describe()}; torch kernels {torch.backends.cpu.get_cpu_capability()}; "
          f"2 torch threads per workload; median of {a.repeat} processes; ratios against "
          f"{a.policies[0]}")
    print(f"{'workload':10} {'beside':6} {'policy':10} | {'wall s':>7} {'CPU-s':>6} | "
          f"{'wall ratio':>10} {'CPU ratio':>9} | conv FLOP/CPU-s of peak")
    for w in a.workloads:
        for b in a.beside:
            others = _others(b)
            try:
                time.sleep(0.3)
                runs = {p: [] for p in a.policies}
                for _ in range(a.repeat):  # interleaved, so that drift in load hits all alike
                    for p in a.policies:
                        runs[p].append(measure(w, p))
            finally:
                for o in others:
                    o.kill()
                    o.wait()
            med = {p: {k: statistics.median(r[k] for r in runs[p]) for k in ("wall", "cpu")}
                   for p in a.policies}
            base = med[a.policies[0]]
            for p in a.policies:
                m = med[p]
                line = (f"{w:10} {b:6} {p:10} | {m['wall']:7.2f} {m['cpu']:6.2f} | "
                        f"{m['wall'] / base['wall']:10.2f} {m['cpu'] / base['cpu']:9.2f} |")
                if "flop" in runs[p][0]:
                    peak = statistics.median(r["peak_per_cpu_s"] for r in runs[p])
                    line += f" {runs[p][0]['flop'] / m['cpu'] / peak:.0%}"
                print(line, flush=True)


if __name__ == "__main__":
    main()
