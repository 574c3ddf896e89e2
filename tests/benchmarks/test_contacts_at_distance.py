"""benchmarks.contacts_at_distance: strata, the distance-adjusted difference against hand-computed cases, and the
report read from a table1 experiment folder (plain and gzipped episodes)."""
import gzip
import json

import pytest

from benchmarks import contacts_at_distance as cad
from benchmarks.table1 import EVAL_DIR, parse_rows, run_dir

BINS = (0.0, 0.5, 1.0)


def ep(dist, cold, scenario="s", col=None):
    return {"eval_scenario": scenario, "table_dist": dist, "table_collisions_drone": cold,
            "table_collisions": cold if col is None else col}


def test_strata_bins_are_closed_below_and_the_last_is_open_above():
    strata = cad.strata_means([ep(0.0, 1), ep(0.49, 2), ep(0.5, 3), ep(0.99, 4), ep(1.0, 5), ep(7.0, 6),
                               ep(0.2, 7, scenario="t")], "table_collisions_drone", BINS)
    assert strata == {("s", 0): [1.0, 2.0], ("s", 1): [3.0, 4.0], ("s", 2): [5.0, 6.0], ("t", 0): [7.0]}


def test_adjusted_difference_undoes_a_simpson_reversal():
    # within each distance bin the row has exactly one contact more; it reaches the near bin more often, so the raw
    # difference has the other sign: raw = 2.0 - 3.0 = -1, at equal distance +1
    base = [ep(0.2, 0)] + [ep(2.0, 4)] * 3
    other = [ep(0.2, 1)] * 3 + [ep(2.0, 5)]
    r = cad.adjusted_difference(base, other, "table_collisions_drone", BINS)
    assert r == pytest.approx({"raw": -1.0, "adjusted": 1.0, "coverage": 1.0})


def test_adjusted_difference_weights_and_coverage():
    # stratum near: 2 v 2 episodes, difference 1, weight 2*2/4 = 1; stratum far: 1 v 1, difference 4, weight 0.5;
    # one episode of the row in the middle bin has no partner: it counts in raw, not at equal distance
    base = [ep(0.1, 0), ep(0.2, 2), ep(3.0, 1)]
    other = [ep(0.1, 1), ep(0.3, 3), ep(3.0, 5), ep(0.7, 10)]
    r = cad.adjusted_difference(base, other, "table_collisions_drone", BINS)
    assert r["adjusted"] == pytest.approx((1 * 1 + 0.5 * 4) / 1.5)
    assert r["raw"] == pytest.approx((1 + 3 + 5 + 10) / 4 - (0 + 2 + 1) / 3)
    assert r["coverage"] == pytest.approx(6 / 7)
    # raw averages scenarios with equal weights, whatever their episode counts
    two = cad.adjusted_difference([ep(0.1, 0, "a"), ep(0.1, 0, "b"), ep(0.1, 0, "b")],
                                  [ep(0.1, 2, "a"), ep(0.1, 6, "b")], "table_collisions_drone", BINS)
    assert two["raw"] == pytest.approx((2 + 6) / 2)
    assert cad.adjusted_difference([ep(0.1, 0)], [ep(3.0, 1)], "table_collisions_drone", BINS) is None


def write_experiment(root, label, seed, episodes, gz):
    rd = run_dir(root, "mix", parse_rows(label)[0], seed) / EVAL_DIR
    rd.mkdir(parents=True)
    text = "".join(json.dumps(e) + "\n" for e in episodes)
    if gz:
        with gzip.open(rd / "episodes.jsonl.gz", "wt") as f:
            f.write(text)
    else:
        (rd / "episodes.jsonl").write_text(text)


def test_report_from_an_experiment_folder(tmp_path, capsys):
    for seed, extra in ((0, 1), (1, 2)):  # the se3 row has `extra` more contacts in every stratum
        base = [ep(0.2, 1), ep(2.0, 3), ep(2.0, 3)]
        write_experiment(tmp_path, "deepsets/none", seed, base, gz=seed == 0)
        write_experiment(tmp_path, "deepsets/se3", seed, [ep(0.2, 1 + extra)] * 2 + [ep(2.0, 3 + extra)], gz=False)
    text = cad.main(["--out", str(tmp_path), "--train-scenario", "mix", "--rows", "deepsets/none,deepsets/se3",
                     "--seeds", "0,1", "--bins", "0,1"])
    assert "| deepsets/none | 1.00 (2) | 3.00 (4) | 2.33 (6) |" in text
    assert "| deepsets/se3 | 2.50 (4) | 4.50 (2) | 3.17 (6) |" in text
    # raw per seed: (2+2+4)/3 - 7/3 = 1/3 and (3+3+5)/3 - 7/3 = 4/3; at equal distance exactly 1 and 2
    assert "| deepsets/se3 − deepsets/none | 2 | +0.83 ± 0.50 | +1.50 ± 0.50 | 2/2 | 0.50 (0.500) | 100% |" in text
    assert "raw +0.33, +1.33; at equal distance +1.00, +2.00" in text
    assert "## contacts_at_distance —" in capsys.readouterr().out


def test_bad_input_is_named(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cad.main(["--out", str(tmp_path), "--train-scenario", "mix"])
    assert "no evaluation episodes under" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cad.main(["--out", str(tmp_path), "--bins", "1,0.5"])
    assert "--bins '1,0.5'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cad.main(["--out", str(tmp_path), "--rows", "deepset/none"])
    assert "architecture/symmetry" in capsys.readouterr().err


def test_a_pooled_line_of_more_than_16_votes_uses_the_sampled_p():
    labels = ["deepsets/none", "deepsets/se3", "kattention/none", "kattention/se3"]
    found = {label: {s: [ep(0.2, 1 + (label.endswith("se3")))] for s in range(9)} for label in labels}
    text = cad.report(found, labels, "cold", BINS)
    assert "| deepsets/se3 − deepsets/none | 9 | +1.00 ± 0.00 | +1.00 ± 0.00 | 9/9 | 0.00 (0.004) | 100% |" in text
    assert "| every pair above (one vote per architecture and seed) | 18 | | +1.00 ± 0.00 | 18/18 | ≈ 0.00 | |" in text
