"""benchmarks.paired: the exact sign-flip test against a brute-force enumeration and hand-counted cases, and the
paired table of a symmetry row against its `none` row on common seeds."""
import itertools

import numpy as np
import pytest

from benchmarks import paired


def brute_force_p(d):
    """Enumerate the 2^n sign patterns with itertools (an independent route to the same exact p)."""
    obs = abs(sum(d))
    hits = [abs(sum(s * x for s, x in zip(signs, d))) >= obs - 1e-12
            for signs in itertools.product((1, -1), repeat=len(d))]
    return sum(hits) / len(hits)


def test_sign_flip_p_hand_counted_cases():
    assert paired.sign_flip_p([1.0, 2.0, 3.0]) == pytest.approx(2 / 8)  # only all-plus and all-minus reach |6|
    # +-1 +-2 +-3 gives |sums| 6, 0, 2, 4, 4, 2, 0, 6: six of eight are >= |1 - 2 + 3| = 2
    assert paired.sign_flip_p([1.0, -2.0, 3.0]) == pytest.approx(6 / 8)
    assert paired.sign_flip_p([0.0, 0.0]) == 1.0  # no difference is never evidence
    assert paired.sign_flip_p([-5.0]) == 1.0  # one seed cannot say anything
    assert paired.sign_flip_p([0.5] * 6) == pytest.approx(paired.min_p(6)) == pytest.approx(2 / 64)


def test_sign_flip_p_matches_brute_force_enumeration():
    rng = np.random.default_rng(0)
    for n in range(1, 9):
        for _ in range(5):
            d = rng.normal(0.3, 1.0, n).round(2)
            assert paired.sign_flip_p(d) == pytest.approx(brute_force_p(list(d)))


def test_sign_flip_p_refuses_what_it_cannot_do_exactly():
    with pytest.raises(ValueError, match="at least one"):
        paired.sign_flip_p([])
    with pytest.raises(ValueError, match="at most 16"):
        paired.sign_flip_p(np.ones(17))


def test_pairs_join_each_symmetry_row_to_its_none_row():
    labels = ["a/none", "a/se3", "a/yaw", "b/se3", "c/none", "a/none lr=1", "a/se3 lr=1", "a/se3 lr=2"]
    assert paired.pairs(labels) == [("a/none", "a/se3"), ("a/none", "a/yaw"), ("a/none lr=1", "a/se3 lr=1")]


def test_paired_markdown_differences_wins_and_per_seed_values():
    base = {0: {"dist": 1.0, "suc": 10.0, "col": 3.0}, 1: {"dist": 0.8, "suc": 20.0, "col": 1.0},
            2: {"dist": 0.9, "suc": 0.0, "col": 2.0}}
    # se3: closer on every seed, more success on 2 of 3, fewer contacts on 1 of 3; seed 3 has no none partner
    other = {0: {"dist": 0.7, "suc": 30.0, "col": 1.0}, 1: {"dist": 0.6, "suc": 10.0, "col": 2.0},
             2: {"dist": 0.6, "suc": 10.0, "col": 2.0}, 3: {"dist": 0.1, "suc": 99.0, "col": 0.0}}
    md = paired.paired_markdown(["x/none", "x/se3"], {"x/none": base, "x/se3": other})
    row = next(line for line in md.splitlines() if line.startswith("| x/se3 − x/none |"))
    cells = row.rstrip(" |").split(" | ")
    assert cells[1] == "3"
    d_dist = np.array([-0.3, -0.2, -0.3])
    assert cells[3] == f"{d_dist.mean():+.2f} ± {d_dist.std():.2f}, better on 3/3, p = 0.25"
    assert cells[4] == "-0.33 ± 1.25, better on 1/3, p = 1.00"  # Col: -2, +1, 0: every flip reaches |sum| 1
    # Suc: +20, -10, +10; |sum| 20 is reached by (+20 -10 +10), (+20 +10 -10), (+20 +10 +10) and their negatives
    assert cells[6] == "+6.7 ± 12.5, better on 2/3, p = 0.75"
    assert cells[2] == "-" and cells[5] == "-"  # Rew and ColD not in these cells
    assert "- x/none → x/se3, seeds 0, 1, 2: Dist 1.00→0.70, 0.80→0.60, 0.90→0.60" in md
    assert "0.250 at 3 seeds" in md


def test_no_pair_no_section():
    one, two = {0: {"dist": 1.0}}, {1: {"dist": 2.0}}
    assert paired.paired_markdown(["x/se3", "y/none"], {"x/se3": one, "y/none": one}) == ""  # not the same arch
    assert paired.paired_markdown(["x/none", "x/se3"], {"x/none": one, "x/se3": two}) == ""  # no common seed


def test_one_common_seed_states_its_floor_of_one():
    # With one seed the sign-flip p cannot go below 1: the header must say so, in the singular.
    md = paired.paired_markdown(["x/none", "x/se3"], {"x/none": {0: {"dist": 1.0}}, "x/se3": {0: {"dist": 0.5}}})
    assert "allow: 1.000 at 1 seed)" in md
    assert "1 seeds" not in md
    assert "better on 1/1, p = 1.00" in md


def test_sampled_p_agrees_with_the_exact_test():
    rng = np.random.default_rng(1)
    for n in (5, 10, 14):
        d = rng.normal(0.4, 1.0, n)
        assert paired.sign_flip_p_sampled(d) == pytest.approx(paired.sign_flip_p(d), abs=0.01)  # se <= 0.002
    assert paired.sign_flip_p_sampled(np.ones(20)) < 1e-3  # all 20 one way: exact p = 2^-19
    assert paired.sign_flip_p_sampled(np.ones(20)) == paired.sign_flip_p_sampled(np.ones(20))  # fixed seed


