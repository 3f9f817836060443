"""Per-modality condition dropout on a toy: 4 modes of 675-d vectors, each material with a type,
a noisy text embedding and 3 noisy image embeddings of its mode; train with dropout 0.1 and 0.5,
sample with one modality at guidance 2 (no NBRDF clamp constraint: `negative_step` 0, since
the toy's vectors are no NBRDFs; the default 30 drags them off every mode), report mode hits and
distance to the mode.
Usage: OMP_NUM_THREADS=1 python benchmarks/conditions_dropout_toy.py"""
import argparse, math, tempfile, numpy as np, torch
from pathlib import Path
from neumat import machine
from neumat.diffusion import DenoiserConfig, Sampler, ScheduleConfig, TrainConfig, train
from neumat.diffusion.sample import sample
argparse.ArgumentParser(description=__doc__.split("\n")[0]).parse_args()  # --help, no options
torch.set_num_threads(1)
print(f"machine: {machine.describe()}", flush=True)
rng = np.random.default_rng(0); n = 256
centres = rng.normal(size=(4, 675)).astype(np.float32)
mode = rng.integers(0, 4, n)
w = centres[mode] + 0.05 * rng.normal(size=(n, 675)).astype(np.float32)
td, idr = rng.normal(size=(4, 6)), rng.normal(size=(4, 4))
text = td[mode] + 0.3 * rng.normal(size=(n, 6)); img = idr[mode][:, None] + 0.3 * rng.normal(size=(n, 3, 4))
for p in (0.1, 0.5):
    d = Path(tempfile.mkdtemp())
    cfg = DenoiserConfig(width=64, depth=2, heads=4, mlp_ratio=2.0, n_classes=4, vector_conditions={"text": 6, "image": 4})
    tc = TrainConfig(steps=400, batch_size=64, lr=2e-3, warmup_steps=20, ema_decay=0.99, cond_drop=p, checkpoint_every=400, log_every=50)
    train(w, mode, list("abcd"), cfg, ScheduleConfig(timesteps=100), tc, d / "m.pt", d / "c.pt", seed=0, device="cpu", vectors={"text": text, "image": img})
    s = Sampler(d / "m.pt", device="cpu"); want = np.repeat(np.arange(4), 10)
    for name, c in (("type", list("abcd")), ("text", td), ("image", idr)):
        cond = {name: [c[i] for i in want] if name == "type" else c[want]}
        x = sample(s, 40, 1, cond, {name: 2.0}, steps=20, negative_step=0.0)  # toy vectors: no NBRDF clamp
        dist = np.linalg.norm(x[:, None] - centres[None], axis=-1) / math.sqrt(675)
        print(f"cond_drop {p} {name}: hits {(dist.argmin(1) == want).mean():.3f}, median RMS distance to nearest mode {np.median(dist.min(1)):.3f}", flush=True)
