"""Batched NBRDF fitting: many materials trained at once, each its own network (NeuMERL, §3.2).

Every material m has its own weights w_m (675,), Adam moments and data; one step runs all of
them through batched matmuls (`torch.baddbmm` over the material axis). The summed loss has
block-diagonal gradients, so a batch of B materials gives exactly the B single fits.

Objective (paper eq. 2, Sztrajman et al. 2021), per material, mean over samples and channels:

    L = |log(1 + f cos(theta_i)) - log(1 + f_hat cos(theta_i))|,  cos at the bin centre.

Data: the shard's MERL bins (shared by all materials) and physical BRDF values. The bins are
split 80/20 (train/val) and minibatches walk through a fresh random permutation of the training
bins every epoch; split and order are functions of the seed alone, the same for every material.
Each material still sees a uniformly random minibatch sequence, and sharing it lets a step
gather one set of inputs for all materials and run layer 1 as one matmul.

MERL stores phi_d folded to [0, pi) (reciprocity: f(phi_d) = f(phi_d + pi)), but renderers
query the field at any phi_d; with `mirror_phi_d` each training sample is shown at phi_d or
phi_d + pi (d -> (-dx, -dy, dz)) at random, so the field learns the symmetric BRDF instead of
extrapolating to half of its input domain. As all randomness is a function of (seed, epoch),
results do not depend on which materials share a batch, and a run resumed from a checkpoint
(weights, Adam moments, step) continues bit-identically.

Forward and backward are written out by hand (`loss_and_grad`): one pass per layer instead of
autograd's graph, feature-major (samples on the contiguous axis) and into buffers reused every
step; `tests/test_fit.py` checks it against autograd, `benchmarks/fit_throughput.py` measures it.
On the CPU the same step can run in C (`fit_step.c` via `neumat.fit_kernel`, setting
`kernel`): torch's batched matmuls are overhead-bound at 21 x 21. `kernel: auto` takes whichever
step a one-off calibration found faster on this CPU (`fit_kernel.auto_choice`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch

from neumat import fit_kernel, nbrdf
from neumat.io import merl
from neumat.io.atomic import NPZ_ERRORS
from neumat.io.atomic import save_npz as _save_npz  # module attribute: tests patch it

log = logging.getLogger(__name__)
BETAS, EPS = (0.9, 0.999), 1e-8  # Adam, torch.optim.Adam defaults
LEAKY_SLOPE = 0.01  # as neumat.nbrdf
# bump when the sampling of splits/minibatches changes: checkpoints of older code are not resumed
SAMPLING_VERSION = 2
KERNELS = ("auto", "c", "torch")


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """Optimisation settings of one fit (config section `fit:`, see config/schema.yaml)."""
    steps: int = 4000
    lr: float = 5e-3
    lr_final: float = 5e-4  # cosine decay from lr to lr_final over `steps`
    batch: int = 512
    activation: str = "relu"
    mirror_phi_d: bool = True  # also train at phi_d + pi (see module docstring)
    val_fraction: float = 0.2
    materials_per_batch: int = 50
    eval_every: int = 500  # validation-loss history (on `eval_bins` val bins per material)
    eval_bins: int = 4096
    checkpoint_every: int = 500
    kernel: str = "auto"  # step on the CPU: "c" (fit_step.c), "torch", or "auto" (the faster here)

    def __post_init__(self):
        if self.activation not in nbrdf.ACTIVATIONS:
            raise ValueError(f"config fit.activation must be one of {nbrdf.ACTIVATIONS}, "
                             f"got {self.activation!r}")
        if self.kernel not in KERNELS:
            raise ValueError(f"config fit.kernel must be one of {KERNELS}, got {self.kernel!r}")
        if not 0 < self.val_fraction < 1:
            raise ValueError(f"config fit.val_fraction must be in (0, 1), got {self.val_fraction}")
        for k in ("steps", "batch", "materials_per_batch", "eval_every", "eval_bins",
                  "checkpoint_every"):
            if getattr(self, k) < 1:
                raise ValueError(f"config fit.{k} must be >= 1, got {getattr(self, k)}")

    @classmethod
    def from_config(cls, cfg: dict, steps_key: str = "steps") -> "FitSettings":
        """Settings from the `fit:` config section; `steps_key="template_steps"` for the template."""
        names = {f.name for f in dataclasses.fields(cls)} - {"steps"}
        return cls(steps=cfg[steps_key], **{k: v for k, v in cfg.items() if k in names})

    def lr_at(self, step: int) -> float:
        c = 0.5 * (1 + math.cos(math.pi * min(step, self.steps) / self.steps))
        return self.lr_final + (self.lr - self.lr_final) * c


# ----------------------------------------------------------------------------- data


def bin_inputs(bins: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat MERL bin indices -> network inputs (B, 6) and cos(theta_i) (B,) at bin centres."""
    bins = np.asarray(bins)
    if bins.ndim != 1 or len(bins) == 0 or bins.min() < 0 or bins.max() >= merl.N_BINS:
        raise ValueError(f"bins must be a non-empty 1-D array of indices in [0, {merl.N_BINS})")
    th, td, pd = merl.bin_centers()
    ih, rem = np.divmod(bins, merl.N_TD * merl.N_PD)
    idd, ip = np.divmod(rem, merl.N_PD)
    ang = th[ih], td[idd], pd[ip]
    x = torch.as_tensor(merl.half_diff_cartesian(*ang), dtype=torch.float32)
    cos = torch.as_tensor(np.clip(merl.cos_theta_i(*ang), 0, None), dtype=torch.float32)
    return x, cos


