"""The C fit kernel (fit_step.c) against the torch reference step, and how it is built and used.

The agreement tests run for every build of fit_step.c that compiles and runs here: native and,
on x86, the AVX2 (x86-64-v3) and SSE4.2 (x86-64-v2) levels, whose vector width and register
blocking differ (an AVX-512 host tests all three)."""

import dataclasses
import json
import logging
import platform

import pytest
import torch

from neumat import fit, fit_kernel, machine, nbrdf

pytestmark = pytest.mark.skipif(not fit_kernel.available(), reason="the C kernel cannot be built")
B, M, N = 300, 5, 64  # bins in the table, materials, minibatch
X86 = platform.machine().lower() in ("x86_64", "amd64")
MARCHES = [pytest.param(m, marks=pytest.mark.skipif(not (X86 or m == "native") or
                                                    not fit_kernel.available(m),
                                                    reason=f"-march={m} does not build or run here"))
           for m in ("native", "x86-64-v3", "x86-64-v2")]


def problem(seed=0):
    """A table of B bins (inputs + cos, targets of M materials) and one minibatch of it."""
    g = torch.Generator().manual_seed(seed)
    xc_all = torch.randn(B, 7, generator=g)
    xc_all[:, 6] = torch.rand(B, generator=g)
    target = torch.rand(B, 3 * M, generator=g)
    w = nbrdf.init_weights(M, g) * 1.5
    idx = torch.randperm(B, generator=g)[:N][None]
    sign = torch.where(torch.rand(1, N, generator=g) < 0.5, -1.0, 1.0)
    return xc_all, target, w, idx, sign


def reference_minibatch(xc_all, target, idx, sign):
    """The same minibatch as torch's path builds it: feature-major x (6, n), t (M, 3, n), cos."""
    xc = xc_all[idx[0]].t().clone()
    xc[3:5] *= sign[0]
    t = target[idx[0]].view(N, M, 3).permute(1, 2, 0).contiguous()
    return xc[:6].contiguous(), t, xc[6:]


@pytest.mark.parametrize("march", MARCHES)
@pytest.mark.parametrize("activation", nbrdf.ACTIVATIONS)
def test_loss_and_gradient_match_the_torch_step(activation, march):
    xc_all, target, w, idx, sign = problem()
    slope = 0.0 if activation == "relu" else fit.LEAKY_SLOPE
    st = fit_kernel.Stepper(xc_all, target, N, slope=slope, march=march)
    w0, m, v = w.clone(), torch.zeros_like(w), torch.zeros_like(w)
    loss, grad = st.run(w, m, v, idx, sign, torch.zeros(1), 0)  # lr 0: no update
    ref_loss, ref_grad = fit.loss_and_grad(w0, *reference_minibatch(xc_all, target, idx, sign),
                                           activation)
    assert torch.equal(w, w0) and not m.any()
    torch.testing.assert_close(loss, ref_loss, rtol=1e-5, atol=1e-7)
    for a, b in zip(nbrdf.unflatten(grad), nbrdf.unflatten(ref_grad)):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6 * b.abs().max().item())


