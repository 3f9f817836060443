"""Diffusion training time per step at a config's model size (default `config/paper.yaml`:
512 wide, 12 blocks, batch 256), on the CPU or a GPU, against a baseline in the same run.

`neumat.diffusion.train` keeps the loss on the device and reads it once per `log_every` steps,
updates the EMA with one multi-tensor kernel, uses fused AdamW on a GPU and copies the CPU-drawn
randomness from pinned memory without waiting. The baseline is the same loop forced to read the
loss every step (an `on_step` callback, i.e. one host sync per step, as the loop did before).
Where the device computes bfloat16 natively, a third row times the loop with
`diffusion.train.precision: bf16` (bfloat16 autocast of the forward; its loss curve against
fp32: benchmarks/diffusion_precision.py), against the bf16 matmul rate measured here.
ms/step is the difference between a run of `--warmup` steps and one of `--warmup + --steps`
steps, so set-up and the first steps' allocations cancel. Also printed: FLOP per step (torch's
FlopCounterMode on one forward + backward) and the achieved rate as a fraction of the device's
fp32 matmul rate measured here (a 2048^3 mm on the CPU, 8192^3 on a GPU).

    OMP_NUM_THREADS=2 python benchmarks/diffusion_step.py [--device cpu|cuda] [--steps 20]
"""

from __future__ import annotations

import argparse
import importlib
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
import yaml

from neumat import machine
from neumat.device import resolve_device
from neumat.diffusion import Denoiser, DenoiserConfig, Diffusion, ScheduleConfig, TrainConfig

train_mod = importlib.import_module("neumat.diffusion.train")  # the package exports `train`
ROOT = Path(__file__).resolve().parents[1]
BF16 = "neumat loop, bf16 autocast"


def model_settings(config: Path) -> tuple[dict, dict, dict]:
    """(model, schedule, train) keys the config sets under `diffusion`; the rest come from the
    library's dataclass defaults, which tests/test_defaults.py keeps equal to the schema's."""
    cfg = yaml.safe_load(config.read_text()).get("diffusion", {})
    return cfg.get("model", {}), cfg.get("schedule", {}), cfg.get("train", {})


def run_seconds(weights, labels, mcfg, scfg, tcfg, steps, device, sync_each_step,
                precision="fp32", compile="none"):
    cfg = TrainConfig(**{**tcfg, "steps": steps, "log_every": steps, "checkpoint_every": 10**9,
                         "precision": precision, "compile": compile})
    # model files in memory where possible: each run ends with a checkpoint (600 MB at paper
    # size) whose write time would otherwise add noise to the difference of two runs
    shm = "/dev/shm" if Path("/dev/shm").is_dir() else None
    with tempfile.TemporaryDirectory(dir=shm) as tmp:
        t, c = time.perf_counter(), time.process_time()
        r = train_mod.train(weights, labels, [f"t{i}" for i in range(mcfg.n_classes)], mcfg,
                            scfg, cfg, Path(tmp) / "m.pt", Path(tmp) / "ck.pt", 0, device,
                            on_step=(lambda s, l: None) if sync_each_step else None)
        if device.type == "cuda":
            torch.cuda.synchronize()
        # log_every = steps: the one history entry is the mean loss over all steps
        return time.perf_counter() - t, time.process_time() - c, r["history"][-1][1]


def flop_per_step(mcfg, scfg, batch, device) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    model = Denoiser(mcfg).to(device)
    x0 = torch.randn(batch, 675, device=device)
    cond = {"type": torch.zeros(batch, dtype=torch.long, device=device)}
    with FlopCounterMode(display=False) as fc:
        Diffusion(scfg).loss(model, x0, cond, {"type": torch.zeros(batch, dtype=torch.bool,
                                                                  device=device)}).backward()
    return float(fc.get_total_flops())


