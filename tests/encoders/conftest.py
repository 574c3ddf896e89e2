import pytest
import torch


@pytest.fixture(autouse=True)
def one_thread():
    """Tests of tiny models run fastest (and least disturbed by parallel jobs) on one thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
