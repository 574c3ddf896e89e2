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
