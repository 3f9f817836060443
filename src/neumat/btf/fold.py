"""HPB's inverse PCA folded into a Triple Plane's first layer: the fused queries (the C one,
`neumat.btf.query`, and the Triton one, `neumat.btf.query_triton`) then feed the layer HPB's
decorrelated q in place of f_U and skip the C x C rotation per query. `check_lut`: the LUT
shape both kernels need (here, not in `query`, which imports `query_triton`)."""

from __future__ import annotations

import torch


def fold_pca(W1: torch.Tensor, b1: torch.Tensor, cu: int, mean, basis):
    """First layer taking HPB's decorrelated q in place of f_U = mean + basis q:
    W1[:, :cu] basis and b1 + W1[:, :cu] mean (in float64, then float32, on W1's device).
    numpy on the CPU, because torch's float64 matmul starts its OpenMP threads for these tiny
    matrices on every call."""
    f64 = lambda t: t.detach().cpu().double().numpy()
    W = f64(W1).copy()
    wu = W[:, :cu].copy()
    W[:, :cu] = wu @ f64(basis)
    b = f64(b1) + wu @ f64(mean)
    return torch.from_numpy(W).float().to(W1.device), torch.from_numpy(b).float().to(W1.device)


def check_lut(lut: torch.Tensor, channels: int) -> None:
    """HPB's inverse LUT must be (channels, L) with L >= 2 (the kernel interpolates entry k
    with k + 1: L = 1 reads before the row, L = 0 crashes); ValueError otherwise."""
    if lut.dim() != 2 or lut.shape[0] != channels or lut.shape[1] < 2:
        raise ValueError(f"HPB's inverse LUT must be ({channels}, L) with L >= 2 entries "
                         f"(setting lut_size), got shape {tuple(lut.shape)}")
