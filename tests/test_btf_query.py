"""The fused C Triple Plane query (neumat.btf.query) against the model's torch path."""

import copy
import platform

import pytest
import torch

from neumat.btf import query
from neumat.btf.neural import NeuMIP, TriplePlane

pytestmark = pytest.mark.skipif(not query.available(), reason="the C query kernel cannot be built")
X86 = platform.machine().lower() in ("x86_64", "amd64")
MARCHES = [pytest.param(m, marks=pytest.mark.skipif(not (X86 or m == "native") or
                                                    not query.available(m),
                                                    reason=f"-march={m} does not build or run here"))
           for m in ("native", "x86-64-v3", "x86-64-v2")]


def model(**kw):
    m = TriplePlane(37, 23, **kw)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():  # planes with structure at the scale of a texel, a non-trivial MLP
        for p in m.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)
    return m.requires_grad_(False).eval()


def queries(n, seed=0):
    """Random queries with the edge cases: u outside [0, 1) (wraps), wi = wo = the normal
    (phi_h undefined), grazing directions, mirror directions (h on the pole)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 2, generator=g) * 3 - 1
    wi, wo = (torch.nn.functional.normalize(torch.randn(n, 3, generator=g) *
                                            torch.tensor([1, 1, 0]) +
                                            torch.tensor([0, 0, 0.02]) +
                                            torch.rand(n, 1, generator=g) *
                                            torch.tensor([0, 0, 3.0]), dim=-1)
              for _ in range(2))
    wi[0] = wo[0] = torch.tensor([0.0, 0.0, 1.0])
    wi[1], wo[1] = torch.tensor([0.6, 0.0, 0.8]), torch.tensor([-0.6, 0.0, 0.8])
    return u, wi, wo


@pytest.mark.parametrize("march", MARCHES)
@pytest.mark.parametrize("n", [2, 203, 1000])
def test_query_matches_the_torch_path(march, n):
    """Within float32 rounding of the torch path run in float64: the float32 torch path is
    itself 1.1e-4 off it on one of these queries, beyond the tolerance, where the kernel is
    7e-6 off (2026-12-03)."""
    m, (u, wi, wo) = model(), queries(n)
    m64, (u64, wi64, wo64) = copy.deepcopy(m).double(), (t.double() for t in (u, wi, wo))
    ref, raw = m64(u64, wi64, wo64).float(), m64.raw(u64, wi64, wo64).float()
    got = query.query(m, u, wi, wo, march=march)
    assert ref.abs().max() > 0.1  # not all clamped to 0
    # float32 rounding of sums in another order, at the scale of the MLP's outputs (~30 here);
    # RGB = expm1(raw) turns raw's absolute error into a relative one
    scale = raw.abs().max().item()
    torch.testing.assert_close(got, ref, rtol=1e-4 + 3e-6 * scale, atol=3e-6 * scale)
    torch.testing.assert_close(query.query(m, u, wi, wo, raw=True, march=march), raw,
                               rtol=1e-4, atol=3e-6 * scale)


def test_other_widths_and_depths():
    m, (u, wi, wo) = model(u_channels=5, dir_res=9, dir_channels=3, hidden=19, layers=3), \
        queries(300, 1)
    torch.testing.assert_close(query.query(m, u, wi, wo), m(u, wi, wo), rtol=1e-4, atol=1e-5)


def test_features_u_hook_replaces_the_f_u_fetch():
    """Synthesis passes its own positional features (a tensor, or a function of u)."""
    m, (u, wi, wo) = model(), queries(500, 2)
    feat = torch.randn(500, 8, generator=torch.Generator().manual_seed(3))
    ref = torch.relu(torch.expm1(m.decode(feat, wi, wo)))
    torch.testing.assert_close(query.query(m, u, wi, wo, features_u=feat), ref,
                               rtol=1e-4, atol=1e-5)
    shifted = lambda uu: m.features_u(uu + 0.25)  # e.g. a fetch at synthesised coordinates
    torch.testing.assert_close(query.query(m, u, wi, wo, features_u=shifted),
                               m(u + 0.25, wi, wo), rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="features_u"):
        query.query(m, u, wi, wo, features_u=feat[:, :4])


def test_threads_split_the_queries_exactly():
    m, (u, wi, wo) = model(), queries(20000, 4)
    assert torch.equal(query.query(m, u, wi, wo, threads=1), query.query(m, u, wi, wo, threads=3))


def test_fallbacks_give_the_torch_path():
    """NeuMIP, and autograd on a trainable model, run the torch path (gradients flow)."""
    u, wi, wo = queries(100, 5)
    nm = NeuMIP(16, 16).eval()
    with torch.no_grad():
        torch.testing.assert_close(query.query(nm, u, wi, wo), nm(u, wi, wo))
    tp = TriplePlane(16, 16)
    assert not query.supported(tp, u)  # requires grad, grad mode on
    query.query(tp, u, wi, wo).sum().backward()
    assert tp.f_u.grad is not None
    with torch.no_grad():
        assert query.supported(tp, u)


def hpb_queries(n, seed=6):
    """float64 u around 0, around 1e5 and around -1e5 (where float32 u has no sub-texel
    digits left), and the directions of `queries`."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 2, generator=g, dtype=torch.float64) * 40 - 20
    u[: n // 3] += 1e5
    u[n // 3: 2 * n // 3] -= 1e5
    _, wi, wo = queries(n, seed)
    return u, wi, wo


# query seed per method (each test draws its own queries)
FUSED_METHODS = {"hpb": 6, "hextile": 9}


@pytest.mark.parametrize("method", FUSED_METHODS)
@pytest.mark.parametrize("march", MARCHES)
@pytest.mark.parametrize("n", [3, 2000])
def test_fused_synthesis_query_matches_the_torch_synthesis(method, march, n, monkeypatch):
    """Synthesis inside the kernel = its torch path. HPB (grid, hash, taps, blend, LUT per
    tile; PCA folded into layer 1) against decode(HPB.torch_features(u)), which
    tests/test_btf_synthesis.py checks against a float64 reference at u = 1e5; hex-tiling
    (HPB's grid, hash and taps, rotated about each vertex; luminance-weighted, Gain3-sharpened
    blend) against decode(HexTile(u)), with HexTile's torch call barred during the query."""
    from neumat.btf import synthesis
    m, (u, wi, wo) = model(), hpb_queries(n, FUSED_METHODS[method])
    s = synthesis.build(m, method, 5)
    if method == "hpb":
        raw = m.decode(s.torch_features(u), wi, wo)
    else:
        raw = m.decode(s(u), wi, wo)
        monkeypatch.setattr(type(s), "__call__", lambda self, u: pytest.fail("not fused"))
    got = query.query(m, u, wi, wo, features_u=s, raw=True, march=march)
    # float32 rounding, amplified where the 37 x 23 exemplar's LUT steps are steep
    scale = raw.abs().max().item()
    torch.testing.assert_close(got, raw, rtol=1e-4, atol=3e-5 * scale)
    rgb = query.query(m, u, wi, wo, features_u=s, march=march)
    torch.testing.assert_close(rgb, torch.relu(torch.expm1(got)), rtol=1e-5, atol=1e-6)
    if n > 3:  # u is used in float64: its float32 rounding moves the result at 1e5
        off = query.query(m, u.float().double(), wi, wo, features_u=s, raw=True, march=march)
        assert (off - raw)[: n // 3].abs().max() > 100 * (got - raw)[: n // 3].abs().max()


@pytest.mark.parametrize("method, seed", [("hpb", 7), ("hextile", 11)])
def test_fused_synthesis_query_is_a_pure_function_of_u_and_seed(method, seed):
    from neumat.btf import synthesis
    m, (u, wi, wo) = model(), hpb_queries(5000, seed)
    s = synthesis.build(m, method, 9)
    a = query.query(m, u, wi, wo, features_u=s)
    perm = torch.randperm(5000, generator=torch.Generator().manual_seed(0))
    assert torch.equal(a, query.query(m, u, wi, wo, features_u=synthesis.build(m, method, 9)))
    assert torch.equal(a[perm], query.query(m, u[perm], wi[perm], wo[perm], features_u=s))
    assert torch.equal(a[:10], query.query(m, u[:10], wi[:10], wo[:10], features_u=s))
    assert torch.equal(a, query.query(m, u, wi, wo, features_u=s, threads=3))
    assert not torch.allclose(a, query.query(m, u, wi, wo, features_u=synthesis.build(m, method, 10)))


@pytest.mark.parametrize("method", FUSED_METHODS)
def test_tap_prefetch_changes_no_output(method, monkeypatch):
    """The synthesis kernels' tap prefetch (on by default) is a hint: the queries equal
    each other to the bit with it on and off, at u around 0 and +-1e5."""
    from neumat.btf import synthesis
    m, (u, wi, wo) = model(), hpb_queries(3000, 12)
    s = synthesis.build(m, method, 4)
    out = {}
    for pf in ("0", "1"):
        monkeypatch.setenv("NEUMAT_TAP_PREFETCH", pf)
        assert query.tap_prefetch() is (pf == "1")
        out[pf] = query.query(m, u, wi, wo, features_u=s, raw=True)
    assert torch.equal(out["0"], out["1"])


def test_tap_prefetch_is_on_unless_overridden(monkeypatch):
    monkeypatch.delenv("NEUMAT_TAP_PREFETCH", raising=False)
    assert query.tap_prefetch() is True
    monkeypatch.setenv("NEUMAT_TAP_PREFETCH", "0")
    assert query.tap_prefetch() is False
    monkeypatch.setenv("NEUMAT_TAP_PREFETCH", "yes")
    with pytest.raises(ValueError, match="NEUMAT_TAP_PREFETCH must be 0 or 1, got 'yes'"):
        query.tap_prefetch()


def test_synthesized_queries_use_the_fused_path(monkeypatch):
    """Synthesized(model, synth)(u, wi, wo) runs the kernel on the CPU and equals its torch
    path, for HPB and hex-tiling (both synthesised inside the kernel)."""
    from neumat.btf import synthesis
    m, (u, wi, wo) = model(), hpb_queries(600, 8)
    lib, calls = query._library(), []
    monkeypatch.setattr(query, "_library", lambda march="native": calls.append(march) or lib)
    for method in ("hpb", "hextile"):
        w = synthesis.Synthesized(m, synthesis.build(m, method, 2))
        ref = w.torch_forward(u, wi, wo)
        calls.clear()
        with monkeypatch.context() as mp:  # synthesised inside the kernel, not fed to it
            mp.setattr(type(w.synth), "__call__", lambda self, u: pytest.fail(method))
            got = w(u, wi, wo)
        torch.testing.assert_close(got, ref, rtol=1e-3, atol=1e-4 * ref.abs().max().item())
        assert calls, method


@pytest.mark.parametrize("settings", [{"rotation": 0.0, "gain": 0.5},
                                      {"exponent": 2.5, "contrast": 0.0, "gain": 0.9}])
def test_fused_hextile_settings(settings):
    """The blend's other branches: no rotation, no Gain3, a non-integer exponent (powf)."""
    from neumat.btf import synthesis
    m, (u, wi, wo) = model(), hpb_queries(900, 10)
    s = synthesis.build(m, "hextile", 3, settings)
    raw = m.decode(s(u), wi, wo)
    got = query.query(m, u, wi, wo, features_u=s, raw=True)
    torch.testing.assert_close(got, raw, rtol=1e-4, atol=3e-5 * raw.abs().max().item())


def test_fused_hextile_other_widths():
    """A plane of 5 channels (the kernel's generic path; 8 has its own instance)."""
    from neumat.btf import synthesis
    m = model(u_channels=5, dir_res=9, dir_channels=3, hidden=19, layers=3)
    u, wi, wo = hpb_queries(700, 12)
    s = synthesis.build(m, "hextile", 4)
    raw = m.decode(s(u), wi, wo)
    got = query.query(m, u, wi, wo, features_u=s, raw=True)
    torch.testing.assert_close(got, raw, rtol=1e-4, atol=3e-5 * raw.abs().max().item())


def test_tune_is_part_of_the_build_and_its_cache_key():
    """-mtune reaches the compiler, and a kernel tuned otherwise is a different cached library
    (an old build is never loaded for new flags)."""
    from neumat import cbuild
    assert "-mtune=generic" in cbuild.flags("native", tune="generic")
    assert not any(f.startswith("-mtune") for f in cbuild.flags("native"))
    a = cbuild.library_path(query.SOURCE, "native")
    b = cbuild.library_path(query.SOURCE, "native", tune="generic")
    if a is not None:
        assert a != b


@pytest.mark.parametrize("march", MARCHES)
@pytest.mark.parametrize("lut_size", [128, 64])
@pytest.mark.parametrize("channels", [8, 5])
def test_fused_hpb_lut_in_registers_and_gathered_alike(channels, lut_size, march):
    """The kernel looks a 128-entry LUT up in registers (AVX-512) and any other size by
    gathers, and blends 8 channels with a register transpose and other widths by the generic
    loop: all equal HPB's torch path, and the wrapped plane the kernel reads is built once per
    synthesis."""
    from neumat.btf import synthesis
    kw = {} if channels == 8 else dict(u_channels=5, dir_res=9, dir_channels=3, hidden=19, layers=3)
    m, (u, wi, wo) = model(**kw), hpb_queries(1000, 12)
    s = synthesis.build(m, "hpb", 3, {"lut_size": lut_size})
    raw = m.decode(s.torch_features(u), wi, wo)
    got = query.query(m, u, wi, wo, features_u=s, raw=True, march=march)
    torch.testing.assert_close(got, raw, rtol=1e-4, atol=3e-5 * raw.abs().max().item())
    plane = query.hpb_plane(s)
    H, W, C = s.gauss.shape
    assert plane.shape == (H + 1, W + 1, C) and query.hpb_plane(s) is plane
    assert plane.dtype == torch.float16  # half the bytes, the same values (gaussianise rounds)
    assert torch.equal(plane[:H, :W].float(), s.gauss) and torch.equal(plane[H], plane[0])
    assert torch.equal(plane[:, W], plane[:, 0])


@pytest.mark.parametrize("march", MARCHES)
def test_fma_peak_runs_its_chains(march):
    """The benchmarks' FLOP bound (query.fma_peak): the kernel's 12 chains a = a m + c start at
    1 + 1e-3 i, and a = a / 2 + 1 / 2 converges on 1. The rate is one a core can reach: a loop
    the compiler folded away (as it did with m and c constants) would give an absurd one."""
    lib = query._library(march)
    vl = lib.vector_lanes()
    assert vl in (4, 8, 16)
    assert lib.fma_peak(0, 0.5, 0.5) == pytest.approx(vl * sum(1 + 1e-3 * i for i in range(12)))
    assert lib.fma_peak(200, 0.5, 0.5) == pytest.approx(12 * vl)
    assert 1e9 < query.fma_peak(march, seconds=0.02, repeat=1) < 1e12


@pytest.mark.parametrize("march", MARCHES)
def test_plain_query_wraps_u_by_whole_planes(march):
    """The plain query tiles f_U: u and u + k for integer k (values exact in float32, so every
    coordinate is too) give the same result to the bit, negative k included (the kernel's
    floor-modulo in double)."""
    m, (u, wi, wo) = model(), queries(300, 2)
    u = torch.round(u * 64) / 64  # dyadic: (u + k) W - 0.5 exact in float32 for |k| <= 1000
    ref = query.query(m, u, wi, wo, raw=True, march=march)
    for k in (-1000.0, -1.0, 7.0, 1000.0):
        torch.testing.assert_close(query.query(m, u + k, wi, wo, raw=True, march=march), ref,
                                   rtol=0, atol=0)
