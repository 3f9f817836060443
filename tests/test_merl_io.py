"""MERL .binary I/O, lookup and Rusinkiewicz conversions (neumat.io.merl)."""

import io
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from neumat import nbrdf
from neumat.io import merl

SHARED = Path(__file__).parents[2] / "shared"
rng = np.random.default_rng(0)


def hemisphere(n, rng=rng):
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 1e-3
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def write_raw(path, stored, header=(90, 90, 180)):
    """A MERL file written byte by byte, independently of write_merl."""
    with open(path, "wb") as f:
        f.write(np.asarray(header, "<i4").tobytes())
        f.write(np.asarray(stored, "<f8").tobytes())


def analytic(th, td, pd):
    """A smooth, reciprocal, isotropic closed-form BRDF (3, N) with all three dependencies."""
    base = 0.5 * np.cos(th) ** 8 * (1 + 0.3 * np.cos(td)) + 0.1 * np.cos(2 * pd) + 0.2
    return np.stack([base, 0.8 * base, 1.2 * base])


# ----------------------------------------------------------------------------- file format


def test_read_matches_reference_layout_and_scale(tmp_path):
    stored = rng.lognormal(0, 3, merl.SHAPE)
    stored[:, ~merl.valid_mask().reshape(merl.SHAPE[1:])] = -1.0
    write_raw(tmp_path / "a.binary", stored)
    assert (tmp_path / "a.binary").stat().st_size == 34_992_012
    x = merl.read_merl(tmp_path / "a.binary")
    # bit-exact with the reference reader: value = stored[c][phi_d + 180 (theta_d + 90 theta_h)] * scale
    flat = stored.reshape(3, -1)
    i = 7 + 180 * (11 + 90 * 42)
    assert x.reshape(3, -1)[:, i].tolist() == (flat[:, i] * merl.SCALE).tolist()
    assert np.array_equal(x, stored * merl.SCALE[:, None, None, None])
    assert np.array_equal(x[:, ~merl.valid_mask().reshape(merl.SHAPE[1:])].max(1), -merl.SCALE)


def test_write_read_round_trip_bit_exact(tmp_path):
    stored = rng.lognormal(0, 3, merl.SHAPE)
    write_raw(tmp_path / "a.binary", stored)
    x = merl.read_merl(tmp_path / "a.binary")
    merl.write_merl(tmp_path / "b.binary", x)
    assert np.array_equal(merl.read_merl(tmp_path / "b.binary"), x)  # bit-exact
    with open(tmp_path / "b.binary", "rb") as f:
        assert np.frombuffer(f.read(12), "<i4").tolist() == [90, 90, 180]
        back = np.frombuffer(f.read(), "<f8").reshape(merl.SHAPE)
    np.testing.assert_array_max_ulp(back, stored, maxulp=1)
    assert not (tmp_path / "b.binary.part").exists()


def test_written_bytes_are_the_table_over_the_scale(tmp_path):
    """write_merl scales row by row from a reused buffer: the file holds exactly table / SCALE
    in float64, from float64 and float32 tables and from a non-contiguous view."""
    x = rng.lognormal(-3, 3, merl.SHAPE)
    for table in (x, x.astype(np.float32), x[:, ::-1][:, ::-1]):
        merl.write_merl(tmp_path / "c.binary", table)
        raw = (tmp_path / "c.binary").read_bytes()
        assert raw[:12] == np.array([90, 90, 180], "<i4").tobytes()
        stored = np.asarray(table, np.float64) / merl.SCALE[:, None, None, None]
        assert raw[12:] == stored.astype("<f8").tobytes()


