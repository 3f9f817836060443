"""The GPU query's Triton kernel (neumat.btf.query_triton) against the torch path, run on the CPU
through Triton's interpreter (the same arithmetic as on a GPU, none of its speed) and, where a
CUDA device is visible, compiled for it against the torch path on the CPU."""

import importlib
import sys
import types

import pytest
import torch

import neumat.btf.synthesis as syn
from neumat.btf import models, query, query_triton

pytest.importorskip("triton", reason="Triton is not installed (pip install -e '.[test]')")


def _interpret(monkeypatch):
    """TRITON_INTERPRET=1 when the kernels are defined (triton.jit reads it then)."""
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    if "neumat.btf.triton_kernels" in sys.modules:
        importlib.reload(sys.modules["neumat.btf.triton_kernels"])
    yield torch.device("cpu")
    monkeypatch.delenv("TRITON_INTERPRET")
    if "neumat.btf.triton_kernels" in sys.modules:  # the test may not have imported it
        importlib.reload(sys.modules["neumat.btf.triton_kernels"])


@pytest.fixture
def interpreter(monkeypatch):
    yield from _interpret(monkeypatch)


@pytest.fixture(params=["interpreter", "cuda"])
def kernel_device(request, monkeypatch):
    """Where the kernel runs: Triton's interpreter on the CPU, or the compiled kernel on a GPU
    (skipped without one). The reference is always the torch path on the CPU."""
    if request.param == "cuda":
        if not torch.cuda.is_available():
            pytest.skip("no CUDA device: the compiled kernel runs only on a GPU")
        yield torch.device("cuda")
        return
    yield from _interpret(monkeypatch)


def queries(n, seed):
    g = torch.Generator().manual_seed(seed)
    u = (torch.rand(n, 2, generator=g) - 0.5) * 1e3  # wraps many times, negative included
    def hemi():
        w = torch.randn(n, 3, generator=g)
        w[:, 2] = w[:, 2].abs() + 0.05
        return torch.nn.functional.normalize(w, dim=-1)
    wi, wo = hemi(), hemi()
    wi[0] = wo[0] = torch.tensor([0.0, 0.0, 1.0])  # h at the pole: phi_h = 0
    wi[1], wo[1] = torch.tensor([0.6, 0.0, 0.8]), torch.tensor([-0.6, 0.0, 0.8])  # h = n
    wi[2], wo[2] = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0])  # grazing
    return u, wi, wo


@pytest.mark.parametrize("kw", [{}, dict(u_channels=6, dir_channels=5, hidden=24, layers=3),
                                dict(hidden=40, layers=2), dict(dir_res=7, layers=5)])
@torch.no_grad()
def test_kernel_equals_the_torch_path(kernel_device, kw):
    """Every shape the kernel pads (channels to 16, hidden to a power of two, 3 outputs to 16),
    1, 2 or 3 hidden layers, wrap and clamp, and a last block that is not full."""
    torch.manual_seed(0)
    m = models.TriplePlane(23, 17, **kw).eval()
    for p in m.parameters():  # larger than the init, so the MLP's nonlinearity shows
        p.normal_(0, 0.3)
    m.requires_grad_(False)
    u, wi, wo = queries(333, 1)
    want = {False: m(u, wi, wo), True: m.raw(u, wi, wo)}
    d = kernel_device
    m, u, wi, wo = m.to(d), u.to(d), wi.to(d), wo.to(d)
    assert query_triton.supported(m, u, wi, wo)
    for raw in (False, True):
        got = query_triton.query(m, u, wi, wo, raw=raw).cpu()
        torch.testing.assert_close(got, want[raw], rtol=2e-5, atol=2e-5)


@pytest.mark.parametrize("kw", [{}, dict(u_channels=6, hidden=24, layers=3),
                                dict(u_channels=3, hidden=16, layers=2)])
