"""benchmarks.commit_ab: the pieces that decide what an A/B reports (speed, loss agreement, which code ran)."""
import pytest

from benchmarks import commit_ab
from benchmarks.common import ROOT


def _records(rates, times, losses=None):
    out = []
    for i, (rate, t) in enumerate(zip(rates, times)):
        r = {"global_step": 1000 * (i + 1), "time": t, "perf/agent_steps_per_s": rate, "perf/learner_share": 0.9}
        if losses is not None:
            r.update({"losses/policy_loss": losses[i], "losses/value_loss": 2 * losses[i]})
        out.append(r)
    return out


def test_speed_is_the_median_after_the_warm_up():
    # the first 30 % of the span (t < 3) is warm-up: the slow first iterations must not count
    recs = _records([10.0, 20.0, 100.0, 110.0, 90.0, 105.0], [0.0, 1.0, 3.0, 5.0, 7.0, 10.0])
    s = commit_ab.speed(recs)
    assert s["agent_steps_per_s"] == pytest.approx(102.5)
    assert s["agent_steps"] == 6000
    with pytest.raises(ValueError, match="no perf/agent_steps_per_s"):
        commit_ab.speed([{"global_step": 1, "losses/policy_loss": 0.1}])


def test_compare_losses_finds_the_first_difference():
    a = commit_ab.loss_trace(_records([1.0] * 3, [0, 1, 2], losses=[0.5, 0.25, 0.125]))
    same = commit_ab.loss_trace(_records([2.0] * 3, [0, 1, 2], losses=[0.5, 0.25, 0.125]))  # speed may differ
    assert commit_ab.compare_losses(a, same) == "identical (3 records)"
    moved = commit_ab.loss_trace(_records([1.0] * 3, [0, 1, 2], losses=[0.5, 0.25 + 1e-12, 0.125]))
    text = commit_ab.compare_losses(a, moved)
    assert text.startswith("differ from record 1") and "agent step 2000" in text and "losses/policy_loss" in text
    assert "one run logged more (3 vs 2)" in commit_ab.compare_losses(a, a[:2])
    assert commit_ab.compare_losses([], a) == "no losses logged"


def test_resolve_names_the_bad_revision():
    assert len(commit_ab.resolve("HEAD")) >= 7
    with pytest.raises(SystemExit, match="not-a-commit-xyz"):
        commit_ab.resolve("not-a-commit-xyz")


def test_a_tree_must_import_its_own_code(tmp_path):
    commit_ab.check_imports_from(ROOT)  # the project imports itself from its root
    with pytest.raises(RuntimeError):  # an empty folder would run the installed copy (or nothing): refused
        commit_ab.check_imports_from(tmp_path)


def test_bad_arguments_are_refused_before_anything_runs(capsys):
    with pytest.raises(SystemExit):
        commit_ab.parse_args(["--base", "HEAD", "--config", "no/such.yaml"])
    assert "no file no/such.yaml" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        commit_ab.parse_args(["--base", "HEAD", "--set", "algo.lr"])
    assert "KEY=VALUE" in capsys.readouterr().err
