"""Shared fixtures for the swarm_appo tests."""
import pytest
import torch


@pytest.fixture
def one_torch_thread():
    """Tiny policies on small batches: a second OpenMP thread only waits (very long on a loaded machine).
    One thread is also what the evaluation and export commands use."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
