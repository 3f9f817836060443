"""Training (with EMA, regular checkpoints and exact resume) and sampling of the hyperdiffusion
model.

Reproducibility: every random draw of training (batch indices, timesteps, noise, condition
dropout) comes from one CPU `torch.Generator` whose state is saved in each checkpoint together
with the model, EMA, optimiser and step (and torch's global CPU and, on a GPU, CUDA generators:
module dropout), so a run killed at any point and resumed from its last checkpoint ends in
exactly the state of an uninterrupted run (on the same device).
A checkpoint carries a fingerprint of the data, settings and seed; a stale one is ignored.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from neumat import nbrdf
from neumat.device import resolve_device, to_device
from neumat.diffusion.constraints import constraint_for
from neumat.diffusion.field_loss import FieldLoss
from neumat.diffusion.refit import clamp_refit
from neumat.diffusion.model import Denoiser, DenoiserConfig, Normalizer
from neumat.diffusion.schedule import Diffusion, RowNoise, ScheduleConfig, guided
from neumat.io import modelfile
from neumat.io.atomic import save_torch
from neumat.seeds import seed_for

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    steps: int = 5000
    batch_size: int = 128
    lr: float = 3e-4
    weight_decay: float = 0.0
    warmup_steps: int = 250
    ema_decay: float = 0.999
    cond_drop: float = 0.1  # classifier-free guidance: share of labels replaced by null
    grad_clip: float = 1.0
    checkpoint_every: int = 250
    log_every: int = 50
    precision: str = "fp32"  # "bf16": the denoiser's forward under bfloat16 autocast
    compile: str = "none"  # GPU only: the forward under torch.compile in this mode (speed only)
    field_loss: float = 0.0  # weight of the field term (neumat.diffusion.field_loss); 0 = off
    field_eps: float = 3e-3  # its log mapping's eps
    field_bins: int = 1024  # MERL bins it is evaluated at per step
    field_power: float = 1.0  # its weight per example: alpha_bar(t) ** field_power


def lr_at(step: int, cfg: TrainConfig) -> float:
    """Linear warm-up, then cosine decay to 10 % (a pure function of the step: resume-safe)."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    p = (step - cfg.warmup_steps) / max(1, cfg.steps - cfg.warmup_steps)
    return cfg.lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(p, 1.0))))


@torch.no_grad()
def ema_update(ema: torch.nn.Module, model: torch.nn.Module, step: int, decay: float) -> None:
    # warm-up of the decay so short runs are not dominated by the random initialisation
    d = min(decay, (1 + step) / (10 + step))
    # one multi-tensor kernel for all parameters (a launch per tensor on a GPU otherwise);
    # elementwise the same lerp, so the CPU result is bit-identical to a per-tensor loop
    torch._foreach_lerp_(list(ema.parameters()), list(model.parameters()), 1 - d)
    for e, b in zip(ema.buffers(), model.buffers()):
        e.copy_(b)


PRECISIONS = ("fp32", "bf16")


def native_bf16(dev: torch.device) -> str | None:
    """None if `dev` computes bfloat16 natively, else why not (a CPU without AVX512-BF16 or
    AMX would emulate it, far slower than fp32)."""
    if dev.type == "cuda":
        return None if torch.cuda.is_bf16_supported() else f"{torch.cuda.get_device_name(dev)} has no bf16"
    if dev.type == "cpu":
        if torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported():
            return None
        return "this CPU has neither AVX512-BF16 nor AMX (bf16 would be emulated, far slower)"
    return f"bf16 autocast is not set up for {dev.type}"


COMPILE_MODES = ("none", "default", "reduce-overhead")


def forward_of(model: torch.nn.Module, cfg: TrainConfig, dev: torch.device):
    """The module training calls: the model, or on a GPU with `compile` set, the model under
    torch.compile (same parameters, so AdamW, the EMA and checkpoints see no difference). On a
    GPU the step is bound by the host launching kernels (benchmarks/diffusion_step.py);
    reduce-overhead replays forward and backward as CUDA graphs. The CPU ignores it: compiling
    costs tens of seconds there and does not pay off at these sizes."""
    if cfg.compile not in COMPILE_MODES:
        raise ValueError(f"diffusion.train.compile must be one of {COMPILE_MODES}, "
                         f"got {cfg.compile!r}")
    if cfg.compile == "none" or dev.type != "cuda":
        return model
    return torch.compile(model, mode=cfg.compile, dynamic=False)


def check_precision(cfg: TrainConfig, dev: torch.device) -> None:
    if cfg.precision not in PRECISIONS:
        raise ValueError(f"diffusion.train.precision must be one of {PRECISIONS}, got {cfg.precision!r}")
    why = native_bf16(dev) if cfg.precision == "bf16" else None
    if why:
        raise ValueError(f"diffusion.train.precision: bf16 on {dev}: {why}; set it to fp32")