def log_target(values: np.ndarray | torch.Tensor, cos: torch.Tensor,
               bin_major: bool = False) -> torch.Tensor:
    """Physical BRDF (n, 3, B) -> log(1 + f cos), the loss's fixed term: (n, B, 3), or with
    `bin_major` (B, n * 3), the layout `BatchFitter` trains on.

    Built in one float32 buffer, in place: clamp at 0, times cos, log1p, elementwise the same
    operations as `log1p(clamp_min(f, 0) * cos)` and bit-identical to it (tests/test_fit.py),
    where that expression held three temporaries of the values' size and a transposed copy."""
    v = torch.as_tensor(values)
    if v.dim() != 3 or v.shape[1] != 3 or v.shape[2] != len(cos):
        raise ValueError(f"BRDF values must be (n, 3, {len(cos)}), got {tuple(v.shape)}")
    n, _, B = v.shape
    t = torch.empty((B, n, 3) if bin_major else (n, B, 3), dtype=torch.float32)
    (t.permute(1, 2, 0) if bin_major else t.transpose(1, 2)).copy_(v)
    flat = t.view(B, n * 3) if bin_major else t
    flat.clamp_min_(0).mul_(cos[:, None]).log1p_()
    return flat


def _generator(seed: int, *keys: int) -> torch.Generator:
    """A torch generator seeded by a hash of (seed, keys): independent streams per material."""
    state = np.random.SeedSequence([seed, *keys]).generate_state(2, np.uint32)
    return torch.Generator().manual_seed(int(state[0]) << 31 ^ int(state[1]))


def split_bins(n_bins: int, seed: int, val_fraction: float):
    """Train/val split of positions 0..n_bins-1 -> (train, val) sorted int64 tensors."""
    n_val = int(round(val_fraction * n_bins))
    if n_val < 1 or n_val >= n_bins:
        raise ValueError(f"{n_bins} bins cannot be split with val_fraction {val_fraction}")
    perm = torch.randperm(n_bins, generator=_generator(seed, 0))
    return perm[n_val:].sort().values, perm[:n_val].sort().values


