"""benchmarks.hover_probe: window statistics on analytic trajectories (a drone circling its goal with a fixed
offset in its own frame, a drone holding still), the table, and usage errors."""
import numpy as np
import pytest

from benchmarks.hover_probe import hover_stats, main, parse_env_change, probe, table


def rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_a_drone_circling_with_a_body_frame_offset():
    # yaw(t) = w t; the drone sits at R(t) (0, r, 0) from its goal: it circles at radius r, speed w r
    r, w, dt, T = 0.55, 0.6, 0.01, 301  # 3 s window
    t = np.arange(T) * dt
    rot = np.stack([rz(w * ti) for ti in t])[:, None]  # [T, 1, 3, 3]
    goal = np.tile([1.0, -2.0, 2.0], (T, 1, 1))  # [T, 1, 3]
    pos = goal + np.einsum("tmij,j->tmi", rot, np.array([0.0, r, 0.0]))
    vel = np.einsum("tmij,j->tmi", rot, np.array([-w * r, 0.0, 0.0]))  # d/dt R(t) (0, r, 0)
    s = hover_stats(pos, goal, rot, vel, dt)
    assert s["dist"] == pytest.approx(r)
    assert s["body_offset"] == pytest.approx([0.0, r, 0.0], abs=1e-12)
    assert s["body_offset_norm"] == pytest.approx(r)
    assert s["yaw_turned_deg"] == pytest.approx(np.degrees(w * 3.0))
    assert s["speed"] == pytest.approx(w * r)
    assert s["path"] == pytest.approx(w * r * 3.0, rel=1e-4)  # the arc, summed over chords
    assert s["net_move"] == pytest.approx(2 * r * np.sin(w * 3.0 / 2))  # the chord
    assert s["window_s"] == pytest.approx(3.0)


def test_drones_holding_still_at_world_offsets_have_no_common_body_offset():
    # two drones, headings 0 and 180 degrees, each 0.3 m east of its goal: body offsets (+0.3, 0, 0), (-0.3, 0, 0)
    T, dt = 11, 0.01
    rot = np.stack([np.stack([rz(0.0), rz(np.pi)])] * T)  # [T, 2, 3, 3]
    goal = np.zeros((T, 2, 3))
    pos = goal + np.array([0.3, 0.0, 0.0])
    s = hover_stats(pos, goal, rot, np.zeros((T, 2, 3)), dt)
    assert s["dist"] == pytest.approx(0.3)
    assert s["body_offset"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)  # the mean over drones cancels
    assert s["body_offset_norm"] == pytest.approx(0.3)  # each drone's own offset does not
    assert (s["yaw_turned_deg"], s["speed"], s["path"], s["net_move"]) == (0.0, 0.0, 0.0, 0.0)


def test_a_ring_whose_centre_is_off_the_shared_goal():
    """Two swarms of 4 drones holding still on a 0.35-m ring around their shared goal, swarm 0's ring shifted 0.2 m
    east: its east drone ends 0.55 m out (outside 0.5 m as flown, inside once the swarm is centred)."""
    ring = np.array([[0.35, 0, 0], [0, 0.35, 0], [-0.35, 0, 0], [0, -0.35, 0]])
    T, goal0 = 5, np.array([1.0, 2.0, 2.0])
    off = np.concatenate([ring + [0.2, 0.0, 0.0], ring])  # [8, 3]: swarm 0, then swarm 1
    off[4:, 2] -= 0.3  # swarm 1's ring 0.3 m below the goal: inside 0.5 m as flown (0.46 m), centred too
    pos = np.tile(goal0 + off, (T, 1, 1))
    goal = np.tile(goal0, (T, 8, 1))
    rot = np.tile(np.eye(3), (T, 8, 1, 1))
    s = hover_stats(pos, goal, rot, np.zeros((T, 8, 3)), 0.01, num_agents=4)
    assert s["centre_offset"] == pytest.approx(0.25)  # the median of 0.2 (east) and 0.3 (down)
    assert s["centre_vertical"] == pytest.approx(-0.15)  # the median of 0 and -0.3
    assert s["centre_horizontal"] == pytest.approx(0.1)  # the median of 0.2 and 0
    assert s["spread"] == pytest.approx(0.35)
    assert s["within_pct"] == pytest.approx(100 * 7 / 8) and s["within_centred_pct"] == 100.0
    one_swarm = hover_stats(pos, goal, rot, np.zeros((T, 8, 3)), 0.01)  # all 8 as one swarm: 0.1 east, 0.15 down
    assert one_swarm["centre_offset"] == pytest.approx(np.hypot(0.1, 0.15))
    assert (one_swarm["centre_vertical"], one_swarm["centre_horizontal"]) == pytest.approx((-0.15, 0.1))
    with pytest.raises(ValueError, match="8 drones are not whole swarms of 3"):
        hover_stats(pos, goal, rot, np.zeros((T, 8, 3)), 0.01, num_agents=3)


