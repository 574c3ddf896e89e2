"""benchmarks.quality_report: the failure split of an evaluation, the curves figure, and its input checks."""
import json

import pytest

from benchmarks import quality_report as qr


def _episode(policy, success, collided, reached, contacts):
    return {"policy": policy, "agent_success": success, "agent_collided": collided, "agent_reached": reached,
            "collisions_after_grace": contacts}


def test_failure_split_counts_each_drone_once_per_policy():
    eps = [_episode("a", [True, False, False, False], [False, True, False, False], [True, False, True, False], 1),
           _episode("a", [True, True, False, True], [False, False, False, False], [True, True, True, True], 0),
           _episode("b", [False, False], [True, True], [False, False], 3)]
    split = qr.failure_split(eps)
    a, b = split["a"], split["b"]
    assert a["drones"] == 8 and a["success"] == 4 / 8 and a["collided"] == 1 / 8
    assert a["clean_outside"] == 3 / 8 and a["reached"] == 6 / 8  # neither succeeded nor collided: 3 drones
    assert (a["episodes"], a["contact_free_episodes"]) == (2, 1)
    assert (b["drones"], b["collided"], b["clean_outside"], b["contact_free_episodes"]) == (2, 1.0, 0.0, 0)
    assert "| a | 8 | 50.0 | 12.5 | 37.5 | 75.0 | 1/2 |" in qr.report(split)


def test_clean_failures_report_how_far_outside_the_radius_they_end():
    a = _episode("a", [True, False, False, False], [False, True, False, False], [True, False, True, False], 1)
    a["agent_dist_final"] = [0.2, 0.1, 0.55, 0.9]  # clean failures: drones 2 and 3 (drone 1 collided)
    b = _episode("a", [False, True], [False, False], [True, True], 0)
    b["agent_dist_final"] = [0.58, 0.3]  # clean failure: drone 0
    split = qr.failure_split([a, b])["a"]
    assert split["clean_outside"] == 3 / 6
    assert split["clean_outside_median_m"] == pytest.approx(0.58)  # median of 0.55, 0.9, 0.58
    assert split["clean_outside_within_0.6"] == pytest.approx(2 / 3)
    assert "| 1/2 | 0.58 | 66.7 |" in qr.report({"a": split})
    old = qr.failure_split([_episode("c", [False], [False], [False], 0)])["c"]  # an evaluation without distances
    assert old["clean_outside_median_m"] is None and "| 1/1 | - | - |" in qr.report({"c": old})


def test_curves_of_two_runs_and_the_split_in_one_section(tmp_path):
    for name, dist in (("r1", 1.0), ("r2", 0.5)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.jsonl").write_text("".join(
            json.dumps({"global_step": s, "swarm/dist": dist, "swarm/success_rate": 0.1, "swarm/collisions_drone": 2})
            + "\n" for s in (1000, 2000, 3000)))
    episodes = tmp_path / "episodes.jsonl"
    episodes.write_text(json.dumps(_episode("p", [True], [False], [True], 0)) + "\n")
    figure = tmp_path / "curves.png"
    split = qr.main(["--run", f"one={tmp_path / 'r1'}", "--run", f"two={tmp_path / 'r2'}",
                     "--episodes", str(episodes), "--figure", str(figure)])
    assert figure.stat().st_size > 0 and split["p"]["success"] == 1.0


def test_several_evaluation_files_give_one_row_per_policy_and_keep_equal_labels_apart(tmp_path):
    files = []
    for name, success in (("exp1", [True, True]), ("exp2", [False, False]), ("exp3", [True, False])):
        (tmp_path / name).mkdir()
        policy = "other" if name == "exp3" else "seed0 (deepsets/se3)"  # exp1 and exp2 print the same label
        files.append(tmp_path / name / "episodes.jsonl")
        files[-1].write_text(json.dumps(_episode(policy, success, [False, False], success, 0)) + "\n")
    split = qr.main([a for f in files for a in ("--episodes", str(f))])
    assert split["seed0 (deepsets/se3)"]["success"] == 1.0  # the first file keeps the plain label
    assert split[f"seed0 (deepsets/se3) [{tmp_path / 'exp2'}]"]["success"] == 0.0
    assert split["other"]["success"] == 0.5 and len(split) == 3


@pytest.mark.parametrize("argv, message", [
    ([], "give --run"),
    (["--run", "no_equals_sign"], "expected LABEL=RUN_DIR"),
    (["--run", "x=/nonexistent_run"], "metrics.jsonl does not exist"),
    (["--episodes", "/nonexistent.jsonl"], "--episodes: /nonexistent.jsonl does not exist"),
])
def test_bad_arguments_name_the_option(argv, message, capsys):
    with pytest.raises(SystemExit):
        qr.main(argv)
    assert message in capsys.readouterr().err
