"""Triton kernels of `neumat.btf.query_triton` (kept apart: `triton.jit` functions resolve the
names they call as module globals, and this module imports triton, which CPU-only installs
lack)."""

import triton
import triton.language as tl


@triton.jit
def texels(px, py, H, W, WRAP: tl.constexpr):
    """The 4 bilinear taps of a plane (H, W, .) at (px, py) in [0, 1]^2: texel indices y * W + x
    of (x0, y0), (x1, y0), (x0, y1), (x1, y1) and the fractions fx, fy; as
    neumat.btf.neural.fetch (texel centres at (i + .5) / W, wrap or clamp)."""
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
    return y0 * W + x0, y0 * W + x1, y1 * W + x0, y1 * W + x1, fx, fy


@triton.jit
def interp(ptr, i00, i01, i10, i11, fx, fy, S, C: tl.constexpr, P: tl.constexpr, m):
    """(BLOCK, P) float32: channels 0 ... C - 1 of texels of S values (float32, or float16
    widened exactly), bilinearly weighted; the rest zero."""
    c = tl.arange(0, P)
    mc = m[:, None] & (c < C)[None, :]
    a = tl.load(ptr + i00[:, None] * S + c[None, :], mask=mc, other=0.0).to(tl.float32)
    b = tl.load(ptr + i01[:, None] * S + c[None, :], mask=mc, other=0.0).to(tl.float32)
    d = tl.load(ptr + i10[:, None] * S + c[None, :], mask=mc, other=0.0).to(tl.float32)
    e = tl.load(ptr + i11[:, None] * S + c[None, :], mask=mc, other=0.0).to(tl.float32)
    return (((1 - fx) * (1 - fy))[:, None] * a + (fx * (1 - fy))[:, None] * b
            + ((1 - fx) * fy)[:, None] * d + (fx * fy)[:, None] * e)


@triton.jit
def bilinear(ptr, px, py, H, W, C: tl.constexpr, P: tl.constexpr, WRAP: tl.constexpr, m):
    """(BLOCK, P) bilinear fetch of plane (H, W, C) at (px, py) in [0, 1]^2, channels
    >= C zero; as neumat.btf.neural.fetch."""
    i00, i01, i10, i11, fx, fy = texels(px, py, H, W, WRAP)
    return interp(ptr, i00, i01, i10, i11, fx, fy, C, C, P, m)

@triton.jit
def rows(ptr, R: tl.constexpr, K: tl.constexpr):
    """A (R, K) row-major block."""
    return tl.load(ptr + tl.arange(0, R)[:, None] * K + tl.arange(0, K)[None, :])


@triton.jit
def frame(wi_ptr, wo_ptr, q, m):
    """neumat.btf.directions.half_diff: the f_H and f_D plane coordinates of queries q."""
    ix = tl.load(wi_ptr + 3 * q, mask=m, other=0.0)
    iy = tl.load(wi_ptr + 3 * q + 1, mask=m, other=0.0)
    iz = tl.load(wi_ptr + 3 * q + 2, mask=m, other=1.0)
    ox = tl.load(wo_ptr + 3 * q, mask=m, other=0.0)
    oy = tl.load(wo_ptr + 3 * q + 1, mask=m, other=0.0)
    oz = tl.load(wo_ptr + 3 * q + 2, mask=m, other=1.0)
    # h = normalize(wi + wo), d = R_b(-theta_h) R_n(-phi_h) wi
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
    return (hx + 1) / 2, (hy + 1) / 2, (ct * rx - st * iz + 1) / 2, (ry + 1) / 2


@triton.jit
def mlp(fu, fh, fd, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr,
        q, m, PU: tl.constexpr, PD: tl.constexpr, HP: tl.constexpr, NH: tl.constexpr,
        RAW: tl.constexpr):
    """The MLP on the three feature blocks (layer 1 as three dots), stored as (N, 3) RGB, or
    log(1 + RGB) if RAW."""
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


