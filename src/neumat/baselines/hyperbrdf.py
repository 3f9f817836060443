"""HyperBRDF (Gokbudak et al. 2023; github faziletgokbudak/Hyper-neural-materials): a set
encoder maps BRDF samples of one material to a 40-d latent z, one hypernetwork head per tensor
of a target NBRDF turns z into that field's weights. M3ashy Table 3 trains it on MERL and on
AugMERL and scores sparse reconstruction (N = 4000 samples) and compression (all samples
through z).

Architecture and loss (from the reference code, github faziletgokbudak/Hyper-neural-materials):
  * encoder over samples [h_xyz (phi_h = 0), d_xyz, RGB] (9-D): 9 -> 128 -> 128 -> 128 -> 40,
    ReLU, mean over the samples (so the latent does not depend on sample order or count);
  * one head per target tensor: 40 -> 128 -> 128 -> numel, ReLU;
  * target NBRDF 6 -> 60 -> 60 -> 60 -> 60 -> 3, ReLU, linear output y;
  * y = log(1 + (f + 0.002) / (median + 0.002)), median per bin over the training materials;
  * loss MSE(y_hat cos_i, y cos_i) + 0.1 mean(z^2) + 0.1 mean(theta^2), theta = the generated
    target weights; Adam lr 5e-5, grad-norm clip 1.

Choices of ours (the reference code leaves them open or we deviate, said here once):
  * the encoder's RGB inputs are the mapped values y, not raw f (raw MERL values span 1e-4 to
    1e4; y is bounded and is what the decoder predicts);
  * the median is one value per bin, pooled over the training *source* materials and their
    3 channels (`bin_median`); both models share it, so their output mappings are identical and
    only the training set differs;
  * `materials_per_step` materials per optimiser step (reference: 1), each with its own
    random context (encoder input) and query (loss) samples, losses averaged;
  * each head's last layer starts at 0.1x its default init with the bias drawn like a default
    nn.Linear of the target tensor, so the untrained hypernetwork emits a sensible field.

Training is checkpointed like `neumat.diffusion.train`: every random draw comes from one CPU
generator saved with model, optimiser and step, so a killed run resumes to exactly the state of
an uninterrupted one; a checkpoint written for other data or settings is ignored.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from neumat.io import modelfile
from neumat.io.atomic import save_torch
from neumat.seeds import seed_for

log = logging.getLogger(__name__)

EPS = 0.002  # offset of the log mapping (reference code)


@dataclass
class HyperConfig:
    latent: int = 40
    encoder_width: int = 128
    encoder_layers: int = 3  # hidden layers of the set encoder
    head_width: int = 128
    target_width: int = 60
    target_layers: int = 4  # hidden layers of the target NBRDF

    def target_shapes(self) -> list[tuple[int, ...]]:
        """(out, in) weight and (out,) bias shapes of the target NBRDF, in order."""
        dims = [6] + [self.target_width] * self.target_layers + [3]
        return [s for i, o in zip(dims[:-1], dims[1:]) for s in ((o, i), (o,))]


@dataclass
class HyperTrainConfig:  # defaults: config/schema.yaml hyperbrdf.train's (tests/test_defaults.py)
    steps: int = 2000
    lr: float = 5e-5
    materials_per_step: int = 8
    context: int = 4000  # samples per material into the encoder during training
    query: int = 2000  # samples per material in the loss
    grad_clip: float = 1.0
    z_weight: float = 0.1
    theta_weight: float = 0.1
    checkpoint_every: int = 250
    log_every: int = 50


# ----------------------------------------------------------------------------- data mapping


def bin_inputs(bins) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat MERL bins -> field inputs (B, 6) [h, d] and clipped cos(theta_i) (B,) at centres."""
    from neumat.fit import bin_inputs as _bin_inputs

    return _bin_inputs(np.asarray(bins))


def bin_median(values: np.ndarray) -> np.ndarray:
    """Physical BRDF (M, 3, B) of the training sources -> per-bin median over materials and
    channels (B,) float32 (negative = invalid entries count as 0)."""
    v = np.maximum(np.asarray(values, dtype=np.float32), 0)
    return np.median(v.reshape(-1, v.shape[-1]), axis=0).astype(np.float32)


