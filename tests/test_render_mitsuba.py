import numpy as np
import pytest
import torch

from neumat import nbrdf
from neumat.io import images, merl
from neumat.render import gallery, scenes
from neumat.render import mitsuba_bsdf as mb

mi = pytest.importorskip("mitsuba")
VARIANT = mb.select_variant("auto")
JIT = VARIANT != "scalar_rgb"


@pytest.fixture(autouse=True)
def _variant():
    """Each test in the variant measured above, whatever another test module set since."""
    mb.select_variant(VARIANT)


def ggx_table(alpha, kd=0.1, ks=0.25):
    """kd + ks * GGX D(theta_h), tinted per channel."""
    th = merl.grid_angles()[0].reshape(merl.SHAPE[1:])
    a2, t2 = alpha ** 2, np.tan(th) ** 2
    d = a2 / (np.pi * np.cos(th) ** 4 * (a2 + t2) ** 2)
    return (kd + ks * d)[None] * np.array([1.0, 0.8, 0.6])[:, None, None, None]


def random_dirs(n, seed):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.05
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_variant_follows_libllvm():
    with pytest.raises(ValueError, match="render.mitsuba.variant"):
        mb.select_variant("cuda_rgb")
    assert VARIANT == ("llvm_ad_rgb" if mb.find_libllvm() else "scalar_rgb")
    # where the packaged libLLVM is installed (the project's dependency), it must be found:
    # else everything above holds with scalar_rgb, the JIT tests skip, and the run is slow
    import importlib.metadata
    import sys
    try:
        importlib.metadata.version("karellen-llvm-core")
    except importlib.metadata.PackageNotFoundError:
        return
    if sys.platform.startswith("linux"):
        assert mb.find_libllvm() is not None and VARIANT == "llvm_ad_rgb"
        assert mb.llvm_version(mb.find_libllvm())[0] >= 16


def test_a_foreign_or_old_libllvm_in_the_environment_is_passed_over():
    """DRJIT_LIBLLVM_PATH naming a library that is not a libLLVM >= 16 (LLVM 14 and 15 crash
    Dr.Jit's kernels; here a Python extension module) is not given to Dr.Jit: a warning, the
    search goes on, and the variable then names what was found, or is removed."""
    import _ctypes
    import os
    import subprocess
    import sys
    foreign = os.path.realpath(_ctypes.__file__)
    assert mb.llvm_version(foreign) is None
    code = ("import os, neumat.render.mitsuba_bsdf as m; "
            "print(m._LIBLLVM); print(os.environ.get('DRJIT_LIBLLVM_PATH'))")
    r = subprocess.run([sys.executable, "-c", code], env={**os.environ, "DRJIT_LIBLLVM_PATH": foreign},
                       capture_output=True, text=True, check=True)
    lib, env = r.stdout.splitlines()[:2]
    assert foreign not in (lib, env) and "is not a libLLVM >= 16" in r.stderr
    assert env == lib if lib != "None" else env == "None"
    assert lib == str(mb.find_libllvm())  # what the search finds without the variable


def test_fit_lobe_recovers_ggx_roughness():
    for alpha in (0.05, 0.2):
        a, p = mb.fit_lobe(mb.Material(f"ggx{alpha}", table=ggx_table(alpha)))
        assert a == pytest.approx(alpha, rel=0.2) and 0.05 <= p <= 0.95
    lam = mb.Material("lambert", table=np.full(merl.SHAPE, 0.3))
    assert mb.fit_lobe(lam)[1] == 0.05