@triton.jit
def decode(fu, hu, hv, du, dv, fh_ptr, fd_ptr, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr,
           bh_ptr, wl_ptr, bl_ptr, out_ptr, q, m, R, CD: tl.constexpr, PU: tl.constexpr,
           PD: tl.constexpr, HP: tl.constexpr, NH: tl.constexpr, RAW: tl.constexpr):
    """Queries q's RGB from their f_U features (BLOCK, PU) and their half/difference plane
    coordinates (`frame`): the f_H and f_D fetches, then the MLP (every kernel's end)."""
    fh = bilinear(fh_ptr, hu, hv, R, R, CD, PD, False, m)
    fd = bilinear(fd_ptr, du, dv, R, R, CD, PD, False, m)
    mlp(fu, fh, fd, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr,
        q, m, PU, PD, HP, NH, RAW)


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
    hu, hv, du, dv = frame(wi_ptr, wo_ptr, q, m)
    fu = bilinear(fu_ptr, ux, uy, HU, WU, CU, PU, True, m)
    decode(fu, hu, hv, du, dv, fh_ptr, fd_ptr, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr,
           bh_ptr, wl_ptr, bl_ptr, out_ptr, q, m, R, CD, PU, PD, HP, NH, RAW)


@triton.jit
def mix(x):
    """neumat.btf.synthesis.grid._mix on uint32 (wrapping multiplies)."""
    x = x ^ (x >> 16)
    x = x * 0x7FEB352D
    x = x ^ (x >> 15)
    x = x * 0x2C1B3C6D
    return x ^ (x >> 16)


@triton.jit
def triangle_grid(ux, uy):
    """grid.triangle_grid of float64 u: the cell's lower vertex (i0, i1) (int64), whether the
    point is in its upper triangle, the three barycentric weights and the skewed fractions
    (f0, f1) (float32)."""
    # float64 constants: a Python float in a kernel is an fp32 constant, whose rounding
    # (~1e-8) would move the grid by ~1e-3 at u = 1e5
    S3 = tl.full(ux.shape, 1.7320508075688772, tl.float64)
    stx = ux * (2 * S3)
    sty = uy * (2 * S3)
    return triangle_split(stx - sty / S3, 2 * sty / S3)


@triton.jit
def triangle_split(s0, s1):
    """triangle_grid from the skewed coordinates (s0, s1): floor, fractions and weights."""
    b0 = tl.floor(s0)
    b1 = tl.floor(s1)
    f0 = s0 - b0
    f1 = s1 - b1
    z = 1 - f0 - f1
    up = z > 0
    w0 = tl.where(up, z, -z).to(tl.float32)
    w1 = tl.where(up, f1, 1 - f1).to(tl.float32)
    w2 = tl.where(up, f0, 1 - f0).to(tl.float32)
    return b0.to(tl.int64), b1.to(tl.int64), up, w0, w1, w2, f0.to(tl.float32), f1.to(tl.float32)


@triton.jit
def hpb_frac32(u):
    """frac(u) of float64 u as uint32 2^-32 steps, rounded half to even (grid.wrap_fetch_coords;
    low32 in neumat/btf/query_kernel.c): 1.5 2^52 added leaves the rounded integer in the low
    bits. torch.remainder(u, 1) may round to 1, i.e. 2^32, which wraps to 0."""
    f = (u - tl.floor(u)) * 4294967296.0 + 6755399441055744.0
    return (f.to(tl.int64, bitcast=True) & 0xFFFFFFFF).to(tl.uint32)


