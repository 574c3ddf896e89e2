"""Session-wide hooks for the whole suite."""


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