def fingerprint(weights: np.ndarray, labels: np.ndarray, *cfgs, seed: int,
                vectors: dict | None = None) -> str:
    """Identifies a training run: data, labels, condition vectors, settings and seed (a
    checkpoint of another seed is not resumed: it would finish the old run under the new
    seed's name)."""
    h = hashlib.sha256(np.ascontiguousarray(weights, dtype=np.float32).tobytes())
    h.update(np.ascontiguousarray(labels, dtype=np.int64).tobytes())
    for k in sorted(vectors or {}):
        h.update(k.encode() + np.ascontiguousarray(vectors[k], dtype=np.float32).tobytes())
    # `compile` is how the steps run and `checkpoint_every` when they are saved, not what they
    # compute (speed keys): a run resumes across either
    d = [{k: v for k, v in asdict(c).items() if k not in ("compile", "checkpoint_every")
          and not (k.startswith("field_") and not getattr(c, "field_loss", 0))} for c in cfgs]
    # the field keys count only with the field term on: checkpoints of before they existed resume
    h.update(json.dumps(d, sort_keys=True).encode())
    h.update(json.dumps({"seed": int(seed)}).encode())
    return h.hexdigest()


def train(weights: np.ndarray, labels: np.ndarray, class_names: list[str],
          model_cfg: DenoiserConfig, sched_cfg: ScheduleConfig, cfg: TrainConfig,
          out_path: str | os.PathLike, checkpoint_path: str | os.PathLike, seed: int,
          device: str = "auto", on_step=None, vectors: dict | None = None,
          activation: str = "relu") -> dict:
    """Train on weight vectors (N, 675) with type labels (N,) (-1 = untyped) and write the
    final model (EMA weights, normaliser, configs, loss log) to `out_path`. Returns that dict.

    `vectors` name -> (N, D) or (N, K, D) embeddings feed the model's vector conditions (text,
    image; NaN rows = no value); with K alternatives per material (e.g. K renders) one is drawn
    per example. Every condition is dropped independently with probability `cond_drop`, so
    classifier-free guidance works for each one and for any subset.

    `activation`: the NBRDF's, for the field term (`cfg.field_loss` > 0).

    `on_step(step, loss)` is called after every optimiser step (tests use it to simulate a kill)."""
    weights = np.asarray(weights, dtype=np.float32)
    labels = np.asarray(labels, dtype=np.int64)
    if weights.ndim != 2 or weights.shape[1] != nbrdf.N_PARAMS:
        raise ValueError(f"training weights must be (N, {nbrdf.N_PARAMS}), got {weights.shape}")
    if labels.shape != (weights.shape[0],):
        raise ValueError(f"labels must be ({weights.shape[0]},), got {labels.shape}")
    if not np.isfinite(weights).all():
        raise ValueError("training weights contain NaN or inf")
    if model_cfg.n_classes != len(class_names):
        raise ValueError(f"{len(class_names)} class names for n_classes={model_cfg.n_classes}")
    vectors = check_vectors(vectors, model_cfg, len(weights))
    dev = resolve_device(device)
    check_precision(cfg, dev)
    ckpt_path, out_path = Path(checkpoint_path), Path(out_path)
    fp = fingerprint(weights, labels, model_cfg, sched_cfg, cfg, seed=seed, vectors=vectors)

    torch.manual_seed(seed)  # model initialisation (and dropout, if enabled)
    norm = Normalizer.fit(torch.from_numpy(weights)).to(dev)
    model = Denoiser(model_cfg).to(dev)
    ema = copy.deepcopy(model).requires_grad_(False)
    fwd = forward_of(model, cfg, dev)
    # fused AdamW on a GPU (one kernel for every parameter); the CPU keeps the default
    # implementation, so CPU results do not change
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay,
                            fused=True if dev.type == "cuda" else None)
    # the batches' own stream: seeded with `seed` too, they replayed the initial weights' numbers
    gen = torch.Generator().manual_seed(seed_for(seed, "draws"))
    diffusion = Diffusion(sched_cfg)
    field = (FieldLoss(norm, cfg.field_loss, cfg.field_eps, cfg.field_bins, activation,
                       cfg.field_power) if cfg.field_loss else None)
    step, history, elapsed = 0, [], 0.0

    ck = modelfile.resume(ckpt_path, fp, dev, model=model, ema=ema, opt=opt, generator=gen)
    if ck is not None:
        torch.set_rng_state(ck["torch_rng"].cpu())  # map_location put it on `dev`
        if dev.type == "cuda":
            _set_cuda_rng(ck.get("cuda_rng"), ckpt_path)
        step, history, elapsed = ck["step"], ck["history"], ck["elapsed"]
        # the loss summed since the last logged step: a resumed run logs the same history
        run_sum, run_n = ck.get("running", (0.0, 0))

    x_all = norm.encode(torch.from_numpy(weights).to(dev))
    y_all = torch.from_numpy(labels).to(dev)
    v_all = {k: torch.from_numpy(v).to(dev) for k, v in vectors.items()}

    def checkpoint():
        save_torch(ckpt_path, {"fingerprint": fp, "model": model.state_dict(),
                               "ema": ema.state_dict(), "opt": opt.state_dict(),
                               "generator": gen.get_state(), "torch_rng": torch.get_rng_state(),
                               **({"cuda_rng": torch.cuda.get_rng_state_all()}
                                  if dev.type == "cuda" else {}),
                               "step": step, "history": history, "elapsed": elapsed,
                               "running": (0.0 if running is None else running.item(), n_running)})

    model.train()
    # the running loss stays on the device and is read once per `log_every` steps: a .item()
    # per step would make the host wait for the GPU every step
    t0, running, n_running = time.perf_counter(), None, 0
    if ck is not None and run_n:
        running, n_running = torch.tensor(run_sum, dtype=torch.float64, device=dev), int(run_n)
    while step < cfg.steps:
        for g in opt.param_groups:
            g["lr"] = lr_at(step, cfg)
        idx = to_device(torch.randint(0, len(x_all), (cfg.batch_size,), generator=gen), dev)
        drop = to_device(torch.rand(cfg.batch_size, generator=gen) < cfg.cond_drop, dev)
        cond = {"type": y_all[idx]} if model_cfg.n_classes else {}
        drops = {"type": drop} if cond else {}
        for k, v in v_all.items():  # drawn only with vector conditions: type-only runs unchanged
            drops[k] = to_device(torch.rand(cfg.batch_size, generator=gen) < cfg.cond_drop, dev)
            if v.dim() == 3:
                view = to_device(torch.randint(0, v.shape[1], (cfg.batch_size,), generator=gen), dev)
                cond[k] = v[idx, view]
            else:
                cond[k] = v[idx]
        # bf16: the denoiser's matmuls in bfloat16; weights, loss (the prediction minus an fp32
        # target promotes back), gradients, AdamW and the EMA stay fp32
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=cfg.precision == "bf16"):
            loss = diffusion.loss(fwd, x_all[idx], cond or None, drops or None, gen, field)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip:
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        opt.step()
        ema_update(ema, model, step, cfg.ema_decay)
        step += 1
        l64 = loss.detach().double()
        running, n_running = (l64 if running is None else running + l64), n_running + 1
        if step % cfg.log_every == 0 or step == cfg.steps:
            history.append((step, running.item() / n_running))
            running, n_running = None, 0
            log.info("step %d/%d loss %.4f lr %.2e", step, cfg.steps, history[-1][1], lr_at(step - 1, cfg))
        if on_step is not None:
            on_step(step, loss.item())
        if step % cfg.checkpoint_every == 0 or step == cfg.steps:
            elapsed_now = elapsed + time.perf_counter() - t0
            elapsed, t0 = elapsed_now, time.perf_counter()
            checkpoint()

    result = {"model_cfg": model_cfg.to_dict(), "sched_cfg": sched_cfg.to_dict(),
              "train_cfg": asdict(cfg), "class_names": list(class_names),
              "ema": {k: v.cpu() for k, v in ema.state_dict().items()},
              "normalizer": {k: v.cpu() for k, v in norm.state_dict().items()},
              "history": history, "train_seconds": elapsed, "n_train": len(weights),
              "seed": seed, "fingerprint": fp}
    save_torch(out_path, result)
    modelfile.finish(ckpt_path)  # a rerun of the finished job resumes at the last step
    return result


