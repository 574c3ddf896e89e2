"""The learner updates the observation statistics once per batch; workers receive them with the weights."""
from __future__ import annotations

import pytest
import torch

from encoders.obs_norm import FieldScaleNorm
from swarm_appo.config import ConfigError, load_config
from swarm_appo.learner import Learner, stack_fragments
from swarm_appo.model import model_factory
from swarm_appo.rollout import RolloutWorker


def tiny_config(**extra):
    overrides = {"env.num_agents": 2, "env.num_neighbors": 1, "env.episode_duration": 0.3,
                 "runner.envs_per_worker": 2, "algo.rollout": 16, "algo.batch_size": 64, "algo.num_epochs": 2,
                 "model.encoder": "deepsets", "model.encoder_kwargs": "{hidden: 8, out_dim: 8}",
                 "model.head_hidden": 8, "model.normalize_obs": "true", "model.init_action_mean": 0.053}
    overrides.update(extra)
    return load_config(None, [f"{k}={v}" for k, v in overrides.items()])


def test_learner_folds_each_batch_into_the_statistics_and_workers_get_them():
    torch.manual_seed(0)
    cfg = tiny_config()
    layout = cfg.env.obs_layout()
    make_model = model_factory(layout, cfg.model)
    worker = RolloutWorker(cfg.env, make_model, cfg.runner.envs_per_worker, cfg.algo.rollout, seed=1)
    learner = Learner(make_model(), cfg.algo, torch.device("cpu"), seed=0)
    worker.set_weights(*learner.cpu_weights())
    assert torch.equal(learner.model.actor_head[-1].bias, torch.full((4,), 0.053))

    batches = []
    for _ in range(2):
        frags = [worker.collect()]
        batches.append(stack_fragments(frags)["obs"])
        learner.train(frags)
        worker.set_weights(*learner.cpu_weights())
    # the same statistics as one norm fed the two batches directly
    reference = FieldScaleNorm(layout)
    for obs in batches:
        reference.update(torch.as_tensor(obs))
    assert torch.allclose(learner.model.obs_norm.mean_sq_norm, reference.mean_sq_norm, rtol=1e-12)
    assert torch.equal(learner.model.obs_norm.count, reference.count)
    assert torch.equal(worker.model.obs_norm.mean_sq_norm, learner.model.obs_norm.mean_sq_norm)


def test_init_action_mean_outside_the_action_range_is_a_config_error():
    with pytest.raises(ConfigError, match="model.init_action_mean"):
        from swarm_appo.config import validate
        validate(tiny_config(**{"model.init_action_mean": 1.5}))
