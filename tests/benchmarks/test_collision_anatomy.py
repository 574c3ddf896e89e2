"""benchmarks.collision_anatomy: contact onsets and nearest-neighbour distances on hand-made positions."""
import numpy as np

from benchmarks.collision_anatomy import nearest_neighbour, new_contacts


def test_new_contacts_counts_each_onset_once_per_pair():
    N = 3
    touching = np.zeros((2, N, N), bool)
    pos = np.zeros((2 * N, 3))
    pos[:, 0] = [0.0, 1.0, 2.0, 0.0, 1.0, 2.0]  # every drone 1 m from the next
    assert new_contacts(pos, touching, N, 0.1) == []
    pos[1, 0] = 0.05  # swarm 0: drones 0 and 1 touch
    pos[5, 0] = 1.02  # swarm 1: drones 1 and 2 touch
    assert new_contacts(pos, touching, N, 0.1) == [(0, 0, 1), (1, 1, 2)]
    assert new_contacts(pos, touching, N, 0.1) == []  # still touching: no new onset
    pos[1, 0] = 1.0  # they part, then touch again: a second onset
    assert new_contacts(pos, touching, N, 0.1) == []
    pos[1, 0] = 0.05
    assert new_contacts(pos, touching, N, 0.1) == [(0, 0, 1)]


def test_nearest_neighbour_matches_a_brute_force_loop():
    rng = np.random.default_rng(0)
    N, E = 5, 3
    pos = rng.normal(size=(E * N, 3))
    got = nearest_neighbour(pos, N)
    for e in range(E):
        for a in range(N):
            others = [np.linalg.norm(pos[e * N + a] - pos[e * N + b]) for b in range(N) if b != a]
            assert np.isclose(got[e * N + a], min(others))


def test_a_missing_checkpoint_is_a_usage_error(tmp_path, capsys):
    import pytest

    from benchmarks.collision_anatomy import main
    with pytest.raises(SystemExit) as info:
        main(["--checkpoint", str(tmp_path / "no_run")])
    assert info.value.code == 2 and "does not exist" in capsys.readouterr().err


def test_checkpoint_labels(tmp_path):
    from benchmarks.collision_anatomy import parse_checkpoint

    assert parse_checkpoint("se3=runs/a") == ("se3", "runs/a")
    assert parse_checkpoint("runs/a") == ("runs/a", "runs/a")
    odd = tmp_path / "lr=1e-4"  # a run folder with '=' in its name is a path, not a label
    odd.mkdir()
    assert parse_checkpoint(str(odd)) == (str(odd), str(odd))


def test_every_checkpoint_is_checked_before_any_is_flown(tmp_path, capsys):
    import pytest

    from benchmarks.collision_anatomy import main
    with pytest.raises(SystemExit) as info:
        main(["--checkpoint", f"a={tmp_path}", "--checkpoint", f"b={tmp_path / 'missing'}"])
    assert info.value.code == 2 and f"{tmp_path / 'missing'} does not exist" in capsys.readouterr().err


def test_compare_puts_one_row_per_checkpoint():
    from benchmarks.collision_anatomy import TIME_BINS, compare

    def result(contacts, stacked):
        return {"time_bins": TIME_BINS, "coll_dist": 0.092, "prox_dist": 0.184, "agent_steps": 15_007_744,
                "scenario": "static_same_goal", "N": 8, "episodes": 50, "seed": 2024,
                "contacts_per_episode": contacts, "per_bin_per_episode": [0.0, 0.1, 0.2, 1.5, 1.25],
                "stacked_share": stacked, "closing_speed_median": 0.2, "goal_dist_median": 0.5,
                "hover_nn_median": 0.25, "hover_inside_prox_pct": 30.0, "success_pct": 12.5}

    text = compare([("none", result(3.05, 0.07)), ("se3", result(5.7, 0.1))])
    lines = text.splitlines()
    assert lines[2].startswith("| run | agent steps |")
    assert "| 0-1.5 s | 1.5-3 s | 3-5 s | 5-10 s | >= 10 s |" in lines[2]
    assert len(lines[3].split("|")) == len(lines[2].split("|"))  # the separator has a cell per column
    assert lines[4] == ("| none | 15,007,744 | static_same_goal, 8, 50, 2024 | 3.05 | 0.00 | 0.10 | 0.20 | 1.50 | "
                        "1.25 | 7 | 0.20 | 0.50 | 0.250 | 30 | 12.5 |")
    assert lines[5].startswith("| se3 |") and "| 5.70 |" in lines[5] and "| 10 |" in lines[5]
