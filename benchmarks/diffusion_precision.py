"""Training precision: the `ours` hyperdiffusion model trained on a finished run's NeuMERL rows
with `diffusion.train.precision: fp32` (the baseline) and `bf16` (bfloat16 autocast of the
denoiser's forward), same seed, same steps, in the same run. Prints ms per step and their ratio,
each precision's FLOP per wall second (torch's FlopCounterMode on one forward + backward, as
benchmarks/diffusion_step.py counts it) as a fraction of that dtype's matmul rate measured here,
the logged loss curves side by side, the mean training loss over the last fifth of the steps,
and a held-out loss: each final EMA model's x0 loss on the test-split rows at the same drawn
timesteps and noise, evaluated in fp32. bf16 needs native bf16 (AVX512-BF16 or AMX, or a CUDA
GPU); elsewhere the script says so and stops.

    OMP_NUM_THREADS=2 python benchmarks/diffusion_precision.py --results results/<run>
        [--config config/config.yaml] [--steps 1500] [--device cpu]
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import tempfile
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
import yaml

from neumat import machine
from neumat.device import resolve_device
from neumat.diffusion import DenoiserConfig, Diffusion, ScheduleConfig, TrainConfig, dataset
from neumat.diffusion.model import Denoiser, Normalizer

sys.path.insert(0, os.path.dirname(__file__))
from diffusion_step import flop_per_step  # noqa: E402

train_mod = importlib.import_module("neumat.diffusion.train")  # the package exports `train`
ROOT = Path(__file__).resolve().parents[1]


@torch.no_grad()
def held_out_loss(bundle, weights, labels, scfg, seed=0, reps=4) -> tuple[float, float]:
    """x0 error (MSE of the predicted x0) of the EMA model per held-out row, averaged over `reps` draws of (t, noise), in
    fp32: (mean, median) over the rows. The mean is dominated by the few rows whose weights lie
    far outside the training statistics (|w| up to ~2000); the median is the typical row."""
    model = Denoiser(DenoiserConfig.from_dict(bundle["model_cfg"]))
    model.load_state_dict(bundle["ema"])
    model.eval()
    norm = Normalizer()
    norm.load_state_dict(bundle["normalizer"])
    x0 = norm.encode(torch.from_numpy(weights))
    cond = {"type": torch.from_numpy(labels)}
    gen = torch.Generator().manual_seed(seed)
    d = Diffusion(scfg)
    per_row = torch.zeros(len(x0))
    for _ in range(reps):  # Diffusion.loss per row: the same draws of t and noise
        t = torch.randint(0, d.T, (len(x0),), generator=gen)
        x_t = d.q_sample(x0, t, torch.randn(x0.shape, generator=gen))
        x0_hat, _ = d.split(model(x_t, t, cond), x_t, d._ab(t, x_t))  # any `prediction`
        per_row += ((x0_hat - x0) ** 2).mean(1) / reps
    return float(per_row.mean()), float(per_row.median())


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", type=Path, required=True, help="a run with neumerl/weights.npy")
    ap.add_argument("--config", type=Path, default=ROOT / "config/config.yaml")
    ap.add_argument("--steps", type=int, default=1500, help="training steps per precision")
    ap.add_argument("--device", default="cpu", help="cpu | cuda | auto")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    dev = resolve_device(a.device)
    where = machine.describe() + (f"; GPU {torch.cuda.get_device_name(dev)}" if dev.type == "cuda" else "")
    print(f"# {where}; torch {torch.__version__}, {torch.get_num_threads()} threads, {dev}")
    why = train_mod.native_bf16(dev)
    if why:
        raise SystemExit(f"bf16 not measured on {dev}: {why}")

    weights = np.load(a.results / "neumerl/weights.npy")
    man = dataset.read_manifest(a.results / "neumerl/manifest.tsv", len(weights))
    names = dataset.class_names(man["type"])
    train_rows, test_rows = dataset.training_rows(man, "ours"), dataset.reference_rows(man)
    lab = lambda rows: dataset.labels(man["type"].iloc[rows], names)
    cfg = yaml.safe_load(a.config.read_text()).get("diffusion", {})
    mcfg = DenoiserConfig(**cfg.get("model", {}), n_classes=len(names))
    scfg = ScheduleConfig(**cfg.get("schedule", {}))
    tcfg = {**asdict(TrainConfig(**cfg.get("train", {}))), "steps": a.steps,
            "checkpoint_every": 10 ** 9, "log_every": max(1, a.steps // 10)}
    print(f"# {a.config.name} model: width {mcfg.width}, depth {mcfg.depth}, heads {mcfg.heads}; "
          f"batch {tcfg['batch_size']}; {a.steps} steps; {len(train_rows)} training rows, "
          f"{len(test_rows)} held-out rows; seed {a.seed}")

    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for prec in ("fp32", "bf16"):
            b = train_mod.train(weights[train_rows], lab(train_rows), names, mcfg, scfg,
                                TrainConfig(**{**tcfg, "precision": prec}),
                                Path(tmp) / f"{prec}.pt", Path(tmp) / f"{prec}_ck.pt", a.seed, dev)
            runs[prec] = (b, held_out_loss(b, weights[test_rows], lab(test_rows), scfg))
    ms = {p: 1e3 * b["train_seconds"] / a.steps for p, (b, _) in runs.items()}
    # train_seconds is wall time, so the matmul rates are per wall second too (on the CPU at
    # torch's threads; diffusion_step.matmul_rate's CPU figure is per CPU second)
    flop = flop_per_step(mcfg, scfg, tcfg["batch_size"], dev)
    peak = {p: machine.gpu_matmul_rate(dev, dt) if dev.type == "cuda" else
            machine.sgemm_peak(dtype=dt)[0]
            for p, dt in (("fp32", None), ("bf16", torch.bfloat16))}
    print(f"# {flop / 1e9:.2f} GFLOP per step (forward + backward, FlopCounterMode)")
    print(f"{'step':>6s} {'fp32 loss':>10s} {'bf16 loss':>10s}")
    for (s, l32), (_, l16) in zip(runs["fp32"][0]["history"], runs["bf16"][0]["history"]):
        print(f"{s:6d} {l32:10.5f} {l16:10.5f}")
    tail = {}
    for p, (b, held) in runs.items():
        h = [l for s, l in b["history"] if s > 0.8 * a.steps]
        tail[p] = float(np.mean(h))
        print(f"{p}: {ms[p]:7.1f} ms/step, {flop * 1e3 / ms[p] / peak[p]:6.1%} of the {p} "
              f"matmul rate ({peak[p] / 1e9:.0f} GFLOP/s wall), training loss over the last "
              f"fifth {tail[p]:.5f}, "
              f"held-out x0 loss per material: mean {held[0]:.4f}, median {held[1]:.5f}  [{where}]")
    (m32, d32), (m16, d16) = runs["fp32"][1], runs["bf16"][1]
    print(f"bf16 / fp32: {ms['fp32'] / ms['bf16']:.2f}x faster per step; last-fifth training "
          f"loss {tail['bf16'] / tail['fp32'] - 1:+.2%}, held-out loss mean {m16 / m32 - 1:+.2%}, "
          f"median {d16 / d32 - 1:+.2%}  [{where}]")


if __name__ == "__main__":
    main()