def to_target(f, median) -> torch.Tensor:
    """Physical BRDF f (..., B, 3) and median (B,) -> y = log(1 + (f + eps)/(median + eps))."""
    f = torch.as_tensor(f, dtype=torch.float32).clamp_min(0)
    m = torch.as_tensor(median, dtype=torch.float32)[:, None]
    return torch.log1p((f + EPS) / (m + EPS))


def training_targets(values: np.ndarray, median) -> torch.Tensor:
    """Physical BRDF (M, 3, B) and median (B,) -> y (M, B, 3), C-contiguous: `to_target` of the
    transposed values, bit for bit (the same operations in the same order), but with one
    (M, B, 3) float32 buffer mapped in place rather than several full-size temporaries
    (training holds all materials: the old path peaked at ~4x the values)."""
    v = np.asarray(values, dtype=np.float32)
    # np.array copies always (a transposed view that happens to be contiguous, B = 1, would
    # otherwise be mapped in place in the caller's array)
    y = torch.from_numpy(np.array(v.transpose(0, 2, 1), order="C"))
    m = torch.as_tensor(median, dtype=torch.float32)[:, None]
    return y.clamp_min_(0).add_(EPS).div_(m + EPS).log1p_()


def from_target(y, median) -> torch.Tensor:
    """Inverse of `to_target`, clamped at 0: y (..., B, 3), median (B,) -> f."""
    m = torch.as_tensor(median, dtype=torch.float32, device=y.device)[:, None]
    return (torch.expm1(y) * (m + EPS) - EPS).clamp_min(0)


# ----------------------------------------------------------------------------- model


def mlp(dims: list[int]) -> nn.Sequential:
    layers = []
    for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(dims) - 2:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class SetEncoder(nn.Module):
    """Samples (B, N, 9) -> latent (B, latent): a per-sample MLP, then the mean over samples."""

    def __init__(self, cfg: HyperConfig):
        super().__init__()
        self.net = mlp([9] + [cfg.encoder_width] * cfg.encoder_layers + [cfg.latent])

    def forward(self, samples: torch.Tensor, chunk: int = 1 << 15) -> torch.Tensor:
        if samples.dim() != 3 or samples.shape[-1] != 9:
            raise ValueError(f"encoder samples must be (B, N, 9), got {tuple(samples.shape)}")
        if samples.shape[1] <= chunk:
            return self.net(samples).mean(1)
        # many samples (compression: every stored bin) - sum in chunks to bound memory
        total = sum(self.net(samples[:, s:s + chunk]).sum(1)
                    for s in range(0, samples.shape[1], chunk))
        return total / samples.shape[1]