@triton.jit
def queries_grid(u_ptr, hs_bits, N, BLOCK: tl.constexpr):
    """A program's queries q (mask m) and their triangle grid, as HPB and hex-tiling start:
    u float64, the cell's lower vertex (i0, i1) and dn (1 in its lower triangle: the vertices
    are (0,0), (0,1), (1,0) from it, or (1,1), (1,0), (0,1)), the weights, the skewed fractions
    (triangle_grid), frac(u) as uint32 (hpb_frac32) and the seed's hash as uint32."""
    q = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    m = q < N
    ux = tl.load(u_ptr + 2 * q, mask=m, other=0.0)  # float64
    uy = tl.load(u_ptr + 2 * q + 1, mask=m, other=0.0)
    i0, i1, up, w0, w1, w2, f0, f1 = triangle_grid(ux, uy)
    fx = hpb_frac32(ux)
    fy = hpb_frac32(uy)
    hs = hs_bits.to(tl.uint32, bitcast=True)
    dn = tl.where(up, 0, 1).to(tl.int64)
    return q, m, i0, i1, dn, w0, w1, w2, f0, f1, fx, fy, hs


@triton.jit
def widen(x, BLOCK: tl.constexpr, Q: tl.constexpr, P: tl.constexpr):
    """(BLOCK, Q) -> (BLOCK, P), Q <= P <= 4 Q: column i to column i P / Q, zeros between.
    tl.dot wants K >= 16, the planes have 8 channels: synthesis at 8 columns, then widened for
    layer 1, whose rows `query_triton` interleaves to match, does half the work of 16 padded
    columns."""
    if P >= 2 * Q:
        x = tl.reshape(tl.join(x, tl.full((BLOCK, Q), 0.0, x.dtype)), (BLOCK, 2 * Q))
    if P >= 4 * Q:
        x = tl.reshape(tl.join(x, tl.full((BLOCK, 2 * Q), 0.0, x.dtype)), (BLOCK, 4 * Q))
    return x


@triton.jit
def columns(m, C: tl.constexpr, Q: tl.constexpr):
    """The load mask of (BLOCK, Q) channel rows: queries m, channels < C (no column test where
    Q == C, which lets a texel's channels load as one vector)."""
    c = tl.arange(0, Q)
    if Q == C:
        return m[:, None] & (c >= 0)[None, :]
    return m[:, None] & (c < C)[None, :]


@triton.jit
def accumulate(acc, ptr, i00, i01, i10, i11, fx, fy, wk, C: tl.constexpr, Q: tl.constexpr, m):
    """acc (BLOCK, Q) + wk x the bilinear fetch of texels of C values (float32, or float16
    widened exactly), Q columns: a synthesis's tap with its blend weight wk folded into the
    four bilinear weights, so the taps sum into one accumulator."""
    c = tl.arange(0, Q)[None, :]
    mc = columns(m, C, Q)
    a = tl.load(ptr + i00[:, None] * C + c, mask=mc, other=0.0).to(tl.float32)
    b = tl.load(ptr + i01[:, None] * C + c, mask=mc, other=0.0).to(tl.float32)
    d = tl.load(ptr + i10[:, None] * C + c, mask=mc, other=0.0).to(tl.float32)
    e = tl.load(ptr + i11[:, None] * C + c, mask=mc, other=0.0).to(tl.float32)
    return (acc + ((1 - fx) * (1 - fy) * wk)[:, None] * a + (fx * (1 - fy) * wk)[:, None] * b
            + ((1 - fx) * fy * wk)[:, None] * d + (fx * fy * wk)[:, None] * e)


@triton.jit
def hpb_tap(acc, gauss_ptr, fx, fy, bx, by, hs, wk, H, W, C: tl.constexpr, Q: tl.constexpr, m):
    """acc + wk x the bilinear fetch of one triangle vertex (bx, by) (int64) of HPB, (BLOCK, Q):
    its hashed offset (grid.vertex_hash), the fetch position frac(frac(u) + offset) in 32-bit
    fixed point then float32 (grid.wrap_fetch_coords; fx, fy: frac(u) as uint32, hpb_frac32),
    and the Gaussianised plane's four texels, the vertex's blend weight wk folded into the
    bilinear weights (as query_kernel.c's hpb_taps: one accumulator, no per-tap rows)."""
    h = mix(by.to(tl.uint32) ^ mix(bx.to(tl.uint32) ^ hs))
    h = mix(h ^ tl.full(h.shape, 0x9E3779B1, tl.uint32))
    # uint32: the add wraps, modulo 1; one rounding to float32, then an exact scaling (the
    # same value as through float64, without its conversions: query_kernel.c grid_prepare)
    x = (h + fx).to(tl.float32) * 2.3283064365386963e-10  # 2^-32
    h = mix(h ^ tl.full(h.shape, 0x9E3779B2, tl.uint32))
    y = (h + fy).to(tl.float32) * 2.3283064365386963e-10
    top = 1.0 - 5.9604644775390625e-08  # 1 - 2^-24
    i00, i01, i10, i11, tx, ty = texels(tl.minimum(x, top), tl.minimum(y, top), H, W, True)
    return accumulate(acc, gauss_ptr, i00, i01, i10, i11, tx, ty, wk, C, Q, m)


