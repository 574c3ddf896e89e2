"""Paired comparison by seed: each symmetry row against the ``none`` row of the same architecture, on the seeds both
have. Every row of a Table 1 experiment trains the same seeds, so seed k of ``kattention/se3`` and seed k of
``kattention/none`` share their environment stream and initial conditions: the per-seed difference removes what the
seed alone does, and an exact sign-flip test says how often a difference that large comes from seed noise alone.

Under the per-architecture lines, one line per symmetry pools the pairs of every architecture (one vote per
(architecture, seed)): the test of "this symmetry helps whatever the encoder", the paper's group-modular claim.

An experiment run with ``--compare KEY=V1,V2`` is paired the same way along the compared key: each row's ``V2``
variant against its ``V1`` variant (the first value given is the reference), e.g. bf16 against fp32 at equal seeds.

With n paired seeds the smallest attainable two-sided p is 2 / 2^n (0.25 at 3 seeds, 0.125 at 4, 0.031 at 6):
a claim at the 5 % level needs at least 6 seeds whatever the effect size. The report prints that floor with p.
"""
from __future__ import annotations

from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

PAIRED_METRICS = ("rew", "dist", "col", "cold", "suc")  # the paper's columns and drone-drone contacts
MAX_EXACT_SEEDS = 16  # 2^16 sign assignments; beyond that the exact test is not worth its memory here


def sign_flip_p(diffs: Sequence[float]) -> float:
    """Exact two-sided p-value of the paired sign-flip (permutation) test of "mean difference = 0": the share of the
    2^n ways to flip the signs of the n differences whose |mean| is at least the observed one. Under the null
    hypothesis (the symmetry changes nothing) each seed's difference is as likely positive as negative."""
    d = np.asarray(diffs, dtype=np.float64)
    n = d.size
    if n == 0:
        raise ValueError("sign_flip_p needs at least one paired difference")
    if n > MAX_EXACT_SEEDS:
        raise ValueError(f"sign_flip_p is exact: at most {MAX_EXACT_SEEDS} paired seeds, got {n}")
    bits = (np.arange(2 ** n)[:, None] >> np.arange(n)) & 1  # [2^n, n] every sign assignment
    sums = np.abs((1 - 2 * bits) @ d)  # [2^n]
    observed = abs(d.sum())
    return float(np.mean(sums >= observed - 1e-9 * max(1.0, observed)))  # ties (rounding) count as extreme


def sign_flip_p_sampled(diffs: Sequence[float], draws: int = 2 ** 16, seed: int = 0) -> float:
    """``sign_flip_p`` estimated from ``draws`` random sign assignments (fixed seed: the same p every report), for
    more differences than the exact test enumerates; its standard error is at most 0.5 / sqrt(draws) = 0.002."""
    d = np.asarray(diffs, dtype=np.float64)
    signs = 1 - 2 * np.random.default_rng(seed).integers(0, 2, size=(draws, d.size))  # [draws, n]
    observed = abs(d.sum())
    return float(np.mean(np.abs(signs @ d) >= observed - 1e-9 * max(1.0, observed)))


def sign_flip_test(diffs: Sequence[float]) -> Tuple[float, bool]:
    """``(p, exact)``: the exact sign-flip p for up to ``MAX_EXACT_SEEDS`` differences, the sampled estimate beyond
    (a pooled line over many architectures and seeds can pass that)."""
    exact = len(diffs) <= MAX_EXACT_SEEDS
    return (sign_flip_p(diffs) if exact else sign_flip_p_sampled(diffs)), exact


def min_p(n: int) -> float:
    """The smallest p the exact two-sided sign-flip test can give with n seeds."""
    return min(1.0, 2.0 / 2 ** n)


def pairs(labels: Sequence[str]) -> List[Tuple[str, str]]:
    """(``arch/none`` label, ``arch/<symmetry>`` label) for every symmetry row whose ``none`` row is in the
    experiment; a ``--compare`` suffix (`` key=value``) must match too."""
    out = []
    for label in labels:
        head, sep, setting = label.partition(" ")
        arch, _, symmetry = head.partition("/")
        base = f"{arch}/none" + (sep + setting if sep else "")
        if symmetry != "none" and base in labels:
            out.append((base, label))
    return out


def compare_pairs(labels: Sequence[str]) -> List[Tuple[str, str]]:
    """(reference, variant) for every ``--compare`` variant of a row: ``arch/sym key=V2`` against ``arch/sym
    key=V1``, where V1 is the first value of that key in ``labels`` (the order ``--compare`` gave)."""
    first: Dict[Tuple[str, str], str] = {}
    out = []
    for label in labels:
        head, sep, setting = label.partition(" ")
        if not sep:
            continue
        reference = first.setdefault((head, setting.partition("=")[0]), label)
        if reference != label:
            out.append((reference, label))
    return out


def is_compare_pair(base: str, other: str) -> bool:
    """True for a ``--compare`` pair (one row, two settings), False for a symmetry pair (two rows)."""
    return base.partition(" ")[0] == other.partition(" ")[0]


def all_pairs(labels: Sequence[str]) -> List[Tuple[str, str]]:
    """Every pair the report tests: symmetry rows against their ``none`` rows, then ``--compare`` variants."""
    return pairs(labels) + compare_pairs(labels)


