"""Image condition: a small ResNet (He et al. 2016, CIFAR-style) that maps a sphere render to
an embedding, trained here on renders of the AugMERL training materials.

torchvision has no CPU build in this environment, so the network is written out (BasicBlocks,
three stages). The paper used CLIP's image tower (CLIP-PAE), whose weights are not obtainable
offline (docs/stages.md, Multi-modal conditioning).

Training data (`render_views`): each material is rendered by `neumat.render.sphere` under
several point-light positions (the metric light plus `n_lights - 1` others; for a sphere seen
orthographically, moving the light is the same as moving the camera up to an image rotation),
and each training crop gets a random 90-degree rotation / flip, a random crop and an exposure
jitter, so the encoder has to recognise the material and not the light, framing or brightness.

Objectives (`ImageEncoderConfig.objective`):
  * "text" (default): CLIP-style symmetric InfoNCE between the projected image embedding and
    the material's description embedding (all-MiniLM-L6-v2), temperature 0.07. On the published
    NBRDF fits (benchmarks/conditions_realistic.py, 1500 steps) it identified a test material
    across lights 58 % of the time against 33 % for "weights" (chance 3 %).
  * "weights": regress the standardised NeuMERL weight vector (675-d) from the image; the
    embedding is the penultimate layer. Cheap, needs no text, and ties the embedding directly
    to what the diffusion model generates.
The embedding (`embed_dim`) is what the diffusion model sees.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from neumat.io import images, modelfile
from neumat.io.atomic import save_torch
from neumat.render import sphere
from neumat.seeds import seed_for

log = logging.getLogger(__name__)
OBJECTIVES = ("weights", "text")


@dataclass
class ImageEncoderConfig:
    resolution: int = 32  # render size; crops are `crop` pixels
    crop: int = 28
    width: int = 16  # channels of the first stage (doubled per stage)
    blocks: int = 1  # BasicBlocks per stage
    embed_dim: int = 64
    n_lights: int = 6
    objective: str = "text"
    exposure_jitter: float = 0.5  # stops, uniform in [-x, x]
    steps: int = 3000
    batch_size: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4

    def to_dict(self):
        return asdict(self)


def light_positions(n: int) -> list[tuple[float, float, float]]:
    """The metric light first, then n - 1 lights spread in azimuth around the view axis at
    elevations 30..60 degrees from it, all at the metric light's distance."""
    d = float(np.linalg.norm(sphere.LIGHT_POS))
    out = [tuple(float(v) for v in sphere.LIGHT_POS)]
    for k in range(1, n):
        phi = 2 * math.pi * k / max(n - 1, 1) + 0.3
        theta = math.radians(30 + 30 * (k % 2))
        out.append((d * math.sin(theta) * math.cos(phi), d * math.sin(theta) * math.sin(phi),
                    d * math.cos(theta)))
    return out


def render_views(weights, resolution: int, n_lights: int, activation: str = "relu") -> torch.Tensor:
    """(N, 675) fields -> (N, n_lights, H, W, 3) linear HDR renders; view 0 is the metric view."""
    return torch.stack([sphere.render_fields(weights, resolution, activation, light=light)
                        for light in light_positions(n_lights)], 1)


def preprocess(img: torch.Tensor) -> torch.Tensor:
    """Linear HDR (B, H, W, 3) -> network input (B, 3, H, W): log(1 + x), which compresses
    specular highlights so diffuse colour still carries weight."""
    return torch.log1p(img.clamp_min(0)).permute(0, 3, 1, 2).contiguous()


def center_crop(x: torch.Tensor, size: int) -> torch.Tensor:
    o0, o1 = (x.shape[-2] - size) // 2, (x.shape[-1] - size) // 2
    return x[..., o0:o0 + size, o1:o1 + size]


def augment(img: torch.Tensor, crop: int, jitter: float, gen: torch.Generator) -> torch.Tensor:
    """Random exposure (2^U(-j, j)), random crop, random rotation by k * 90 degrees and flip;
    (B, H, W, 3) linear HDR -> (B, 3, crop, crop) network input."""
    b, h, w, _ = img.shape
    scale = 2.0 ** ((torch.rand(b, generator=gen) * 2 - 1) * jitter)
    x = preprocess(img * scale[:, None, None, None])
    oy = torch.randint(0, h - crop + 1, (b,), generator=gen)
    ox = torch.randint(0, w - crop + 1, (b,), generator=gen)
    rot = torch.randint(0, 4, (b,), generator=gen)
    flip = torch.rand(b, generator=gen) < 0.5
    out = []
    for i in range(b):
        c = x[i, :, oy[i]:oy[i] + crop, ox[i]:ox[i] + crop]
        c = torch.rot90(c, int(rot[i]), (1, 2))
        out.append(torch.flip(c, (2,)) if flip[i] else c)
    return torch.stack(out)