def _set_cuda_rng(states, path) -> None:
    """Restore the CUDA generators saved in a checkpoint (GPU runs; module dropout draws from
    them). Not restorable (a checkpoint of a CPU run, or of another number of visible GPUs): the
    run resumes, but a model with dropout then draws other numbers than an uninterrupted run."""
    n = torch.cuda.device_count()
    if states is None or len(states) != n:
        log.warning("%s: %s; resuming without restoring the CUDA random state", path,
                    "no CUDA random state saved" if states is None else
                    f"CUDA random states of {len(states)} GPUs saved, {n} visible now")
        return
    torch.cuda.set_rng_state_all([s.cpu() for s in states])  # map_location put them on `dev`


def check_vectors(vectors: dict | None, model_cfg: DenoiserConfig, n: int) -> dict:
    """Vector-condition arrays as float32, checked against the model's conditions."""
    vectors = {k: np.asarray(v, dtype=np.float32) for k, v in (vectors or {}).items()}
    if set(vectors) != set(model_cfg.vector_conditions):
        raise ValueError(f"vector conditions {sorted(vectors)} given for a model with "
                         f"{sorted(model_cfg.vector_conditions)}")
    for k, v in vectors.items():
        if v.ndim not in (2, 3) or len(v) != n or v.shape[-1] != model_cfg.vector_conditions[k]:
            raise ValueError(f"condition {k!r}: expected ({n}, [K,] "
                             f"{model_cfg.vector_conditions[k]}) embeddings, got {v.shape}")
    return vectors


