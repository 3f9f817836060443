"""The equilateral triangle grid shared by histogram-preserving blending and hex-tiling, and
the integer vertex hash that makes both a pure function of (u, seed) at any u.

Grid (Heitz & Neyret 2018; Mikkelsen 2022, hextiling.h `TriangleGrid`): st = 2 sqrt(3) u is
skewed by s = (st.x - st.y / sqrt(3), 2 st.y / sqrt(3)) (the GLSL column-major
mat2(1, 0, -1/sqrt(3), 2/sqrt(3)); its unskew maps the lattice axes to (1, 0) and (1/2,
sqrt(3)/2), unit vectors 60 deg apart, so triangles are equilateral with side 1 / (2 sqrt(3))
of the exemplar). b = floor(s), f = s - b, z = 1 - f.x - f.y; z > 0: weights (z, f.y, f.x) at
b, b + (0, 1), b + (1, 0); else (-z, 1 - f.y, 1 - f.x) at b + (1, 1), b + (1, 0), b + (0, 1).

Precision: the reference shaders hash vertices with frac(sin(v . k) * 43758.5453) in float32,
which at u = 1e5 (vertices ~3.5e5) has no fractional digits left and every neighbourhood
collapses to a few offsets. Here u is float64, vertices are int64 and the hash is integer
arithmetic (exact for any |vertex| < 2^31); the local fetch coordinate is formed from frac(u)
in float64 and the hash in 32-bit fixed point before it is rounded to float32."""

from __future__ import annotations

import math

import torch

SQRT3 = math.sqrt(3.0)
_M32 = 0xFFFFFFFF


def triangle_grid(u: torch.Tensor):
    """u (N, 2) (any float, computed in float64) -> vertices (N, 3, 2) int64, weights (N, 3)
    float64 (non-negative, summing to 1)."""
    st = u.double() * (2 * SQRT3)
    s = torch.stack([st[:, 0] - st[:, 1] / SQRT3, 2 * st[:, 1] / SQRT3], -1)
    b = torch.floor(s)
    f = s - b
    b = b.long()
    z = 1 - f[:, 0] - f[:, 1]
    up = (z > 0)[:, None]
    w = torch.where(up, torch.stack([z, f[:, 1], f[:, 0]], -1),
                    torch.stack([-z, 1 - f[:, 1], 1 - f[:, 0]], -1))
    e = torch.tensor([[0, 0], [0, 1], [1, 0]], device=u.device)
    o = torch.tensor([[1, 1], [1, 0], [0, 1]], device=u.device)
    v = b[:, None, :] + torch.where(up[:, :, None], e, o)
    return v, w


def vertex_uv(v: torch.Tensor) -> torch.Tensor:
    """Texture-space position (float64) of integer grid vertices (..., 2): the unskew."""
    v = v.double()
    return torch.stack([v[..., 0] + v[..., 1] / 2, v[..., 1] * (SQRT3 / 2)], -1) / (2 * SQRT3)


def _mix(x: torch.Tensor) -> torch.Tensor:
    """32-bit integer finaliser (xor-shift-multiply, constants < 2^31 so int64 never
    overflows); x int64 in [0, 2^32)."""
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & _M32
    x = x ^ (x >> 15)
    x = (x * 0x2C1B3C6D) & _M32
    return x ^ (x >> 16)


def vertex_hash(v: torch.Tensor, seed: int, k: int = 2) -> torch.Tensor:
    """k uniform numbers in [0, 1) (float64) per integer vertex v (..., 2): a pure function
    of (vertex, seed), exact for any int64 vertex (uses its low 32 bits per axis)."""
    s = _mix(torch.full_like(v[..., 0], int(seed) & _M32))
    h = _mix((v[..., 1] & _M32) ^ _mix((v[..., 0] & _M32) ^ s))
    outs = []
    for i in range(k):
        h = _mix(h ^ (0x9E3779B1 + i))
        outs.append(h.double() / 2.0 ** 32)
    return torch.stack(outs, -1)


def wrap_fetch_coords(u: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """frac(u + offset) for u (N, 2) and offsets (N, K, 2) (vertex_hash's, multiples of 2^-32),
    returned as float32 (N, K, 2) in [0, 1). Formed in 32-bit fixed point: frac(u), taken in
    float64 so large u keeps its sub-texel position, rounded to a multiple of 2^-32 (half to
    even) and added to the offset modulo 1, then rounded once to float32. The fused kernels
    (neumat/btf/query_kernel.c, neumat.btf.triton_kernels) do the same integer add, so all
    three agree to the bit here; it is within 2^-32 of the float64 sum."""
    scale = 2.0 ** 32
    f = torch.round(torch.remainder(u.double(), 1.0) * scale).long()
    xy = ((f[:, None, :] + (offset * scale).long()) & _M32).double() / scale
    return xy.float().clamp_(0.0, 1.0 - 2 ** -24)
