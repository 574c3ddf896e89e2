"""Session-wide hooks for the whole suite."""
import os
import sys

import pytest


def pytest_xdist_setupnodes(config, specs):
    """Before pytest-xdist starts its workers: compile the simulator's kernels once, float64 and float32 side by
    side (``quad_env.warmup``). Workers that start together with a cold numba cache would otherwise each compile
    the same kernels at the same moment. Only under ``-n``; a failure here only costs time (kernels then compile
    on first use, as without it), the tests report any real fault."""
    import time

    from quad_env.warmup import warm_in_parallel

    start = time.perf_counter()
    codes = warm_in_parallel(jobs=min(2, len(specs)))
    print(f"\nquad_env.warmup: kernels ready in {time.perf_counter() - start:.1f} s (exit codes {codes})")


@pytest.fixture
def one_torch_thread():
    """Tiny policies on small batches: a second OpenMP thread only waits (very long on a loaded machine).
    One thread is also what the evaluation and export commands use. Restores the thread count after the test."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(autouse=True)
def _one_torch_thread_per_xdist_worker():
    """Under pytest-xdist the suite runs one process per core, so a second torch thread per process only spins
    against the other process (the small test models wait on it far longer than they compute). Set before every
    test: an in-process training sets its learner's threads and keeps them. Not under ``-n 0``, where one process
    has the cores to itself."""
    torch = sys.modules.get("torch")  # only if a test module already imported it: light tests stay light
    if torch is not None and os.environ.get("PYTEST_XDIST_WORKER") and torch.get_num_threads() != 1:
        torch.set_num_threads(1)
    yield
