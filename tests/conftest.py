import pytest
import torch


@pytest.fixture
def one_thread():
    """Tiny models: one thread is fastest, and avoids spin-waiting on a shared 2-core box."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