def epoch_order(n_train: int, seed: int, epoch: int):
    """The order in which the training bins are visited in `epoch`, and which visits see the
    bin mirrored to phi_d + pi -> (order (n,) int64, mirror (n,) bool)."""
    g = _generator(seed, 1, epoch)
    return torch.randperm(n_train, generator=g), torch.randint(0, 2, (n_train,), generator=g) > 0


def mirror_phi_d(x: torch.Tensor, mirror: torch.Tensor) -> torch.Tensor:
    """Inputs (..., 6) = [h, d] -> d rotated by pi about the normal where `mirror` (...,) is set."""
    x = x.clone()
    x[..., 3:5] *= 1 - 2 * mirror[..., None].to(x.dtype)
    return x


# ----------------------------------------------------------------------------- model maths


def _act_(z, activation):
    return z.relu_() if activation == "relu" else torch.nn.functional.leaky_relu_(z, LEAKY_SLOPE)


def _act_backward_(grad, a, activation):
    """grad * act'(z), in place; a = act(z) > 0 exactly where z > 0, so the mask comes from
    the saved activation."""
    if activation == "relu":
        return torch.ops.aten.threshold_backward.grad_input(grad, a, 0, grad_input=grad)
    return torch.ops.aten.leaky_relu_backward.grad_input(grad, a, LEAKY_SLOPE, True,
                                                         grad_input=grad)


class Workspace:
    """Buffers of one batched step, reused every step. Fresh multi-MB activations each step
    cost ~1000 page faults (glibc hands large blocks back to the OS): half of the step time."""

    def __init__(self, M: int, n: int, device="cpu", dtype=torch.float32):
        e = dict(device=device, dtype=dtype)
        self.a1, self.a2, self.d = (torch.empty(M, 21, n, **e) for _ in range(3))
        self.e, self.fc, self.r = (torch.empty(M, 3, n, **e) for _ in range(3))
        self.loss, self.g = torch.empty(M, **e), torch.empty(M, nbrdf.N_PARAMS, **e)
        self.gw1 = torch.empty(M * 21, 6, **e)
        self.xc = torch.empty(7, n, **e)  # the minibatch's inputs (6 rows) and cos (1 row)
        self.t = torch.empty(M, 3, n, **e)  # its targets


def loss_and_grad(w: torch.Tensor, x: torch.Tensor, target: torch.Tensor, cos: torch.Tensor,
                  activation: str = "relu", ws: Workspace | None = None):
    """Eq. 2 loss per material and its gradient, by hand.

    Feature-major, samples on the contiguous axis: x (6, n) inputs and cos (1, n), shared by
    all materials; target (M, 3, n) = log(1 + f cos). Returns loss (M,) and d loss_m / d w_m
    (M, 675) in the flatten order of `neumat.nbrdf`; both live in `ws` (copy them to keep them
    past the next call)."""
    M, n = w.shape[0], x.shape[1]
    ws = ws or Workspace(M, n, x.device, x.dtype)
    W1, b1, W2, b2, W3, b3 = nbrdf.unflatten(w)
    # shared inputs: layer 1 of all materials is one (M*21, 6) x (6, n) matmul
    torch.addmm(b1.reshape(-1, 1), W1.reshape(-1, 6), x, out=ws.a1.view(-1, n))
    a1 = _act_(ws.a1, activation)
    a2 = _act_(torch.baddbmm(b2[..., None], W2, a1, out=ws.a2), activation)
    e = torch.baddbmm(b3[..., None], W3, a2, out=ws.e).exp_()
    fc = torch.sub(e, 1, out=ws.fc).mul_(cos)  # > -1: no clamp in training (see docstring)
    r = torch.log1p(fc, out=ws.r).sub_(target)
    loss = torch.mean(r.abs(), (1, 2), out=ws.loss)
    dy = r.sign_().mul_(cos).mul_(e).div_(fc.add_(1)).div_(n * 3)  # d|r|/dy, (M, 3, n)
    gW1, gb1, gW2, gb2, gW3, gb3 = nbrdf.unflatten(ws.g)
    torch.bmm(dy, a2.transpose(1, 2), out=gW3)
    torch.sum(dy, 2, out=gb3)
    d2 = _act_backward_(torch.bmm(W3.transpose(1, 2), dy, out=ws.d), a2, activation)
    torch.bmm(d2, a1.transpose(1, 2), out=gW2)
    torch.sum(d2, 2, out=gb2)
    d1 = _act_backward_(torch.bmm(W2.transpose(1, 2), d2, out=ws.a2), a1, activation)
    gW1.copy_(torch.mm(d1.view(-1, n), x.t(), out=ws.gw1).view(M, 21, 6))
    torch.sum(d1, 2, out=gb1)
    return loss, ws.g


