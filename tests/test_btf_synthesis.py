"""Dynamic BTF synthesis on the positional plane (neumat.btf.synthesis)."""

import copy
import math

import numpy as np
import pytest
import torch

import neumat.btf.synthesis as syn
from neumat.btf.neural import NeuMIP, TriplePlane
from neumat.btf.synthesis import grid, hpb, quilting

DYNAMIC = ["linear", "hpb", "hextile"]


def _plane_model(seed=0, size=24, cls=TriplePlane):
    m = cls(size, size)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():   # smooth, skewed, correlated channels: closer to a trained f_U
        base = torch.randn(1, 3, size, size, generator=g)
        base = torch.nn.functional.avg_pool2d(base, 3, 1, 1, count_include_pad=False)[0]
        mix = torch.randn(3, m.f_u.shape[-1], generator=g)
        m.f_u.copy_(torch.exp(torch.einsum("chw,cd->hwd", base, mix)) * 0.1)
    return m.eval()


def test_grid_is_equilateral_and_barycentric():
    v = torch.tensor([[0, 0], [0, 1], [1, 0], [1, 1]])
    d = torch.cdist(grid.vertex_uv(v), grid.vertex_uv(v)) * 2 * math.sqrt(3)
    assert torch.allclose(d[:3, :3], 1 - torch.eye(3, dtype=d.dtype))
    assert torch.allclose(d[3, 1:3], torch.ones(2, dtype=d.dtype))
    u = torch.rand(5000, 2, dtype=torch.float64) * 7 - 3
    verts, w = grid.triangle_grid(u)
    assert (w >= 0).all() and torch.allclose(w.sum(1), torch.ones(5000, dtype=w.dtype))
    assert torch.allclose((grid.vertex_uv(verts) * w[..., None]).sum(1), u, atol=1e-12)


@pytest.mark.parametrize("method", DYNAMIC)
def test_same_u_and_seed_give_the_same_value(method):
    torch.manual_seed(0)
    m = _plane_model()
    a, b = syn.build(m, method, 7), syn.build(m, method, 7)
    u = torch.rand(3003, 2, dtype=torch.float64) * 40
    fa = a(u)
    perm = torch.randperm(3003)
    assert torch.equal(fa, a(u)) and torch.equal(fa, b(u))
    assert torch.equal(fa[perm], a(u[perm]))            # no dependence on the batch
    assert torch.equal(fa[:10], a(u[:10]))              # SIMD body and scalar tail agree
    assert not torch.allclose(fa, syn.build(m, method, 8)(u))


def _mix_ref(x):
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    x ^= x >> 15
    x = (x * 0x2C1B3C6D) & 0xFFFFFFFF
    return x ^ (x >> 16)


def _hash_ref(vx, vy, seed, k):
    s = _mix_ref(seed & 0xFFFFFFFF)
    h = _mix_ref((vy & 0xFFFFFFFF) ^ _mix_ref((vx & 0xFFFFFFFF) ^ s))
    out = []
    for i in range(k):
        h = _mix_ref(h ^ (0x9E3779B1 + i))
        out.append(h / 2 ** 32)
    return out


def _bilinear64(plane, x, y):
    H, W, _ = plane.shape
    x, y = x * W - 0.5, y * H - 0.5
    x0, y0 = math.floor(x), math.floor(y)
    fx, fy = x - x0, y - y0
    t = lambda yy, xx: plane[yy % H, xx % W]
    return ((1 - fx) * (1 - fy) * t(y0, x0) + fx * (1 - fy) * t(y0, x0 + 1)
            + (1 - fx) * fy * t(y0 + 1, x0) + fx * fy * t(y0 + 1, x0 + 1))


def _hpb_ref(s: hpb.HPB, u):
    """HPB at one point, everything in Python float64 / ints (independent of torch)."""
    x, y = (c * 2 * math.sqrt(3) for c in u)
    s0, s1 = x - y / math.sqrt(3), 2 * y / math.sqrt(3)
    b0, b1 = math.floor(s0), math.floor(s1)
    f0, f1 = s0 - b0, s1 - b1
    z = 1 - f0 - f1
    if z > 0:
        vs, ws = [(b0, b1), (b0, b1 + 1), (b0 + 1, b1)], [z, f1, f0]
    else:
        vs, ws = [(b0 + 1, b1 + 1), (b0 + 1, b1), (b0, b1 + 1)], [-z, 1 - f1, 1 - f0]
    gauss = s.gauss.double().numpy()
    g = sum(w * (_bilinear64(gauss, (u[0] % 1 + hx) % 1, (u[1] % 1 + hy) % 1) - 0.5)
            for w, (hx, hy) in zip(ws, [_hash_ref(vx, vy, s.seed, 2) for vx, vy in vs]))
    g = g / math.sqrt(sum(w * w for w in ws)) + 0.5
    lut = s.lut.double().numpy()
    L = lut.shape[1]
    q = [np.interp(np.clip(gc, 0, 1) * L - 0.5, np.arange(L), lut[c]) for c, gc in enumerate(g)]
    return np.asarray(q) @ s.basis.double().numpy().T + s.mean.double().numpy()