def test_table_has_a_row_per_result_and_a_cell_per_column():
    r = {"scenario": "static_diff_goal", "N": 8, "episodes": 10, "seed": 7, "window_s": 3.0, "dist": 0.55,
         "body_offset": [0.11, 0.57, -0.05], "body_offset_norm": 0.58, "yaw_turned_deg": 96.4, "speed": 0.33,
         "path": 0.97, "net_move": 0.45, "centre_offset": 0.21, "centre_vertical": -0.123,
         "centre_horizontal": 0.17, "spread": 0.36, "within_pct": 62.5,
         "within_centred_pct": 98.75, "col": 1.234, "touched_pct": 37.5, "success_pct": 6.0}
    lines = table([("se3", r), ("none", dict(r, body_offset=[0.0, -0.01, 0.0], stochastic=True))]).splitlines()
    assert len(lines) == 4 and all(len(line.split("|")) == len(lines[0].split("|")) for line in lines)
    assert lines[2] == ("| se3 | static_diff_goal, 8, 10, 7 | 3.0 | 0.55 | +0.11, +0.57, -0.05 | 0.58 | 96 | 0.33 | "
                        "0.97 | 0.45 | 0.21 | -0.12, 0.17 | 0.36 | 62 / 99 | 1.23 | 38 | 6.0 |")
    assert lines[3].startswith("| none | static_diff_goal, 8, 10, 7, sampled actions |")
    assert "+0.00, -0.01, +0.00" in lines[3]


@pytest.mark.parametrize("args, message", [
    (["--episodes", "0"], "--episodes must be >= 1"),
    (["--window", "0"], "--window must be > 0"),
    (["--num-agents", "0"], "--num-agents must be >= 1"),
    (["--scenario", "static_same_goal", "--scenario", "statc_same_goal"],
     "--scenario: unknown ['statc_same_goal']; valid: ['dynamic_diff_goal',"),
    (["--env-change", "downwash=false", "--env-change", "downwsh=false"],
     "--env-change: unknown env key 'downwsh'; valid: ['num_agents',"),
    (["--env-change", "downwash"], "--env-change 'downwash': expected KEY=VALUE"),
])
def test_bad_arguments_are_usage_errors(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as info:
        main(["--checkpoint", str(tmp_path), *args])
    assert info.value.code == 2 and message in capsys.readouterr().err


def test_every_checkpoint_is_checked_before_any_is_flown(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["--checkpoint", f"a={tmp_path}", "--checkpoint", f"b={tmp_path / 'missing'}"])
    assert info.value.code == 2 and f"{tmp_path / 'missing'} does not exist" in capsys.readouterr().err


def test_env_changes_are_parsed_as_yaml_and_fly_in_the_changed_environment():
    """The change reaches the environment that is flown: a 0.3-s episode cannot hold a 0.5-s window, a 0.6-s one
    can; a value the env refuses is an error naming its key."""
    import torch

    from swarm_appo.config import load_config
    from swarm_appo.evaluation import LoadedPolicy
    from swarm_appo.model import model_factory

    assert parse_env_change("downwash=false, drag_coeff=0.02") == {"downwash": False, "drag_coeff": 0.02}
    cfg = load_config(None, ["env.num_agents=2", "env.num_neighbors=1", "env.scenario=static_same_goal"])
    factory = model_factory(cfg.env.obs_layout(), cfg.model)
    torch.manual_seed(0)
    loaded = LoadedPolicy(cfg, factory(), factory, 0, "tiny")
    with pytest.raises(ValueError, match="--window 0.5 s is longer than the episode \\(0.3 s\\)"):
        probe(loaded, episodes=1, window_s=0.5, env_change={"episode_duration": 0.3})
    out = probe(loaded, episodes=1, window_s=0.5, env_change={"episode_duration": 0.6, "downwash": False})
    assert out["episode_s"] == pytest.approx(0.6) and out["env_change"] == {"episode_duration": 0.6, "downwash": False}
    assert out["col"] == 0 and out["touched_pct"] == 0  # a 0.6-s episode ends inside the 1.5-s grace period
    assert probe(loaded, episodes=1, window_s=0.5, env_change={"episode_duration": 0.7})["episode_s"] == \
        pytest.approx(0.7)
    with pytest.raises(ValueError, match="env.episode_duration must be > 0"):
        probe(loaded, episodes=1, window_s=0.5, env_change={"episode_duration": -1.0})