class HyperBRDF(nn.Module):
    """Set encoder + one hypernetwork head per target tensor + the batched target NBRDF."""

    def __init__(self, cfg: HyperConfig):
        super().__init__()
        self.cfg = cfg
        self.shapes = cfg.target_shapes()
        self.encoder = SetEncoder(cfg)
        self.heads = nn.ModuleList(
            mlp([cfg.latent, cfg.head_width, cfg.head_width, math.prod(s)]) for s in self.shapes)
        with torch.no_grad():
            for k, (head, shape) in enumerate(zip(self.heads, self.shapes)):
                last = head[-1]
                last.weight.mul_(0.1)
                fan_in = shape[1] if len(shape) == 2 else self.shapes[k - 1][1]
                bound = 1 / math.sqrt(fan_in)
                last.bias.uniform_(-bound, bound)

    @property
    def n_target(self) -> int:
        return sum(math.prod(s) for s in self.shapes)

    def encode(self, x6: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Inputs (B, N, 6) or (N, 6) and mapped values y (B, N, 3) -> latents (B, latent)."""
        if x6.dim() == 2:
            x6 = x6.expand(y.shape[0], *x6.shape)
        return self.encoder(torch.cat([x6, y], -1))

    def params(self, z: torch.Tensor) -> list[torch.Tensor]:
        """Latents (B, latent) -> target tensors [(B, out, in), (B, out), ...]."""
        return [h(z).reshape(len(z), *s) for h, s in zip(self.heads, self.shapes)]

    @staticmethod
    def field(params: list[torch.Tensor], x6: torch.Tensor) -> torch.Tensor:
        """Target NBRDF with per-material weights at x6 (N, 6) or (B, N, 6) -> y (B, N, 3)."""
        h = x6
        n = len(params) // 2
        for k in range(n):
            W, b = params[2 * k], params[2 * k + 1]
            h = (torch.einsum("nk,bok->bno", h, W) if h.dim() == 2
                 else torch.bmm(h, W.transpose(1, 2))) + b[:, None]
            if k < n - 1:
                h = torch.relu(h)
        return h

    def decode(self, z: torch.Tensor, x6: torch.Tensor, chunk: int = 1 << 14) -> torch.Tensor:
        """Latents (B, latent) -> mapped values y (B, N, 3) at x6 (N, 6), in chunks of x6."""
        p = self.params(z)
        return torch.cat([self.field(p, x6[s:s + chunk]) for s in range(0, len(x6), chunk)], 1)


def flatten_params(params: list[torch.Tensor]) -> torch.Tensor:
    """Target tensors -> (B, n_target), in `HyperConfig.target_shapes` order."""
    return torch.cat([p.reshape(len(p), -1) for p in params], -1)


def loss_terms(model: HyperBRDF, x_ctx, y_ctx, x_q, y_q, cos_q, cfg: HyperTrainConfig):
    """Total loss and its parts for a batch: context (B, K, 6/3), query (B, Q, 6/3), cos (B, Q)."""
    z = model.encode(x_ctx, y_ctx)
    params = model.params(z)
    y_hat = model.field(params, x_q)
    mse = torch.mean((y_hat * cos_q[..., None] - y_q * cos_q[..., None]) ** 2)
    zreg = torch.mean(z ** 2)
    treg = torch.mean(flatten_params(params) ** 2)
    return mse + cfg.z_weight * zreg + cfg.theta_weight * treg, (mse, zreg, treg)


# ----------------------------------------------------------------------------- training


# How `train` draws its samples; in the checkpoint fingerprint, so a checkpoint written by the
# earlier scheme (argsort of uniforms) is not resumed with this one's draws
DRAWS = "randperm"


def fingerprint(y: np.ndarray, bins: np.ndarray, seed: int, *cfgs,
                draws: str | None = None) -> str:
    # hashes the buffer itself: no copy of a C-contiguous float32 y (tobytes() copied it)
    h = hashlib.sha256(np.ascontiguousarray(y, dtype=np.float32))
    h.update(np.ascontiguousarray(bins, dtype=np.int64))
    # checkpoint_every sets when steps are saved, not what they compute (a speed key): a run
    # resumes across it
    d = [{k: v for k, v in asdict(c).items() if k != "checkpoint_every"} for c in cfgs]
    extra = [{"draws": draws}] if draws else []  # without: the fingerprint of earlier commits
    h.update(json.dumps(d + [seed] + extra, sort_keys=True).encode())
    return h.hexdigest()


def train(values: np.ndarray, bins: np.ndarray, median: np.ndarray, model_cfg: HyperConfig,
          cfg: HyperTrainConfig, out_path, checkpoint_path, seed: int, device: str = "cpu",
          on_step=None, bins_key: str = "hyperbrdf.train_bins") -> dict:
    """Train on materials' physical BRDF `values` (M, 3, B) at flat MERL `bins` (B,), with the
    mapping's `median` at those bins (B,). Writes the model bundle to `out_path` (and returns
    it); checkpoints to `checkpoint_path` and resumes from it. `on_step(step, loss)` after every
    optimiser step (tests simulate a kill with it). `bins_key`: the config key that set B, named
    when B is too small (hyperbrdf.train_bins, or augmerl.bins where the shards store fewer)."""
    values = np.asarray(values, dtype=np.float32)
    bins = np.asarray(bins)
    if values.ndim != 3 or values.shape[1] != 3 or values.shape[2] != len(bins):
        raise ValueError(f"values must be (M, 3, {len(bins)}), got {values.shape}")
    if len(values) == 0:
        raise ValueError("no training materials")
    if not np.isfinite(values).all():
        raise ValueError("training values contain NaN or inf")
    if len(bins) < max(cfg.context, cfg.query):
        raise ValueError(f"{len(bins)} bins per material ({bins_key}), fewer than "
                         f"hyperbrdf.train.context={cfg.context} or "
                         f"query={cfg.query} samples per step")
    from neumat.device import resolve_device

    dev = resolve_device(device)
    ckpt_path, out_path = Path(checkpoint_path), Path(out_path)
    x_all, cos_all = (t.to(dev) for t in bin_inputs(bins))
    y_all = training_targets(values, median)  # (M, B, 3): values + one buffer of their size
    fp = fingerprint(y_all.numpy(), bins, seed, model_cfg, cfg, draws=DRAWS)
    y_all = y_all.to(dev)

    torch.manual_seed(seed)
    model = HyperBRDF(model_cfg).to(dev)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    # the draws' own stream: seeded with `seed` too, they replayed the initial weights' numbers
    gen = torch.Generator().manual_seed(seed_for(seed, "draws"))
    # `running`: [loss, mse, z_reg, theta_reg] of each step since the last logged one, kept as
    # tensors on the device and read once per log_every steps (a .item() per value and step
    # waited for the device every step); saved and resumed as lists of floats
    step, history, elapsed, running = 0, [], 0.0, []
    ck = modelfile.resume(ckpt_path, fp, dev, model=model, opt=opt, generator=gen)
    if ck is not None:
        step, elapsed = int(ck["step"]), float(ck["elapsed"])
        history = [tuple(r) for r in ck["history"]]
        running = [torch.tensor(r, dtype=torch.float32, device=dev)
                   for r in ck.get("running", [])]  # since the last logged step

    def read(rows: list[torch.Tensor]) -> list[list[float]]:
        return torch.stack(rows).tolist() if rows else []

    def checkpoint():
        save_torch(ckpt_path, {"fingerprint": fp, "model": model.state_dict(),
                               "opt": opt.state_dict(), "generator": gen.get_state(),
                               "step": step, "history": history, "elapsed": elapsed,
                               "running": read(running)})

    M, B = y_all.shape[:2]
    b = min(cfg.materials_per_step, M)
    t0 = time.perf_counter()
    model.train()
    while step < cfg.steps:
        mats = torch.randint(0, M, (b,), generator=gen)
        # independent random samples per material, each without replacement: the context the
        # encoder sees, the query the loss is taken on (a prefix of a random permutation;
        # argsort of B uniforms cost more than the model step at B = 131072)
        ctx = torch.stack([torch.randperm(B, generator=gen)[:cfg.context] for _ in range(b)])
        qry = torch.stack([torch.randperm(B, generator=gen)[:cfg.query] for _ in range(b)])
        mats, ctx, qry = mats.to(dev), ctx.to(dev), qry.to(dev)
        # the drawn rows only (indexing y_all[mats] first copied each material's B x 3 values)
        y_ctx, y_q = y_all[mats[:, None], ctx], y_all[mats[:, None], qry]
        loss, parts = loss_terms(model, x_all[ctx], y_ctx, x_all[qry], y_q, cos_all[qry], cfg)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip:
            nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        opt.step()
        step += 1
        running.append(torch.stack([loss, *parts]).detach())
        if step % cfg.log_every == 0 or step == cfg.steps:
            history.append((step, *np.mean(read(running), 0).tolist()))
            running = []
            log.info("step %d/%d loss %.5f (mse %.5f, z %.4f, theta %.4f)", *history[-1][:1],
                     cfg.steps, *history[-1][1:])
        if on_step is not None:
            on_step(step, loss.item())
        if step % cfg.checkpoint_every == 0 or step == cfg.steps:
            elapsed, t0 = elapsed + time.perf_counter() - t0, time.perf_counter()
            checkpoint()

    bundle = {"model_cfg": asdict(model_cfg), "train_cfg": asdict(cfg),
              "state": {k: v.cpu() for k, v in model.state_dict().items()},
              "history": [list(h) for h in history], "train_seconds": elapsed,
              "n_train": M, "seed": seed, "fingerprint": fp}
    save_torch(out_path, bundle)
    modelfile.finish(ckpt_path)  # a rerun of the finished job resumes at the last step
    return bundle


HISTORY_COLUMNS = ["step", "loss", "mse", "z_reg", "theta_reg"]


def load(bundle, device: str = "cpu") -> HyperBRDF:
    """A trained model from a bundle dict or file (eval mode)."""
    source = bundle if not isinstance(bundle, dict) else "the HyperBRDF bundle"
    if not isinstance(bundle, dict):
        bundle = modelfile.load(bundle, finite=True)
    rule = "train_hyperbrdf (hyperbrdf/<trainset>/model.pt)"
    modelfile.require(bundle, ("model_cfg", "state"), source, f"a HyperBRDF model (rule {rule})")
    model = modelfile.build(lambda: HyperBRDF(HyperConfig(**bundle["model_cfg"])),
                            bundle["state"], source, rule)
    return model.to(device).eval()


# ----------------------------------------------------------------------------- inference


@torch.no_grad()
def encode_values(model: HyperBRDF, values, bins, median_at_bins) -> torch.Tensor:
    """Materials' physical BRDF (n, 3, K) at flat bins (K,) -> latents (n, latent)."""
    dev = next(model.parameters()).device
    x, _ = bin_inputs(bins)
    y = to_target(np.asarray(values, dtype=np.float32).transpose(0, 2, 1), median_at_bins)
    return torch.cat([model.encode(x.to(dev), y[i:i + 1].to(dev)) for i in range(len(y))])