def test_vertex_hash_is_exact_integer_arithmetic():
    v = torch.tensor([[346410, 346411], [-5, 7], [2 ** 31 - 1, -(2 ** 31)]])
    got = grid.vertex_hash(v, 12345, 3)
    for row, vv in zip(got, v.tolist()):
        assert row.tolist() == _hash_ref(*vv, 12345, 3)
    # float32 sin-hash of the reference shaders collapses there; ours keeps neighbours apart
    assert len({tuple(r) for r in grid.vertex_hash(v[:1] + torch.arange(50)[:, None], 1).tolist()}) == 50


def test_wrap_fetch_coords_is_frac_of_the_sum_in_fixed_point():
    u = torch.tensor([[1e5 + 0.25, -0.75], [3.5, 2 ** 40 + 0.125]], dtype=torch.float64)
    off = torch.tensor([[[0.5, 0.75]], [[0.75, 2 ** -32]]], dtype=torch.float64)
    xy = grid.wrap_fetch_coords(u, off)
    assert xy.dtype == torch.float32
    # wraps to 0 at 1; frac(u) survives u = 2^40; 0.125 + 2^-32 rounds to float32's 0.125
    assert xy[:, 0].tolist() == [[0.75, 0.0], [0.25, 0.125]]
    # random u and hash offsets: within one float32 rounding (plus 2^-32) of the float64 frac
    g = torch.Generator().manual_seed(0)
    u = (torch.rand(4000, 2, generator=g, dtype=torch.float64) - 0.5) * 2e5
    off = grid.vertex_hash(torch.randint(-2 ** 20, 2 ** 20, (4000, 3, 2), generator=g), 5)
    ref = torch.remainder(torch.remainder(u, 1.0)[:, None] + off, 1.0)
    xy = grid.wrap_fetch_coords(u, off)
    err = xy.double() - ref
    err = torch.minimum(err.abs(), 1 - err.abs())  # 0 and 1 are the same place
    assert err.max() <= 2 ** -24 + 2 ** -32 and (xy < 1).all() and (xy >= 0).all()


@pytest.mark.parametrize("path", ["default", "torch"])
def test_hpb_at_u_1e5_equals_float64_reference(path):
    """default: the C kernel where it is built (else torch); torch: the torch path."""
    s = syn.build(_plane_model(), "hpb", 11)
    f = s if path == "default" else s.torch_features
    g = np.random.default_rng(0)
    pts = [(1e5 + a, 1e5 + b) for a, b in g.random((25, 2))] + [tuple(g.random(2)) for _ in range(5)]
    u = torch.tensor(pts, dtype=torch.float64)
    got = f(u).double().numpy()
    ref = np.stack([_hpb_ref(s, p) for p in pts])
    # float32 rounding of the fetch and of the features only (measured 5e-7 vs std 0.07)
    assert np.abs(got - ref).max() < 1e-4 * np.std(ref)
    # the same points through float32 u (what a float32 hash/coordinate path sees) are off
    got32 = f(u.float().double()).double().numpy()
    assert np.abs(got32[:25] - ref[:25]).max() > 100 * np.abs(got[:25] - ref[:25]).max()


def test_hpb_kernel_matches_torch_path():
    from neumat.btf.synthesis import kernel
    if not kernel.available():
        pytest.skip("no C compiler: HPB runs its torch path only")
    s = syn.build(_plane_model(), "hpb", 3)
    u = torch.rand(20000, 2, dtype=torch.float64) * 30 - 10
    u[:50] += 1e5
    k, t = s(u), s.torch_features(u)
    assert (k - t).abs().max() < 1e-4 * t.std()


def _grid_ref(u):
    x, y = (c * 2 * math.sqrt(3) for c in u)
    s0, s1 = x - y / math.sqrt(3), 2 * y / math.sqrt(3)
    b0, b1 = math.floor(s0), math.floor(s1)
    f0, f1 = s0 - b0, s1 - b1
    z = 1 - f0 - f1
    if z > 0:
        return [(b0, b1), (b0, b1 + 1), (b0 + 1, b1)], [z, f1, f0]
    return [(b0 + 1, b1 + 1), (b0 + 1, b1), (b0, b1 + 1)], [-z, 1 - f1, 1 - f0]