@triton.jit
def triple_plane_hpb(u_ptr, wi_ptr, wo_ptr, gauss_ptr, lut_ptr, fh_ptr, fd_ptr, w1u_ptr,
                     w1h_ptr, w1d_ptr, b1_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr, N,
                     HG, WG, L, R, hs_bits, CU: tl.constexpr, CD: tl.constexpr,
                     PU: tl.constexpr, PD: tl.constexpr, QU: tl.constexpr, HP: tl.constexpr,
                     NH: tl.constexpr, RAW: tl.constexpr, BLOCK: tl.constexpr):
    """The query with f_U synthesised by histogram-preserving blending (neumat.btf.synthesis.hpb,
    its torch path `torch_features`): u float64, the triangle grid in float64, the integer vertex
    hash, three bilinear fetches of the Gaussianised plane at QU columns, the variance-preserving
    blend and the inverse LUT, widened to the PU rows of layer 1 (`widen`); the inverse PCA is
    folded into layer 1 by the caller. The blend and the LUT's scale ride on the bilinear
    weights, so the taps sum into one accumulator that is the LUT coordinate: on an H200, one
    frame, +16.8 and +17.0 % over the plain kernel before, +6.2 and +8.5 % after, with
    query_triton.LAUNCH's shape (benchmarks/btf_triton_stages.py, two runs, 2026-11-28)."""
    q, m, i0, i1, dn, w0, w1, w2, _, _, fx, fy, hs = queries_grid(u_ptr, hs_bits, N, BLOCK)
    # hpb.blend, G = sum_k (g_k - 0.5) w_k inv + 0.5 (inv = 1 / sqrt(sum w_k^2)), and the LUT's
    # coordinate x = L G - 0.5 as one sum: x = sum_k (L inv w_k) g_k + bias
    inv = 1.0 / tl.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    s = L * inv
    bias = L * 0.5 * (1 - inv * (w0 + w1 + w2)) - 0.5
    x = tl.full((BLOCK, QU), 0.0, tl.float32) + bias[:, None]
    x = hpb_tap(x, gauss_ptr, fx, fy, i0 + dn, i1 + dn, hs, w0 * s, HG, WG, CU, QU, m)
    x = hpb_tap(x, gauss_ptr, fx, fy, i0 + dn, i1 + 1 - dn, hs, w1 * s, HG, WG, CU, QU, m)
    x = hpb_tap(x, gauss_ptr, fx, fy, i0 + 1 - dn, i1 + dn, hs, w2 * s, HG, WG, CU, QU, m)
    # hpb.inverse_lut per channel (row c of the (C, L) table), linear, clamped at both ends
    # (G clamped to [0, 1] is x in [-0.5, L - 0.5], inside which [0, L - 1] is the clamp)
    x = tl.minimum(tl.maximum(x, 0.0), L - 1.0)
    k0 = tl.minimum(tl.floor(x).to(tl.int32), L - 2)
    mc = columns(m, CU, QU)
    base = lut_ptr + tl.arange(0, QU)[None, :] * L + k0
    a = tl.load(base, mask=mc, other=0.0)
    b = tl.load(base + 1, mask=mc, other=0.0)
    qf = widen(tl.where(mc, a + (x - k0.to(tl.float32)) * (b - a), 0.0), BLOCK, QU, PU)
    hu, hv, du, dv = frame(wi_ptr, wo_ptr, q, m)
    decode(qf, hu, hv, du, dv, fh_ptr, fd_ptr, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr,
           bh_ptr, wl_ptr, bl_ptr, out_ptr, q, m, R, CD, PU, PD, HP, NH, RAW)


