"""env.reward.collision_anneal_steps: the trainer scales the collision penalties from 0 to full over that many
agent steps, and the scale travels with the published weights to every rollout worker (in process here; on Ray
in test_training.py, next to the module's Ray fixture)."""
import pytest

from swarm_appo.config import ConfigError, load_config
from swarm_appo.model import model_factory
from swarm_appo.sampling import SerialSampler
from swarm_appo.trainer import env_schedule, train

from .test_training import read_metrics, tiny_config


def test_schedule_is_linear_up_to_the_anneal_steps_then_full(tmp_path):
    cfg = tiny_config(tmp_path, "s", **{"env.reward.collision_anneal_steps": 1000})
    assert [env_schedule(cfg, s)["collision_scale"] for s in (0, 250, 1000, 5000)] == [0.0, 0.25, 1.0, 1.0]
    off = tiny_config(tmp_path, "o")
    assert off.env.reward.collision_anneal_steps == 0 and env_schedule(off, 0)["collision_scale"] == 1.0


def test_a_negative_anneal_is_a_config_error_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match="env.reward.collision_anneal_steps"):
        load_config(None, ["env.reward.collision_anneal_steps=-5"])


def test_serial_workers_collect_with_the_published_scale(tmp_path):
    cfg = tiny_config(tmp_path, "w")
    make_model = model_factory(cfg.env.obs_layout(), cfg.model)
    sampler = SerialSampler(cfg.env, make_model, num_workers=2, envs_per_worker=1, rollout=8, seed=0)
    sampler.publish(0, make_model().state_dict(), {"collision_scale": 0.25})
    assert [sampler.get()["collision_scale"] for _ in range(2)] == [0.25, 0.25]
    assert all(w.env.collision_scale == 0.25 for w in sampler.workers)
    sampler.publish(1, make_model().state_dict(), {"collision_scale": 0.5})
    assert sampler.get()["collision_scale"] == 0.5


def test_training_anneals_and_logs_the_scale(tmp_path):
    cfg = tiny_config(tmp_path, "t", **{"env.reward.collision_anneal_steps": 256})
    result = train(cfg, progress=False)
    logged = [(r["global_step"], r["charts/collision_scale"]) for r in read_metrics(result.run_dir)
              if "charts/collision_scale" in r]
    assert logged and all(scale == min(1.0, step / 256) for step, scale in logged)
    assert logged[0][1] < 1.0 and logged[-1][1] == 1.0