@pytest.mark.parametrize("march", MARCHES)
def test_adam_steps_match_the_torch_step(march):
    xc_all, target, w, idx, sign = problem(1)
    idx, sign = idx.repeat(3, 1), sign.repeat(3, 1)  # three steps on the same minibatch
    lr = torch.tensor([1e-2, 5e-3, 2e-3])
    st = fit_kernel.Stepper(xc_all, target, N, march=march)
    wc, mc, vc = w.clone(), torch.zeros_like(w), torch.zeros_like(w)
    st.run(wc, mc, vc, idx, sign, lr, 0)
    wt, mt, vt = w.clone(), torch.zeros_like(w), torch.zeros_like(w)
    for k in range(3):
        _, g = fit.loss_and_grad(wt, *reference_minibatch(xc_all, target, idx[k:k + 1],
                                                          sign[k:k + 1]))
        fit.adam_step(wt, g, mt, vt, k + 1, lr[k].item())
    assert not torch.equal(wc, w)
    torch.testing.assert_close(mc, mt, rtol=1e-3, atol=1e-6)
    torch.testing.assert_close(wc, wt, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("march", MARCHES)
@pytest.mark.parametrize("activation", nbrdf.ACTIVATIONS)
def test_evaluation_loss_matches_field_loss(activation, march):
    """Over 203 bins: 3 chunks of 64 and a tail that is no whole vector; f clamped at 0."""
    xc_all, target, w, _, _ = problem(3)
    slope = 0.0 if activation == "relu" else fit.LEAKY_SLOPE
    idx = torch.randperm(B, generator=torch.Generator().manual_seed(4))[:203]
    got = fit_kernel.Stepper(xc_all, target, N, threads=2, slope=slope,
                             march=march).losses(w, idx)
    t = target[idx].view(len(idx), M, 3).transpose(0, 1)
    ref = fit.field_loss(w, xc_all[idx, :6], t, xc_all[idx, 6:], activation)
    assert (nbrdf.forward_raw(w, xc_all[idx, :6], activation) < 0).any()  # the clamp matters
    torch.testing.assert_close(got, ref, rtol=2e-6, atol=0)


def test_threads_do_not_change_the_result():
    xc_all, target, w, idx, sign = problem(2)
    idx, sign, lr = idx.repeat(4, 1), sign.repeat(4, 1), torch.full((4,), 1e-2)
    out = []
    for threads in (1, 3):
        wk, m, v = w.clone(), torch.zeros_like(w), torch.zeros_like(w)
        fit_kernel.Stepper(xc_all, target, N, threads).run(wk, m, v, idx, sign, lr, 0)
        out.append(wk)
    assert torch.equal(*out)


def test_denormal_mode_is_restored():
    """The kernel flushes denormals inside the call only; torch must still see them after."""
    xc_all, target, w, idx, sign = problem()
    fit_kernel.Stepper(xc_all, target, N).run(w, torch.zeros_like(w), torch.zeros_like(w), idx,
                                              sign, torch.full((1,), 1e-3), 0)
    tiny = torch.tensor([1e-39]) * torch.tensor([1.0])  # a float32 denormal
    assert tiny.item() != 0


def test_bad_shapes_and_minibatch_sizes_are_refused():
    xc_all, target, w, idx, sign = problem()
    with pytest.raises(ValueError, match="multiple of 16"):
        fit_kernel.Stepper(xc_all, target, 50)
    st = fit_kernel.Stepper(xc_all, target, N)
    z = torch.zeros_like(w)
    with pytest.raises(ValueError, match="out of range"):
        st.run(w, z, z.clone(), idx + B, sign, torch.zeros(1), 0)
    with pytest.raises(ValueError, match="float32"):
        st.run(w.double(), z, z.clone(), idx, sign, torch.zeros(1), 0)


def test_kernel_setting_resolves_and_errors_name_the_key(monkeypatch):
    monkeypatch.setattr(fit_kernel, "auto_choice", lambda *a: "c")
    s = fit.FitSettings()
    assert fit.resolve_kernel(s, "cpu") == "c"
    assert fit.resolve_kernel(dataclasses.replace(s, kernel="torch"), "cpu") == "torch"
    assert fit.resolve_kernel(dataclasses.replace(s, batch=500), "cpu") == "torch"
    with pytest.raises(ValueError, match="fit.kernel: c.*multiple of 16"):
        fit.resolve_kernel(dataclasses.replace(s, batch=500, kernel="c"), "cpu")
    with pytest.raises(ValueError, match="fit.kernel"):
        fit.FitSettings(kernel="cuda")


def test_without_a_compiler_the_torch_path_is_used(monkeypatch, tmp_path, caplog):
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    monkeypatch.setenv("NEUMAT_CACHE", str(tmp_path))
    fit_kernel._library.cache_clear()
    try:
        assert not fit_kernel.available()
        assert "no C compiler" in caplog.text
        assert fit.resolve_kernel(fit.FitSettings(), "cpu") == "torch"
    finally:
        fit_kernel._library.cache_clear()


def test_the_library_is_cached_per_source_and_cpu(monkeypatch, tmp_path):
    monkeypatch.setenv("NEUMAT_CACHE", str(tmp_path))
    fit_kernel._library.cache_clear()
    try:
        assert fit_kernel.available()
        built = list(tmp_path.glob("fit_step-*.so"))
        assert len(built) == 1 and not list(tmp_path.glob("tmp*"))  # no temporary left behind
        mtime = built[0].stat().st_mtime_ns
        fit_kernel._library.cache_clear()
        assert fit_kernel.available() and built[0].stat().st_mtime_ns == mtime  # not rebuilt
    finally:
        fit_kernel._library.cache_clear()


def test_variants_target_their_isa():
    """The -march levels the tests build really differ in vector ISA (else they test nothing)."""
    if not X86:
        pytest.skip("x86 levels only")
    assert machine.compiler_isa("x86-64-v3") == "AVX2"
    assert machine.compiler_isa("x86-64-v2") == "SSE4.2"
    assert fit_kernel.runs_here("native") and fit_kernel.runs_here("x86-64-v2")
    assert fit_kernel.runs_here("x86-64-v4") == ("avx512f" in machine.cpu_flags())


@pytest.fixture
def fresh_cache(monkeypatch, tmp_path):
    """An empty kernel cache, and no in-process memory of builds or choices."""
    monkeypatch.setenv("NEUMAT_CACHE", str(tmp_path))
    fit_kernel._library.cache_clear()
    fit_kernel.auto_choice.cache_clear()
    yield tmp_path
    fit_kernel._library.cache_clear()
    fit_kernel.auto_choice.cache_clear()


def test_auto_takes_the_faster_step_and_caches_the_choice(monkeypatch, fresh_cache, caplog):
    calls = []

    def fake(batch, activation, march):  # the C step slower here: auto must not take it
        calls.append((batch, activation))
        return dict(c_us=900.0, torch_us=90.0, choice="torch")

    monkeypatch.setattr(fit_kernel, "_calibrate", fake)
    caplog.set_level(logging.INFO, "neumat.fit_kernel")
    s = fit.FitSettings()
    assert fit.resolve_kernel(s, "cpu") == "torch"
    assert "fit kernel auto: torch" in caplog.text and "900.0" in caplog.text
    stored = json.loads(next(fresh_cache.glob("fit_step-*.so.choice.json")).read_text())
    assert stored == {"batch=512 activation=relu": dict(c_us=900.0, torch_us=90.0,
                                                        choice="torch")}
    assert fit.resolve_kernel(dataclasses.replace(s, kernel="c"), "cpu") == "c"  # c forces C
    fit_kernel.auto_choice.cache_clear()  # a new process: the file answers, no new timing
    assert fit.resolve_kernel(s, "cpu") == "torch" and len(calls) == 1
    # another minibatch size is timed on its own and kept beside the first
    fit_kernel.auto_choice.cache_clear()
    monkeypatch.setattr(fit_kernel, "_calibrate",
                        lambda *a: dict(c_us=30.0, torch_us=90.0, choice="c"))
    assert fit.resolve_kernel(dataclasses.replace(s, batch=256), "cpu") == "c"
    stored = json.loads(next(fresh_cache.glob("fit_step-*.so.choice.json")).read_text())
    assert sorted(stored) == ["batch=256 activation=relu", "batch=512 activation=relu"]


def test_calibration_times_both_steps(fresh_cache):
    """The real calibration: positive per-material-step times, the choice the faster one."""
    r = fit_kernel._calibrate(64, "relu", None)
    assert r["c_us"] > 0 and r["torch_us"] > 0
    assert r["choice"] == ("c" if r["c_us"] <= r["torch_us"] else "torch")