def norm(c: int) -> nn.GroupNorm:
    """GroupNorm over c channels, batch-size independent (single images): groups of gcd(8, c),
    so any conditions.image.encoder.width works (8 groups failed for c = 12, 20, ...) and the
    widths that worked keep their groups."""
    return nn.GroupNorm(math.gcd(8, c), c)


class BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.c1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.n1 = norm(cout)
        self.c2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.n2 = norm(cout)
        self.skip = (nn.Identity() if stride == 1 and cin == cout else
                     nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False),
                                   norm(cout)))

    def forward(self, x):
        h = F.relu(self.n1(self.c1(x)))
        return F.relu(self.n2(self.c2(h)) + self.skip(x))


class ImageEncoder(nn.Module):
    """ResNet: stem -> 3 stages (width, 2 width, 4 width; stride 1, 2, 2) -> global mean pool ->
    embedding (embed_dim) -> head (675 standardised weights, or the 384-d text space)."""

    def __init__(self, cfg: ImageEncoderConfig, head_dim: int):
        super().__init__()
        self.cfg = cfg
        w = cfg.width
        self.stem = nn.Sequential(nn.Conv2d(3, w, 3, 1, 1, bias=False), norm(w),
                                  nn.ReLU())
        layers, cin = [], w
        for i, cout in enumerate((w, 2 * w, 4 * w)):
            for j in range(cfg.blocks):
                layers.append(BasicBlock(cin, cout, 2 if (i > 0 and j == 0) else 1))
                cin = cout
        self.stages = nn.Sequential(*layers)
        self.embed = nn.Linear(cin, cfg.embed_dim)
        self.head = nn.Sequential(nn.SiLU(), nn.Linear(cfg.embed_dim, head_dim))

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """Network input (B, 3, h, w) -> embedding (B, embed_dim)."""
        return self.embed(self.stages(self.stem(x)).mean((2, 3)))

    def forward(self, x):
        return self.head(self.features(x))


def _targets(cfg, weights, text):
    if cfg.objective == "weights":
        w = torch.as_tensor(weights, dtype=torch.float32)
        mean, std = w.mean(0), w.std(0).clamp_min(1e-6)
        return (w - mean) / std
    if cfg.objective == "text":
        if text is None:
            raise ValueError("image encoder objective 'text' needs the text embeddings")
        return F.normalize(torch.as_tensor(text, dtype=torch.float32), dim=-1)
    raise ValueError(f"conditions.image.encoder.objective: {cfg.objective!r} is not one of "
                     f"{OBJECTIVES}")


def _loss(cfg, pred, target):
    if cfg.objective == "weights":
        return F.mse_loss(pred, target)
    z = F.normalize(pred, dim=-1)
    logits = z @ target.T / 0.07
    # materials with the same description are positives of each other, not negatives
    pos = (target @ target.T > 0.999).float()
    pos = pos / pos.sum(1, keepdim=True)
    return 0.5 * (torch.sum(-pos * F.log_softmax(logits, 1), 1).mean()
                  + torch.sum(-pos * F.log_softmax(logits.T, 1), 1).mean())


CHECKPOINT_SECONDS = 30.0  # between checkpoints: when state is saved, not what it computes