class Sampler:
    """A trained model (EMA weights) ready to sample weight vectors."""

    def __init__(self, bundle: dict | str | os.PathLike, device: str = "auto"):
        source = bundle if not isinstance(bundle, dict) else "the model bundle"
        if not isinstance(bundle, dict):
            bundle = modelfile.load(bundle, finite=True)
        modelfile.require(bundle, ("class_names", "model_cfg", "ema", "normalizer", "sched_cfg"),
                          source, "a diffusion model (rules train_diffusion, train_multimodal, "
                          "train_refiner: diffusion/<model>/model.pt)")
        self.device = resolve_device(device)
        self.class_names = bundle["class_names"]
        rule = "train_diffusion, train_multimodal or train_refiner"
        self.model = modelfile.build(lambda: Denoiser(DenoiserConfig.from_dict(bundle["model_cfg"])),
                                     bundle["ema"], source, rule)
        self.model.to(self.device).eval()
        self.norm = modelfile.build(Normalizer, bundle["normalizer"], source, rule)
        self.norm.to(self.device)
        self.diffusion = Diffusion(ScheduleConfig(**bundle["sched_cfg"]))

    def labels_of(self, types: list[str]) -> torch.Tensor:
        """Type names -> class indices; '' -> -1, the null class (that sample unconditioned)."""
        unknown = sorted(set(types) - set(self.class_names) - {""})
        if unknown:
            raise ValueError(f"unknown material type(s) {unknown}; known: {self.class_names}")
        return torch.tensor([self.class_names.index(t) if t else -1 for t in types])

    @torch.no_grad()
    def sample(self, n: int, seed: int, types: list[str] | None = None, steps: int = 100,
               eta: float = 0.0, guidance: float = 1.0, batch_size: int = 256,
               clip: float | None = None, negative_step: float = 30.0,
               activation: str = "relu", category: str | None = None,
               category_step: float = 0.0, refit_steps: int = 0,
               particle_step: float = 0.0, offset: int = 0,
               temperature: float = 1.0) -> np.ndarray:
        """n weight vectors (n, 675) float32; `types` (len n) conditions on material type with
        classifier-free guidance scale `guidance`, None samples unconditionally.
        `negative_step` > 0: clamp-aware constraint at every DDIM step
        (`neumat.diffusion.constraints.NegativeConstraint`, NBRDF `activation`); `category` and
        `category_step` > 0: category guidance after it (`CategoryConstraint`); `particle_step`
        > 0: particle guidance over each batch after those (`ParticleGuidance`); `temperature`:
        the DDIM start x_T scaled by it (`RowNoise`); `refit_steps`
        > 0: the clamp-aware refit of the samples (`neumat.diffusion.refit`). `offset`: these
        are rows offset ... offset + n - 1 of the draw of `seed`, so a draw made in several calls
        (the `neumat sample` progress batches) equals one call (but for particle guidance,
        which acts within a batch)."""
        if types is not None and len(types) != n:
            raise ValueError(f"{len(types)} types for {n} samples")
        labels = self.labels_of(types) if types is not None else None
        # the same draws at any batch_size
        rows = RowNoise(seed_for(seed, "ddim"), nbrdf.N_PARAMS, temperature)
        constrain = constraint_for(self, negative_step, seed, activation, category, category_step,
                                   particle_step)
        out = []
        for s in range(0, n, batch_size):
            b = min(batch_size, n - s)
            cond = {"type": labels[s:s + b].to(self.device)} if labels is not None else None
            z = self.diffusion.ddim_sample(guided(self.model, cond, guidance),
                                           (b, nbrdf.N_PARAMS), steps, eta, None, self.device,
                                           clip=clip, constrain=constrain,
                                           noise=rows.batch(offset + s, b))
            out.append(self.norm.decode(z).float().cpu().numpy())
        w = np.concatenate(out) if out else np.zeros((0, nbrdf.N_PARAMS), np.float32)
        return clamp_refit(w, refit_steps, seed, activation=activation, device=self.device)
