"""Drone-drone contacts at equal distance to the goal: is a row's extra ColD explained by its drones being nearer
their goals (the crowd at a shared goal), or does it collide more than its ``none`` row at the same distance?

    python -m benchmarks.contacts_at_distance --out benchmarks/table1_runs/quality_mix_15m --train-scenario mix \\
        --rows deepsets/none,deepsets/se3,kattention/none,kattention/se3 --seeds 0,1,2,3 [--append]

Reads the evaluation episodes of a ``benchmarks.table1`` experiment (``--out`` of a run or its ``--archive``): no
training, no simulation. Each episode gives its Dist (mean distance to the goal over the last seconds) and its
contacts. Episodes are put in strata (evaluation scenario x Dist bin). For each symmetry row and its ``none`` row,
per seed:
- raw: the table's difference, the mean over scenarios of (row - none);
- at equal distance: the difference within each stratum both rows reach, averaged with the weights
  n_none n_row / (n_none + n_row) (Cochran-Mantel-Haenszel), and the share of episodes in such strata (coverage).
Seeds are paired as in ``benchmarks.paired`` (sign-flip p, its floor 2 / 2^n printed with it).

Caveat: Dist is an outcome too (a contact can push a drone off its goal), so the adjusted figure describes the rows
at equal distance; it is not a causal effect of the symmetry with distance held fixed.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from benchmarks.common import load_average, publish, section_header
from benchmarks.paired import min_p, pairs, sign_flip_test
from benchmarks.table1 import EVAL_DIR, parse_rows, row_label, run_dir
from benchmarks.table1_archive import existing, read_jsonl

METRICS = {"cold": ("table_collisions_drone", "ColD"), "col": ("table_collisions", "Col")}
DIST_KEY = "table_dist"
DEFAULT_BINS = (0.0, 0.5, 0.75, 1.0, 1.5, 2.5)  # m; the last bin is open above


def parse_bins(text: str) -> Tuple[float, ...]:
    edges = tuple(float(x) for x in text.split(",") if x.strip())
    if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:])) or edges[0] < 0:
        raise argparse.ArgumentTypeError(f"--bins {text!r}: at least two increasing edges >= 0 (m)")
    return edges


def strata_means(episodes: Sequence[dict], key: str, bins: Sequence[float]) -> Dict[Tuple[str, int], List[float]]:
    """(evaluation scenario, Dist bin index) -> the metric of each episode in it. Bin i holds
    bins[i] <= Dist < bins[i + 1], the last bin everything from bins[-1] up; Dist below bins[0] is bin 0."""
    out: Dict[Tuple[str, int], List[float]] = {}
    for e in episodes:
        i = max(0, int(np.searchsorted(bins, e[DIST_KEY], side="right")) - 1)
        out.setdefault((e["eval_scenario"], i), []).append(float(e[key]))
    return out


def adjusted_difference(base: Sequence[dict], other: Sequence[dict], key: str,
                        bins: Sequence[float]) -> Optional[Dict[str, float]]:
    """``other`` minus ``base`` in the metric ``key``: raw (mean over scenarios of the per-scenario difference of
    means) and at equal distance (stratum differences weighted n_b n_o / (n_b + n_o)); ``coverage`` = share of both
    rows' episodes in strata that both reach. None when no stratum is shared."""
    sb, so = strata_means(base, key, bins), strata_means(other, key, bins)
    shared = sorted(set(sb) & set(so))
    if not shared:
        return None
    w = np.array([len(sb[s]) * len(so[s]) / (len(sb[s]) + len(so[s])) for s in shared])
    d = np.array([np.mean(so[s]) - np.mean(sb[s]) for s in shared])
    scenarios = sorted({e["eval_scenario"] for e in base} & {e["eval_scenario"] for e in other})
    raw = np.mean([np.mean([float(e[key]) for e in other if e["eval_scenario"] == sc])
                   - np.mean([float(e[key]) for e in base if e["eval_scenario"] == sc]) for sc in scenarios])
    covered = sum(len(sb[s]) + len(so[s]) for s in shared) / (len(base) + len(other))
    return {"raw": float(raw), "adjusted": float((w * d).sum() / w.sum()), "coverage": float(covered)}


def by_bin(episodes: Sequence[dict], key: str, bins: Sequence[float]) -> List[Tuple[int, float]]:
    """(episodes, mean metric) per Dist bin, pooled over scenarios and seeds (descriptive)."""
    strata = strata_means(episodes, key, bins)
    out = []
    for i in range(len(bins)):
        vals = [v for (sc, j), vs in strata.items() if j == i for v in vs]
        out.append((len(vals), float(np.mean(vals)) if vals else float("nan")))
    return out


def bin_names(bins: Sequence[float]) -> List[str]:
    return [f"{a:g}-{b:g} m" for a, b in zip(bins, bins[1:])] + [f">= {bins[-1]:g} m"]