def pooled_groups(pair_list: Sequence[Tuple[str, str]]) -> Dict[str, List[Tuple[str, str]]]:
    """The pairs grouped by what they test, over rows: a symmetry (with its ``--compare`` setting) over
    architectures, ``every <symmetry> row − its none row[ <setting>]``; or a ``--compare`` value over rows,
    ``every <setting> row − its <reference setting> row``. Only groups of >= 2 pairs."""
    groups: Dict[str, List[Tuple[str, str]]] = {}
    for base, other in pair_list:
        head, sep, setting = other.partition(" ")
        if is_compare_pair(base, other):
            name = f"every {setting} row − its {base.partition(' ')[2]} row"
        else:
            name = f"every {head.partition('/')[2]} row − its none row" + (sep + setting if sep else "")
        groups.setdefault(name, []).append((base, other))
    return {k: v for k, v in groups.items() if len(v) >= 2}


def _eval_specs() -> Mapping[str, Any]:
    from swarm_appo.eval_tables import METRICS

    return METRICS


def paired_stats(base: Dict[int, Dict[str, float]], other: Dict[int, Dict[str, float]], metric: str,
                 specs: Optional[Mapping[str, Any]] = None) -> Optional[dict]:
    """The per-seed differences ``other - base`` of one metric on the seeds both rows have, with their mean,
    population std, the number of seeds where ``other`` is better, and the sign-flip p. ``specs`` maps a metric to
    its ``column``, ``decimals`` and ``higher_is_better`` (default: the evaluation's ``eval_tables.METRICS``)."""
    cols = specs if specs is not None else _eval_specs()
    seeds = sorted(s for s in set(base) & set(other) if metric in base[s] and metric in other[s])
    if not seeds:
        return None
    b = np.array([base[s][metric] for s in seeds])
    o = np.array([other[s][metric] for s in seeds])
    d = o - b
    better = d > 0 if cols[metric].higher_is_better else d < 0
    return {"seeds": seeds, "base": b, "other": o, "mean": float(d.mean()), "std": float(d.std()),
            "better": int(better.sum()), "p": sign_flip_p(d)}


def paired_markdown(labels: Sequence[str], by_seed: Dict[str, Dict[int, Dict[str, float]]],
                    metrics: Sequence[str] = PAIRED_METRICS, specs: Optional[Mapping[str, Any]] = None) -> str:
    """A table of the paired differences (symmetry row minus its ``none`` row; ``--compare`` variant minus its
    reference), one row per pair, and the per-seed values under it; "" when the experiment has no such pair with a
    common seed. ``metrics`` and ``specs`` as in ``paired_stats`` (default: the evaluation's columns)."""
    cols = specs if specs is not None else _eval_specs()
    rows, details, counts = [], [], set()
    for base, other in all_pairs(labels):
        if base not in by_seed or other not in by_seed:
            continue
        stats = {m: paired_stats(by_seed[base], by_seed[other], m, cols) for m in metrics}
        stats = {m: s for m, s in stats.items() if s is not None}
        if not stats:
            continue
        n = max(len(s["seeds"]) for s in stats.values())
        counts.add(n)
        cells = []
        for m in metrics:
            s, dec = stats.get(m), cols[m].decimals
            cells.append("-" if s is None else f"{s['mean']:+.{dec}f} ± {s['std']:.{dec}f}, better on "
                         f"{s['better']}/{len(s['seeds'])}, p = {s['p']:.2f}")
        rows.append(f"| {other} − {base} | {n} | " + " | ".join(cells) + " |")
        per_seed = "; ".join(
            f"{cols[m].column} " + ", ".join(f"{x:.{cols[m].decimals}f}→{y:.{cols[m].decimals}f}"
                                                for x, y in zip(s["base"], s["other"]))
            for m, s in stats.items())
        seeds = next(iter(stats.values()))["seeds"]
        details.append(f"- {base} → {other}, seeds {', '.join(map(str, seeds))}: {per_seed}")
    if not rows:
        return ""
    # The same symmetry over every architecture (the paper's "group-modular" claim), or the same --compare value over
    # every row: all (row, seed) pairs in one test, each pair one vote.
    for name, group in pooled_groups(all_pairs(labels)).items():
        present = [(b, o) for b, o in group if b in by_seed and o in by_seed]
        cells, n = [], 0
        for m in metrics:
            found = [paired_stats(by_seed[b], by_seed[o], m, cols) for b, o in present]
            found = [f for f in found if f is not None]
            if len(found) < 2:
                cells.append("-")
                continue
            d = np.concatenate([f["other"] - f["base"] for f in found])
            n = max(n, d.size)
            p, exact = sign_flip_test(d)
            dec = cols[m].decimals
            cells.append(f"{d.mean():+.{dec}f} ± {d.std():.{dec}f}, better on {sum(f['better'] for f in found)}/"
                         f"{d.size}, p {'=' if exact else '≈'} {p:.2f}")
        if n:
            archs = ", ".join(o.partition(" ")[0] if is_compare_pair(b, o) else o.partition("/")[0] for b, o in present)
            rows.append(f"| {name} ({archs}) | {n} | " + " | ".join(cells) + " |")
            counts.add(n)
    floor = ", ".join(f"{min_p(n):.3f} at {n} seed{'s' if n != 1 else ''}" for n in sorted(counts))
    head = ("| paired by seed | seeds | " + " | ".join(f"Δ {cols[m].column}" for m in metrics) + " |")
    return "\n".join([
        "Paired by seed (on each common seed, the symmetry row minus its `none` row, or a `--compare` variant "
        "minus the first value's; mean ± population std of the differences; better on k/n = seeds where the "
        "first-named row is better; p = exact two-sided sign-flip test; an `every ... row` line pools the pairs of "
        "every row, one vote per (row, seed); "
        f"the smallest p these seeds allow: {floor}):",
        "",
        head, "|---|---:|" + "---|" * len(metrics), *rows, "", *details])
