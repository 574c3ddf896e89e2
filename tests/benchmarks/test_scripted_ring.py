"""benchmarks.scripted_ring: the ring slots are where they should be, and the controller really holds them
(the reference row of the quality goal is a measurement, not a number written down)."""
import numpy as np

from benchmarks import scripted_ring
from swarm_appo.config import load_config
from swarm_appo.evaluation import evaluation_env


def test_ring_slots_are_evenly_spaced_at_the_radius():
    slots = scripted_ring.ring_offsets(8, 0.35)
    np.testing.assert_allclose(np.linalg.norm(slots, axis=1), 0.35)
    np.testing.assert_allclose(slots[:, 2], 0.0)
    gaps = np.linalg.norm(slots - np.roll(slots, 1, axis=0), axis=1)
    np.testing.assert_allclose(gaps, 2 * 0.35 * np.sin(np.pi / 8))  # chord of 1/8 of the circle


def test_the_controller_holds_the_ring_and_radius_zero_crowds_the_goal():
    cfg = load_config("configs/table1/recipe.yaml", ["env.episode_duration=8.0"])
    env_cfg = evaluation_env(cfg.env)
    ring = scripted_ring.fly_ring(env_cfg, 0.35, episodes=2, seed=5)
    assert abs(ring["dist"] - 0.35) < 0.1  # mean over the last 5 s: arrived and holding the slot
    crowd = scripted_ring.fly_ring(env_cfg, 0.0, episodes=2, seed=5)
    assert crowd["cold"] > 5 * max(ring["cold"], 1.0)  # all eight at one point keep hitting each other


def test_bad_radii_are_a_usage_error(capsys):
    import pytest
    for bad in ("a,b", "-0.3"):
        with pytest.raises(SystemExit) as exit_info:
            scripted_ring.main(["--radii", bad, "--no-append"])
        assert exit_info.value.code == 2 and "--radii" in capsys.readouterr().err
