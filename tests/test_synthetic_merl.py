"""Analytic MERL-format materials (neumat.data.synthetic_merl)."""

import functools
import re

import numpy as np
import pytest

from neumat.data import catalog, synthetic_merl as sm
from neumat.io import merl

SPECS = sm.make_specs(12, seed=0)  # two of each family
table = functools.cache(sm.make_table)


def albedo(spec, theta_o, n=200):
    """Directional albedo int f cos(theta_i) d omega_i, by a quadrature over the half vector
    independent of the module's own: theta_h = ((k + .5) / n)^2 pi/2 resolves narrow lobes
    around the normal, and d omega_i = 4 (wo . h) d omega_h."""
    t = (np.arange(n) + 0.5) / n
    th, dth = t ** 2 * np.pi / 2, 2 * t / n * np.pi / 2
    ph = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    h = np.stack([np.sin(TH) * np.cos(PH), np.sin(TH) * np.sin(PH), np.cos(TH)], -1).reshape(-1, 3)
    dw_h = (np.sin(TH) * dth[:, None] * np.pi / n).ravel()
    wo = np.array([np.sin(theta_o), 0.0, np.cos(theta_o)])
    odh = h @ wo
    wi = 2 * odh[:, None] * h - wo
    f = sm.evaluate(spec, wi, np.broadcast_to(wo, wi.shape))
    return (f * np.where(odh > 0, 4 * odh * np.clip(wi[:, 2], 0, None) * dw_h, 0)[:, None]).sum(0)


def test_deterministic_and_seeded():
    assert sm.make_specs(12, 0) == SPECS
    assert sm.make_specs(12, 1) != SPECS
    assert sm.make_specs(5, 0) == SPECS[:5]  # a prefix does not depend on the count
    assert np.array_equal(table(SPECS[2]), sm.make_table(sm.make_specs(3, 0)[2]))


@pytest.mark.parametrize("count", [2, 6, 40])
def test_names_types_valid_and_unique(count):
    specs = sm.make_specs(count, 3)
    names = [s.name for s in specs]
    assert len(set(names)) == count
    for s in specs:
        assert re.fullmatch(r"[a-z]+(-[a-z]+)*\d*", s.name), s.name  # MERL style
        assert s.type == catalog.material_type(s.name)
        assert s.type and not s.type[-1].isdigit()
        assert not set(s.type.split("-")) & catalog.COLOUR_WORDS
    assert {s.family for s in specs} >= ({"lambertian", "conductor"} if count == 2
                                         else {f for f, _ in sm.FAMILIES})


def test_small_counts_cover_diverse_families():
    assert [s.family for s in sm.make_specs(6, 7)] == [f for f, _ in sm.FAMILIES]


def test_colour_word_matches_colour():
    checked = 0
    for s in sm.make_specs(150, 1):
        words = s.name.split("-")
        if "blue" in words and max(s.diffuse) > 0:
            assert s.diffuse[2] > 3 * s.diffuse[0], s
            checked += 1
        if "red" in words and max(s.diffuse) > 0:
            assert s.diffuse[0] > 3 * s.diffuse[2], s
            checked += 1
        if "gold" in words and s.family == "conductor":
            assert s.f0[0] > s.f0[1] > s.f0[2], s
            checked += 1
    assert checked >= 5


def test_catalog_uses_specs():
    cat = catalog.synthetic_catalog(8, 0)
    assert list(cat["name"]) == [s.name for s in SPECS[:8]]
    assert list(cat["type"]) == [s.type for s in SPECS[:8]]


def test_table_format_and_below_horizon():
    t = table(SPECS[0])
    assert t.shape == merl.SHAPE and t.dtype == np.float64
    valid = merl.valid_mask()
    flat = t.reshape(3, -1)
    assert np.array_equal(flat[:, ~valid], np.broadcast_to(-merl.SCALE[:, None], (3, (~valid).sum())))
    assert (flat[:, valid] >= 0).all() and np.isfinite(flat).all()


def test_grid_mask_matches_merl():
    assert np.array_equal(sm._grid_terms()[4], merl.valid_mask())