def _hextile_ref(s, u):
    """Hex-tiling at one point in Python float64 / ints (rotation about the vertex centre)."""
    vs, ws = _grid_ref(u)
    pl = s.plane.double().numpy()
    la, lb = s.lum_weights[:-1].double().numpy(), float(s.lum_weights[-1])
    cs, W = [], []
    for (vx, vy), w in zip(vs, ws):
        hx, hy, ha = _hash_ref(vx, vy, s.seed, 3)
        a = (2 * math.pi * ha - math.pi) * s.s["rotation"]
        cx, cy = (vx + vy / 2) / (2 * math.sqrt(3)), vy * (math.sqrt(3) / 2) / (2 * math.sqrt(3))
        dx, dy = u[0] - cx, u[1] - cy
        px = math.cos(a) * dx - math.sin(a) * dy + cx % 1 + hx
        py = math.sin(a) * dx + math.cos(a) * dy + cy % 1 + hy
        t = _bilinear64(pl, px % 1, py % 1)
        cs.append(t)
        lum = min(max(float(la @ t) + lb, 0.0), 1.0)
        W.append((1 + s.s["contrast"] * (lum - 1)) * w ** s.s["exponent"])
    W = np.asarray(W) / sum(W)
    k = math.log(1 - s.s["gain"]) / math.log(0.5)
    W = np.where(W < 0.5, 0.5 * (2 * W) ** k, 1 - 0.5 * (2 - 2 * W) ** k)
    W /= W.sum()
    return sum(wi * c for wi, c in zip(W, cs))


def test_hextile_at_u_1e5_equals_float64_reference():
    m = _plane_model()
    s = syn.build(m, "hextile", 5)
    g = np.random.default_rng(2)
    pts = [(1e5 + a, 1e5 + b) for a, b in g.random((25, 2))] + [tuple(g.random(2)) for _ in range(5)]
    u = torch.tensor(pts, dtype=torch.float64)
    got = s(u).double().numpy()
    ref = np.stack([_hextile_ref(s, p) for p in pts])
    assert np.abs(got - ref).max() < 1e-4 * np.std(ref)
    got32 = s(u.float().double()).double().numpy()
    assert np.abs(got32[:25] - ref[:25]).max() > 100 * np.abs(got[:25] - ref[:25]).max()


def test_hextile_features_are_float16_values_and_its_luminance_fit_is_least_squares():
    from neumat.btf.synthesis import hextile
    m = _plane_model()
    s = syn.build(m, "hextile", 5)
    f = s.plane
    assert torch.equal(f, f.half().float())  # what the C kernel stores in float16, exactly
    assert (f - m.f_u.detach()).abs().max() <= 2 ** -11 * m.f_u.detach().abs().max()
    # the fit's residual is orthogonal to the features and to 1 (normal equations)
    lum = syn.luminance(m).double().reshape(-1)
    A = torch.cat([f.double().reshape(-1, f.shape[-1]), torch.ones(len(lum), 1, dtype=torch.float64)], 1)
    res = A @ s.lum_weights.double() - lum
    assert (A.T @ res).abs().max() < 1e-5 * len(lum)
    assert 0 < s.lum_r2 <= 1
    # a luminance linear in the features is recovered exactly, R^2 = 1; noise lowers R^2
    g = torch.Generator().manual_seed(1)
    plane = torch.rand(20, 30, 4, generator=g)
    coef = torch.tensor([0.1, -0.2, 0.3, 0.05, 0.4])
    exact = plane @ coef[:-1] + coef[-1]
    got, r2 = hextile.fit_luminance(plane, exact)
    torch.testing.assert_close(got, coef, rtol=0, atol=1e-6)
    assert r2 > 1 - 1e-9
    _, r2 = hextile.fit_luminance(plane, (exact + 0.1 * torch.rand(20, 30, generator=g)).clamp(0, 1))
    assert 0.3 < r2 < 0.99
    c = torch.tensor([[0.0, 0, 0, 0], [10.0, 0, 0, 0], [-10.0, 0, 0, 0]])
    torch.testing.assert_close(hextile.HexTile(1, plane, coef).luminance_of(c),
                               torch.tensor([0.4, 1.0, 0.0]))
    with pytest.raises(ValueError, match=r"must lie in \[0, 1\]"):
        hextile.fit_luminance(plane, exact + 2)
    with pytest.raises(ValueError, match=r"needs \(H, W\) = \(20, 30\)"):
        hextile.fit_luminance(plane, exact.T)
    again = type(s).from_state(m.f_u.detach(), 5, s.state())
    assert torch.equal(again.plane, s.plane) and torch.equal(again.lum_weights, s.lum_weights)
    assert again.lum_r2 == s.lum_r2
    with pytest.raises(ValueError, match="float16 ends at 65504"):
        type(s).from_state(m.f_u.detach() * 1e6, 5, s.state())
    with pytest.raises(ValueError, match=r"lacks \['lum_weights', 'plane_shape'\] \(a state of an older"):
        type(s).from_state(m.f_u.detach(), 5, {"luminance": syn.luminance(m)})
    with pytest.raises(ValueError, match="luminance weights have shape"):
        type(s).from_state(m.f_u.detach(), 5, {**s.state(), "lum_weights": torch.zeros(3)})
    with pytest.raises(ValueError, match="not all finite"):
        bad = s.lum_weights.clone()
        bad[0] = float("nan")
        type(s).from_state(m.f_u.detach(), 5, {**s.state(), "lum_weights": bad})