def train(views: torch.Tensor, weights: np.ndarray, cfg: ImageEncoderConfig, seed: int,
          text: np.ndarray | None = None, checkpoint=None) -> dict:
    """Train on renders `views` (N, K, H, W, 3) of N materials with weights (N, 675) (and text
    embeddings (N, 384) for objective 'text'). Returns a bundle (config, state, history). With
    `checkpoint`, the training state (model, AdamW, the draws' generator, step, history) is
    saved there every CHECKPOINT_SECONDS and at the end, and a killed training resumes from it
    bit for bit (the learning rate is a function of the step)."""
    if views.shape[2] != cfg.resolution:
        raise ValueError(f"renders are {views.shape[2]} px, encoder resolution {cfg.resolution}")
    if not cfg.crop <= cfg.resolution:
        raise ValueError("conditions.image.encoder.crop must not exceed "
                         "conditions.image.encoder.resolution")
    target = _targets(cfg, weights, text)
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed_for(seed, "draws"))  # not the init's numbers
    model = ImageEncoder(cfg, target.shape[1])
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    n, k = views.shape[:2]
    history, running, step, elapsed = [], [], 0, 0.0
    fp = modelfile.fingerprint([views, weights, text], {"cfg": cfg.to_dict(), "seed": seed}) \
        if checkpoint else None
    ck = modelfile.resume(checkpoint, fp, model=model, opt=opt, generator=gen) \
        if checkpoint else None
    if ck is not None:
        step, elapsed = int(ck["step"]), float(ck["elapsed"])
        history, running = [tuple(r) for r in ck["history"]], list(ck["running"])
    t0 = saved = time.perf_counter()
    for step in range(step, cfg.steps):
        lr = cfg.lr * 0.5 * (1 + math.cos(math.pi * step / cfg.steps))  # cosine to 0
        for g in opt.param_groups:
            g["lr"] = lr
        mi = torch.randint(0, n, (cfg.batch_size,), generator=gen)
        vi = torch.randint(0, k, (cfg.batch_size,), generator=gen)
        x = augment(views[mi, vi], cfg.crop, cfg.exposure_jitter, gen)
        loss = _loss(cfg, model(x), target[mi])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        running.append(loss.item())
        if (step + 1) % max(1, cfg.steps // 20) == 0 or step + 1 == cfg.steps:
            history.append((step + 1, float(np.mean(running))))
            running = []
            log.info("image encoder step %d/%d loss %.4f", step + 1, cfg.steps, history[-1][1])
        if checkpoint and (step + 1 == cfg.steps or time.perf_counter() - saved > CHECKPOINT_SECONDS):
            Path(checkpoint).parent.mkdir(parents=True, exist_ok=True)
            save_torch(checkpoint, {"fingerprint": fp, "model": model.state_dict(),
                                    "opt": opt.state_dict(), "generator": gen.get_state(),
                                    "step": step + 1, "history": history, "running": running,
                                    "elapsed": elapsed + time.perf_counter() - t0})
            saved = time.perf_counter()
    return {"cfg": cfg.to_dict(), "head_dim": int(target.shape[1]),
            "state": {k_: v.detach().clone() for k_, v in model.state_dict().items()},
            "history": history, "train_seconds": elapsed + time.perf_counter() - t0, "n_train": n,
            "seed": seed}


def load(bundle) -> ImageEncoder:
    """An encoder from a `train` bundle or its file (weights_only: tensors and plain values)."""
    source = bundle if not isinstance(bundle, dict) else "the encoder bundle"
    if not isinstance(bundle, dict):
        bundle = modelfile.load(bundle, finite=True)
    modelfile.require(bundle, ("cfg", "head_dim", "state"), source,
                      "an image encoder (rule train_image_encoder: conditions/image_encoder.pt)")
    model = modelfile.build(lambda: ImageEncoder(ImageEncoderConfig(**bundle["cfg"]), bundle["head_dim"]),
                            bundle["state"], source, "train_image_encoder")
    return model.eval()


@torch.no_grad()
def embed(model: ImageEncoder, images, batch: int = 256) -> np.ndarray:
    """Linear HDR renders (B, H, W, 3) at the encoder's resolution -> (B, embed_dim) float32;
    deterministic (centre crop, no jitter)."""
    img = torch.as_tensor(np.asarray(images), dtype=torch.float32)
    r = model.cfg.resolution
    if img.dim() != 4 or img.shape[1:] != (r, r, 3):
        raise ValueError(f"images must be (B, {r}, {r}, 3) linear HDR, got {tuple(img.shape)}")
    out = [model.features(center_crop(preprocess(img[s:s + batch]), model.cfg.crop))
           for s in range(0, len(img), batch)]
    return torch.cat(out).numpy().astype(np.float32) if out else np.zeros((0, model.cfg.embed_dim),
                                                                          np.float32)


def embed_fields(model: ImageEncoder, weights, activation: str = "relu") -> np.ndarray:
    """(N, 675) fields -> (N, n_lights, embed_dim): the embedding of each light's render."""
    views = render_views(weights, model.cfg.resolution, model.cfg.n_lights, activation)
    n, k = views.shape[:2]
    return embed(model, views.reshape(n * k, *views.shape[2:])).reshape(n, k, -1)


def retrieve(embeddings: np.ndarray, library: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """For each embedding (M, D), the row (of `rows`) whose metric-view embedding in `library`
    (len(rows), D) is nearest (squared Euclidean): image retrieval, the baseline image-conditioned
    sampling is scored against and, with `conditions.image.strength` < 1, its starting point."""
    e, lib = np.asarray(embeddings), np.asarray(library)
    return np.asarray(rows)[((e[:, None] - lib[None]) ** 2).sum(-1).argmin(1)]


def best_of(score: np.ndarray, draws: int, k: int) -> np.ndarray:
    """Indices of the k highest scores in each consecutive group of `draws` (one image's
    candidates), in the groups' order, best first; ties keep the draw order."""
    score = np.asarray(score, np.float64)
    if draws < k or len(score) % draws:
        raise ValueError(f"{len(score)} scores are not groups of {draws} draws (>= k = {k})")
    groups = score.reshape(-1, draws)
    top = np.argsort(-groups, axis=1, kind="stable")[:, :k]
    return (top + draws * np.arange(len(groups))[:, None]).reshape(-1)


def draw_candidates(draw, conditions: int, k: int, constrained: int, unconstrained: int,
                    seed: int, negative_step: float) -> tuple[np.ndarray, np.ndarray]:
    """The candidates of best of n: (draws (conditions kd, 675), free (conditions kd,) bool),
    kd = k (constrained + unconstrained) per condition, each condition's k constrained draws
    first (conditions.image.candidates: `negative_step`, `seed`), then its k unconstrained
    ones (conditions.image.unconstrained_candidates: negative step 0, seed stream
    "unconstrained" of `seed`), which keep the look of fields that clamp by nature.
    `draw(idx, seed, negative_step)` draws the rows `idx` of the conditions' repeated
    conditions, targets and starts."""
    from neumat.nbrdf import N_PARAMS
    from neumat.seeds import seed_for
    kd = k * (constrained + unconstrained)
    free = np.arange(conditions * kd) % kd >= k * constrained
    w = np.zeros((len(free), N_PARAMS), np.float32)
    for part, s, neg in [(~free, seed, negative_step),
                         (free, seed_for(seed, "unconstrained"), 0.0)]:
        idx = np.flatnonzero(part)
        if len(idx):
            w[idx] = draw(idx, s, neg)
    return w, free


def score_draws(draws: np.ndarray, images, angles: int, seed: int, activation: str):
    """(render PSNR, clamps) of each draw for best of n: draws (M kd, 675) in groups of kd per
    conditioning image (images (M, R, R, 3), linear HDR in the metric view); the PSNR of each
    draw's metric-view render against its image, and whether its field clamps negative values on
    `angles` bins (seed stream "candidates_clamp" of `seed`, not the one conditions_eval
    reports clamping with)."""
    from neumat.conditions import evaluate as ev
    from neumat.seeds import seed_for
    images = np.asarray(images)
    targets = np.repeat(images, len(draws) // len(images), 0)
    psnr = ev.render_psnr(draws, targets, images.shape[1], activation)
    clamps = ev.negative_share(draws, angles, seed_for(seed, "candidates_clamp"), activation)
    return psnr, clamps


def selection_score(psnr: np.ndarray, clamps: np.ndarray, clamp_penalty: float) -> np.ndarray:
    """A candidate's score for best_of: its render PSNR against the image (dB), less
    `clamp_penalty` dB where its field clamps negative values (conditions.image.clamp_penalty)."""
    return np.asarray(psnr, np.float64) - clamp_penalty * np.asarray(clamps, bool)


def choose(draws: np.ndarray, images, k: int, angles: int, seed: int, activation: str,
           clamp_penalty: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best of n over `draws` (M kd, 675) in groups of kd per image (images (M, R, R, 3)):
    (indices of each image's k kept draws, best first; render PSNR and clamps of every draw),
    by score_draws less `clamp_penalty` dB for a clamping draw."""
    psnr, clamps = score_draws(draws, images, angles, seed, activation)
    keep = best_of(selection_score(psnr, clamps, clamp_penalty), len(draws) // len(images), k)
    return keep, psnr, clamps


def load_image(path, resolution: int) -> np.ndarray:
    """A user's reference image -> (resolution, resolution, 3) linear HDR.

    EXR is read as linear radiance, other formats as sRGB decoded to linear (`neumat.io.images`). The image should
    show one sphere filling the frame, like the metric view; it is centre-cropped to a square
    and resized (area averaging) to the encoder's resolution."""
    from pathlib import Path

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"conditioning image {p} does not exist (a path of config "
                                f"conditions.image.images, or of --image)")
    img = images.read_linear(p)
    h, w = img.shape[:2]
    s = min(h, w)
    img = img[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    t = torch.as_tensor(img).permute(2, 0, 1)[None]
    t = F.interpolate(t, size=(resolution, resolution), mode="area")
    return t[0].permute(1, 2, 0).numpy()

