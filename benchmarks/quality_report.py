"""The quality goal's report (issue 15 item 6): learning curves of several runs side by side, and where the drones
of an evaluation fail (collided, or clean but outside the success radius at the end).

    python -m benchmarks.quality_report --run "30 M=runs/quality3_deepsets_se3" --run "60 M=runs/quality_60m"
        [--episodes runs/quality_60m/eval_q60/episodes.jsonl ...] [--figure benchmarks/figures/x.png] [--append]

Curves come from each run's metrics.jsonl (training episodes, so with the training aids) through
``benchmarks.table1.plot_curves``; the failure split from the per-drone flags of ``swarm_appo.evaluate``'s
episodes.jsonl (no training aids).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
from collections import defaultdict
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

from benchmarks.common import RESULTS, load_average, publish, section_header
from benchmarks.table1 import plot_curves, read_metrics


def parse_run(text: str) -> Tuple[str, Path]:
    label, sep, path = text.partition("=")
    if not sep or not label or not path:
        raise argparse.ArgumentTypeError(f"--run {text!r}: expected LABEL=RUN_DIR")
    if not (Path(path) / "metrics.jsonl").exists():
        raise argparse.ArgumentTypeError(f"--run {text!r}: {path}/metrics.jsonl does not exist")
    return label, Path(path)


def read_episodes(paths: List[Path]) -> List[dict]:
    """The episodes of several evaluation files. A policy label met in an earlier file gets the file's folder
    appended, so two evaluations that print the same label (e.g. "seed0 (deepsets/se3)" of two experiments)
    stay two rows instead of being pooled."""
    episodes, seen = [], set()
    for path in paths:
        eps = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        labels = {e["policy"] for e in eps}
        clash = labels & seen
        for e in eps:
            if e["policy"] in clash:
                e["policy"] = f"{e['policy']} [{path.parent}]"
        seen |= {e["policy"] for e in eps}
        episodes += eps
    return episodes


NEAR_M = 0.6  # "just outside" the 0.5-m success radius: how near the clean failures' misses are


def failure_split(episodes: List[dict]) -> Dict[str, Dict[str, float]]:
    """Per policy: shares of drones that succeeded, collided after the grace period, or stayed clean but ended
    outside the success radius; the reached share (within the radius at some time, no collision: QuadSwarm's
    success); contact-free episodes; and, where the evaluation recorded each drone's final distance
    (``agent_dist_final``), how far outside the radius the clean failures end: their median final distance and
    the share of them within 0.6 m (None for older evaluation files, or without clean failures)."""
    by_policy: Dict[str, List[dict]] = defaultdict(list)
    for e in episodes:
        by_policy[e["policy"]].append(e)
    out = {}
    for policy, eps in by_policy.items():
        flags = [(s, c, r) for e in eps
                 for s, c, r in zip(e["agent_success"], e["agent_collided"], e["agent_reached"])]
        n = len(flags)
        known = all("agent_dist_final" in e for e in eps)  # older evaluation files lack it
        outside = [d for e in eps if known  # final distances of the clean failures
                   for s, c, d in zip(e["agent_success"], e["agent_collided"], e["agent_dist_final"])
                   if not s and not c]
        out[policy] = {"drones": n, "success": sum(s for s, _, _ in flags) / n,
                       "collided": sum(c for _, c, _ in flags) / n,
                       "clean_outside": sum(not s and not c for s, c, _ in flags) / n,
                       "reached": sum(r for _, _, r in flags) / n,
                       "episodes": len(eps),
                       "contact_free_episodes": sum(e["collisions_after_grace"] == 0 for e in eps),
                       "clean_outside_median_m": float(np.median(outside)) if outside else None,
                       "clean_outside_within_0.6": float(np.mean(np.asarray(outside) <= NEAR_M)) if outside else None}
    return out


def report(split: Dict[str, Dict[str, float]], figure: Path = None) -> str:
    lines = []
    if split:
        lines += ["| policy | drones | Suc % | collided % | clean, outside 0.5 m at the end % | Reached % | "
                  "contact-free episodes | clean outside: median final distance (m) | of them within 0.6 m % |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for policy, s in split.items():
            median, near = s["clean_outside_median_m"], s["clean_outside_within_0.6"]
            lines.append(f"| {policy} | {s['drones']} | {100 * s['success']:.1f} | {100 * s['collided']:.1f} | "
                         f"{100 * s['clean_outside']:.1f} | {100 * s['reached']:.1f} | "
                         f"{s['contact_free_episodes']}/{s['episodes']} | "
                         + ("- | - |" if median is None else f"{median:.2f} | {100 * near:.1f} |"))
    if figure is not None:
        lines += ["", f"![learning curves]({os.path.relpath(figure, RESULTS.parent)})"]  # as RESULTS.md links it
    return "\n".join(lines)


def main(argv=None) -> Dict[str, Dict[str, float]]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=parse_run, action="append", default=[], help="LABEL=RUN_DIR, repeatable")
    p.add_argument("--episodes", type=Path, action="append", default=[],
                   help="episodes.jsonl of a swarm_appo.evaluate output folder, repeatable (one table row per policy)")
    p.add_argument("--figure", type=Path, help="PNG of the runs' learning curves (needs --run)")
    p.add_argument("--append", action="store_true", help="append the figures to benchmarks/RESULTS.md")
    args = p.parse_args(argv)
    if not args.run and not args.episodes:
        p.error("give --run LABEL=RUN_DIR (curves) and/or --episodes FILE (failure split)")
    if args.figure is not None and not args.run:
        p.error("--figure needs at least one --run")
    for path in args.episodes:
        if not path.exists():
            p.error(f"--episodes: {path} does not exist")
    started, load_before = datetime.datetime.now().isoformat(timespec="seconds"), load_average()
    figure = None
    if args.figure is not None:
        figure = plot_curves({label: [read_metrics(rd)] for label, rd in args.run}, args.figure,
                             "training episodes (training aids on)")
    split = failure_split(read_episodes(args.episodes))
    header = section_header("quality_report", started, argv, ["benchmarks"], load_before)
    publish("\n".join(header + ["", report(split, figure)]), args.append)
    return split


if __name__ == "__main__":
    main()