def matmul_rate(device, dtype=torch.float32) -> float:
    """FLOP per wall second on a GPU, per CPU second of this process on the CPU (which does not
    depend on what else runs on a shared machine)."""
    if device.type != "cuda":
        return machine.sgemm_peak(dtype=dtype)[1]
    return machine.gpu_matmul_rate(device, dtype)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", type=Path, default=ROOT / "config/paper.yaml")
    ap.add_argument("--device", default="auto", help="auto | cpu | cuda")
    ap.add_argument("--steps", type=int, default=20, help="timed steps per variant")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--materials", type=int, default=2400, help="training set size (random)")
    ap.add_argument("--compile", nargs="*", default=[], metavar="MODE",
                    help="GPU: also time the fp32 and bf16 loops with diffusion.train.compile "
                         "set to each MODE (default, reduce-overhead)")
    ap.add_argument("--cprofile", type=int, default=0, metavar="STEPS",
                    help="also print cProfile's top host functions of a STEPS-step fp32 run")
    ap.add_argument("--profile", action="store_true",
                    help="also print torch.profiler's top operators of 10 steps per precision")
    a = ap.parse_args()
    device = resolve_device(a.device)
    m, s, t = model_settings(a.config)
    mcfg, scfg = DenoiserConfig(**m, n_classes=48), ScheduleConfig(**s)
    t = asdict(TrainConfig(**t))
    rng = np.random.default_rng(0)
    weights = rng.normal(size=(a.materials, 675)).astype(np.float32)
    labels = rng.integers(-1, 48, a.materials)

    where = machine.describe()
    if device.type == "cuda":
        where += f"; GPU {torch.cuda.get_device_name(device)}"
    print(f"# {where}; torch {torch.__version__}, {torch.get_num_threads()} threads")
    print(f"# {a.config.name}: width {mcfg.width}, depth {mcfg.depth}, heads {mcfg.heads}, "
          f"batch {t['batch_size']}; {a.steps} timed steps on {device}")
    ms, busy = {}, {}
    variants = [("per-step sync (baseline)", True, "fp32", None), ("neumat loop", False, "fp32", None)]
    no_bf16 = train_mod.native_bf16(device)
    if no_bf16 is None:
        variants.append((BF16, False, "bf16", None))
    for mode in a.compile:
        variants.append((f"neumat loop, compiled {mode}", False, "fp32", mode))
        if no_bf16 is None:
            variants.append((f"{BF16}, compiled {mode}", False, "bf16", mode))
    mean_loss = {}
    for name, sync, prec, mode in variants:
        mode = mode or "none"
        # a discarded first run on every device: it pays the lazy set-up (CUDA's cuBLAS handles
        # and autocast caches; on the CPU the first allocations and kernels' dispatch, which
        # made the first variant's short run the longer one: a negative ms/step) and compilation
        t0 = time.perf_counter()
        run_seconds(weights, labels, mcfg, scfg, t, a.warmup, device, sync, prec, mode)
        if mode != "none":
            print(f"# {name}: first run (compilation) {time.perf_counter() - t0:.0f} s")
        short = run_seconds(weights, labels, mcfg, scfg, t, a.warmup, device, sync, prec, mode)
        long = run_seconds(weights, labels, mcfg, scfg, t, a.warmup + a.steps, device, sync,
                           prec, mode)
        ms[name] = 1e3 * (long[0] - short[0]) / a.steps
        busy[name] = ms[name] if device.type == "cuda" else 1e3 * (long[1] - short[1]) / a.steps
        mean_loss[name] = long[2]
    flop = flop_per_step(mcfg, scfg, t["batch_size"], device)
    rate = {"fp32": matmul_rate(device)}
    if BF16 in ms:
        rate["bf16"] = matmul_rate(device, torch.bfloat16)
    per = "wall s" if device.type == "cuda" else "CPU s"
    for name, v in ms.items():
        r, kind = flop / (busy[name] / 1e3), "bf16" if name.startswith(BF16) else "fp32"
        print(f"{name:26s} {v:9.2f} ms/step (wall), {busy[name]:9.2f} ms/step ({per})  "
              f"{r / 1e9:8.1f} GFLOP per {per}  {r / rate[kind]:6.1%} of the {kind} matmul rate "
              f"({rate[kind] / 1e9:.0f} GFLOP per {per}); mean loss over the "
              f"{a.warmup + a.steps} steps {mean_loss[name]:.6f}")
    print(f"speed-up over the baseline: {ms['per-step sync (baseline)'] / ms['neumat loop']:.2f}x; "
          f"{flop / 1e9:.1f} GFLOP per step")
    if BF16 in ms:
        print(f"bf16 autocast over the fp32 loop: {ms['neumat loop'] / ms[BF16]:.2f}x")
    else:
        print(f"bf16 autocast: not timed ({no_bf16})")
    for mode in a.compile:  # compiled against the eager fp32 loop (README's ratios)
        for name in (f"neumat loop, compiled {mode}", f"{BF16}, compiled {mode}"):
            if name in ms:
                print(f"{name} over the eager fp32 loop: {ms['neumat loop'] / ms[name]:.2f}x")
    if a.cprofile:
        host_profile(weights, labels, mcfg, scfg, t, device, a.cprofile)
    if a.profile:
        profile(weights, labels, mcfg, scfg, t, device, ["fp32"] + (["bf16"] if BF16 in ms else []))


def host_profile(weights, labels, mcfg, scfg, t, device, steps):
    """Where the host's time goes in the loop: cProfile over a `steps`-step run (set-up included),
    top functions by own time. On a GPU the host launches work; where it is slower than the GPU,
    this is the step's time."""
    import cProfile
    import pstats
    run_seconds(weights, labels, mcfg, scfg, t, 3, device, False, "fp32")
    pr = cProfile.Profile()
    pr.enable()
    run_seconds(weights, labels, mcfg, scfg, t, steps, device, False, "fp32")
    pr.disable()
    print(f"# cProfile, fp32, {steps} steps (set-up included), top 25 by own time")
    pstats.Stats(pr).sort_stats("tottime").print_stats(25)


def profile(weights, labels, mcfg, scfg, t, device, precisions, steps=10):
    """Where a step's time goes: torch.profiler over `steps` steps, top operators by device time."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as prof
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    for prec in precisions:
        run_seconds(weights, labels, mcfg, scfg, t, 3, device, False, prec)
        with prof(activities=acts) as p:
            run_seconds(weights, labels, mcfg, scfg, t, steps, device, False, prec)
        print(f"# profile, {prec}, {steps} steps (set-up and the final checkpoint included: "
              "its device-to-host copies are those, not the steps')")
        print(p.key_averages().table(sort_by=key, row_limit=18, max_name_column_width=60))


if __name__ == "__main__":
    main()
