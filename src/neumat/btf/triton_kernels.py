"""Triton kernels of `neumat.btf.query_triton` (kept apart: `triton.jit` functions resolve the
names they call as module globals, and this module imports triton, which CPU-only installs
lack)."""

import triton
import triton.language as tl


@triton.jit
def bilinear(ptr, px, py, H, W, C: tl.constexpr, P: tl.constexpr, WRAP: tl.constexpr, m):
    """(BLOCK, P) bilinear fetch of plane (H, W, C) at (px, py) in [0, 1]^2, channels
    >= C zero; as neumat.btf.neural.fetch (texel centres at (i + .5) / W, wrap or clamp)."""
    x = px * W - 0.5
    y = py * H - 0.5
    if not WRAP:
        x = tl.minimum(tl.maximum(x, 0.0), W - 1.0)
        y = tl.minimum(tl.maximum(y, 0.0), H - 1.0)
    x0f = tl.floor(x)
    y0f = tl.floor(y)
    fx = x - x0f
    fy = y - y0f
    x0 = x0f.to(tl.int32)
    y0 = y0f.to(tl.int32)
    if WRAP:  # a floor modulo whatever `%` does with negatives (C on the GPU)
        x0 = x0 % W
        x0 = tl.where(x0 < 0, x0 + W, x0)
        y0 = y0 % H
        y0 = tl.where(y0 < 0, y0 + H, y0)
        x1 = tl.where(x0 + 1 == W, 0, x0 + 1)
        y1 = tl.where(y0 + 1 == H, 0, y0 + 1)
    else:
        x1 = tl.minimum(x0 + 1, W - 1)
        y1 = tl.minimum(y0 + 1, H - 1)
    c = tl.arange(0, P)
    mc = m[:, None] & (c < C)[None, :]
    a = tl.load(ptr + (y0 * W + x0)[:, None] * C + c[None, :], mask=mc, other=0.0)
    b = tl.load(ptr + (y0 * W + x1)[:, None] * C + c[None, :], mask=mc, other=0.0)
    d = tl.load(ptr + (y1 * W + x0)[:, None] * C + c[None, :], mask=mc, other=0.0)
    e = tl.load(ptr + (y1 * W + x1)[:, None] * C + c[None, :], mask=mc, other=0.0)
    return (((1 - fx) * (1 - fy))[:, None] * a + (fx * (1 - fy))[:, None] * b
            + ((1 - fx) * fy)[:, None] * d + (fx * fy)[:, None] * e)

@triton.jit
def rows(ptr, R: tl.constexpr, K: tl.constexpr):
    """A (R, K) row-major block."""
    return tl.load(ptr + tl.arange(0, R)[:, None] * K + tl.arange(0, K)[None, :])

@triton.jit
def triple_plane(u_ptr, wi_ptr, wo_ptr, fu_ptr, fh_ptr, fd_ptr, w1u_ptr, w1h_ptr, w1d_ptr,
                 b1_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr, N, HU, WU, R,
                 CU: tl.constexpr, CD: tl.constexpr, PU: tl.constexpr, PD: tl.constexpr,
                 HP: tl.constexpr, NH: tl.constexpr, RAW: tl.constexpr,
                 BLOCK: tl.constexpr):
    q = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = q < N
    ux = tl.load(u_ptr + 2 * q, mask=m, other=0.0)
    uy = tl.load(u_ptr + 2 * q + 1, mask=m, other=0.0)
    ix = tl.load(wi_ptr + 3 * q, mask=m, other=0.0)
    iy = tl.load(wi_ptr + 3 * q + 1, mask=m, other=0.0)
    iz = tl.load(wi_ptr + 3 * q + 2, mask=m, other=1.0)
    ox = tl.load(wo_ptr + 3 * q, mask=m, other=0.0)
    oy = tl.load(wo_ptr + 3 * q + 1, mask=m, other=0.0)
    oz = tl.load(wo_ptr + 3 * q + 2, mask=m, other=1.0)
    # neumat.btf.directions.half_diff: h = normalize(wi + wo), d = R_b(-th) R_n(-ph) wi
    sx = ix + ox
    sy = iy + oy
    sz = iz + oz
    nrm = tl.maximum(tl.sqrt(sx * sx + sy * sy + sz * sz), 1e-12)
    hx = sx / nrm
    hy = sy / nrm
    ct = tl.minimum(tl.maximum(sz / nrm, -1.0), 1.0)
    st = tl.sqrt(hx * hx + hy * hy)
    big = st > 1e-8
    sc = tl.maximum(st, 1e-8)
    cp = tl.where(big, hx / sc, 1.0)
    sp = tl.where(big, hy / sc, 0.0)
    rx = cp * ix + sp * iy
    ry = -sp * ix + cp * iy
    fu = bilinear(fu_ptr, ux, uy, HU, WU, CU, PU, True, m)
    fh = bilinear(fh_ptr, (hx + 1) / 2, (hy + 1) / 2, R, R, CD, PD, False, m)
    fd = bilinear(fd_ptr, (ct * rx - st * iz + 1) / 2, (ry + 1) / 2, R, R, CD, PD, False, m)
    x = (tl.dot(fu, rows(w1u_ptr, PU, HP), input_precision="ieee")
         + tl.dot(fh, rows(w1h_ptr, PD, HP), input_precision="ieee")
         + tl.dot(fd, rows(w1d_ptr, PD, HP), input_precision="ieee")
         + tl.load(b1_ptr + tl.arange(0, HP))[None, :])
    x = tl.maximum(x, 0.0)
    for i in tl.static_range(NH):
        x = tl.dot(x, rows(wh_ptr + i * HP * HP, HP, HP), input_precision="ieee")
        x = tl.maximum(x + tl.load(bh_ptr + i * HP + tl.arange(0, HP))[None, :], 0.0)
    y = (tl.dot(x, rows(wl_ptr, HP, 16), input_precision="ieee")
         + tl.load(bl_ptr + tl.arange(0, 16))[None, :])
    if not RAW:  # relu(expm1(y)); exp - 1 loses at most ~1e-7 absolute near 0
        y = tl.maximum(tl.exp(y) - 1.0, 0.0)
    k = tl.arange(0, 16)
    tl.store(out_ptr + 3 * q[:, None] + k[None, :], y, mask=m[:, None] & (k < 3)[None, :])
