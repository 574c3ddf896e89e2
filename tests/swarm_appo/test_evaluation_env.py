"""The final evaluation judges a policy in the training environment minus the training aids."""
from quad_env import EnvConfig, VecQuadEnv
from swarm_appo.trainer import evaluation_env


def test_evaluation_env_switches_respawn_off_and_keeps_the_rest():
    train = EnvConfig(num_agents=3, scenario="swap_goals", respawn_on_floor=True,
                      reward=dict(crash=5.0, tilt=1.0))
    ev = evaluation_env(train)
    assert ev.respawn_on_floor is False
    assert train.respawn_on_floor is True  # the training config is not modified
    assert (ev.num_agents, ev.scenario, ev.reward.crash, ev.reward.tilt) == (3, "swap_goals", 5.0, 1.0)
    # and the evaluation env really lets a crashed drone lie on the floor
    env = VecQuadEnv(ev, num_envs=1, seed=0)
    for _ in range(400):
        env.step([[-1.0] * 4] * 3)
    assert (env.get_state().pos[:, 2] <= ev.physics.floor_z).all()
    assert env.episode_stats(0)["respawns"] == 0
