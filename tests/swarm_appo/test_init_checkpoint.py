"""runner.init_checkpoint: a new run starts from another run's policy, in its own directory, with fresh counters;
a policy that does not fit is a ConfigError naming the key, before any run directory exists."""
import json

import pytest
import torch

from swarm_appo.checkpoint import TrainingState
from swarm_appo.config import ConfigError, load_config
from swarm_appo.trainer import Trainer, train

from tests.swarm_appo.test_training import tiny_overrides


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    """A tiny trained run (serial, deepsets) and its final checkpoint's state."""
    root = tmp_path_factory.mktemp("init")
    torch.set_num_threads(1)
    result = train(load_config(None, tiny_overrides(root, "first")), progress=False)
    state, _ = TrainingState.load_latest(result.run_dir)
    return root, result.run_dir, state


def second(root, name, init, **extra):
    return load_config(None, tiny_overrides(root, name, **{"runner.init_checkpoint": str(init), **extra}))


def test_a_new_run_starts_from_the_checkpoint_weights_with_fresh_counters(first_run):
    root, run_dir, state = first_run
    assert state.agent_steps > 0
    with Trainer(second(root, "stage2", run_dir), progress=False) as trainer:  # the run directory: newest checkpoint
        loaded = trainer.learner.model.state_dict()
        assert trainer.agent_steps == 0 and trainer.learner.version == 0
        assert not trainer.learner.optimizer.state  # Adam starts afresh
        assert trainer.run_dir != run_dir
    for name, tensor in state.learner["model"].items():
        torch.testing.assert_close(loaded[name], tensor, rtol=0, atol=0, msg=name)
    # a fresh network from the same seed differs: the equality above is the checkpoint's doing
    with Trainer(load_config(None, tiny_overrides(root, "fresh")), progress=False) as fresh:
        assert any(not torch.equal(fresh.learner.model.state_dict()[k], v) for k, v in state.learner["model"].items())


def test_the_new_run_keeps_its_own_history(first_run):
    root, run_dir, state = first_run
    before = (run_dir / "metrics.jsonl").read_text()
    result = train(second(root, "stage2_trained", run_dir), progress=False)
    steps = [json.loads(line)["global_step"] for line in (result.run_dir / "metrics.jsonl").read_text().splitlines()]
    assert steps[0] < state.agent_steps and steps == sorted(steps)  # counted from 0, not from the first run's steps
    assert (run_dir / "metrics.jsonl").read_text() == before  # the first run is untouched
    saved, _ = TrainingState.load_latest(result.run_dir)
    assert saved.config["runner"]["init_checkpoint"] == str(run_dir)  # where it came from, in its config


@pytest.mark.parametrize("extra,words", [
    ({"model.encoder": "kattention"}, ["model.encoder", "'deepsets' there", "'kattention' here"]),
    ({"model.encoder_kwargs.hidden": 48}, ["model.encoder_kwargs"]),
    ({"env.neighbor_obs": "pos_vel"}, ["do not fit", "env.neighbor_obs"]),
])
def test_a_policy_that_does_not_fit_is_refused_before_a_run_dir_exists(first_run, extra, words):
    root, run_dir, _ = first_run
    with pytest.raises(ConfigError, match="runner.init_checkpoint") as info:
        Trainer(second(root, "misfit", run_dir, **extra), progress=False)
    for word in words:
        assert word in str(info.value)
    assert not (root / "misfit").exists()


def test_a_missing_or_empty_source_is_refused(first_run, tmp_path):
    root, _, _ = first_run
    with pytest.raises(ConfigError, match="runner.init_checkpoint: .*does not exist"):
        Trainer(second(root, "nowhere", tmp_path / "no_such_run"), progress=False)
    (tmp_path / "empty_run").mkdir()
    with pytest.raises(ConfigError, match="runner.init_checkpoint: no valid checkpoint"):
        Trainer(second(root, "empty", tmp_path / "empty_run"), progress=False)
    assert not (root / "nowhere").exists() and not (root / "empty").exists()


def test_a_checkpoint_file_works_too_and_init_values_may_differ(first_run):
    root, run_dir, state = first_run
    ckpt = sorted((run_dir / "checkpoints").glob("ckpt_*.pt"))[-1]
    with Trainer(second(root, "from_file", ckpt, **{"model.init_log_std": -1.0}), progress=False) as trainer:
        torch.testing.assert_close(trainer.learner.model.log_std.detach(), state.learner["model"]["log_std"])