def test_evaluate_grid_is_the_field_at_every_bin_whatever_the_chunk():
    w = nbrdf.init_weights(3, torch.Generator().manual_seed(4)) * 2
    valid = merl.valid_mask()
    for act in nbrdf.ACTIVATIONS:
        t = nbrdf.evaluate_grid(w, act)
        assert t.shape == (3, *merl.SHAPE) and t.dtype == np.float64
        flat = t.reshape(3, 3, -1)
        sub = rng.choice(np.flatnonzero(valid), 5000, replace=False)
        direct = nbrdf.forward(w, torch.from_numpy(merl.grid_inputs()[sub].copy()), act)
        np.testing.assert_allclose(flat[:, :, sub], direct.numpy().transpose(0, 2, 1), rtol=1e-5, atol=1e-6)
        assert (flat[:, :, ~valid] == -merl.SCALE[None, :, None]).all()
    # the same bits whatever the (power-of-two) chunk: the smallest default and the old one
    for chunk in (1024, 1 << 18):
        assert np.array_equal(nbrdf.evaluate_grid(w[:2], act, chunk=chunk), t[:2])
    assert np.array_equal(nbrdf.evaluate_grid(w[1:2], act)[0], t[1])  # batch-independent


def test_channel_major_layers_are_the_row_major_field():
    """Shared inputs go through the layers channel-major (nbrdf.forward_raw_channels, for
    speed); per-field inputs through row-major bmm: the same field to float32 rounding, and
    forward_channels is forward transposed, bit for bit."""
    w = nbrdf.init_weights(5, torch.Generator().manual_seed(3)) * 2
    x = torch.from_numpy(merl.valid_grid_inputs_t()[:, ::97].T.copy())
    for act in nbrdf.ACTIVATIONS:
        shared = nbrdf.forward_raw(w, x, act)
        per_field = nbrdf.forward_raw(w, x.expand(len(w), *x.shape).contiguous(), act)
        assert shared.shape == per_field.shape == (5, len(x), 3)
        torch.testing.assert_close(shared, per_field, rtol=1e-5, atol=1e-5)
        assert torch.equal(nbrdf.forward_channels(w, x.t(), act),
                           nbrdf.forward(w, x, act).transpose(1, 2))


def test_round_trip_of_arbitrary_table_within_one_ulp(tmp_path):
    x = rng.lognormal(-3, 3, merl.SHAPE)
    merl.write_merl(tmp_path / "c.binary", x)
    np.testing.assert_array_max_ulp(merl.read_merl(tmp_path / "c.binary"), x, maxulp=1)


def test_wrong_size_names_file(tmp_path):
    p = tmp_path / "short.binary"
    write_raw(p, np.zeros(100))
    with pytest.raises(merl.MerlFormatError, match=r"short\.binary.*bytes"):
        merl.read_merl(p)


def test_wrong_header_names_file(tmp_path):
    p = tmp_path / "hdr.binary"
    write_raw(p, np.zeros(merl.SHAPE), header=(180, 90, 90))
    with pytest.raises(merl.MerlFormatError, match=r"hdr\.binary.*header \[180, 90, 90\]"):
        merl.read_merl(p)


def test_nan_names_file(tmp_path):
    p = tmp_path / "nan.binary"
    stored = np.ones(merl.SHAPE)
    stored[1, 3, 4, 5] = np.nan
    write_raw(p, stored)
    with pytest.raises(merl.MerlFormatError, match=r"nan\.binary.*NaN"):
        merl.read_merl(p)


