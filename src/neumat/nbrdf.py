"""The NBRDF neural field (Sztrajman et al. 2021) used throughout M3ashy.

MLP 6 -> 21 -> 21 -> 3 (675 parameters). Input: [h_xyz (phi_h = 0), d_xyz]; output:
max(exp(x) - 1, 0) = physical BRDF per RGB channel.

Flatten order (the diffusion model's input format, fixed forever):
    [W1 (21x6), b1 (21), W2 (21x21), b2 (21), W3 (3x21), b3 (3)]
each weight row-major as (out, in), i.e. torch.nn.Linear's `weight` layout. Keras kernels
(in, out) must be transposed.

Every function takes a *batch* of weight vectors (B, 675), so many materials are evaluated
in one batched matmul.
"""

from __future__ import annotations

import numpy as np
import torch

LAYERS = [(6, 21), (21, 21), (21, 3)]  # (in, out)
PARAM_SHAPES = [s for i, o in LAYERS for s in ((o, i), (o,))]
PARAM_NAMES = ["W1", "b1", "W2", "b2", "W3", "b3"]
N_PARAMS = sum(int(np.prod(s)) for s in PARAM_SHAPES)  # 675
ACTIVATIONS = ("relu", "leaky_relu")


def unflatten(w: torch.Tensor) -> list[torch.Tensor]:
    """(B, 675) -> [W1 (B,21,6), b1 (B,21), W2, b2, W3, b3] views."""
    if w.shape[-1] != N_PARAMS:
        raise ValueError(f"NBRDF weight vectors have {N_PARAMS} entries, got {w.shape[-1]}")
    out, k = [], 0
    for shape in PARAM_SHAPES:
        n = int(np.prod(shape))
        out.append(w[..., k:k + n].reshape(*w.shape[:-1], *shape))
        k += n
    return out


def flatten(params: list[torch.Tensor]) -> torch.Tensor:
    """Inverse of `unflatten`: list of (B, *shape) tensors -> (B, 675)."""
    b = params[0].shape[0]
    return torch.cat([p.reshape(b, -1) for p in params], -1)


def _act(x, activation):
    if activation == "relu":
        return torch.relu(x)
    if activation == "leaky_relu":
        return torch.nn.functional.leaky_relu(x, 0.01)
    raise ValueError(f"unknown activation {activation!r}; choose from {ACTIVATIONS}")


def forward_raw(w: torch.Tensor, x: torch.Tensor, activation: str = "relu") -> torch.Tensor:
    """Pre-output-activation value. w (B, 675), x (B, N, 6) or (N, 6) -> (B, N, 3); for
    shared inputs (N, 6) computed channel-major (`forward_raw_channels`) and returned as a
    transposed view."""
    if x.dim() == 2:  # shared inputs for all materials
        return forward_raw_channels(w, x.t(), activation).transpose(1, 2)
    W1, b1, W2, b2, W3, b3 = unflatten(w)
    h = _act(torch.bmm(x, W1.transpose(1, 2)) + b1[:, None], activation)
    h = _act(torch.baddbmm(b2[:, None], h, W2.transpose(1, 2)), activation)
    return torch.baddbmm(b3[:, None], h, W3.transpose(1, 2))


def forward_raw_channels(w: torch.Tensor, xt: torch.Tensor,
                         activation: str = "relu") -> torch.Tensor:
    """`forward_raw` channel-major: w (B, 675), xt (6, N) shared inputs -> (B, 3, N). Each
    layer is W @ H, (out, in) x (in, N), the long dimension last, where the matmul kernels run
    faster than on (N, in) x (in, out): a forward pass 1.65x (1 field x 2^15 inputs) and 1.85x
    (8 x 2^12), the clamp-aware step's penalty gradient (32 fields x 4096 directions, forward
    and backward) 1.31x on one thread; 1.23x, 1.64x and 1.44x on two; with MKL, oneDNN and
    ATen held to AVX2 1.70x, 1.70x and 1.34x (benchmarks/nbrdf_layout.py, AMD EPYC AVX-512,
    2026-11-26). The same values as row-major to float32 rounding."""
    W1, b1, W2, b2, W3, b3 = unflatten(w)
    h = _act(torch.matmul(W1, xt) + b1[..., None], activation)
    h = _act(torch.baddbmm(b2[..., None], W2, h), activation)
    return torch.baddbmm(b3[..., None], W3, h)


