"""runner.compile: the learner's forward compiled with torch.compile (inductor, here on the CPU) trains the same
model as the eager one on a fixed batch, and leaves the checkpoint's keys unchanged."""
from __future__ import annotations

import pytest
import torch
from torch._dynamo.utils import counters  # dynamo's own statistics: how many graphs it compiled

from swarm_appo.config import ConfigError, load_config
from swarm_appo.learner import Learner
from swarm_appo.model import model_factory

from .test_training import fixed_fragments, tiny_config

CPU = torch.device("cpu")


def test_a_compiled_learner_takes_the_same_steps_as_the_eager_one(tmp_path):
    cfg = tiny_config(tmp_path, "c", **{"model.encoder": "se3_kattention", "model.size": "small"})
    fragments = fixed_fragments(cfg)
    make = model_factory(cfg.env.obs_layout(), cfg.model)
    learners, stats, graphs = {}, {}, {}
    for mode in ("off", "default"):
        torch.manual_seed(0)
        counters.clear()
        learners[mode] = Learner(make(), cfg.algo, CPU, seed=0, compile=mode)
        stats[mode] = learners[mode].train(fragments)  # all epochs: several optimizer steps
        graphs[mode] = counters["stats"]["unique_graphs"]  # graphs dynamo captured during train()
    eager, compiled = learners["off"], learners["default"]
    assert graphs["off"] == 0 and graphs["default"] >= 1  # only the compiled learner ran a compiled graph
    assert compiled.num_updates == eager.num_updates > 1
    # fused kernels reorder float32 sums: equal to rounding, compounded over a few Adam steps
    for k in ("losses/policy_loss", "losses/value_loss", "losses/grad_norm"):
        assert stats["default"][k] == pytest.approx(stats["off"][k], rel=1e-3, abs=1e-5), k
    e_state, c_state = eager.state_dict()["model"], compiled.state_dict()["model"]
    assert list(c_state) == list(e_state)  # a compiled learner's checkpoint loads into an eager model
    start = make().state_dict()
    for k, v in e_state.items():
        if v.is_floating_point():
            torch.testing.assert_close(c_state[k], v, rtol=1e-4, atol=1e-5)
    moved = [k for k, v in e_state.items() if v.is_floating_point() and not torch.equal(v, start[k])]
    assert moved  # the weights did change: the comparison above is between trained models


def test_unknown_compile_modes_are_refused_with_the_key(tmp_path):
    with pytest.raises(ConfigError, match="runner.compile.*'off', 'default', 'reduce-overhead'"):
        load_config(None, ["runner.compile=max"])
    with pytest.raises(ValueError, match="unknown compile mode 'max'"):
        Learner(torch.nn.Linear(1, 1), load_config(None, []).algo, CPU, seed=0, compile="max")