@pytest.mark.parametrize("spec", SPECS[:6], ids=lambda s: s.family)
def test_table_is_brdf_at_bin_centres(spec):
    idx = np.random.default_rng(1).choice(np.nonzero(merl.valid_mask())[0], 2000, replace=False)
    wi, wo = merl.half_diff_to_dirs(*(a[idx] for a in merl.grid_angles()))
    np.testing.assert_allclose(table(spec).reshape(3, -1)[:, idx].T,
                               sm.evaluate(spec, wi, wo), rtol=1e-6)


def test_lambertian_is_constant():
    spec = next(s for s in SPECS if s.family == "lambertian")
    t = table(spec).reshape(3, -1)[:, merl.valid_mask()]
    np.testing.assert_allclose(t, np.asarray(spec.diffuse)[:, None] / np.pi * np.ones_like(t))
    np.testing.assert_allclose(albedo(spec, 0.7), spec.diffuse, rtol=1e-3)


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_energy_conserving(spec):
    a = np.array([albedo(spec, t) for t in np.radians([0, 45, 75, 88])])
    assert (a <= 1.0).all(), a
    assert (a > 0.01).all(), a


def test_bright_plastic_conserves_energy_where_naive_sum_would_not():
    white = sm.Spec(name="white-plastic", type="plastic", family="plastic",
                    diffuse=(0.9, 0.9, 0.9), alpha=0.2, ior=1.6)
    coat = sm.Spec(name="coat", type="coat", family="plastic", alpha=0.2, ior=1.6)
    grazing = np.radians(85)
    assert (albedo(coat, grazing) + 0.9 > 1.05).all()  # Lambertian + coat would create energy
    assert (albedo(white, grazing) <= 1.0).all()
    assert (albedo(white, grazing) > 0.9).all()


def test_plastic_albedo_is_coat_plus_coupled_diffuse():
    # E_total(mu) = E_spec(mu) + rho (1 - E_spec(mu)) for the Kelemen coupling
    spec = next(s for s in SPECS if s.family == "plastic")
    mu, e = sm.albedo_table(spec)
    for theta in np.radians([10, 60]):
        e_spec = np.array([np.interp(np.cos(theta), mu, e[c]) for c in range(3)])
        np.testing.assert_allclose(albedo(spec, theta), e_spec + np.asarray(spec.diffuse) * (1 - e_spec),
                                   atol=0.01)


@pytest.mark.parametrize("spec", SPECS[:6], ids=lambda s: s.family)
def test_reciprocal(spec):
    rng = np.random.default_rng(2)
    v = rng.normal(size=(2, 5000, 3))
    v[..., 2] = np.abs(v[..., 2])
    wi, wo = v / np.linalg.norm(v, axis=-1, keepdims=True)
    np.testing.assert_allclose(sm.evaluate(spec, wi, wo), sm.evaluate(spec, wo, wi), rtol=1e-10)


def test_isotropic():
    spec = next(s for s in SPECS if s.family == "conductor")
    rng = np.random.default_rng(3)
    th, td, pd = rng.uniform(0, 1.2, (3, 1000))
    a = sm.evaluate(spec, *merl.half_diff_to_dirs(th, td, pd, 0.0))
    b = sm.evaluate(spec, *merl.half_diff_to_dirs(th, td, pd, rng.uniform(-3, 3, 1000)))
    np.testing.assert_allclose(a, b, rtol=1e-9)


def test_mirror_is_sharp_and_metal_is_coloured():
    mirror = next(s for s in SPECS if s.family == "mirror")
    t = table(mirror)
    assert t[:, 0, 10].max() > 1000 * t[:, 30, 10].max()  # specular peak vs 10 deg off it
    gold = sm.Spec(name="gold-metallic-paint", type="metallic-paint", family="conductor",
                   alpha=0.2, f0=(1.0, 0.78, 0.34))
    rgb = sm.make_table(gold)[:, 20, 20, 90]
    assert rgb[0] > rgb[1] > rgb[2]


def test_bad_count():
    with pytest.raises(ValueError, match="count"):
        sm.make_specs(0, 0)
