"""DFMF reader / writer: round trips, random access, colour models, errors."""

import struct

import numpy as np
import pytest

from neumat.btf.directions import ubo2014_angles
from neumat.io import dfmf

ANG = ubo2014_angles()[:7]  # 7 views x 7 lights keep the files tiny


def _factors(rng, w, h, k, n=len(ANG)):
    U = [rng.standard_normal((n * n, k)).astype(np.float32) * 0.3 for _ in range(3)]
    SV = [rng.standard_normal((w * h, k)).astype(np.float32) * 0.3 for _ in range(3)]
    return U, SV


def _dense(U, SV, model):
    raw = np.stack([u @ s.T for u, s in zip(U, SV)], -1)          # (rows, texels, 3)
    return dfmf.to_rgb(raw, model)


@pytest.mark.parametrize("scalar,model", [(2, 11), (4, 11), (4, 0), (8, 0)])
def test_round_trip_random_access(tmp_path, scalar, model):
    rng = np.random.default_rng(0)
    w, h, k = 5, 4, 3
    U, SV = _factors(rng, w, h, k)
    p = tmp_path / "x.btf"
    dfmf.write_dfmf(p, U, SV, ANG, ANG, w, h, color_model=model, scalar=scalar)
    b = dfmf.DFMF(p)
    assert (b.width, b.height, b.n_lights, b.n_views) == (w, h, 7, 7)
    np.testing.assert_allclose(b.header.views, ANG)
    dt = dfmf.SCALARS[scalar]
    ref = _dense([u.astype(dt) for u in U], [s.astype(dt) for s in SV], model)
    t = rng.integers(0, w * h, 50)
    l = rng.integers(0, 7, 50)
    v = rng.integers(0, 7, 50)
    got = b.decode(t, l, v)
    want = ref[v * 7 + l, t]                                      # row = view * L + light
    np.testing.assert_allclose(got, want, rtol=2e-3 if scalar == 2 else 1e-5, atol=1e-5)
    # texel index is y * width + x: image() is the reshaped texel row
    np.testing.assert_allclose(b.image(2, 3), ref[3 * 7 + 2].reshape(h, w, 3), rtol=2e-3, atol=1e-5)


def test_colour_model_11_inverse():
    rgb = np.array([[0.2, 0.5, 0.1], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.03, 0.01, 0.2]])
    back = dfmf.to_rgb(dfmf.from_rgb(rgb, 11), 11)
    np.testing.assert_allclose(back, rgb, atol=1e-5)
    # known answers, from BT.601's analog YUV (not from the code's matrix): Y = 0.299 R +
    # 0.587 G + 0.114 B, U = -0.14713 R - 0.28886 G + 0.436 B, V = 0.615 R - 0.51499 G -
    # 0.10001 B; model 11 stores log(Y + 1e-5), U / (Y + 1e-5), V / (Y + 1e-5). (White alone,
    # as before, gives Y = 1 whatever U and V's coefficients are.)
    bt601 = np.array([[0.299, 0.587, 0.114], [-0.14713, -0.28886, 0.436],
                      [0.615, -0.51499, -0.10001]])
    for c in np.eye(3):
        y, u, v = bt601 @ c
        raw = dfmf.from_rgb(c[None], 11)[0]
        np.testing.assert_allclose(raw, [np.log(y + 1e-5), u / (y + 1e-5), v / (y + 1e-5)],
                                   rtol=2e-4, atol=1e-6)
    # and decoding a hand-made raw value: R = Y + 1.13983 V, G = Y - 0.39465 U - 0.5806 V,
    # B = Y + 2.03211 U with U, V scaled back by Y + 1e-5
    y, ud, vd = 0.5, 0.2, -0.1
    u, v = ud * (y + 1e-5), vd * (y + 1e-5)
    np.testing.assert_allclose(dfmf.to_rgb(np.array([[np.log(y + 1e-5), ud, vd]]), 11)[0],
                               [y + 1.13983 * v, y - 0.39465 * u - 0.5806 * v, y + 2.03211 * u],
                               rtol=1e-6)


def test_roi_maps_texels(tmp_path):
    rng = np.random.default_rng(1)
    U, SV = _factors(rng, 6, 5, 2)
    p = tmp_path / "x.btf"
    dfmf.write_dfmf(p, U, SV, ANG, ANG, 6, 5, color_model=0, scalar=4)
    full, crop = dfmf.DFMF(p), dfmf.DFMF(p, roi=(2, 1, 3, 2))
    np.testing.assert_allclose(crop.image(1, 4), full.image(1, 4)[1:3, 2:5])


