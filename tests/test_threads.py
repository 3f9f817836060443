"""Thread counts are speed keys (config/speed_keys.yaml): where a key claims the same bits on 1
and 2 threads, the library path behind it gives them. Each test computes one step on 1 and on 2
threads (torch intra-op threads, or OpenBLAS's for numpy) and compares bit for bit."""


import numpy as np
import pytest
import torch
from threadpoolctl import threadpool_limits

from neumat.baselines.pca import NielsenPCA, WeightPCA
from neumat.btf import models


@pytest.fixture
def torch_threads():
    n = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(n)


def _plane_model_grads(method: str) -> dict:
    torch.manual_seed(0)
    m = models.NEURAL[method](24, 24)
    for p in m.parameters():
        torch.nn.init.normal_(p, std=0.3)
    n = 4096  # many queries per texel, so the taps' gradients collide
    uv = torch.rand(n, 2)
    wi = torch.nn.functional.normalize(torch.randn(n, 3) + torch.tensor([0, 0, 2.0]), dim=-1)
    target = torch.rand(n, 3)
    m.zero_grad()
    (m.raw(uv, wi, wi.flip(0)) - target).abs().mean().backward()
    return {k: p.grad.clone() for k, p in m.named_parameters()}


@pytest.mark.parametrize("method", ["triple_plane", "neumip"])
def test_btf_plane_gradients_are_the_same_on_one_and_two_threads(torch_threads, method):
    """btf.threads: the planes' gradients (bilinear taps summed back into the plane) were
    thread-dependent with plane[idx] (this test failed on them): now the same bytes, and so are
    the biases'. The MLP's weight gradients are GEMMs whose reduction runs over the queries; MKL
    splits it between threads on Intel CPUs (not on the AMD EPYC), so there they agree to float32
    rounding only (held to 1e-6 of the largest here). Every gradient is the same bytes on a
    repeat at the same thread count."""
    torch_threads(1)
    one = _plane_model_grads(method)
    torch_threads(2)
    two, again = _plane_model_grads(method), _plane_model_grads(method)
    for k in one:
        assert torch.equal(two[k], again[k]), k
        if k.startswith("net.") and k.endswith(".weight"):
            scale = one[k].abs().max()
            assert (one[k] - two[k]).abs().max() <= 1e-6 * scale, k
        else:
            assert torch.equal(one[k], two[k]), k


def _tables(n=48, bins=10731, seed=0):  # the tiny run's PCA-A shapes
    rng = np.random.default_rng(seed)
    base = rng.lognormal(-2, 1, (1, 3, bins))
    return base * rng.lognormal(0, 0.5, (n, 3, 1)) * rng.lognormal(0, 0.1, (n, 3, bins))


def test_pca_baselines_sample_the_same_on_one_and_two_blas_threads():
    """baselines.threads: PCA-A's tables moved by 3e-8 between 1 and 2 OpenBLAS threads when its
    encode/decode products ran on the job's threads (tiny config)."""
    tables = _tables()
    bins = np.arange(tables.shape[-1])
    out = {}
    for t in (1, 2):
        with threadpool_limits(t, user_api="blas"):
            a = NielsenPCA(8, bins).fit(tables)
            w = WeightPCA(8).fit(np.log(tables[:, 0, :675]))
            out[t] = (a.sample(16, 3), a.coefficients(tables), w.sample(16, 4))
    for x, y in zip(out[1], out[2]):
        assert np.array_equal(x, y)