LOSS_CHUNK = 1 << 15  # points per forward pass of field_loss


def _loss_sums(w, x, target, cos, activation="relu", chunk=LOSS_CHUNK) -> torch.Tensor:
    """Sum of |r| per material (M,) float64, as `field_loss` (chunked to bound memory)."""
    total = torch.zeros(w.shape[0], dtype=torch.float64, device=w.device)
    with torch.no_grad():
        for s in range(0, x.shape[-2], chunk):
            f = nbrdf.forward(w, x[..., s:s + chunk, :], activation)
            r = torch.log1p(f * cos[..., s:s + chunk, :]) - target[:, s:s + chunk]
            total += r.abs().sum((1, 2)).double()
    return total


def field_loss(w: torch.Tensor, x: torch.Tensor, target: torch.Tensor, cos: torch.Tensor,
               activation: str = "relu", chunk: int = LOSS_CHUNK) -> torch.Tensor:
    """Eq. 2 loss per material over all given points, no gradient (chunked to bound memory).

    x (n, 6) shared or (M, n, 6), target (M, n, 3), cos (n, 1) or (M, n, 1) -> (M,) float64."""
    return _loss_sums(w, x, target, cos, activation, chunk) / (x.shape[-2] * 3)


def adam_step(w, g, m, v, step: int, lr: float):
    """In-place Adam update (torch.optim.Adam semantics), row-wise independent; step from 1."""
    m.lerp_(g, 1 - BETAS[0])
    v.mul_(BETAS[1]).addcmul_(g, g, value=1 - BETAS[1])
    denom = (v / (1 - BETAS[1] ** step)).sqrt_().add_(EPS)
    w.addcdiv_(m, denom, value=-lr / (1 - BETAS[0] ** step))


# ----------------------------------------------------------------------------- the fitter


def resolve_kernel(settings: FitSettings, device) -> str:
    """The step implementation a fit uses: "c" (CPU, minibatch a multiple of 16, a C compiler)
    or "torch" (any device). Results of the two agree to float32 rounding, not bit for bit,
    so the resolved kernel is part of a checkpoint's fingerprint."""
    if settings.kernel == "torch":
        return "torch"
    why = ("the device is not the CPU" if torch.device(device).type != "cpu" else
           f"fit.batch {settings.batch} is not a multiple of {fit_kernel.VECTOR}"
           if settings.batch % fit_kernel.VECTOR else
           None if fit_kernel.available() else "it could not be compiled (see the log)")
    if why is None and settings.kernel == "auto":  # C only where it is the faster step here
        why = (None if fit_kernel.auto_choice(settings.batch, settings.activation) == "c" else
               "the torch step is faster on this CPU (fit_kernel.auto_choice)")
    if why is None:
        return "c"
    if settings.kernel == "c":
        raise ValueError(f"config fit.kernel: c, but the C kernel cannot be used: {why}")
    log.info("fit kernel: torch (the C kernel is not used: %s)", why)
    return "torch"