def test_blend_preserves_mean_and_variance_of_gaussians():
    g = torch.Generator().manual_seed(0)
    n = 400_000
    u = torch.rand(n, 2, generator=g, dtype=torch.float64) * 10
    _, w = grid.triangle_grid(u)
    taps = 0.5 + hpb.SIGMA * torch.randn(n, 3, 2, generator=g, dtype=torch.float64)
    out = hpb.blend(taps, w)
    assert abs(out.mean().item() / 0.5 - 1) < 0.01
    assert (out.std(0) / hpb.SIGMA - 1).abs().max().item() < 0.01
    lin = (taps * w[..., None]).sum(1)          # the naive blend does lose variance
    assert lin.std().item() < 0.9 * hpb.SIGMA


def test_lut_inverts_T_on_the_exemplar():
    g = np.random.default_rng(1)
    q = torch.tensor(np.stack([g.exponential(size=4096), g.normal(size=4096) ** 3,
                               np.where(g.random(4096) < 0.3, 5.0, 0.0) + g.normal(size=4096) * .1], 1),
                     dtype=torch.float32)
    G = hpb.gaussianise(q)
    assert abs(G.mean().item() - 0.5) < 1e-3 and abs(G.std().item() / hpb.SIGMA - 1) < 0.02
    back = hpb.inverse_lut(G, hpb.build_lut(q, 128))
    for c in range(3):
        a, b = np.sort(q[:, c].numpy()), np.sort(back[:, c].numpy())
        w1 = np.mean(np.abs(a - b))
        assert w1 < 0.02 * a.std(), (c, w1, a.std())
        inner = slice(41, -41)   # beyond the LUT's outermost entries values clamp (1% each side)
        assert np.median(np.abs(a[inner] - b[inner])) < 0.02 * a.std()
    # and on a whole plane: LUT then inverse PCA gives the exemplar back
    m = _plane_model()
    s = syn.build(m, "hpb", 0)
    rec = hpb.inverse_lut(s.gauss.reshape(-1, s.gauss.shape[-1]), s.lut) @ s.basis.T + s.mean
    x = m.f_u.detach().reshape(rec.shape)
    assert (rec - x).abs().median() < 0.03 * x.std()


def test_hpb_preserves_the_histogram_and_linear_blend_does_not():
    from scipy.stats import wasserstein_distance
    m = _plane_model()
    u = torch.rand(60_000, 2, dtype=torch.float64) * 15
    ex = m.f_u.detach().reshape(-1, m.f_u.shape[-1]).numpy()
    d = {k: np.mean([wasserstein_distance(syn.build(m, k, 3)(u)[:, c].numpy(), ex[:, c]) / ex[:, c].std()
                     for c in range(ex.shape[1])]) for k in ("hpb", "linear")}
    assert d["hpb"] < 0.5 * d["linear"], d


def test_quilting_seams_beat_random_placement():
    g = np.random.default_rng(0)
    yy, xx = np.mgrid[0:32, 0:32]
    ex = np.stack([np.sin(2 * np.pi * (xx + 0.3 * yy) / 8), np.cos(2 * np.pi * yy / 16),
                   np.sin(2 * np.pi * (xx - yy) / 32)], -1) + 0.05 * g.normal(size=(32, 32, 3))
    q, err_q = quilting.quilt(ex, 96, 96, 12, np.random.default_rng(1))
    r, err_r = quilting.quilt(ex, 96, 96, 12, np.random.default_rng(1), random_placement=True)
    assert q.shape == (96, 96, 3)
    assert err_q < 0.2 * err_r, (err_q, err_r)
    eg_q, eg_r = quilting.excess_gradient(q, ex), quilting.excess_gradient(r, ex)
    assert eg_q < 0.5 * eg_r, (eg_q, eg_r)