@torch.no_grad()
def predict(model: HyperBRDF, z: torch.Tensor, x6, median) -> torch.Tensor:
    """Physical BRDF (n, N, 3) of latents z (n, latent) at inputs x6 (N, 6) whose per-bin
    medians are `median` (N,)."""
    dev = next(model.parameters()).device
    y = model.decode(z.to(dev), torch.as_tensor(x6, dtype=torch.float32, device=dev))
    return from_target(y, median)



# ----------------------------------------------------------------------------- Table 3 tasks

TASKS = ("sparse", "compression")


def task_bins(task: str, bins: np.ndarray, sparse_samples: int, seed: int, key) -> np.ndarray:
    """Positions into a material's stored `bins` that the encoder sees: a fixed random
    `sparse_samples` of them (sparse; from the named stream of the material's `key`, its name
    in the workflow) or all of them (compression)."""
    if task == "compression":
        return np.arange(len(bins))
    if task != "sparse":
        raise ValueError(f"unknown task {task!r}; choose from {TASKS}")
    if sparse_samples > len(bins):
        raise ValueError(f"sparse reconstruction needs {sparse_samples} samples, the material "
                         f"has {len(bins)} stored bins (augmerl.bins)")
    # keyed by the material, not its place in the list: adding a test material moved the
    # bins of every one after it (a review of 2026-11-29)
    rng = np.random.default_rng(seed_for(seed, "sparse", key))
    return np.sort(rng.choice(len(bins), sparse_samples, replace=False))


@torch.no_grad()
def reconstruct(model: HyperBRDF, values: np.ndarray, bins: np.ndarray, median_full: np.ndarray,
                views: dict, task: str, sparse_samples: int, seed: int,
                keys=None) -> dict[str, torch.Tensor]:
    """Encode each material's samples for `task`, decode, render in every view.

    values (n, 3, B) physical BRDF at flat MERL `bins` (B,); median_full (N_BINS,) the mapping's
    median; views: name -> `sphere.SphereView`; keys (n,): the materials' names, which key
    their sparse bins (default: their positions). Returns view -> linear HDR (n, H, W, 3)."""
    zs = []
    keys = range(len(values)) if keys is None else list(keys)
    for i, key in enumerate(keys):
        k = task_bins(task, bins, sparse_samples, seed, key)
        zs.append(encode_values(model, values[i:i + 1, :, k], bins[k], median_full[bins[k]]))
    z = torch.cat(zs)
    out = {}
    for name, v in views.items():
        f = predict(model, z, v.x6, median_full[v.bins.cpu().numpy()])
        out[name] = v.composite(f.to(v.weight.device)).cpu()
    return out