@torch.no_grad()
def test_hpb_kernel_equals_the_torch_synthesis(kernel_device, kw):
    """HPB inside the kernel (float64 grid and fetch coordinates, integer hash, blend, LUT,
    inverse PCA folded into layer 1) = Synthesized.torch_forward, near u = 0 and at |u| ~ 1e5
    (where an fp32 grid constant alone moved results by ~1e-2); another seed, another result.
    The taps run at the channels' power of two and are widened to layer 1's 16 rows: 8 columns
    (8 channels, and 6 masked) doubled, 4 (3 channels) quadrupled."""
    torch.manual_seed(0)
    m = models.TriplePlane(23, 17, **kw).eval()
    for p in m.parameters():
        p.normal_(0, 0.3)
    m.requires_grad_(False)
    h = syn.build(m, "hpb", 5, {})
    _, wi, wo = queries(300, 6)
    g = torch.Generator().manual_seed(7)
    other = syn.build(m, "hpb", 6, {})
    us = [(torch.rand(300, 2, generator=g, dtype=torch.float64) - 0.5) * 2 * s
          for s in (10.0, 1e5)]
    want = [(syn.Synthesized(m, h).torch_forward(u, wi, wo), m.decode(h.torch_features(u), wi, wo))
            for u in us]
    d = kernel_device
    m, wi, wo = m.to(d), wi.to(d), wo.to(d)  # the HPB tables follow the model in the kernel
    for u, (out, raw) in zip(us, want):
        u = u.to(d)
        torch.testing.assert_close(query_triton.query(m, u, wi, wo, synth=h).cpu(), out,
                                   rtol=2e-5, atol=3e-5)
        torch.testing.assert_close(query_triton.query(m, u, wi, wo, raw=True, synth=h).cpu(), raw,
                                   rtol=2e-5, atol=3e-5)
    _float16_plane_is_exact(m, u, wi, wo, h)
    assert not torch.allclose(query_triton.query(m, u, wi, wo, synth=other),
                              query_triton.query(m, u, wi, wo, synth=h))


def _float16_plane_is_exact(m, u, wi, wo, synth):
    """The kernel reads the synthesised plane as float16 (its default packing): the very
    results of the same kernel reading it as float32, since the synthesis rounded it so."""
    half = query_triton._pack(m, synth)
    full = query_triton._pack(m, synth, half=False)
    key = "gauss" if synth.method == "hpb" else "plane"
    assert half[key].dtype == torch.float16 and full[key].dtype == torch.float32
    assert torch.equal(query_triton.query(m, u, wi, wo, packed=half, synth=synth),
                       query_triton.query(m, u, wi, wo, packed=full, synth=synth))


@pytest.mark.parametrize("kw, settings", [
    ({}, {}),
    (dict(u_channels=6, hidden=24, layers=3), {"rotation": 0.3, "gain": 0.5}),
    (dict(u_channels=16), {"exponent": 2.5, "contrast": 0.0, "gain": 0.9})])
@torch.no_grad()
def test_hextile_kernel_equals_the_torch_synthesis(kernel_device, kw, settings):
    """Hex-tiling inside the kernel (float64 grid, hash, rotation by a polynomial sin/cos, the
    plane's luminance channel fetched with the features, the weights, Gain3 or not, an integer
    or real exponent; 6, 8 and 16 channels, so 8, 16 and 32 padded) = Synthesized.torch_forward
    near u = 0 and at |u| ~ 1e5; another seed, another result."""
    torch.manual_seed(0)
    m = models.TriplePlane(23, 17, **kw).eval()
    for p in m.parameters():
        p.normal_(0, 0.3)
    m.requires_grad_(False)
    h = syn.build(m, "hextile", 5, settings)
    _, wi, wo = queries(300, 8)
    g = torch.Generator().manual_seed(9)
    us = [(torch.rand(300, 2, generator=g, dtype=torch.float64) - 0.5) * 2 * s
          for s in (10.0, 1e5)]
    want = [(syn.Synthesized(m, h).torch_forward(u, wi, wo), m.decode(h(u), wi, wo))
            for u in us]
    d = kernel_device
    h = syn.build(m.to(d), "hextile", 5, settings)  # its plane on the kernel's device
    other = syn.build(m, "hextile", 6, settings)
    wi, wo = wi.to(d), wo.to(d)
    for u, (out, raw) in zip(us, want):
        u = u.to(d)
        torch.testing.assert_close(query_triton.query(m, u, wi, wo, synth=h).cpu(), out,
                                   rtol=1e-4, atol=3e-5 * out.abs().max().item())
        torch.testing.assert_close(query_triton.query(m, u, wi, wo, raw=True, synth=h).cpu(),
                                   raw, rtol=1e-4, atol=3e-5 * raw.abs().max().item())
    _float16_plane_is_exact(m, u, wi, wo, h)
    assert not torch.allclose(query_triton.query(m, u, wi, wo, synth=other),
                              query_triton.query(m, u, wi, wo, synth=h))


