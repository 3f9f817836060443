import numpy as np
import pytest
import torch

from neumat import nbrdf
from neumat.data import synthetic_merl
from neumat.io import merl
from neumat.render import sphere

R = 32


def constant_field(value):
    w = torch.zeros(1, nbrdf.N_PARAMS)
    w[0, -3:] = torch.as_tensor(np.log1p(value), dtype=torch.float32)
    return w


def test_lambertian_known_answer():
    """White Lambertian: point-light term I cos / d^2 / pi plus AMBIENT * albedo 1."""
    img = sphere.render_fields(constant_field(np.full(3, 1 / np.pi)), R)[0]
    row, col = 10, 12
    x, y = (col + 0.5) / R * 2 - 1, 1 - (row + 0.5) / R * 2
    p = np.array([x, y, np.sqrt(1 - x * x - y * y)])
    to_l = sphere.LIGHT_POS - p
    d2 = to_l @ to_l
    expected = sphere.LIGHT_INTENSITY * max(p @ to_l, 0) / np.sqrt(d2) / d2 / np.pi + sphere.AMBIENT
    np.testing.assert_allclose(img[row, col].numpy(), expected, rtol=1e-5)
    # a pixel facing away from the light sees only the environment
    np.testing.assert_allclose(img[25, 20].numpy(), sphere.AMBIENT, rtol=1e-5)
    assert (img[0, 0] == 0).all()  # background
    assert not sphere.sphere_view(R).mask[0, 0]


def test_fields_tables_and_callable_agree_on_a_constant_brdf():
    c = np.array([0.1, 0.2, 0.3])
    a = sphere.render_fields(constant_field(c), R)
    b = sphere.render_fn(lambda wi, wo: torch.tensor(c, dtype=torch.float32).expand(1, len(wi), 3),
                         1, R)
    t = np.broadcast_to(c[:, None, None, None], merl.SHAPE)[None].astype(np.float32)
    d = sphere.render_tables(t, R)
    torch.testing.assert_close(a, b)
    torch.testing.assert_close(d, b)


def test_fields_match_direct_evaluation_in_the_local_frame():
    """The precomputed 6-D inputs equal the torch Rusinkiewicz transform of (wi, wo)."""
    w = nbrdf.init_weights(3, torch.Generator().manual_seed(1))
    a = sphere.render_fields(w, R, activation="leaky_relu")
    b = sphere.render_fn(lambda wi, wo: nbrdf.forward(w, merl.dirs_to_half_diff_torch(wi, wo),
                                                      "leaky_relu"), 3, R)
    torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_tables_match_merl_lookup():
    rng = np.random.default_rng(0)
    tables = rng.uniform(-0.1, 1.0, size=(2, *merl.SHAPE)).astype(np.float32)

    def fn(wi, wo):
        return torch.as_tensor(np.stack([merl.lookup(t, wi.double().numpy(), wo.double().numpy())
                                         for t in tables]), dtype=torch.float32)

    a, b = sphere.render_tables(tables, R, chunk=1), sphere.render_fn(fn, 2, R)
    # the view bins its float64 geometry; the reference re-bins float32 directions, which flips
    # a few pixels in the light-view plane across the phi_d = 0 / pi bin edge
    same = torch.isclose(a, b, rtol=1e-5, atol=1e-6).all(-1)
    assert same.float().mean() > 0.98


def test_batches_and_chunks_do_not_change_renders():
    w = nbrdf.init_weights(5, torch.Generator().manual_seed(2))
    full = sphere.render_fields(w, R)
    torch.testing.assert_close(sphere.render_fields(w, R, chunk=2), full)
    torch.testing.assert_close(sphere.render_fields(w[3:4], R), full[3:4])
    assert full.dtype == torch.float32 and full.shape == (5, R, R, 3)


def test_highlight_where_the_half_vector_is_the_normal():
    """A sharp lobe around theta_h = 0 peaks at the pixel whose normal bisects the light and
    the camera direction - checks the local frame of both wi and wo."""
    def lobe(wi, wo):
        h = torch.nn.functional.normalize(wi + wo, dim=-1)
        return torch.exp(-(1 - h[:, 2]) * 2000)[None, :, None].expand(1, -1, 3)

    r = 64
    img = sphere.render_fn(lobe, 1, r)[0].mean(-1)
    row, col = np.unravel_index(int(img.argmax()), img.shape)
    x, y = (col + 0.5) / r * 2 - 1, 1 - (row + 0.5) / r * 2
    # solve n = normalize(normalize(L - n) + z) by fixed-point iteration
    n = np.array([0, 0, 1.0])
    for _ in range(50):
        lgt = sphere.LIGHT_POS - n
        n = lgt / np.linalg.norm(lgt) + np.array([0, 0, 1.0])
        n /= np.linalg.norm(n)
    assert abs(x - n[0]) < 3 / r and abs(y - n[1]) < 3 / r


