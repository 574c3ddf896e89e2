"""quad_env.warmup compiles what the simulator's common configs reach, so a later process only loads kernels."""
import json
import subprocess
import sys

import pytest

from quad_env import warmup

# A fresh process steps the warmed configs and reports numba's cache hits and misses of every quad_env kernel.
PROBE = """
import json, sys
import numpy as np
from numba.core.registry import CPUDispatcher
from quad_env import kernels, obstacles, replay, rng, scenarios
from quad_env.vec_env import VecQuadEnv
from quad_env.warmup import variants

for dtype in sys.argv[1:]:
    for cfg in variants(dtype):
        env = VecQuadEnv(cfg, num_envs=48, seed=1)
        for _ in range(cfg.episode_steps + 1):
            env.step(np.zeros((env.num_drones, 4), np.float32))
hits = misses = 0
for module in (kernels, obstacles, replay, rng, scenarios):
    for obj in vars(module).values():
        if isinstance(obj, CPUDispatcher):
            hits += sum(obj.stats.cache_hits.values())
            misses += sum(obj.stats.cache_misses.values())
print(json.dumps({"hits": hits, "misses": misses}))
"""


def probe(*dtypes):
    out = subprocess.run([sys.executable, "-c", PROBE, *dtypes], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_after_the_warmup_a_fresh_process_compiles_nothing():
    # the suite's own numba cache: cheap when the xdist hook (tests/conftest.py) has warmed it already
    assert warmup.warm_in_parallel(jobs=2) == [0, 0]
    stats = probe("float64", "float32")
    assert stats["misses"] == 0
    assert stats["hits"] >= 10  # it did load the step, observe, spawn and scenario kernels from the cache


def test_bad_arguments_name_the_valid_values(capsys):
    with pytest.raises(ValueError, match=r"unknown sim dtype\(s\) \['float16'\]; valid: \['float64', 'float32'\]"):
        warmup.warm_in_parallel(["float16"])
    with pytest.raises(ValueError, match="jobs must be >= 1"):
        warmup.warm_in_parallel(jobs=0)
    with pytest.raises(SystemExit):
        warmup.main(["--dtypes", "float16", "--jobs", "1"])
    assert "unknown sim dtype 'float16'" in capsys.readouterr().err