@torch.no_grad()
def test_query_routes_hextile_on_cuda_tensors_to_its_kernel(interpreter, monkeypatch):
    """query.query sends a hex-tiling (and an HPB) synthesis on CUDA tensors to the Triton
    kernel with the synthesis, and anything else it cannot run to the torch path."""
    seen = []
    monkeypatch.setattr(query_triton, "supported", lambda *a: True)
    monkeypatch.setattr(query_triton, "try_query",
                        lambda m, u, wi, wo, raw=False, synth=None: seen.append(synth) or "gpu")
    m = models.TriplePlane(8, 8).eval()
    m.requires_grad_(False)
    wi = types.SimpleNamespace(device=torch.device("cuda"))  # query reads only its device
    for method in ("hextile", "hpb"):
        s = syn.build(m, method, 1, {})
        assert query.query(m, torch.zeros(4, 2), wi, wi, features_u=s) == "gpu"
        assert seen.pop() is s
    assert query.query(m, torch.zeros(4, 2), wi, wi) == "gpu" and seen.pop() is None


def test_packing_is_kept_until_a_parameter_changes(interpreter):
    m = models.TriplePlane(8, 8).eval()
    m.requires_grad_(False)
    first = query_triton.packed(m)
    assert query_triton.packed(m) is first
    with torch.no_grad():
        m.net[0].weight.add_(1.0)
    second = query_triton.packed(m)
    assert second is not first
    torch.testing.assert_close(second["w1u"][:8, :32], m.net[0].weight[:, :8].T)


def test_each_synthesis_keeps_its_packing(interpreter):
    """Plain and synthesised queries in turn (paper Fig. 9) reuse their packings instead of
    repacking on every call; another seed is another packing."""
    m = models.TriplePlane(8, 8).eval()
    m.requires_grad_(False)
    h, x = syn.build(m, "hpb", 1, {}), syn.build(m, "hextile", 1, {})
    first = [query_triton.packed(m, s) for s in (None, h, x)]
    assert [query_triton.packed(m, s) for s in (None, h, x)] == first
    assert all(a is b for a, b in zip(first, [query_triton.packed(m, s) for s in (None, h, x)]))
    other = syn.build(m, "hpb", 2, {})
    assert query_triton.packed(m, other)["hs"] != first[1]["hs"]
    assert query_triton.packed(m, h) is first[1]


def test_not_supported_where_it_cannot_run(monkeypatch):
    """Without the interpreter a CPU tensor never goes to Triton (the C query serves the CPU);
    NeuMIP and autograd use the torch path."""
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    m = models.TriplePlane(8, 8).eval()
    u, wi, wo = queries(10, 2)
    assert not query_triton.supported(m, u, wi, wo)  # CPU, and parameters require grad
    m.requires_grad_(False)
    assert not query_triton.supported(m, u, wi, wo)  # CPU
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    assert query_triton.supported(m, u, wi, wo)
    assert not query_triton.supported(models.NeuMIP(8, 8).requires_grad_(False), u, wi, wo)
    m.requires_grad_(True)
    assert not query_triton.supported(m, u, wi, wo)


@torch.no_grad()
def test_query_routes_only_cuda_tensors_to_triton(interpreter, monkeypatch):
    """query.query keeps the C kernel for CPU tensors, even with the interpreter on."""
    calls = []
    monkeypatch.setattr(query_triton, "query", lambda *a, **k: calls.append(1))
    m = models.TriplePlane(8, 8).eval()
    m.requires_grad_(False)
    u, wi, wo = queries(50, 3)
    torch.testing.assert_close(query.query(m, u, wi, wo), m(u, wi, wo), rtol=1e-5, atol=1e-6)
    assert not calls


@torch.no_grad()
def test_a_failing_kernel_is_logged_once_and_the_torch_path_takes_over(interpreter, monkeypatch,
                                                                         caplog):
    """The kernel has not run on a GPU yet: if it fails there, the error is logged with the way
    to turn it off, `available()` turns False, and nothing calls it again in this process."""
    calls = []

    def broken():
        calls.append(1)
        raise RuntimeError("no kernel for this GPU")

    monkeypatch.setattr(query_triton, "_kernel", broken)
    monkeypatch.setattr(query_triton, "_failed", [])
    m = models.TriplePlane(8, 8).eval()
    m.requires_grad_(False)
    u, wi, wo = queries(20, 4)
    with caplog.at_level("WARNING", logger="neumat.btf.query_triton"):
        assert query_triton.try_query(m, u, wi, wo) is None
    assert "NEUMAT_TRITON=0" in caplog.text and "no kernel for this GPU" in caplog.text
    assert calls == [1] and not query_triton.available("cpu")
    assert not query_triton.supported(m, u, wi, wo)


def test_neumat_triton_0_turns_it_off(interpreter, monkeypatch):
    m = models.TriplePlane(8, 8).eval()
    m.requires_grad_(False)
    u, wi, wo = queries(10, 5)
    assert query_triton.supported(m, u, wi, wo)
    monkeypatch.setenv("NEUMAT_TRITON", "0")
    assert not query_triton.available("cpu") and not query_triton.supported(m, u, wi, wo)