def load(out: Path, scenario: str, rows, seeds: Sequence[int]) -> Dict[str, Dict[int, List[dict]]]:
    """row label -> seed -> evaluation episodes, for the runs that have them."""
    found: Dict[str, Dict[int, List[dict]]] = {}
    for row in rows:
        for seed in seeds:
            path = existing(run_dir(out, scenario, row, seed) / EVAL_DIR / "episodes.jsonl")
            if path is not None:
                found.setdefault(row_label(row), {})[seed] = read_jsonl(path)
    return found


def _p(diffs: np.ndarray) -> str:
    """The sign-flip p with its floor at this many seeds; ``≈`` where it is sampled (more than 16 differences)."""
    p, exact = sign_flip_test(diffs)
    return f"{p:.2f} ({min_p(len(diffs)):.3f})" if exact else f"≈ {p:.2f}"


def report(found: Dict[str, Dict[int, List[dict]]], labels: Sequence[str], metric: str,
           bins: Sequence[float]) -> str:
    key, column = METRICS[metric]
    lines = [f"**{column} per episode by Dist bin** (all scenarios and seeds pooled; episodes in brackets)", "",
             "| row | " + " | ".join(bin_names(bins)) + " | all |", "|---|" + "---:|" * (len(bins) + 1)]
    for label in labels:
        if label not in found:
            continue
        eps = [e for seed_eps in found[label].values() for e in seed_eps]
        cells = [f"{m:.2f} ({n})" if n else "-" for n, m in by_bin(eps, key, bins)]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {np.mean([float(e[key]) for e in eps]):.2f} "
                     f"({len(eps)}) |")
    lines += ["", f"**{column}: row − its none row, raw and at equal distance** (strata: evaluation scenario x Dist "
              f"bin; mean ± std over seeds; p: paired sign-flip over seeds, its floor in brackets)", "",
              "| pair | seeds | raw | at equal distance | higher at equal distance | p | coverage |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    votes = []
    details = []
    for base, other in pairs(list(labels)):
        if base not in found or other not in found:
            continue
        per_seed = {s: adjusted_difference(found[base][s], found[other][s], key, bins)
                    for s in sorted(set(found[base]) & set(found[other]))}
        per_seed = {s: r for s, r in per_seed.items() if r is not None}
        if not per_seed:
            continue
        adj = np.array([r["adjusted"] for r in per_seed.values()])
        raw = np.array([r["raw"] for r in per_seed.values()])
        cov = np.mean([r["coverage"] for r in per_seed.values()])
        votes += list(adj)
        lines.append(f"| {other} − {base} | {len(adj)} | {raw.mean():+.2f} ± {raw.std():.2f} | "
                     f"{adj.mean():+.2f} ± {adj.std():.2f} | {int((adj > 0).sum())}/{len(adj)} | {_p(adj)} | "
                     f"{cov:.0%} |")
        details.append(f"- {base} → {other}, seeds {', '.join(map(str, per_seed))}: raw "
                       + ", ".join(f"{r['raw']:+.2f}" for r in per_seed.values()) + "; at equal distance "
                       + ", ".join(f"{r['adjusted']:+.2f}" for r in per_seed.values()))
    if len(details) > 1:
        v = np.array(votes)
        lines.append(f"| every pair above (one vote per architecture and seed) | {len(v)} | | {v.mean():+.2f} ± "
                     f"{v.std():.2f} | {int((v > 0).sum())}/{len(v)} | {_p(v)} | |")
    return "\n".join(lines + [""] + details)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="contacts_at_distance", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="a benchmarks.table1 experiment folder (its --out or --archive)")
    p.add_argument("--train-scenario", default="static_same_goal", help="the scenario the rows were trained on")
    p.add_argument("--rows", default="deepsets/none,deepsets/se3,kattention/none,kattention/se3,graphormer/none,"
                                     "graphormer/se3", help="rows as in benchmarks.table1")
    p.add_argument("--seeds", default="0,1,2,3")
    p.add_argument("--metric", choices=sorted(METRICS), default="cold", help="cold: drone-drone contacts, col: all")
    p.add_argument("--bins", type=parse_bins, default=DEFAULT_BINS, help="Dist bin edges in m, comma-separated")
    p.add_argument("--append", action="store_true", help="append the report to benchmarks/RESULTS.md")
    return p


def main(argv: Optional[Sequence[str]] = None) -> str:
    p = build_parser()
    args = p.parse_args(argv)
    try:
        rows = parse_rows(args.rows)
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError as exc:
        p.error(str(exc))
    started, load_before = time.strftime("%Y-%m-%dT%H:%M:%S"), load_average()
    found = load(Path(args.out), args.train_scenario, rows, seeds)
    if not found:
        p.error(f"no evaluation episodes under {args.out}/runs/{args.train_scenario}/<row>/seed<k>/{EVAL_DIR}/ "
                f"for rows {args.rows} and seeds {args.seeds}")
    text = "\n".join(section_header("contacts_at_distance", started, argv, (), load_before)
                     + ["", report(found, [row_label(r) for r in rows], args.metric, args.bins)])
    publish(text, args.append)
    return text


if __name__ == "__main__":
    main()