@triton.jit
def sincos(a):
    """sin and cos of float32 a (|a| < 2^10) as plain arithmetic, as sincos_polyf in
    neumat/btf/query_kernel.c (a = n pi/2 + r with a two-part pi/2, Taylor to r^9 / r^10,
    then the quadrant): hex-tiling's angle comes in float32 from the hash's top 24 bits."""
    n = tl.floor(a * 0.63661977 + 0.5)
    r = (a - n * 1.5707964) + n * 4.371139e-08
    r2 = r * r
    sp = r * (1 + r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880)))))
    cp = 1 + r2 * (-0.5 + r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320 + r2 * (
        -1.0 / 3628800)))))
    k = (n - 4 * tl.floor(n * 0.25)).to(tl.int32)  # quadrant, 0 ... 3
    odd = (k & 1) != 0
    s0 = tl.where(odd, cp, sp)
    c0 = tl.where(odd, sp, cp)
    return tl.where((k & 2) != 0, -s0, s0), tl.where(((k + 1) & 2) != 0, -c0, c0)


@triton.jit
def fixed32(z):
    """float32 z (|z| < 1) as a 32-bit fixed-point fraction modulo 1 (uint32): 2 (int32)(z 2^31),
    as query_kernel.c's rxa, rya."""
    return (z * 2147483648.0).to(tl.int32).to(tl.uint32, bitcast=True) * 2


@triton.jit
def hex_tap(lum_ptr, fx, fy, e0, e1, bx, by, hs, rotation, H, W, m, LUM4: tl.constexpr):
    """One triangle vertex (bx, by) (int64) of hex-tiling, as the C kernel (query_kernel.c
    grid_prepare): its hashed offset and angle (grid.vertex_hash, k = 3); the patch rotated
    about the vertex centre c: with d = u - c, the fetch coordinate frac(offset + R d + frac(c))
    is frac(offset + frac(u) + (R d - d)), so the offset and frac(u) (fx, fy) add in 32-bit
    fixed point and only R d - d is float32, d from the skewed fractions less the vertex's
    corner (e0, e1), unskewed (grid.vertex_uv). Returns the bilinear taps (texels and
    fractions, as `texels`) and the luminance there, clamped to [0, 1] (BLOCK; the plane's is
    linear in the features, unclamped: query_triton._pack_hex); the features are fetched once the
    blend weights are known (`accumulate`). LUM4: the luminance plane holds each texel's 2 x 2
    wrapped neighbourhood (H, W, 4) (query_triton._pack_hex), so a tap's four values are one
    16-byte load, not four scattered 4-byte ones; else the plain (H, W) plane (the layout
    before, kept for benchmarks/btf_triton_stages.py's A/B). The same values either way."""
    h = mix(by.to(tl.uint32) ^ mix(bx.to(tl.uint32) ^ hs))
    hx = mix(h ^ tl.full(h.shape, 0x9E3779B1, tl.uint32))
    h0 = mix(hx ^ tl.full(h.shape, 0x9E3779B2, tl.uint32))
    ha = mix(h0 ^ tl.full(h.shape, 0x9E3779B3, tl.uint32))
    a = (6.2831855 * ((ha >> 8).to(tl.float32) * 5.9604644775390625e-08) - 3.1415927) * rotation
    sn, cs = sincos(a)
    dx = (e0 + 0.5 * e1) * 0.28867513459481287  # 1 / (2 sqrt 3)
    dy = e1 * 0.25  # (sqrt 3 / 2) / (2 sqrt 3)
    zx = (cs - 1) * dx - sn * dy
    zy = sn * dx + (cs - 1) * dy
    x = (hx + fx + fixed32(zx)).to(tl.float32) * 2.3283064365386963e-10  # 2^-32
    y = (h0 + fy + fixed32(zy)).to(tl.float32) * 2.3283064365386963e-10
    top = 1.0 - 5.9604644775390625e-08  # 1 - 2^-24
    i00, i01, i10, i11, tx, ty = texels(tl.minimum(x, top), tl.minimum(y, top), H, W, True)
    if LUM4:
        k = tl.arange(0, 4)
        v = tl.load(lum_ptr + i00[:, None] * 4 + k[None, :], mask=m[:, None] & (k >= 0)[None, :],
                    other=0.0)
        ad, be = tl.split(tl.reshape(v, (v.shape[0], 2, 2)))  # (x0, x1) of rows y0 and y1
        a, d = tl.split(ad)
        b, e = tl.split(be)
    else:
        a = tl.load(lum_ptr + i00, mask=m, other=0.0)
        b = tl.load(lum_ptr + i01, mask=m, other=0.0)
        d = tl.load(lum_ptr + i10, mask=m, other=0.0)
        e = tl.load(lum_ptr + i11, mask=m, other=0.0)
    lum = ((1 - tx) * (1 - ty)) * a + (tx * (1 - ty)) * b + ((1 - tx) * ty) * d + (tx * ty) * e
    return i00, i01, i10, i11, tx, ty, tl.minimum(tl.maximum(lum, 0.0), 1.0)