class BatchFitter:
    """Fits M materials at once. Data on `device`; state = (w, m, v, step, history).

    x (B, 6), cos (B,): the shared bins; target (M, B, 3) = `log_target`, or bin-major
    (B, M * 3) = `log_target(..., bin_major=True)`, the layout trained on (used as it is, no
    copy, when it is a contiguous float32 tensor on `device`); ids (M,) material ids
    (bookkeeping); init (M, 675) initial weights."""

    def __init__(self, x, cos, target, ids, init, settings: FitSettings, seed: int,
                 device="cpu"):
        self.s, self.seed, self.dev = settings, seed, torch.device(device)
        self.ids = [int(i) for i in ids]
        bin_major = target.dim() == 2
        M, B = (target.shape[1] // 3, target.shape[0]) if bin_major else target.shape[:2]
        if (init.shape != (M, nbrdf.N_PARAMS) or len(self.ids) != M or x.shape[0] != B
                or target.shape[-1] != (3 * M if bin_major else 3)):
            raise ValueError(f"inconsistent fit inputs: target {tuple(target.shape)}, "
                             f"init {tuple(init.shape)}, {len(self.ids)} ids, {x.shape[0]} bins")
        self.train_idx, self.val_idx = (i.to(self.dev) for i in
                                        split_bins(B, seed, settings.val_fraction))
        self.n_train = len(self.train_idx)
        if self.n_train < settings.batch:
            raise ValueError(f"{self.n_train} training bins per material < config fit.batch "
                             f"{settings.batch}; store more bins (augmerl.bins) or lower the batch")
        self.steps_per_epoch = self.n_train // settings.batch
        self.x, self.cos = x.to(self.dev), cos.to(self.dev)
        # bin-major (B, M * 3): a minibatch gathers n rows of contiguous values, not M * n
        self.target = (target.to(self.dev, torch.float32).contiguous() if bin_major else
                       target.to(self.dev).permute(1, 0, 2).reshape(B, M * 3).contiguous())
        self.w = init.detach().to(self.dev, torch.float32).clone()
        self.m, self.v = torch.zeros_like(self.w), torch.zeros_like(self.w)
        self.step, self.history = 0, []  # history: (step, val loss on eval bins (M,))
        self._epoch = -1
        self._xc = torch.cat([self.x, self.cos[:, None]], 1)  # (B, 7): one gather for both
        self.kernel = resolve_kernel(settings, self.dev)
        slope = 0.0 if settings.activation == "relu" else LEAKY_SLOPE
        # C kernel: the job's threads split the materials; torch path: buffers of one step
        self._c = (fit_kernel.Stepper(self._xc, self.target, settings.batch,
                                      torch.get_num_threads(), slope)
                   if self.kernel == "c" else None)
        self._ws = None if self._c else Workspace(M, settings.batch, self.dev)

    def _points(self, idx):
        """Bin positions (k,) -> inputs (k, 6), targets (M, k, 3), cos (k, 1)."""
        t = self.target.index_select(0, idx).view(len(idx), -1, 3).transpose(0, 1)
        return self.x.index_select(0, idx), t, self.cos.index_select(0, idx)[:, None]

    def _epoch_bins(self, epoch):
        """Training-bin positions in visiting order (n_train,) and the phi_d signs of `epoch`."""
        if epoch != self._epoch:
            order, mirror = epoch_order(self.n_train, self.seed, epoch)
            self._bins = self.train_idx[order.to(self.dev)]
            self._sign = 1 - 2 * mirror.to(self.dev, torch.float32) * self.s.mirror_phi_d
            self._epoch = epoch
        return self._bins, self._sign

    def _schedule(self, step, k):
        """Bin positions (k, batch) and phi_d signs (k, batch) of steps step ... step + k - 1."""
        idx, sign, b = [], [], self.s.batch
        for epoch, i in (divmod(s, self.steps_per_epoch) for s in range(step, step + k)):
            bins, sg = self._epoch_bins(epoch)
            idx.append(bins[i * b:(i + 1) * b])
            sign.append(sg[i * b:(i + 1) * b])
        return torch.stack(idx), torch.stack(sign)

    def _minibatch(self, step):
        """Training minibatch of `step`, feature-major in the workspace (see `loss_and_grad`)."""
        (idx,), (sign,) = self._schedule(step, 1)
        ws = self._ws
        ws.xc.copy_(self._xc.index_select(0, idx).t())
        ws.t.view(-1, len(idx)).copy_(self.target.index_select(0, idx).t())
        ws.xc[3:5].mul_(sign)  # d -> (-dx, -dy, dz): phi_d + pi
        return ws.xc[:6], ws.t, ws.xc[6:]

    def _run(self, k):
        """k training steps; returns the last step's minibatch loss (M,)."""
        lrs = [self.s.lr_at(s) for s in range(self.step, self.step + k)]
        if self._c:  # minibatches, loss, gradient and Adam of all k steps in one call
            idx, sign = self._schedule(self.step, k)
            loss, _ = self._c.run(self.w, self.m, self.v, idx, sign,
                                  torch.tensor(lrs, dtype=torch.float32), self.step)
            self.step += k
            return loss
        for lr in lrs:
            loss, g = loss_and_grad(self.w, *self._minibatch(self.step), self.s.activation,
                                    self._ws)
            self.step += 1
            adam_step(self.w, g, self.m, self.v, self.step, lr)
        return loss

    def train(self, until: int | None = None, on_checkpoint=None):
        """Run steps up to `until` (default: settings.steps); `on_checkpoint(self)` every
        `checkpoint_every` steps."""
        until = self.s.steps if until is None else until
        while self.step < until:
            # run up to the next evaluation, checkpoint, last step or `until`
            stop = min(until, *((self.step // e + 1) * e for e in (self.s.eval_every,
                                                                   self.s.checkpoint_every)))
            if self.step < self.s.steps:
                stop = min(stop, self.s.steps)
            loss = self._run(stop - self.step)
            if self.step % self.s.eval_every == 0 or self.step == self.s.steps:
                self.history.append((self.step, self.eval_loss("val", self.s.eval_bins)))
                log.info("step %d/%d: train batch loss %.4g, val loss median %.4g", self.step,
                         self.s.steps, loss.median().item(), np.median(self.history[-1][1]))
            if on_checkpoint and self.step % self.s.checkpoint_every == 0:
                on_checkpoint(self)
        return self

    def eval_loss(self, split: str, limit: int | None = None) -> np.ndarray:
        """Eq. 2 loss (M,) on the train or val bins (`limit` of them, evenly strided over the
        sorted bins: the first `limit` were theta_h < 0.4 deg alone, the specular peak, whose
        loss was 3x the whole split's)."""
        idx = {"train": self.train_idx, "val": self.val_idx}[split]
        if limit is not None and limit < len(idx):
            idx = idx[torch.linspace(0, len(idx) - 1, limit).long().to(idx.device)]
        if self._c:
            return self._c.losses(self.w, idx).numpy()
        # gathered a chunk at a time (all train bins at once were a copy of 0.8 targets), the
        # sums taken in field_loss's chunks and order: the same float64 total
        total, n = None, len(idx)
        for s in range(0, n, LOSS_CHUNK):
            part = _loss_sums(self.w, *self._points(idx[s:s + LOSS_CHUNK]), self.s.activation)
            total = part if total is None else total.add_(part)
        return (total / (n * 3)).cpu().numpy()

    def state(self) -> dict[str, np.ndarray]:
        steps = np.array([s for s, _ in self.history], dtype=np.int64)
        hist = np.stack([h for _, h in self.history]) if self.history else np.zeros((0, len(self.ids)))
        return dict(w=self.w.cpu().numpy(), m=self.m.cpu().numpy(), v=self.v.cpu().numpy(),
                    step=np.int64(self.step), history_steps=steps, history=hist)

    def load_state(self, st: dict):
        for k in ("w", "m", "v"):
            getattr(self, k).copy_(torch.as_tensor(st[k]))
        self.step = int(st["step"])
        self.history = list(zip(st["history_steps"].tolist(), list(st["history"])))
        return self


def fit(values, bins, ids, init, settings: FitSettings, seed: int, device="cpu",
        on_checkpoint=None, state=None) -> BatchFitter:
    """Fit materials `ids` with data values (M, 3, B) at flat MERL bins (B,), from init (M, 675)."""
    x, cos = bin_inputs(bins)
    init = torch.as_tensor(np.asarray(init), dtype=torch.float32)
    if init.dim() == 1:
        init = init.expand(len(ids), -1)
    # the one copy of the targets, in the fitter's layout (on another device: moved there)
    f = BatchFitter(x, cos, log_target(values, cos, bin_major=True), ids, init, settings, seed,
                    device)
    if state is not None:
        f.load_state(state)
    return f.train(on_checkpoint=on_checkpoint)


# ----------------------------------------------------------------------------- shards


# Settings a checkpoint resumes across: `checkpoint_every` only says when the state is saved
# (train() runs the same steps in any chunks: tests/test_fit.py), and `materials_per_batch`
# which materials train together, each with its own weights, Adam state and data (a resumed
# run finishes the running group at its size, then takes groups of the new size). Both are
# speed keys (config/speed_keys.yaml).
RESUMABLE_ACROSS = ("checkpoint_every", "materials_per_batch")


def fingerprint(settings: FitSettings, seed: int, ids, init, kernel: str, bins, values) -> str:
    """Identifies a fitting job: the settings that change results, seed, sampling, kernel, the
    materials' ids and initial weights, and the data fitted (the bins and the values, hashed
    a material at a time: no copy of the shard); a checkpoint with another fingerprint is not
    resumed. The data count because a checkpoint outlives the config: after e.g. an
    `augmerl.pca_dims` change a shard holds other materials under the same ids."""
    cfg = {k: v for k, v in dataclasses.asdict(settings).items() if k not in RESUMABLE_ACROSS}
    h = hashlib.sha256(json.dumps([cfg, seed, SAMPLING_VERSION, kernel,
                                   list(np.shape(values))]).encode())
    h.update(np.asarray(ids, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(init, dtype=np.float32).tobytes())
    h.update(np.ascontiguousarray(bins, dtype=np.int64).tobytes())
    for v in values:
        h.update(np.ascontiguousarray(v, dtype=np.float32))
    return h.hexdigest()[:16]


def _resume_state(ck: Path, fp: str, keys) -> tuple[dict, dict | None, float] | None:
    """(finished groups' results, running group's state or None, seconds) from the checkpoint
    `ck`, or None (logged) where it belongs to another job or cannot be read: a checkpoint is no
    Snakemake output, so --rerun-incomplete never removes a damaged one, and failing on it would
    fail every rerun; the fit starts over and overwrites it."""
    try:
        with np.load(ck, allow_pickle=False) as z:
            if str(z["fingerprint"]) != fp:
                log.warning("%s: checkpoint of other settings/data, starting over", ck)
                return None
            done = {k: list(z[k]) for k in keys}
            running = {k[4:]: z[k] for k in z.files if k.startswith("run_")} or None
            return done, running, float(z["seconds"])
    except NPZ_ERRORS as e:
        log.warning("%s: unreadable fit checkpoint (%s: %s); starting over (the file is "
                    "overwritten at the next checkpoint)", ck, type(e).__name__, e)
        return None


def fit_many(values, bins, ids, init, settings: FitSettings, seed: int, device="cpu",
             checkpoint: str | Path | None = None) -> dict[str, np.ndarray]:
    """Fit all materials in groups of `materials_per_batch`, checkpointing to `checkpoint`.

    A killed run restarts from its last checkpoint (finished groups, and the running group's
    weights, Adam moments and step) when the settings (but `RESUMABLE_ACROSS`), seed, data,
    ids and init are unchanged; an unreadable checkpoint is logged and replaced.
    Returns ids, weights (n, 675) float32, train_loss, val_loss (n,), history_steps (k,),
    val_history (k, n), and the wall time."""
    ids = np.asarray(ids, dtype=np.int64)
    init = np.asarray(init, dtype=np.float32)
    init = np.broadcast_to(init, (len(ids), nbrdf.N_PARAMS)).copy()
    ck = Path(checkpoint) if checkpoint else None
    fp = fingerprint(settings, seed, ids, init, resolve_kernel(settings, device), bins, values)
    done = dict(weights=[], train_loss=[], val_loss=[], val_history=[])
    running, t_prev = None, 0.0
    resumed = _resume_state(ck, fp, list(done)) if ck and ck.exists() else None
    if resumed:
        done, running, t_prev = resumed
        log.info("%s: resuming, %d materials done%s", ck, len(done["weights"]),
                 f", group of {len(running['w'])} at step {int(running['step'])}"
                 if running else "")
    t0 = time.perf_counter()
    steps = None

    def save(fitter=None):
        if not ck:
            return
        extra = {f"run_{k}": v for k, v in fitter.state().items()} if fitter else {}
        _save_npz(ck, fingerprint=np.array(fp), seconds=np.float64(t_prev + time.perf_counter() - t0),
                  **{k: np.array(v) for k, v in done.items()}, **extra)

    s = len(done["weights"])
    while s < len(ids):
        # a running group from the checkpoint keeps its size (materials_per_batch may differ)
        sl = slice(s, min(s + (len(running["w"]) if running else settings.materials_per_batch),
                          len(ids)))
        log.info("materials %d-%d of %d", sl.start, sl.stop - 1, len(ids))
        f = fit(values[sl], bins, ids[sl], init[sl], settings, seed, device, on_checkpoint=save,
                state=running)
        running = None
        st = f.state()
        steps = st["history_steps"]
        done["weights"] += list(st["w"])
        done["train_loss"] += list(f.eval_loss("train"))
        done["val_loss"] += list(f.eval_loss("val"))
        done["val_history"] += list(st["history"].T)
        del f  # its targets, before the next group's are built
        save()
        s = sl.stop
    if steps is None:  # every group came from the checkpoint
        steps = np.array(sorted({*range(settings.eval_every, settings.steps + 1,
                                        settings.eval_every), settings.steps}), dtype=np.int64)
    return dict(ids=ids, weights=np.array(done["weights"], dtype=np.float32),
                train_loss=np.array(done["train_loss"]), val_loss=np.array(done["val_loss"]),
                history_steps=steps, val_history=np.array(done["val_history"]).T,
                seconds=np.float64(t_prev + time.perf_counter() - t0))


# Evaluation, results on disk, merging and plots live in their own modules; their names stay
# importable from here (`from neumat import fit; fit.load_fits(...)`).
from neumat.fit_eval import export_merl, psnr, render_psnr  # noqa: E402,F401
from neumat.fit_merge import load_fits, merge_fits, save_fits  # noqa: E402,F401
from neumat.fit_plots import plot_fit_quality  # noqa: E402,F401


def calibration_fitter(kernel: str, batch: int, activation: str, materials: int,
                       n_bins: int) -> "BatchFitter":
    """A BatchFitter on random targets for `fit_kernel.auto_choice` to time (half the bins for
    training: a few minibatches per epoch)."""
    rng = np.random.default_rng(0)
    bins = np.sort(rng.choice(merl.N_BINS, n_bins, replace=False))
    x, cos = bin_inputs(bins)
    target = torch.as_tensor(rng.random((materials, n_bins, 3), dtype=np.float32))
    s = dataclasses.replace(FitSettings(), batch=batch, activation=activation, kernel=kernel,
                            steps=10 ** 6, val_fraction=0.5)
    init = nbrdf.init_weights(materials, torch.Generator().manual_seed(0))
    return BatchFitter(x, cos, target, range(materials), init, s, seed=0)


fit_kernel.FITTER = calibration_fitter
