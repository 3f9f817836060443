"""Transformer denoiser over NBRDF weight vectors (HyperDiffusion / G.pt style).

Tokens: one per layer tensor of `neumat.nbrdf` (W1, b1, W2, b2, W3, b3), or per piece of it
when the tensor holds more than `token_values` values, each projected to width d by its own
linear map, plus a timestep token and one token per condition. Learned positional embeddings
tell the tokens apart. The output of each tensor token is projected back to its piece's size
and the pieces are concatenated to the 675-vector again. A token reaches only d - 1 directions
(its final LayerNorm removes the mean), so a piece with more values than that cannot take every
value: W2's 441 values through one 256-wide token put a floor under the default model's error at
low noise. token_values below d splits it (opt-in: docs/stages.md, Hyperdiffusion).

Conditions plug in as modules that turn a batch of condition values into one (B, d) token and
own a learned "null" token for classifier-free guidance:
  - `ClassCondition`: integer labels (material type; -1 = no label),
  - `VectorCondition`: fixed-size embeddings (text: `neumat.conditions.text`, image:
    `neumat.conditions.image`; NaN rows = no value).
The denoiser takes `cond: dict[name, tensor]`; a missing name means null for the whole batch.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import nn

from neumat import nbrdf

TENSOR_SIZES = [int(np.prod(s)) for s in nbrdf.PARAM_SHAPES]  # [126, 21, 441, 21, 63, 3]


@dataclass
class DenoiserConfig:
    width: int = 256
    depth: int = 4
    heads: int = 8
    mlp_ratio: float = 4.0
    dropout: float = 0.0
    n_classes: int = 48  # material types; index n_classes is the null class
    # most values per tensor token; a larger tensor is split into near-equal pieces (0: one
    # token per tensor, as model files from before this key hold)
    token_values: int = 0
    vector_conditions: dict[str, int] = field(default_factory=dict)  # name -> embedding size

    def to_dict(self):
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "DenoiserConfig":
        """The config a model file records; files written before `token_values` existed have
        one token per tensor."""
        return cls(**{"token_values": 0, **d})


def token_sizes(token_values: int) -> list[int]:
    """Values per tensor token: each NBRDF tensor in near-equal pieces of at most token_values
    (0: whole tensors)."""
    sizes = []
    for n in TENSOR_SIZES:
        k = 1 if token_values <= 0 else -(-n // token_values)
        sizes += [n // k + (i < n % k) for i in range(k)]
    return sizes


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding of (possibly fractional) timesteps t (B,) -> (B, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device) / half)
    args = t.float()[:, None] * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], -1)
    return nn.functional.pad(emb, (0, dim % 2))


class ClassCondition(nn.Module):
    """Integer labels -> token; label -1 (or a dropped label) -> the null token."""

    def __init__(self, n_classes: int, width: int):
        super().__init__()
        self.n_classes = n_classes
        self.embed = nn.Embedding(n_classes + 1, width)  # last row = null

    def null(self, b: int, device) -> torch.Tensor:
        return self.embed(torch.full((b,), self.n_classes, device=device))

    def forward(self, labels: torch.Tensor, drop: torch.Tensor | None = None) -> torch.Tensor:
        labels = labels.long()
        if ((labels < -1) | (labels >= self.n_classes)).any():
            raise ValueError(f"class labels must lie in [-1, {self.n_classes}), got "
                             f"{labels.min().item()}..{labels.max().item()}")
        null = labels < 0
        if drop is not None:
            null = null | drop
        return self.embed(torch.where(null, self.n_classes, labels))


class VectorCondition(nn.Module):
    """A fixed-size embedding (e.g. sentence or image features) -> token; NaN rows -> null."""

    def __init__(self, dim: int, width: int):
        super().__init__()
        self.dim = dim
        self.proj = nn.Sequential(nn.Linear(dim, width), nn.SiLU(), nn.Linear(width, width))
        self.null_token = nn.Parameter(torch.zeros(width))

    def null(self, b: int, device) -> torch.Tensor:
        return self.null_token.expand(b, -1)

    def forward(self, emb: torch.Tensor, drop: torch.Tensor | None = None) -> torch.Tensor:
        if emb.shape[-1] != self.dim:
            raise ValueError(f"condition embedding has size {emb.shape[-1]}, expected {self.dim}")
        null = torch.isnan(emb).any(-1)
        if drop is not None:
            null = null | drop
        tok = self.proj(torch.nan_to_num(emb))
        return torch.where(null[:, None], self.null_token.expand_as(tok), tok)


class Block(nn.Module):
    """Pre-norm transformer block."""

    def __init__(self, width: int, heads: int, mlp_ratio: float, dropout: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(width)
        self.attn = nn.MultiheadAttention(width, heads, dropout=dropout, batch_first=True)
        self.norm2 = nn.LayerNorm(width)
        hidden = int(width * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(width, hidden), nn.GELU(), nn.Dropout(dropout),
                                 nn.Linear(hidden, width), nn.Dropout(dropout))

    def forward(self, x):
        h = self.norm1(x)
        x = x + self.attn(h, h, h, need_weights=False)[0]
        return x + self.mlp(self.norm2(x))


class Denoiser(nn.Module):
    """f(x_t, t, cond) -> prediction (x0 or eps) in the normalised weight space, (B, 675)."""

    def __init__(self, cfg: DenoiserConfig):
        super().__init__()
        self.cfg = cfg
        w = cfg.width
        if w % cfg.heads:
            raise ValueError(f"diffusion.model.width ({w}) must be divisible by heads ({cfg.heads})")
        self.sizes = token_sizes(cfg.token_values)
        self.embed_in = nn.ModuleList([nn.Linear(n, w) for n in self.sizes])
        self.time_mlp = nn.Sequential(nn.Linear(w, w), nn.SiLU(), nn.Linear(w, w))
        conds = {"type": ClassCondition(cfg.n_classes, w)} if cfg.n_classes > 0 else {}
        conds.update({k: VectorCondition(dim, w) for k, dim in cfg.vector_conditions.items()})
        self.cond_names = list(conds)
        # "c_" prefix: "type" would clash with nn.Module.type
        self.conditions = nn.ModuleDict({f"c_{k}": v for k, v in conds.items()})
        n_tokens = len(self.sizes) + 1 + len(conds)
        self.pos = nn.Parameter(torch.randn(n_tokens, w) * 0.02)
        self.blocks = nn.ModuleList([Block(w, cfg.heads, cfg.mlp_ratio, cfg.dropout)
                                     for _ in range(cfg.depth)])
        self.norm = nn.LayerNorm(w)
        self.embed_out = nn.ModuleList([nn.Linear(w, n) for n in self.sizes])
        for lin in self.embed_out:  # start as the zero predictor: stable first steps
            nn.init.zeros_(lin.weight)
            nn.init.zeros_(lin.bias)

    def condition_tokens(self, cond: dict | None, b: int, device, drop: dict | None = None):
        cond, drop = cond or {}, drop or {}
        unknown = set(cond) - set(self.cond_names)
        if unknown:
            raise ValueError(f"unknown condition(s) {sorted(unknown)}; model has "
                             f"{self.cond_names}")
        toks = []
        for name in self.cond_names:
            mod = self.conditions[f"c_{name}"]
            toks.append(mod(cond[name], drop.get(name)) if name in cond else mod.null(b, device))
        return toks

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: dict | None = None,
                drop: dict | None = None) -> torch.Tensor:
        """x (B, 675) noisy normalised weights, t (B,) timesteps, cond name -> (B, ...) values,
        drop name -> (B,) bool (classifier-free-guidance dropout: use the null token)."""
        b = x.shape[0]
        parts = torch.split(x, self.sizes, dim=-1)
        toks = [emb(p) for emb, p in zip(self.embed_in, parts)]
        toks.append(self.time_mlp(timestep_embedding(t, self.cfg.width)))
        toks += self.condition_tokens(cond, b, x.device, drop)
        h = torch.stack(toks, 1) + self.pos
        for blk in self.blocks:
            h = blk(h)
        h = self.norm(h)
        return torch.cat([out(h[:, i]) for i, out in enumerate(self.embed_out)], -1)


class Normalizer(nn.Module):
    """Per-coordinate standardisation of weight vectors; statistics travel with the model."""

    def __init__(self, mean: torch.Tensor | None = None, std: torch.Tensor | None = None,
                 min_std: float = 1e-6):
        super().__init__()
        n = nbrdf.N_PARAMS
        self.register_buffer("mean", torch.zeros(n) if mean is None else mean.float())
        self.register_buffer("std", torch.ones(n) if std is None else std.float().clamp_min(min_std))

    @classmethod
    def fit(cls, w: torch.Tensor) -> "Normalizer":
        return cls(w.mean(0), w.std(0) if w.shape[0] > 1 else torch.ones(w.shape[1]))

    def encode(self, w):
        return (w - self.mean) / self.std

    def decode(self, z):
        return z * self.std + self.mean
