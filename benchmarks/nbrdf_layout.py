"""NBRDF layers channel-major (`nbrdf.forward_raw` on shared inputs, since 2026-11-26: W @ H,
the N inputs last) against row-major (H @ W^T, the N inputs first: the version before, the
baseline, in the same run), on the passes the workflow runs most: a forward pass at 2^15
shared inputs for 1 field and at 2^12 for 8 (MERL export, metrics, renders), and a forward and backward
pass at 4096 directions for 32 fields (the clamp-aware constraint at every DDIM step, and each
step of the clamp refit). Prints ms per call (best of --repeat), the ratio, the largest
difference of the values (float32 rounding), and the matmuls' rate as a fraction of this
machine's fp32 sgemm rate (2048^3, measured in the same run), with the ISA and the CPU model.

    OMP_NUM_THREADS=1 python benchmarks/nbrdf_layout.py [--repeat 20]
"""

from __future__ import annotations

import argparse

import torch

from constraint_step import best_ms  # this directory
from neumat import machine, nbrdf
from neumat.diffusion import constraints

FLOP_PER_INPUT = 2 * sum(i * o for i, o in nbrdf.LAYERS)  # the matmuls' multiply-adds


def row_major(w: torch.Tensor, x: torch.Tensor, activation: str = "relu") -> torch.Tensor:
    """The baseline: forward_raw before 2026-11-26 for shared inputs x (N, 6) -> (B, N, 3)."""
    W1, b1, W2, b2, W3, b3 = nbrdf.unflatten(w)
    h = nbrdf._act(torch.einsum("nk,bok->bno", x, W1) + b1[:, None], activation)
    h = nbrdf._act(torch.baddbmm(b2[:, None], h, W2.transpose(1, 2)), activation)
    return torch.baddbmm(b3[:, None], h, W3.transpose(1, 2))


def forward_only(f, w, x):
    with torch.no_grad():
        return f(w, x)


def forward_backward(f, w, x):
    """The constraint's penalty gradient (constraints.negative_penalty with layers `f`)."""
    p = w.clone().requires_grad_(True)
    pen = torch.relu(-f(p, x)).flatten(1).mean(1).sum()
    return torch.autograd.grad(pen, p)[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=20)
    a = ap.parse_args()
    peak = machine.sgemm_peak()[0]
    print(f"machine: {machine.describe()}; torch threads {torch.get_num_threads()}, "
          f"fp32 sgemm {peak / 1e9:.0f} GFLOP/s")
    print(f"{'pass':40s} {'row-major ms':>12s} {'channel ms':>10s} {'speed-up':>8s} "
          f"{'of sgemm':>8s} {'max diff':>9s}")
    gen = torch.Generator().manual_seed(0)
    cases = [("forward, 1 field x 2^15 inputs", forward_only, 1, 1 << 15, 1),
             ("forward, 8 fields x 2^12 inputs", forward_only, 8, 1 << 12, 1),
             ("forward+backward, 32 fields x 4096", forward_backward, 32, 4096, 3)]
    for name, kind, b, n, passes in cases:
        w = nbrdf.init_weights(b, gen) * 2
        x = constraints.constraint_directions(7, n)
        base = best_ms(lambda: kind(row_major, w, x), a.repeat)
        new = best_ms(lambda: kind(nbrdf.forward_raw, w, x), a.repeat)
        diff = (kind(row_major, w, x) - kind(nbrdf.forward_raw, w, x)).abs().max().item()
        rate = passes * b * n * FLOP_PER_INPUT / (new * 1e-3) / peak
        print(f"{name:40s} {base:12.2f} {new:10.2f} {base / new:7.2f}x {rate:8.1%} {diff:9.1e}")


if __name__ == "__main__":
    main()
