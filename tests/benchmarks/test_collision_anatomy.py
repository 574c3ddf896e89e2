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