@pytest.mark.skipif(not JIT, reason="vectorised checks need the llvm variant")
@pytest.mark.parametrize("kind", ["field", "table"])
def test_plugin_matches_reference_and_pdf_is_consistent(kind):
    if kind == "field":
        m = mb.Material("f", weights=nbrdf.init_weights(1, torch.Generator().manual_seed(0))[0].numpy())
    else:
        m = mb.Material("t", table=ggx_table(0.15))
    bsdf = mi.load_dict(mb.bsdf_dict(m))
    wi, wo = random_dirs(500, 1), random_dirs(500, 2)
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(*wi.T.astype(np.float32))
    ctx = mi.BSDFContext()
    val = np.array(bsdf.eval(ctx, si, mi.Vector3f(*wo.T.astype(np.float32)))).reshape(3, -1).T
    ref = m.evaluate(wi, wo) * wo[:, 2:3]
    np.testing.assert_allclose(val, ref, rtol=2e-3, atol=1e-5)
    # sampled weights = eval / pdf, and the sampling pdf integrates to <= 1 (~1 near the normal)
    s = mi.load_dict({"type": "independent"})
    s.seed(0, 500)
    bs, w = bsdf.sample(ctx, si, s.next_1d(), s.next_2d())
    e, pdf = bsdf.eval_pdf(ctx, si, bs.wo)
    ok = np.array(bs.pdf) > 0
    np.testing.assert_allclose(np.array(pdf)[ok], np.array(bs.pdf)[ok], rtol=1e-4)
    e, pdf = np.array(e).reshape(3, -1)[:, ok], np.array(pdf)[ok]
    np.testing.assert_allclose(np.array(w).reshape(3, -1)[:, ok], e / pdf, rtol=1e-3)
    n = 400
    ct, ph = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi)
    st = np.sqrt(1 - ct ** 2)
    dirs = np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3).astype(np.float32)
    si1 = mi.SurfaceInteraction3f()
    si1.wi = mi.Vector3f(*np.tile([[0.1, 0.0, 0.995]], (len(dirs), 1)).T.astype(np.float32))
    total = np.array(bsdf.pdf(ctx, si1, mi.Vector3f(*dirs.T))).sum() * 2 * np.pi / len(dirs)
    # all mass above the horizon for a narrow lobe; a wide GGX lobe loses some below it
    lower = 0.97 if kind == "table" else 1 - bsdf_p_spec(m) * 0.5
    assert lower < total < 1.01


def bsdf_p_spec(m):
    return mb.fit_lobe(m)[1]


@pytest.mark.skipif(not JIT, reason="a furnace render in scalar mode is too slow for a unit test")
def test_white_furnace():
    """A white Lambertian sphere under a uniform unit environment reflects radiance 1."""
    m = mb.Material("white", table=np.full(merl.SHAPE, 1 / np.pi))
    scene = scenes.sphere_scene(m, 16, 256, np.ones((8, 16, 3), np.float32))
    img = scenes.render(scene)
    assert abs(img[6:10, 6:10].mean() - 1) < 0.02


@pytest.mark.skipif(not JIT, reason="no traced kernels in scalar mode")
def test_new_material_reuses_the_compiled_kernel():
    """Weights and lobe are kernel inputs, not literals: a second new material launches only
    kernels already compiled for the first (with literals, each material compiled its own)."""
    import drjit as dr
    w = nbrdf.init_weights(2, torch.Generator().manual_seed(1234)).numpy()
    env = scenes.sky_envmap(8)
    render = [lambda i=i: scenes.render(scenes.sphere_scene(
        mb.Material(f"reuse-{i}", weights=w[i]), 8, 1, env)) for i in range(2)]
    render[0]()
    dr.kernel_history()  # clears it
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        img = render[1]()
        hist = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert np.isfinite(img).all() and hist
    assert all(k["cache_hit"] for k in hist), [k["hash"] for k in hist if not k["cache_hit"]]
    # a large render bakes the material in (INLINE_SAMPLES): the same image
    assert not mb.bsdf_dict(mb.Material("reuse-1", weights=w[1]), 8 * 8)["inline"]
    assert mb.bsdf_dict(mb.Material("reuse-1", weights=w[1]), mb.INLINE_SAMPLES)["inline"]
    scene = scenes.sphere_scene(mb.Material("reuse-1", weights=w[1]), 8, 1, env)
    scene["object"]["bsdf"]["inline"] = True
    np.testing.assert_allclose(scenes.render(scene), img, rtol=1e-5, atol=1e-6)