def test_wrapper_answers_the_query_api_and_round_trips(tmp_path):
    models = {"triple_plane": _plane_model(), "neumip": _plane_model(1, cls=NeuMIP)}
    n = 500
    u = torch.rand(n, 2, dtype=torch.float64) * 3
    wi = torch.nn.functional.normalize(torch.rand(n, 3) + torch.tensor([0, 0, .5]), dim=-1)
    for name, m in models.items():
        plain = syn.Synthesized(m, syn.build(m, "tiling", 0))
        assert torch.allclose(plain(u, wi, wi), m(torch.remainder(u, 1).float(), wi, wi), atol=1e-6)
    for method in ("hpb", "hextile", "quilting"):
        st = {"scale": 2, "block": 8} if method == "quilting" else {}
        synths = {k: syn.build(m, method, 4, st) for k, m in models.items()}
        syn.save(tmp_path / f"{method}.pt", method, 4, st, synths)
        back = syn.load(tmp_path / f"{method}.pt", models)
        for k in models:
            assert torch.equal(back[k].synth(u), synths[k](u))
            assert back[k](u, wi, wi).shape == (n, 3)


@pytest.mark.skipif(not torch.cuda.is_available(),
                    reason="no CUDA device: building from a model on a GPU needs one")
@pytest.mark.parametrize("method", DYNAMIC)
def test_builds_from_a_model_on_the_gpu(method):
    """A synthesis built from a model on CUDA computes what the CPU build does (hex-tiling's
    luminance once made its tensors on the CPU and failed there)."""
    u = (torch.rand(500, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
         - 0.5) * 50
    m = _plane_model()  # one model: its MLP's init (which hex-tiling's luminance reads) is not
    want = syn.build(m, method, 5)(u)  # seeded by _plane_model, so two calls differ
    got = syn.build(copy.deepcopy(m).cuda(), method, 5)(u.cuda()).cpu()
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("n, k", [(100, 1), (1 << 18, 225)])
def test_histogram_positions_give_plain_tiling_the_exemplar_histogram(n, k):
    """Every exemplar texel equally often (k times): plain tiling's W1 is 0 but for the float32
    rounding of its fetch coordinates (4e-6 here; a random draw of positions with replacement
    left it at ~0.003), and the draw is the seed's."""
    from neumat.btf.synthesis import stage
    m = _plane_model()
    ex = m.f_u.detach().reshape(-1, m.f_u.shape[-1]).numpy()
    u = stage.texel_centres(24, 24, 15, seed=5, n=n)
    assert u.shape == (24 * 24 * k, 2) and u.dtype == torch.float64
    assert (u >= 0).all() and (u < 15).all()
    assert torch.equal(u, stage.texel_centres(24, 24, 15, seed=5, n=n))
    if k == 225:  # the whole x15 area, each texel centre once
        assert len(torch.unique(u, dim=0)) == len(u)
    else:
        assert not torch.equal(u, stage.texel_centres(24, 24, 15, seed=6, n=n))
    tiled = syn.build(m, "tiling", 0)(u).numpy()
    assert stage.histogram_distance(tiled, ex) < 1e-4
    assert stage.histogram_distance(syn.build(m, "linear", 0)(u).numpy(), ex) > 0.05


def test_linear_reference_blends_hpbs_patches():
    """The evaluation's linear blending is HPB's patches (its seed), naively blended."""
    from neumat.btf.synthesis import stage
    m = _plane_model()
    u = torch.rand(20_000, 2, dtype=torch.float64) * 15
    lin = stage.references(m, patch_seed=11)["linear"].synth(u)[:, 0].numpy()
    h = syn.build(m, "hpb", 11)(u)[:, 0].numpy()
    other = syn.build(m, "hpb", 12)(u)[:, 0].numpy()
    assert np.corrcoef(lin, h)[0, 1] > 0.9 and abs(np.corrcoef(lin, other)[0, 1]) < 0.3


@pytest.mark.parametrize("lights", [[[0.3, 0.2, 1.0]], [[0.8, 0.6, 1.2], [-1.2, 1.5, 0.7], [0.0, -1.0, 1.0]]])
def test_evaluation_and_section_take_any_number_of_lights(tmp_path, lights):
    from neumat.btf import models
    from neumat.btf.synthesis import stage
    path = tmp_path / "tp.pt"
    torch.manual_seed(0)  # the MLP's init: 8 % of seeds give a black render (ACF undefined)
    models.save(_plane_model(), path)
    render = {"width": 8, "height": 8, "spp": 1, "scales": [1, 3]}
    stage.evaluate("m", {"triple_plane": path}, {}, render, {"scale": 2, "px_per_tile": 8},
                   lights, 2.0, 0, 1, tmp_path / "m.tsv", tmp_path / "a.png", tmp_path / "b.png",
                   tmp_path / "c.png")
    import pandas as pd
    df = pd.read_csv(tmp_path / "m.tsv", sep="\t")
    n = len(lights)
    assert [c for c in df.columns if c.startswith("dmean_l")] == [f"dmean_l{j + 1}" for j in range(n)]
    assert set(df.method) == {"tiling", "linear"}
    tiling = df.set_index("method").loc["tiling"]
    assert tiling["w1"] < 1e-4 and tiling["acf"] > 0.99
    # at random positions tiling's values are bilinear mixes too: its W1 is no longer ~0
    assert tiling["w1_random"] > 10 * tiling["w1"] and np.isfinite(df["w1_random"]).all()
    stage.write_section([tmp_path / "m.tsv"], tmp_path / "s.md", tmp_path / "s.tsv",
                        {"scale": 2}, render, 15, 8)
    md = (tmp_path / "s.md").read_text()
    table = [line for line in md.splitlines() if line.startswith("|")]
    assert table[0].count("dmean L") == n and f"dmean L{n + 1}" not in table[0]
    assert len({line.count("|") for line in table}) == 1  # header, rule and rows line up


def test_autocorrelation_leaves_out_a_direction_without_variance():
    """A render that varies only in its first 4 columns: shifted 4 pixels along x, one slice is
    constant (no correlation), so the ACF is the y direction's alone (NaN before: max() took
    the NaN that came first); a black render has none (NaN)."""
    from neumat.btf.synthesis import stage
    img = np.zeros((16, 16, 3))
    img[:, :4] = np.random.default_rng(0).random((16, 4, 1))
    L = img[..., 0]
    along_y = np.corrcoef(L[:-4].reshape(-1), L[4:].reshape(-1))[0, 1]
    assert np.isfinite(along_y)
    assert stage.autocorrelation_at(img, 4) == pytest.approx(along_y)
    assert np.isnan(stage.autocorrelation_at(np.zeros((16, 16, 3)), 4))


def test_hpb_torch_path_is_independent_of_the_batch():
    """The torch path (the reference and the fallback) is a pure function of (u, seed) to the
    bit: no BLAS call whose kernel, and rounding, changes with the number of rows (addmm did
    for fewer than 8)."""
    s = syn.build(_plane_model(), "hpb", 7)
    u = torch.rand(700, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 40
    full = s.torch_features(u)
    for n in (1, 2, 3, 5, 7, 8, 9, 17):
        for i in range(0, 120, n):
            assert torch.equal(full[i:i + n], s.torch_features(u[i:i + n])), (n, i)
    perm = torch.randperm(700, generator=torch.Generator().manual_seed(2))
    assert torch.equal(full[perm], s.torch_features(u[perm]))
    # still mean + basis q, the C kernel's features to float32 rounding
    from neumat.btf.synthesis import kernel
    if kernel.available():
        assert (s(u) - full).abs().max() < 1e-4 * full.std()


@pytest.mark.parametrize("method", ["tiling", "linear", "hpb", "hextile", "quilting"])
def test_no_queries_give_empty_answers(method):
    m = _plane_model()
    s = syn.build(m, method, 3, {"scale": 2, "block": 8} if method == "quilting" else None)
    u, d = torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, 3)
    C = m.f_u.shape[-1]
    assert s(u).shape == (0, C)
    if method == "hpb":
        assert s.torch_features(u).shape == (0, C)
    w = syn.Synthesized(m, s)
    assert w(u, d, d).shape == (0, 3) and w.torch_forward(u, d, d).shape == (0, 3)


@pytest.mark.parametrize("method, settings, match", [
    ("hpb", {"lut_sz": 64}, r"unknown hpb setting.*'lut_sz'.*\['lut_size'\]"),
    ("hpb", {"lut_size": 1}, r"'lut_size' must be an integer >= 2"),
    ("hpb", {"lut_size": 0}, r"'lut_size' must be an integer >= 2"),
    ("hpb", {"lut_size": 64.5}, r"'lut_size' must be an integer >= 2"),
    ("hpb", {"lut_size": True}, r"'lut_size' must be an integer >= 2"),
    ("hextile", {"gain": 1.0}, r"'gain' must be a number in \(0, 1\)"),
    ("hextile", {"gain": 0}, r"'gain' must be a number in \(0, 1\)"),
    ("hextile", {"gian": 0.9}, r"unknown hextile setting.*'gian'"),
    ("hextile", {"contrast": 1.5}, r"'contrast' must be a number in \[0, 1\]"),
    ("hextile", {"exponent": 0}, r"'exponent' must be a number in \(0, 32\]"),
    ("hextile", {"exponent": 100.0}, r"'exponent' must be a number in \(0, 32\]"),
    ("hextile", {"rotation": float("nan")}, r"'rotation' must be a number >= 0"),
    ("hextile", {"rotation": "1"}, r"'rotation' must be a number >= 0"),
    ("quilting", {"tolerance": 0.5}, r"'tolerance' must be a number >= 1"),
    ("quilting", {"scale": 0}, r"'scale' must be an integer >= 1"),
    ("quilting", {"block": 0}, r"'block' must be a number > 0"),
    ("quilting", {"block": 7.5}, r"'block' above 1 is a side in texels: give a whole number "
                                 r">= 6 \(or a fraction <= 1 of the exemplar side\), got 7.5"),
    ("quilting", {"block": 3}, r"'block' above 1 is a side in texels.*got 3"),
    ("tiling", {"scale": 2}, r"unknown tiling setting.*it takes no settings"),
    ("linear", {"lut_size": 2}, r"unknown linear setting"),
])
def test_bad_settings_are_refused_naming_the_key_and_range(method, settings, match):
    m = _plane_model()
    with pytest.raises(ValueError, match=match):
        syn.build(m, method, 1, settings)
    cls = syn.SYNTHS[method]
    good = {"scale": 2, "block": 8} if method == "quilting" else {}
    state = syn.build(m, method, 1, good).state()
    with pytest.raises(ValueError, match=match):  # a saved file's settings: the same checks
        cls.from_state(m.f_u.detach(), 1, state, settings)


def test_good_settings_are_taken_whole_numbers_as_integers():
    m = _plane_model()
    s = syn.build(m, "hpb", 1, {"lut_size": 64.0})
    assert s.lut.shape == (m.f_u.shape[-1], 64)
    h = syn.build(m, "hextile", 1, {"exponent": 32, "contrast": 1, "gain": 0.999, "rotation": 0})
    assert h.s == {"rotation": 0.0, "contrast": 1.0, "exponent": 32.0, "gain": 0.999}
    q = syn.build(m, "quilting", 1, {"scale": 2.0, "block": 8, "tolerance": 1})
    assert q.s["scale"] == 2 and isinstance(q.s["scale"], int) and q.quilted.shape[0] == 48


def test_library_ranges_are_the_schema_ranges():
    """config/schema.yaml (the workflow's check) and neumat.btf.synthesis.settings (the
    library's) allow the same keys, types, bounds and defaults."""
    import yaml
    from pathlib import Path
    from neumat.btf.synthesis import settings
    schema = yaml.safe_load((Path(__file__).parents[1] / "config/schema.yaml").read_text())
    props = schema["properties"]["btf_synthesis"]["properties"]
    for method in ("hpb", "hextile", "quilting"):
        sch, spec = props[method]["properties"], settings.SPECS[method]
        assert props[method]["additionalProperties"] is False
        assert set(sch) == set(spec), method
        for key, r in spec.items():
            p = sch[key]
            assert p["type"] == ("integer" if r.integer else "number"), (method, key)
            assert p["default"] == r.default, (method, key)
            lo = p.get("exclusiveMinimum", p.get("minimum"))
            hi = p.get("exclusiveMaximum", p.get("maximum"))
            assert (lo, "exclusiveMinimum" in p) == ((r.lo, r.lo_open) if r.lo is not None
                                                     else (None, False)), (method, key)
            assert (hi, "exclusiveMaximum" in p) == ((r.hi, r.hi_open) if r.hi is not None
                                                     else (None, False)), (method, key)


def test_the_kernel_refuses_a_lut_of_fewer_than_two_entries():
    """Backstop below the settings check: an HPB whose LUT was cut after the build is refused
    before the C kernel reads it (L = 0 crashed it, L = 1 read the entry before the row)."""
    from neumat.btf import query
    from neumat.btf.synthesis import kernel
    m = _plane_model()
    s = syn.build(m, "hpb", 1)
    s.lut = s.lut[:, :1].contiguous()
    u = torch.rand(10, 2, dtype=torch.float64)
    d = torch.tensor([[0.0, 0.0, 1.0]]).expand(10, 3)
    with pytest.raises(ValueError, match=r"L >= 2 entries \(setting lut_size\)"):
        kernel.hpb_features(u, s)
    with torch.no_grad(), pytest.raises(ValueError, match=r"L >= 2 entries"):
        query.query(m, u, d, d, features_u=s)


@pytest.mark.parametrize("settings", [{"exponent": 32.0}, {"exponent": 32.0, "gain": 0.5},
                                      {"exponent": 31.5, "contrast": 1.0}])
def test_hextile_largest_exponent_stays_finite_and_kernel_equals_torch(settings):
    """At the largest allowed exponent the weights stay normal floats in the torch path (at
    100 all three underflowed: 0 / 0), and the fused C query equals it."""
    m = _plane_model()
    s = syn.build(m, "hextile", 3, settings)
    g = torch.Generator().manual_seed(4)
    u = torch.rand(3000, 2, generator=g, dtype=torch.float64) * 3 + 1e5
    wi = torch.nn.functional.normalize(torch.rand(3000, 3, generator=g) + torch.tensor([0, 0, 1.0]), dim=1)
    f = s(u)
    assert torch.isfinite(f).all() and (f.abs().sum(1) > 0).all()
    w = syn.Synthesized(m, s)
    ref = w.torch_forward(u, wi, wi)
    torch.testing.assert_close(w(u, wi, wi), ref, rtol=1e-4, atol=1e-5 * ref.abs().max().item())


def test_hextile_black_taps_at_contrast_1_give_equal_weights_in_both_paths():
    """contrast 1 and luminance 0 at all three taps: every blend weight is 0 before Gain3.
    Gain3's floored power (the C kernel's powk floor, hextile.POW_FLOOR) makes them 1/3 each in
    the torch path as in C (it was 0 / 0 = NaN in torch), the plain average of the taps: that
    of weights w^exponent = 1 (a tiny exponent) without luminance weighting. Without Gain3 both
    paths give features 0."""
    from neumat.btf.synthesis import hextile
    m = _plane_model()
    u = torch.rand(2000, 2, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 3
    wi = torch.nn.functional.normalize(torch.rand(2000, 3) + torch.tensor([0, 0, 1.0]), dim=1)
    plane = m.f_u.detach()
    dark = {"lum_weights": torch.zeros(plane.shape[-1] + 1), "plane_shape": list(plane.shape)}
    s = hextile.HexTile.from_state(plane, 3, dark, {"contrast": 1.0, "gain": 0.7})
    f = s(u)
    assert torch.isfinite(f).all()
    flat = hextile.HexTile.from_state(plane, 3, dark, {"contrast": 0.0, "exponent": 1e-9})
    torch.testing.assert_close(f, flat(u), rtol=1e-5, atol=1e-7)
    w = syn.Synthesized(m, s)
    ref = w.torch_forward(u, wi, wi)
    assert torch.isfinite(ref).all()
    torch.testing.assert_close(w(u, wi, wi), ref, rtol=1e-4, atol=1e-5 * ref.abs().max().item())
    none = hextile.HexTile.from_state(plane, 3, dark, {"contrast": 1.0, "gain": 0.5})
    assert torch.equal(none(u), torch.zeros_like(f))
    w = syn.Synthesized(m, none)
    torch.testing.assert_close(w(u, wi, wi), w.torch_forward(u, wi, wi))


@pytest.mark.parametrize("method", ["hpb", "hextile", "quilting"])
def test_load_refuses_a_state_of_another_model(tmp_path, method):
    """A saved state belongs to the plane it was built from: another plane's shape is an error
    naming the file and the model, not a bare torch.cat error or HPB answering silently from
    its stored exemplar."""
    st = {"scale": 2, "block": 8} if method == "quilting" else {}
    m = _plane_model()
    path = tmp_path / f"{method}.pt"
    syn.save(path, method, 4, st, {"triple_plane": syn.build(m, method, 4, st)})
    others = [_plane_model(size=20), TriplePlane(24, 20), TriplePlane(24, 24, u_channels=6)]
    for other in others:
        with pytest.raises(ValueError, match=rf"{method}\.pt: the {method} state of "
                                             r"'triple_plane' does not fit the given"):
            syn.load(path, {"triple_plane": other})
    u = torch.rand(50, 2, dtype=torch.float64) * 3
    assert torch.equal(syn.load(path, {"triple_plane": m})["triple_plane"].synth(u),
                       syn.build(m, method, 4, st)(u))


def test_the_section_flags_scales_whose_tiles_are_narrower_than_a_pixel():
    """At the tiny config's 72 x 54 render a tile at x45 spans less than a pixel (FLIP there
    measures aliasing); at the default 320 x 240 none does, and the section says nothing."""
    from neumat.btf.synthesis import stage
    spans = {s: stage.tile_span_px(72, 54, s) for s in (1, 15, 45)}
    assert spans[1] == pytest.approx(15 * spans[15]) == pytest.approx(45 * spans[45])
    assert spans[15] > 1 > spans[45]
    note = stage.subpixel_note({"width": 72, "height": 54, "spp": 1, "scales": [1, 15, 45]})
    assert note.endswith("less than a pixel at x45, so FLIP and PSNR there mostly measure "
                         "aliasing (which exemplar texels the samples happen to hit), not the "
                         "synthesis.")
    assert stage.subpixel_note({"width": 320, "height": 240, "spp": 2, "scales": [1, 15, 45]}) == ""