def test_pooled_line_takes_every_architecture_and_seed_as_one_vote():
    # two architectures, 3 and 2 common seeds: the pooled line tests all 5 differences together
    by_seed = {"a/none": {0: {"dist": 1.0}, 1: {"dist": 1.0}, 2: {"dist": 1.0}},
               "a/se3": {0: {"dist": 0.5}, 1: {"dist": 0.7}, 2: {"dist": 1.2}},
               "b/none": {0: {"dist": 2.0}, 1: {"dist": 2.0}, 7: {"dist": 9.0}},
               "b/se3": {0: {"dist": 1.0}, 1: {"dist": 1.9}},
               "b/yaw": {0: {"dist": 3.0}}}  # a yaw row alone (one architecture): no pooled yaw line
    md = paired.paired_markdown(["a/none", "a/se3", "b/none", "b/se3", "b/yaw"], by_seed, metrics=("dist",))
    d = np.array([-0.5, -0.3, 0.2, -1.0, -0.1])
    row = next(line for line in md.splitlines() if line.startswith("| every se3 row − its none row"))
    assert row == (f"| every se3 row − its none row (a, b) | 5 | {d.mean():+.2f} ± {d.std():.2f}, better on 4/5, "
                   f"p = {paired.sign_flip_p(d):.2f} |")
    assert "every yaw row" not in md
    assert "0.062 at 5 seeds" in md  # the pooled line's own floor
    # --compare variants pool separately, each with its own setting
    labels = ["a/none x=1", "a/se3 x=1", "b/none x=1", "b/se3 x=1", "a/none x=2", "a/se3 x=2"]
    assert paired.pooled_groups(paired.pairs(labels)) == {
        "every se3 row − its none row x=1": [("a/none x=1", "a/se3 x=1"), ("b/none x=1", "b/se3 x=1")]}


def test_pooled_line_beyond_the_exact_test_uses_the_sampled_p():
    by_seed = {}
    for k in range(6):  # 6 architectures x 3 seeds = 18 > 16 differences
        by_seed[f"a{k}/none"] = {s: {"dist": 1.0} for s in range(3)}
        by_seed[f"a{k}/se3"] = {s: {"dist": 0.9} for s in range(3)}
    md = paired.paired_markdown(list(by_seed), by_seed, metrics=("dist",))
    assert "| 18 | -0.10 ± 0.00, better on 18/18, p ≈ 0.00 |" in md


def test_sign_flip_test_is_exact_up_to_the_limit_and_sampled_beyond():
    d = np.linspace(0.1, 1.0, paired.MAX_EXACT_SEEDS)
    assert paired.sign_flip_test(d) == (paired.sign_flip_p(d), True)
    more = np.ones(paired.MAX_EXACT_SEEDS + 1)
    assert paired.sign_flip_test(more) == (paired.sign_flip_p_sampled(more), False)


def test_compare_pairs_join_each_variant_to_the_first_value_of_its_row():
    labels = ["a/none p=fp32", "a/none p=bf16", "a/se3 p=fp32", "a/se3 p=bf16", "b/se3 p=fp32", "a/none"]
    assert paired.compare_pairs(labels) == [("a/none p=fp32", "a/none p=bf16"), ("a/se3 p=fp32", "a/se3 p=bf16")]
    assert paired.compare_pairs(["a/se3 p=1", "a/se3 p=2", "a/se3 p=3"]) == [("a/se3 p=1", "a/se3 p=2"),
                                                                           ("a/se3 p=1", "a/se3 p=3")]
    assert paired.compare_pairs(["a/none", "a/se3"]) == []  # no --compare: nothing to pair along a key
    # all_pairs: the symmetry pairs within each setting, then the compare pairs
    assert paired.all_pairs(labels[:4]) == [("a/none p=fp32", "a/se3 p=fp32"), ("a/none p=bf16", "a/se3 p=bf16"),
                                            ("a/none p=fp32", "a/none p=bf16"), ("a/se3 p=fp32", "a/se3 p=bf16")]


def test_paired_markdown_reports_compare_variants_and_pools_them_over_rows():
    # bf16 against fp32 on two rows, 2 seeds each: the per-row lines and the pooled line over the 4 (row, seed) pairs
    by_seed = {"a/se3 p=fp32": {0: {"dist": 1.0}, 1: {"dist": 0.8}},
               "a/se3 p=bf16": {0: {"dist": 0.9}, 1: {"dist": 1.0}},
               "b/se3 p=fp32": {0: {"dist": 0.5}, 1: {"dist": 0.6}},
               "b/se3 p=bf16": {0: {"dist": 0.4}, 1: {"dist": 0.3}}}
    md = paired.paired_markdown(list(by_seed), by_seed, metrics=("dist",))
    assert "| a/se3 p=bf16 − a/se3 p=fp32 | 2 | +0.05 ± 0.15, better on 1/2, p = 1.00 |" in md
    assert "| b/se3 p=bf16 − b/se3 p=fp32 | 2 | -0.20 ± 0.10, better on 2/2, p = 0.50 |" in md
    d = np.array([-0.1, 0.2, -0.1, -0.3])
    assert (f"| every p=bf16 row − its p=fp32 row (a/se3, b/se3) | 4 | {d.mean():+.2f} ± {d.std():.2f}, better on "
            f"3/4, p = {paired.sign_flip_p(d):.2f} |") in md
    assert "- a/se3 p=fp32 → a/se3 p=bf16, seeds 0, 1: Dist 1.00→0.90, 0.80→1.00" in md
    assert "every se3 row" not in md  # no none row here: no symmetry pair