def test_view_directions_are_unit_and_above_the_horizon():
    v = sphere.SphereView(R)
    for d in (v.wi, v.wo):
        torch.testing.assert_close(d.norm(dim=-1), torch.ones(len(d)))
        assert (d[:, 2] > 0).all()
    assert (v.weight[:v.n_lit] > 0).all() and len(v.pixel) == v.n_lit
    # the albedo nodes: none below the horizon weighs; each view angle's weights integrate
    # AMBIENT cos(theta_i) to AMBIENT pi
    amb = v.weight[v.n_lit:].double().reshape(v.n_theta, -1)
    assert (amb >= 0).all()
    np.testing.assert_allclose(amb.sum(1).numpy(), sphere.AMBIENT * np.pi, rtol=1e-6)
    # cos(theta_o) of a lit pixel is the z of its normal (orthographic camera along -z)
    r = v.resolution
    c = (np.arange(r) + 0.5) / r * 2 - 1
    x, y = c[v.pixel.numpy() % r], -c[v.pixel.numpy() // r]
    np.testing.assert_allclose(v.wo[:v.n_lit, 2].numpy(), np.sqrt(1 - x ** 2 - y ** 2), rtol=1e-5)


@pytest.mark.parametrize("alpha", [0.02, 0.05, 0.1, 0.3])
def test_albedo_of_sharp_lobes_matches_a_dense_quadrature(alpha):
    """The environment term's albedo quadrature (AMB_TH x AMB_PHI half vectors) integrates a
    GGX lobe within 0.5 % of a 400 x 400 grid at every view angle; the cosine-weighted 16 x 16
    grid it replaced missed roughness 0.05 by 0.83 (a highlight ring on every glossy sphere)."""
    spec = synthetic_merl.Spec("ggx", "ggx", "metal", alpha=alpha, f0=(1.0, 1.0, 1.0))  # F = 1

    def ggx(wi, wo):
        f = synthetic_merl.evaluate(spec, wi.reshape(-1, 3), wo.reshape(-1, 3))
        return f[:, 0].reshape(wi.shape[:-1])
    theta_o, wi, wo, w = sphere.albedo_quadrature()
    got = (ggx(wi, wo) * w).reshape(len(theta_o), -1).sum(1)
    dwi, dwo, dw = sphere.half_vector_nodes(theta_o, 400, 400, half=True)
    ref = (ggx(dwi, dwo) * dw).sum(1)
    assert ref.min() > 0.5  # the lobe is there at every angle
    np.testing.assert_allclose(got, ref, rtol=5e-3)


def test_tonemap_srgb_curve():
    x = np.array([0.0, 0.0031308, 0.5, 1.0, 7.0, -1.0])
    assert sphere.tonemap(x[:, None].repeat(3, 1))[:, 0].tolist() == [0, 10, 188, 255, 255, 0]
    assert sphere.tonemap(np.full(3, 0.25), exposure=1.0).tolist() == [188] * 3


def test_srgb_decode_inverts_the_metric_curve():
    x = torch.linspace(0, 1, 1001)
    np.testing.assert_allclose(sphere.srgb_decode(sphere.to_srgb(x, 0.0)), x, atol=2e-7)
    # known answers: the curve's linear toe (1/12.92) and mid grey (sRGB 0.5 -> 0.214 linear)
    np.testing.assert_allclose(sphere.srgb_decode(torch.tensor([0.04, 0.5])), [0.04 / 12.92, 0.21404],
                               rtol=1e-4)


def test_bad_shapes_are_reported():
    with pytest.raises(ValueError, match=r"\(B, 675\)"):
        sphere.render_fields(torch.zeros(2, 10), R)
    with pytest.raises(ValueError, match="tables must have shape"):
        sphere.render_tables(np.zeros((1, 3, 90, 90)), R)
    with pytest.raises(ValueError, match="expected"):
        sphere.render_fn(lambda wi, wo: torch.zeros(2, len(wi), 3), 1, R)