def test_writer_rejects_bad_tables(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        merl.write_merl(tmp_path / "x.binary", np.zeros((3, 90, 90, 90)))
    bad = np.zeros(merl.SHAPE)
    bad[0, 0, 0, 0] = np.inf
    with pytest.raises(ValueError, match="NaN or inf"):
        merl.write_merl(tmp_path / "x.binary", bad)
    assert not (tmp_path / "x.binary").exists()


# ----------------------------------------------------------------------------- lookup


@pytest.fixture(scope="module")
def analytic_table(tmp_path_factory):
    p = tmp_path_factory.mktemp("merl") / "analytic.binary"
    merl.write_merl(p, analytic(*merl.grid_angles()).reshape(merl.SHAPE))
    return merl.read_merl(p)


def test_lookup_matches_closed_form_at_bin_centres(analytic_table):
    idx = rng.choice(np.nonzero(merl.valid_mask())[0], 5000, replace=False)
    th, td, pd = (a[idx] for a in merl.grid_angles())
    wi, wo = merl.half_diff_to_dirs(th, td, pd, phi_h=rng.uniform(-np.pi, np.pi, idx.size))
    ok = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    np.testing.assert_allclose(merl.lookup(analytic_table, wi[ok], wo[ok]),
                               analytic(th[ok], td[ok], pd[ok]).T, rtol=1e-12)


def test_lookup_matches_closed_form_elsewhere(analytic_table):
    wi, wo = hemisphere(20000), hemisphere(20000)
    err = np.abs(merl.lookup(analytic_table, wi, wo) - analytic(*merl.dirs_to_half_diff(wi, wo)).T)
    # nearest bin: |df/dtheta_h| <= 1.7 over a half-bin <= pi/180, plus theta_d and phi_d terms
    assert err.max() < 0.035
    assert err.mean() < 0.004


def test_lookup_below_horizon_is_zero(analytic_table):
    wi, wo = hemisphere(100), hemisphere(100)
    wo[:, 2] *= -1
    assert not merl.lookup(analytic_table, wi, wo).any()


def test_lookup_reciprocal():
    table = rng.random(merl.SHAPE)  # generic values: any index asymmetry would show
    wi, wo = hemisphere(50000), hemisphere(50000)
    assert np.array_equal(merl.lookup(table, wi, wo), merl.lookup(table, wo, wi))


def test_bin_index_known_values():
    # theta_h bins are non-linear: bin = floor(90 sqrt(theta_h / (pi/2)))
    assert merl.angles_to_index(np.pi / 8, 0.0, 0.0) == 45 * 90 * 180
    assert merl.angles_to_index(0.0, np.pi / 4, 0.0) == 45 * 180
    # phi_d folded to [0, pi): -pi/2 -> pi/2 -> bin 90
    assert merl.angles_to_index(0.0, 0.0, -np.pi / 2) == 90
    assert merl.angles_to_index(0.0, 0.0, np.pi / 2) == 90


# ----------------------------------------------------------------------------- conversions


def test_dirs_half_diff_round_trip():
    wi, wo = hemisphere(10000), hemisphere(10000)
    th, td, pd = merl.dirs_to_half_diff(wi, wo)
    h = wi + wo
    wi2, wo2 = merl.half_diff_to_dirs(th, td, pd, phi_h=np.arctan2(h[:, 1], h[:, 0]))
    np.testing.assert_allclose(wi2, wi, atol=1e-9)
    np.testing.assert_allclose(wo2, wo, atol=1e-9)


def test_half_diff_dirs_round_trip():
    n = 10000
    th, td = rng.uniform(0.01, np.pi / 2 - 0.01, (2, n))
    pd = rng.uniform(-np.pi + 0.01, np.pi - 0.01, n)
    back = merl.dirs_to_half_diff(*merl.half_diff_to_dirs(th, td, pd, rng.uniform(-3, 3, n)))
    for a, b in zip(back, (th, td, pd)):
        np.testing.assert_allclose(a, b, atol=1e-7)


def test_cos_theta_i_matches_directions():
    th, td, pd = rng.uniform(0, np.pi / 2, (3, 1000))
    wi, _ = merl.half_diff_to_dirs(th, td, pd)
    np.testing.assert_allclose(merl.cos_theta_i(th, td, pd), wi[:, 2], atol=1e-12)


def test_numpy_and_torch_conversions_agree():
    wi, wo = hemisphere(5000), hemisphere(5000)
    x_np = merl.half_diff_cartesian(*merl.dirs_to_half_diff(wi, wo))
    x_t = merl.dirs_to_half_diff_torch(torch.from_numpy(wi), torch.from_numpy(wo))
    np.testing.assert_allclose(x_t.numpy(), x_np, atol=1e-10)


def test_valid_mask_counts():
    m = merl.valid_mask()
    assert m.shape == (merl.N_BINS,) and m.dtype == bool
    assert m.sum() == 1_096_216  # valid bins of the MERL grid at bin centres
    # its closed form equals the definition: both directions of the bin centre above the horizon
    wi, wo = merl.half_diff_to_dirs(*merl.grid_angles())
    assert np.array_equal(m, (wi[:, 2] > 0) & (wo[:, 2] > 0))


def test_cached_grid_arrays_are_shared_and_read_only():
    """valid_mask, grid_angles and grid_inputs are computed once per process and shared, so no
    caller may change them for the others; grid_inputs is the neural-field input of each bin."""
    assert merl.valid_mask() is merl.valid_mask()
    for a in (merl.valid_mask(), *merl.grid_angles(), merl.grid_inputs()):
        with pytest.raises(ValueError, match="read-only"):
            a[0] = 0
    bins = np.array([0, 123_456, merl.N_BINS - 1])
    np.testing.assert_array_equal(
        merl.grid_inputs()[bins],
        merl.half_diff_cartesian(*(a[bins] for a in merl.grid_angles())).astype(np.float32))


# ----------------------------------------------------------------------------- NBRDF decode


def keras_to_flat(h5) -> np.ndarray:
    """Keras dense_1..3 kernels (in, out) -> nbrdf flatten order [W1 (out, in), b1, ...]."""
    parts = []
    for n in ("dense_1", "dense_2", "dense_3"):
        g = h5[n][n]
        parts += [g["kernel:0"][()].T.ravel(), g["bias:0"][()].ravel()]
    return np.concatenate(parts).astype(np.float64)


@pytest.mark.slow
def test_neural_field_agrees_with_shared_decode(tmp_path):
    archive = SHARED / "data" / "merl_nbrdf.zip"
    tool = SHARED / "tools" / "nbrdf_to_merl.py"
    if not (archive.exists() and tool.exists()):
        pytest.skip(f"{SHARED} (NBRDF archive and decoder) not available")
    h5py = pytest.importorskip("h5py")
    name = "blue-acrylic"
    with zipfile.ZipFile(archive) as z:
        data = z.read(f"merl_nbrdf/{name}.h5")
    (tmp_path / f"{name}.h5").write_bytes(data)
    subprocess.run([sys.executable, str(tool), str(tmp_path / "out"), str(tmp_path / f"{name}.h5")],
                   check=True, capture_output=True)
    decoded = merl.read_merl(tmp_path / "out" / f"{name}.binary").reshape(3, -1)

    with h5py.File(io.BytesIO(data), "r") as f:
        w = torch.from_numpy(keras_to_flat(f))[None]
    assert w.shape == (1, nbrdf.N_PARAMS)
    # the decoder evaluates bins at their lower-edge angles
    i, j, k = np.unravel_index(np.arange(merl.N_BINS), merl.SHAPE[1:])
    th, td, pd = (i / 90) ** 2 * np.pi / 2, j / 90 * np.pi / 2, k / 180 * np.pi
    wi, wo = merl.half_diff_to_dirs(th, td, pd)
    valid = (wi[:, 2] > 0) & (wo[:, 2] > 0)
    assert np.array_equal(decoded[:, ~valid], np.broadcast_to(-merl.SCALE[:, None], (3, (~valid).sum())))
    sub = rng.choice(np.nonzero(valid)[0], 200_000, replace=False)
    x = torch.from_numpy(merl.half_diff_cartesian(th[sub], td[sub], pd[sub]))
    ours = nbrdf.forward(w, x, "relu")[0].numpy().T
    np.testing.assert_allclose(decoded[:, sub], ours, rtol=1e-9, atol=1e-12)
    assert decoded[:, sub].max() > 0.1  # a real, non-trivial material