def forward(w: torch.Tensor, x: torch.Tensor, activation: str = "relu") -> torch.Tensor:
    """Physical BRDF values (B, N, 3) = max(exp(raw) - 1, 0)."""
    return torch.relu(torch.expm1(forward_raw(w, x, activation)))


def forward_channels(w: torch.Tensor, xt: torch.Tensor, activation: str = "relu") -> torch.Tensor:
    """`forward` channel-major: w (B, 675), xt (6, N) shared inputs -> (B, 3, N) physical BRDF
    values, the layout of a MERL file (`evaluate_grid`)."""
    return torch.relu(torch.expm1(forward_raw_channels(w, xt, activation)))


def init_weights(n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """(n, 675) weights with torch.nn.Linear's default init (Kaiming-uniform, a = sqrt(5))."""
    parts = []
    for fan_in, fan_out in LAYERS:
        bound = 1.0 / np.sqrt(fan_in)
        parts.append((torch.rand(n, fan_out * fan_in, generator=generator) * 2 - 1) * bound)
        parts.append((torch.rand(n, fan_out, generator=generator) * 2 - 1) * bound)
    return torch.cat(parts, -1)


def materials_per_pass(n_points: int) -> int:
    """Materials per NBRDF pass over `n_points` shared inputs: about 2^15 points in all, so the
    hidden activations (21 floats a point) stay in cache and the allocator reuses them instead
    of mapping and zeroing fresh pages every pass. 64 materials a pass took about 4x as long at
    20,000-53,000 points (benchmarks/plausibility.py; AMD EPYC AVX-512, 2026-11-26)."""
    return max(1, (1 << 15) // max(1, n_points))


def evaluate_grid(w: torch.Tensor, activation: str = "relu", chunk: int | None = None,
                  device: str | torch.device = "cpu") -> np.ndarray:
    """Evaluate fields on the full MERL grid -> (B, 3, 90, 90, 180) float64 physical BRDF.

    Only the valid (above-horizon) bins are evaluated (1,096,216 of 1,458,000), by
    `forward_channels`; the others are -1/scale like measured MERL files (negative = invalid).
    Against row-major layers at every bin (the version before): 2.04x for one table, 2.20x
    for 8 (one thread; 2 threads 1.44x and 1.71x; benchmarks/merl_export.py, AMD EPYC
    AVX-512, 2026-11-26).
    `chunk` bins at a time; on the CPU by default 2^15 / B rounded down to a power of two (at
    least 1024), so a chunk's activations stay in cache and the allocator reuses them. With
    2^18 bins each chunk mapped and zeroed fresh pages: one table took 1.10-1.25x and a batch
    of 8 3.9-4.2x as long (row-major layers then; merl_export.py before 52ebb93, 2026-11-26).
    The values do not depend on the chunk size (power-of-two chunks, on this machine:
    tests/test_merl_io.py)."""
    from neumat.io import merl

    grid = merl.valid_grid_inputs_t()
    w = w.to(device=device, dtype=torch.float32)
    if not chunk:  # a GPU wants large launches; cache sizes matter on the CPU
        # a power of two: matmul kernels are chosen by size, and a chunk of 10922 bins (2^15 / 3)
        # moved values by float32 rounding (up to 7e-7 near 2) where every power of two from
        # 2^10 to 2^18 gave the same bits (tests/test_merl_io.py)
        per = (1 << 15) // max(1, w.shape[0])
        chunk = 1 << 18 if w.device.type != "cpu" else 1 << max(10, per.bit_length() - 1)
    valid = np.empty((w.shape[0], 3, grid.shape[1]), dtype=np.float32)
    with torch.no_grad():
        for s in range(0, grid.shape[1], chunk):
            # a writable copy of the chunk (torch warns on the shared read-only array)
            x = torch.from_numpy(grid[:, s:s + chunk].copy()).to(device)
            valid[:, :, s:s + chunk] = forward_channels(w, x, activation).cpu().numpy()
    # channel-major as the file, so the reshape below copies nothing
    out = np.empty((w.shape[0], 3, merl.N_BINS), dtype=np.float64)
    mask = merl.valid_mask()
    for table, values in zip(out, valid):
        for row, v, scale in zip(table, values, merl.SCALE):
            row.fill(-1.0 * scale)
            np.place(row, mask, v)  # the valid bins, in file order
    return out.reshape(w.shape[0], *merl.SHAPE)
