"""Trainer defaults: learner threads + rollout workers never exceed the cores (runner.learner_threads=0); wandb
groups and tags name the architecture and symmetry."""
import pytest

from swarm_appo import trainer
from swarm_appo.config import load_config


@pytest.mark.parametrize("cores,overrides,workers,expected", [
    (2, [], 1, 1),                                   # the 2-core laptop: one worker, one learner thread
    (16, [], 15, 1),
    (16, ["runner.num_workers=4"], 4, 12),           # fewer workers: the learner gets the rest
    (16, ["runner.num_workers=40"], 40, 1),          # oversubscribed by the user: still at least one
    (8, ["runner.serial=true"], 7, 8),               # workers take turns with the learner
    (8, ["runner.learner_threads=3"], 7, 3),         # explicit
    (8, ["runner.ray_address=auto"], 30, 1),         # cluster: this node may host a worker per core
])
def test_learner_threads_fill_the_cores_left(monkeypatch, cores, overrides, workers, expected):
    monkeypatch.setattr(trainer.os, "cpu_count", lambda: cores)
    cfg = load_config(None, overrides)
    assert trainer.learner_threads(cfg, workers) == expected


def test_wandb_group_and_tags_name_architecture_and_symmetry():
    cfg = load_config(None, ["model.encoder=se3_kattention"])
    assert trainer.model_group(cfg) == "kattention/se3"
    assert trainer.model_tags(cfg) == ("kattention", "symmetry:se3", "size:small", "scenario:static_same_goal")
    assert trainer.model_group(load_config(None, ["model.symmetry=yaw", "model.body_frame_obs=null"])) == "deepsets/yaw"


def test_linear_lr_schedule_decays_to_zero_at_the_budget_and_constant_stays():
    cfg = load_config(None, ["algo.lr=1e-3", "algo.lr_schedule=linear", "runner.total_agent_steps=1000"])
    assert [trainer.scheduled_lr(cfg, s) for s in (0, 250, 1000, 2000)] == pytest.approx([1e-3, 7.5e-4, 0.0, 0.0])
    const = load_config(None, ["algo.lr=1e-3"])
    assert trainer.scheduled_lr(const, 10**9) == 1e-3


def test_linear_lr_schedule_reaches_the_optimizer_in_a_run(tmp_path):
    import json

    from swarm_appo.config import ConfigError

    with pytest.raises(ConfigError, match="algo.lr_schedule must be one of"):
        load_config(None, ["algo.lr_schedule=cosine"])
    cfg = load_config(None, ["env.num_agents=2", "env.num_neighbors=1", "env.episode_duration=0.3",
                             "runner.serial=true", "runner.num_workers=1", "runner.envs_per_worker=2",
                             "algo.rollout=16", "algo.batch_size=64", "algo.num_epochs=1", "algo.lr=1e-3",
                             "algo.lr_schedule=linear", "runner.total_agent_steps=256", "runner.final_eval_episodes=0",
                             f"runner.run_dir={tmp_path}", "runner.name=lr", "wandb.mode=disabled"])
    trainer.train(cfg, progress=False)
    records = [json.loads(line) for line in (tmp_path / "lr" / "metrics.jsonl").read_text().splitlines()]
    lrs = [r["charts/learning_rate"] for r in records]
    steps = [r["global_step"] for r in records]
    assert lrs == pytest.approx([1e-3 * (1 - s / 256) for s in steps])  # set from the steps at training time
    assert lrs == sorted(lrs, reverse=True) and lrs[0] < 1e-3