@triton.jit
def power(x, e, IE: tl.constexpr):
    """hextile._power: x^IE by repeated multiplication for a whole IE >= 0, else exp(e log x)
    (e > 0, the schema's bound: 0 at x = 0, without taking log 0)."""
    if IE >= 0:
        out = tl.full(x.shape, 1.0, tl.float32)
        for _ in tl.static_range(IE):
            out = out * x
    else:
        out = tl.where(x > 0, tl.exp(e * tl.log(tl.maximum(x, 1e-30))), 0.0)
    return out


@triton.jit
def gain3(x, k):
    """hextile.gain3's per-weight gain (before its renormalisation). Its power is floored as
    hextile.POW_FLOOR's, one binade higher (2^-125), so that 0.25 m p stays a normal float
    where a GPU flushes subnormals: where all three weights are 0 (hextile's docstring) they
    still come out 1/3 each; elsewhere a floored weight is invisible beside the others."""
    s = tl.where(x >= 0.5, 2.0, 0.0)
    m = 2.0 * (1 - s)
    p = tl.maximum(tl.exp(k * tl.log(tl.maximum(s + x * m, 1e-30))), 2.3509887e-38)
    return 0.5 * s + 0.25 * m * p


@triton.jit
def hex_weights(w0, w1, w2, l0, l1, l2, contrast, exponent, gain_k, IE: tl.constexpr,
                GAIN: tl.constexpr):
    """hextile's blend weights of three vertices: W_i = (1 + contrast (lum_i - 1))
    w_i^exponent, normalised, then gain3 and normalised again (unless GAIN is off)."""
    v0 = (1 + contrast * (l0 - 1)) * power(w0, exponent, IE)
    v1 = (1 + contrast * (l1 - 1)) * power(w1, exponent, IE)
    v2 = (1 + contrast * (l2 - 1)) * power(w2, exponent, IE)
    tot = tl.maximum(v0 + v1 + v2, 1e-30)
    v0 = v0 / tot
    v1 = v1 / tot
    v2 = v2 / tot
    if GAIN:
        v0 = gain3(v0, gain_k)
        v1 = gain3(v1, gain_k)
        v2 = gain3(v2, gain_k)
        tot = v0 + v1 + v2
        v0 = v0 / tot
        v1 = v1 / tot
        v2 = v2 / tot
    return v0, v1, v2


