"""EnvConfig / PhysicsConfig validation and the packed kernel parameters."""
import numpy as np
import pytest

from quad_env import EnvConfig, PhysicsConfig, RewardConfig
from quad_env.params import F_MOTOR_GAIN, F_SENSE_R, F_TMAX, I_COLL_KICK, I_TAIL_STEPS, I_THRUST_NOISE, pack_params


def test_nested_sections_accept_dicts():
    cfg = EnvConfig(reward={"pos": 1.0}, physics={"mass": 0.03, "inertia": [1e-5, 1e-5, 2e-5]})
    assert isinstance(cfg.reward, RewardConfig) and cfg.reward.pos == 1.0
    assert isinstance(cfg.physics, PhysicsConfig) and cfg.physics.inertia == (1e-5, 1e-5, 2e-5)
    assert cfg.validate() is cfg and cfg.to_dict()["physics"]["mass"] == 0.03


@pytest.mark.parametrize("kwargs,key", [
    (dict(nan_policy="ignore"), "env.nan_policy"),
    (dict(episode_duration=0.001), "env.episode_duration"),
    (dict(reward={"collision": -1.0}), "env.reward.collision"),
    (dict(reward={"proximity_dist": 0.0}), "env.reward.proximity_dist"),
    (dict(reward={"collision_form": "per_pair"}), "env.reward.collision_form"),
    (dict(physics={"inertia": (1.0, 2.0)}), "env.physics.inertia"),
    (dict(physics={"wall_restitution": 1.5}), "env.physics.wall_restitution"),
    (dict(physics={"reortho_interval": 0}), "env.physics.reortho_interval"),
    (dict(physics={"floor_z": 20.0}), "env.physics.floor_z"),
    (dict(sensing_radius=0.0), "env.sensing_radius"),
])
def test_validation_names_the_key(kwargs, key):
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        EnvConfig(**kwargs).validate()


def test_packed_parameters():
    cfg = EnvConfig(sensing_radius=None, episode_duration=3.0)
    f, i = pack_params(cfg, obs_dim=150)
    assert f[F_TMAX] == pytest.approx(1.9 * 0.028 * 9.81 / 4)
    assert f[F_MOTOR_GAIN] == pytest.approx(0.005 / 0.0375)
    assert np.isinf(f[F_SENSE_R])
    assert i[I_TAIL_STEPS] == 300  # episode shorter than 5 s: the whole episode
    _, quiet = pack_params(cfg, obs_dim=150, noise=False)
    assert i[I_THRUST_NOISE] == 1 and quiet[I_THRUST_NOISE] == 0 and quiet[I_COLL_KICK] == 0


def test_collision_form_default_and_valid_values():
    assert RewardConfig().collision_form == "paper"
    with pytest.raises(ValueError, match=r"\['paper', 'pairwise'\], got 'Paper'"):
        EnvConfig(reward={"collision_form": "Paper"}).validate()
    EnvConfig(reward={"collision_form": "pairwise"}).validate()