def test_exr_png_round_trip(tmp_path):
    img = np.random.default_rng(0).uniform(0, 5, (5, 7, 3)).astype(np.float32)
    images.write_exr(tmp_path / "a.exr", img)
    np.testing.assert_array_equal(images.read_exr(tmp_path / "a.exr"), img)
    from PIL import Image

    def srgb8(x):  # IEC 61966-2-1, written out here: the PNG's known answer
        x = np.clip(x.astype(np.float64), 0, 1)
        return np.round(255 * np.where(x <= 0.0031308, 12.92 * x,
                                       1.055 * x ** (1 / 2.4) - 0.055)).astype(np.uint8)
    lin = img / 4  # mostly inside [0, 1], some above: clipped to 255
    for exposure in (0.0, 1.0):
        scenes.write_png(tmp_path / "a.png", lin, exposure=exposure)
        png = np.asarray(Image.open(tmp_path / "a.png"))
        assert png.dtype == np.uint8 and png.shape == (5, 7, 3)
        np.testing.assert_array_equal(png, srgb8(lin * 2.0 ** exposure))


def test_generated_textures():
    env = scenes.sky_envmap(16)
    assert env.shape == (16, 32, 3) and env.max() == 200 and env.min() > 0
    mask = scenes.blend_mask(32)
    assert mask.shape == (32, 32, 1) and mask.min() == 0 and mask.max() == 1
    n = scenes.ripple_normals(32) * 2 - 1
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-5)
    assert (n[..., 2] > 0).all()


def test_gallery_layout(tmp_path):
    imgs = [np.full((10, 12, 3), v, np.uint8) for v in (0, 100, 200)]
    g = gallery.gallery(imgs, ["a", "b", "c"], tmp_path / "g.png", ncols=2, pad=2, label_height=5)
    assert g.shape == (2 * (10 + 5 + 2) + 2, 2 * (12 + 2) + 2, 3)
    assert (g[2:12, 2:14] == 0).all() and (g[2:12, 16:28] == 100).all()
    assert (tmp_path / "g.png").exists()
    with pytest.raises(ValueError, match="labels"):
        gallery.gallery(imgs, ["a"])


def test_gallery_title_wraps_to_the_grid_width():
    """A narrow grid (the tiny run's constrained gallery: two 48-px cells) cut a one-line title
    short; the title wraps onto as many lines as it needs, each within the canvas."""
    imgs = [np.zeros((48, 48, 3), np.uint8)] * 2
    plain = gallery.gallery(imgs, ["a", "b"], ncols=2)
    title = "not produced within budget: metallic, plastic, mirror; fewer than asked: diffuse"
    g = gallery.gallery(imgs, ["a", "b"], ncols=2, title=title)
    assert g.shape[1] == plain.shape[1]
    lines = -(-len(title) // ((plain.shape[1] - 8) // 6))  # at least this many lines
    assert g.shape[0] - plain.shape[0] >= 14 * lines
    top = g[:g.shape[0] - plain.shape[0]]
    assert (top[:, -4:] == 255).all()  # nothing drawn into the right margin
    # a single narrow cell: a word longer than the grid widens the canvas, not broken up
    one = gallery.gallery(imgs[:1], ["a"], title="fewer than asked: medium-specular")
    assert one.shape[1] >= 6 * len("medium-specular")


def test_a_scene_s_weights_file_is_checked_by_name(tmp_path):
    """A scene's `.npy` of the wrong shape raised numpy's reshape error, naming no file; NaN
    weights rendered black."""
    from neumat import nbrdf
    from neumat.render.mitsuba_bsdf import material_from_file
    np.save(tmp_path / "short.npy", np.zeros(21, np.float32))
    with pytest.raises(ValueError, match=r"short\.npy: holds float32 of shape \(21,\), not NBRDF"):
        material_from_file(tmp_path / "short.npy")
    np.save(tmp_path / "zero_d.npy", np.float32(1))  # numpy's IndexError before
    with pytest.raises(ValueError, match=r"zero_d\.npy: holds float32 of shape \(\), not NBRDF"):
        material_from_file(tmp_path / "zero_d.npy")
    w = np.zeros((2, nbrdf.N_PARAMS), np.float32)
    w[1, 0] = np.inf
    np.save(tmp_path / "w.npy", w)
    assert material_from_file(tmp_path / "w.npy", 0).weights.shape == (nbrdf.N_PARAMS,)
    with pytest.raises(ValueError, match=r"w\.npy: weight vector 1 holds NaN or inf"):
        material_from_file(tmp_path / "w.npy", 1)