@triton.jit
def triple_plane_hex(u_ptr, wi_ptr, wo_ptr, plane_ptr, lum_ptr, fh_ptr, fd_ptr, w1u_ptr, w1h_ptr,
                     w1d_ptr, b1_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr, N, HP_, WP_, R,
                     hs_bits, rotation, contrast, exponent, gain_k,
                     CU: tl.constexpr, CD: tl.constexpr, PU: tl.constexpr, PD: tl.constexpr,
                     QU: tl.constexpr, HP: tl.constexpr, NH: tl.constexpr, IE: tl.constexpr,
                     GAIN: tl.constexpr, RAW: tl.constexpr, BLOCK: tl.constexpr,
                     LUM4: tl.constexpr = True):
    """The query with f_U synthesised by hex-tiling (neumat.btf.synthesis.hextile, its torch
    path `HexTile.__call__`; the arithmetic of the C kernel's btf_triple_plane_hex): u float64,
    the triangle grid in float64, per vertex the integer hash, the rotation (float32, about the
    vertex, in fixed point as HPB's fetch coordinate) and the bilinear fetch of the luminance
    plane (LUM4: (H, W, 4), each texel's 2 x 2 neighbourhood; `hex_tap`), then the
    luminance-weighted, contrast-sharpened blend weights, and only then the (H, W, CU)
    feature plane's taps at QU columns, each weight folded into its
    bilinear weights (one accumulator, as HPB's), widened to layer 1's PU rows. On an H200
    (README, "Running on Slurm or a GPU"): float32 in place of float64 for the rotation,
    +22.6 -> +14.4 to +14.8 % over the plain kernel; the one accumulator, +16.5 -> +13.6 %
    (benchmarks/btf_triton_stages.py, one run, 2026-11-28); the luminance's 2 x 2
    neighbourhood in one load (LUM4), +10.8 to +12.0 -> +7.9 to +10.2 % (the same, four runs,
    2026-11-29)."""
    q, m, i0, i1, dn, w0, w1, w2, f0, f1, fx, fy, hs = queries_grid(u_ptr, hs_bits, N, BLOCK)
    dnf = dn.to(tl.float32)
    a00, a01, a10, a11, ax, ay, l0 = hex_tap(lum_ptr, fx, fy, f0 - dnf, f1 - dnf, i0 + dn,
                                             i1 + dn, hs, rotation, HP_, WP_, m, LUM4)
    b00, b01, b10, b11, bx, by, l1 = hex_tap(lum_ptr, fx, fy, f0 - dnf, f1 - (1 - dnf), i0 + dn,
                                             i1 + 1 - dn, hs, rotation, HP_, WP_, m, LUM4)
    c00, c01, c10, c11, cx, cy, l2 = hex_tap(lum_ptr, fx, fy, f0 - (1 - dnf), f1 - dnf,
                                             i0 + 1 - dn, i1 + dn, hs, rotation, HP_, WP_, m,
                                             LUM4)
    v0, v1, v2 = hex_weights(w0, w1, w2, l0, l1, l2, contrast, exponent, gain_k, IE, GAIN)
    fu = tl.full((BLOCK, QU), 0.0, tl.float32)
    fu = accumulate(fu, plane_ptr, a00, a01, a10, a11, ax, ay, v0, CU, QU, m)
    fu = accumulate(fu, plane_ptr, b00, b01, b10, b11, bx, by, v1, CU, QU, m)
    fu = accumulate(fu, plane_ptr, c00, c01, c10, c11, cx, cy, v2, CU, QU, m)
    fu = widen(fu, BLOCK, QU, PU)
    hu, hv, du, dv = frame(wi_ptr, wo_ptr, q, m)
    decode(fu, hu, hv, du, dv, fh_ptr, fd_ptr, w1u_ptr, w1h_ptr, w1d_ptr, b1_ptr, wh_ptr,
           bh_ptr, wl_ptr, bl_ptr, out_ptr, q, m, R, CD, PU, PD, HP, NH, RAW)