def _write(tmp_path, **kw):
    rng = np.random.default_rng(2)
    U, SV = _factors(rng, 3, 3, 2)
    p = tmp_path / "x.btf"
    dfmf.write_dfmf(p, U, SV, ANG, ANG, 3, 3, **kw)
    return p


def test_wrong_magic(tmp_path):
    p = _write(tmp_path)
    data = bytearray(p.read_bytes())
    data[1:5] = b"FMF1"
    p.write_bytes(bytes(data))
    with pytest.raises(dfmf.DFMFError, match=r"x\.btf.*signature"):
        dfmf.DFMF(p)


def test_truncated(tmp_path):
    p = _write(tmp_path)
    p.write_bytes(p.read_bytes()[:-10])
    with pytest.raises(dfmf.DFMFError, match=r"x\.btf.*truncated"):
        dfmf.DFMF(p)
    p.write_bytes(p.read_bytes()[:200])
    with pytest.raises(dfmf.DFMFError, match="truncated"):
        dfmf.DFMF(p)


def test_inconsistent_sizes(tmp_path):
    p = _write(tmp_path)
    data = bytearray(p.read_bytes())
    # width field: after signature, meta block, sampling block
    meta = struct.unpack_from("<I", data, 10)[0]
    pos = 10 + meta + 4 + 7 * (8 + 4 + 7 * 8)
    assert struct.unpack_from("<II", data, pos) == (3, 3)
    struct.pack_into("<I", data, pos, 4)
    p.write_bytes(bytes(data))
    with pytest.raises(dfmf.DFMFError, match="expected 49 .* 12 texels"):
        dfmf.DFMF(p)
    with pytest.raises(dfmf.DFMFError, match="trailing"):
        q = _write(tmp_path)
        q.write_bytes(q.read_bytes() + b"\0\0")
        dfmf.DFMF(q)


def test_index_errors(tmp_path):
    b = dfmf.DFMF(_write(tmp_path))
    with pytest.raises(IndexError, match="light"):
        b.decode([0], [7], [0])
    with pytest.raises(dfmf.DFMFError, match="roi"):
        dfmf.DFMF(b.path, roi=(2, 2, 3, 3))


def test_corrupt_view_count_is_named_before_any_allocation(tmp_path):
    p = _write(tmp_path)
    data = bytearray(p.read_bytes())
    pos = 10 + struct.unpack_from("<I", data, 10)[0]  # after the meta block: the view count
    assert struct.unpack_from("<I", data, pos)[0] == 7
    struct.pack_into("<I", data, pos, 0xFFFFFFF0)
    p.write_bytes(bytes(data))
    with pytest.raises(dfmf.DFMFError, match=r"x\.btf: corrupt header: 4294967280 views"):
        dfmf.DFMF(p)


def test_non_finite_factors_are_refused_naming_the_file(tmp_path):
    """A NaN inside the payload passes the header and size checks; a fit would train on NaN
    loss and save the model."""
    rng = np.random.default_rng(0)
    U, SV = _factors(rng, 3, 3, 2)
    SV[1][4, 1] = np.nan
    p = tmp_path / "x.btf"
    dfmf.write_dfmf(p, U, SV, ANG, ANG, 3, 3, color_model=0, scalar=4)
    b = dfmf.DFMF(p)
    with pytest.raises(dfmf.DFMFError, match=r"x\.btf: channel 1's SV factor hold NaN or inf \(1 of 18\)"):
        b.factors()
    with pytest.raises(dfmf.DFMFError, match=r"x\.btf: decoded values hold NaN"):
        b.decode([4], [0], [0])
    assert np.isfinite(b.decode([0], [0], [0])).all()  # the other texels still decode


def test_a_non_finite_angle_is_refused_when_the_file_opens(tmp_path):
    """A NaN view angle opened fine, then a fit failed with an IndexError deep in its fetch."""
    rng = np.random.default_rng(0)
    U, SV = _factors(rng, 3, 3, 2)
    views = ANG.copy()
    views[2, 0] = np.nan
    p = tmp_path / "x.btf"
    dfmf.write_dfmf(p, U, SV, views, ANG, 3, 3, color_model=0, scalar=4)
    with pytest.raises(dfmf.DFMFError, match=r"x\.btf: corrupt header: view angles hold NaN"):
        dfmf.DFMF(p)
