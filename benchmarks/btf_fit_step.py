"""Training time per step of the neural BTF fits (rules btf_triple_plane and btf_neumip,
`neumat.btf.neural.train`) at a config's batch, on 1 thread and on `--threads`, for their
Slurm time limit (workflow/rules/common.smk `btf_fit_runtime`).

A synthetic wood BTF of `--size`^2 texels (`neumat.btf.synthetic`, the tiny config's kind) is
fitted with the config's model settings (default `config/paper.yaml`: batch 65,536). ms/step is
the difference between a run of `--warmup` steps and one of `--warmup + --steps`, so loading,
set-up cancels (best of `--repeat`, after a discarded run). Per method and thread count it prints ms/step,
the process's CPU microseconds per query-step (what the rule's budget scales), the speed-up over 1 thread
(the baseline, same run) and the MLP's share of the machine's fp32 matmul rate measured here
(a 2048^3 mm on the same threads; the MLP's forward + backward as 6 x its weights' FLOP per
query, the planes' fetches and Adam step not counted).

    OMP_NUM_THREADS=2 python benchmarks/btf_fit_step.py [--config config/paper.yaml]
        [--methods triple_plane neumip] [--threads 2] [--steps 6] [--warmup 2] [--size 64] [--repeat 2]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch
import yaml

from neumat import machine
from neumat.btf import models, synthetic
from neumat.btf.data import BTFData
from neumat.btf.neural import train

ROOT = Path(__file__).resolve().parents[1]


def settings(config: Path, method: str) -> dict:
    """The config's btf.<method> keys over the schema's defaults (the rule's settings)."""
    schema = yaml.safe_load((ROOT / "config/schema.yaml").read_text())
    props = schema["properties"]["btf"]["properties"][method]["properties"]
    s = {k: v["default"] for k, v in props.items() if "default" in v}
    s.update(yaml.safe_load(config.read_text()).get("btf", {}).get(method, {}) or {})
    return s


def seconds(data, method: str, s: dict, steps: int) -> tuple[float, float]:
    """(wall, CPU) seconds of `steps` training steps, set-up included."""
    model = models.NEURAL[method](data.width, data.height, **{
        k: v for k, v in s.items() if k not in ("steps", "batch", "lr", "checkpoint_every")})
    t0, c0 = time.perf_counter(), time.process_time()
    train(model, data, steps, s["batch"], s["lr"], seed=0)
    return time.perf_counter() - t0, time.process_time() - c0


def matmul_rate(threads: int) -> float:
    """fp32 FLOP/s of a 2048^3 mm on `threads` threads (best of 3)."""
    torch.set_num_threads(threads)
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    a @ b
    best = min((lambda t: (a @ b, time.perf_counter() - t)[1])(time.perf_counter())
               for _ in range(3))
    return 2 * 2048 ** 3 / best


def mlp_flop_per_query(data, method: str, s: dict) -> float:
    model = models.NEURAL[method](data.width, data.height, **{
        k: v for k, v in s.items() if k not in ("steps", "batch", "lr", "checkpoint_every")})
    w = sum(m.weight.numel() for m in model.modules() if isinstance(m, torch.nn.Linear))
    return 6.0 * w  # forward 2 w, backward 4 w


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, default=ROOT / "config/paper.yaml")
    ap.add_argument("--methods", nargs="+", default=list(models.NEURAL), choices=list(models.NEURAL))
    ap.add_argument("--threads", type=int, default=2, help="besides 1 (the baseline)")
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--size", type=int, default=64, help="texels per side of the synthetic BTF")
    ap.add_argument("--repeat", type=int, default=2, help="best of")
    a = ap.parse_args()
    print(machine.describe())
    print(f"config {a.config.name}; synthetic wood BTF {a.size}^2 texels; {a.steps} steps timed "
          f"after {a.warmup}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "wood.btf"
        synthetic.synthesize("wood", a.size, 0, 8, path)
        data = BTFData(path)
        print("method        threads  batch   ms/step  CPU-us/query-step  speed-up  MLP share of mm rate")
        for method in a.methods:
            s = settings(a.config, method)
            flop = mlp_flop_per_query(data, method, s)
            base = None
            for th in sorted({1, a.threads}):
                torch.set_num_threads(th)
                seconds(data, method, s, a.warmup)  # discarded: a process's first steps
                # ran ~5x slower (allocator growth), which a difference would not cancel
                runs = []
                for _ in range(a.repeat):
                    (w0, c0), (w1, c1) = (seconds(data, method, s, a.warmup),
                                          seconds(data, method, s, a.warmup + a.steps))
                    runs.append(((w1 - w0) / a.steps, (c1 - c0) / a.steps))
                t, cpu = min(runs)
                base = base or t
                rate = matmul_rate(th)
                print(f"{method:13s} {th:7d}  {s['batch']:6d}  {1e3 * t:8.1f}  "
                      f"{1e6 * cpu / s['batch']:17.2f}  {base / t:7.2f}x  "
                      f"{flop * s['batch'] / t / rate:8.1%}")


if __name__ == "__main__":
    main()
