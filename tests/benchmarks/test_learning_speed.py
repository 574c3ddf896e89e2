"""benchmarks.learning_speed: the area under a training-distance curve and the steps to 1 m against hand-computed
values (linear and uneven curves, a curve that never gets there), and its table paired by seed."""
import numpy as np
import pytest

from benchmarks import learning_speed as ls
from benchmarks import paired


def records(steps, dists):
    return [{"global_step": s, "swarm/dist": d} for s, d in zip(steps, dists)]


def no_smoothing(y):
    return y


def test_a_straight_line_has_the_mean_of_its_ends_and_reaches_1m_where_it_crosses():
    s = ls.curve_summary(records([0, 1e6, 2e6, 3e6], [3.0, 2.0, 1.0, 0.0]), no_smoothing)
    assert s["dist_auc"] == pytest.approx(1.5)  # the trapezoid rule is exact on a line
    assert s["steps_to_1m"] == pytest.approx(3.0)  # 1.0 is not below 1 m: the first point below is at 3 M
    assert s["reached"] == 1.0


def test_uneven_logging_is_weighted_by_agent_steps_not_by_record():
    # from 3 m down to 1 m over the first 1 M steps, then 1 m for 2 M: (2 * 1 + 1 * 2) / 3
    s = ls.curve_summary(records([0, 1e6, 3e6], [3.0, 1.0, 1.0]), no_smoothing)
    assert s["dist_auc"] == pytest.approx(4.0 / 3.0)
    assert np.mean([3.0, 1.0, 1.0]) == pytest.approx(5.0 / 3.0)  # a plain mean over records would say 1.67


def test_a_run_that_never_reaches_1m_counts_at_its_last_step_and_says_so():
    s = ls.curve_summary(records([0, 2e6, 5e6], [3.0, 2.0, 1.5]), no_smoothing)
    assert s["steps_to_1m"] == pytest.approx(5.0) and s["reached"] == 0.0


def test_the_crossing_is_read_off_the_smoothed_curve():
    # one noisy dip below 1 m at 1 M steps: raw it counts, under a 3-point running mean it does not
    steps, dist = [0, 1e6, 2e6, 3e6, 4e6], [2.0, 0.5, 2.0, 0.8, 0.8]
    assert ls.curve_summary(records(steps, dist), no_smoothing)["steps_to_1m"] == pytest.approx(1.0)

    def mean3(y):
        return np.array([np.mean(y[max(0, i - 1):i + 2]) for i in range(len(y))])
    assert ls.curve_summary(records(steps, dist), mean3)["steps_to_1m"] == pytest.approx(4.0)


def test_records_without_a_finite_distance_are_skipped_and_order_is_by_step():
    recs = records([2e6, 0, 1e6], [1.0, 3.0, 2.0])
    recs += [{"global_step": 5e5}, {"global_step": 7e5, "swarm/dist": float("nan")}]
    s = ls.curve_summary(recs, no_smoothing)
    assert s["dist_auc"] == pytest.approx(2.0)
    assert ls.curve_summary(records([0], [1.0]), no_smoothing) == {}  # one point spans no steps
    assert ls.curve_summary([], no_smoothing) == {}


def test_speed_table_means_over_seeds_and_pairs_lower_as_better():
    fast = {0: records([0, 1e6, 2e6], [2.0, 0.5, 0.5]), 1: records([0, 1e6, 2e6], [2.0, 1.5, 0.5])}
    slow = {0: records([0, 1e6, 2e6], [2.0, 2.0, 0.5]), 1: records([0, 1e6, 2e6], [2.0, 2.0, 1.5])}
    by_seed = ls.summaries({"x/none": slow, "x/se3": fast}, no_smoothing)
    assert by_seed["x/se3"][0]["dist_auc"] == pytest.approx(0.875)  # (1.25 * 1 + 0.5 * 1) / 2
    md = ls.speed_markdown(["x/none", "x/se3"], by_seed)
    assert "| x/se3 | 2 | 1.12 ± 0.25 | 1.5 ± 0.5 | 2/2 |" in md  # AUC 0.875 and 1.375; 1 M and 2 M
    assert "| x/none | 2 | 1.75 ± 0.12 | 2.0 ± 0.0 | 1/2 |" in md  # 1.625, 1.875; seed 1 never below 1 m: at 2 M
    row = next(line for line in md.splitlines() if line.startswith("| x/se3 − x/none |"))
    assert "better on 2/2" in row.split(" | ")[2]  # lower AUC on both seeds is better
    assert ls.speed_markdown(["x/none"], {}) == ""


def test_paired_reads_the_direction_from_the_given_specs():
    base, other = {0: {"m": 1.0}, 1: {"m": 2.0}}, {0: {"m": 3.0}, 1: {"m": 4.0}}
    up = {"m": ls.CurveMetric("M", 1, True)}
    down = {"m": ls.CurveMetric("M", 1, False)}
    assert paired.paired_stats(base, other, "m", up)["better"] == 2
    assert paired.paired_stats(base, other, "m", down)["better"] == 0
    md = paired.paired_markdown(["x/none", "x/se3"], {"x/none": base, "x/se3": other}, metrics=("m",), specs=up)
    assert "| x/se3 − x/none | 2 | +2.0 ± 0.0, better on 2/2, p = 0.50 |" in md
