"""How fast a row learns, read off its training curve (metrics.jsonl): the paper credits symmetry with sample
efficiency as well as with the final numbers, and the final evaluation alone cannot show that.

Two numbers per run, both from ``swarm/dist`` (the training swarm's mean distance to its goals over the last 5 s of
each training episode, stochastic actions, with the training aids):

- ``dist_auc``: the distance averaged over the run's agent steps (the area under the curve divided by the steps it
  spans, trapezoid rule on the logged points): lower = closer to the goal sooner and for longer. No threshold.
- ``steps_to_1m``: the agent steps (millions) at which the curve, smoothed as the figure draws it, first falls below
  ``REACH_M`` = 1 m. A run that never gets there counts as its last logged step (censored: its true value is later).

Every row of a Table 1 experiment shares the budget and the seeds, so both are paired by seed like the evaluation
columns (``benchmarks.paired``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Sequence

import numpy as np

REACH_M = 1.0  # the threshold of steps_to_1m (m)
DIST_KEY = "swarm/dist"


@dataclass(frozen=True)
class CurveMetric:
    column: str  # header in the Markdown tables
    decimals: int
    higher_is_better: bool


CURVE_METRICS: Dict[str, CurveMetric] = {
    "dist_auc": CurveMetric("Dist AUC (m)", 2, False),
    "steps_to_1m": CurveMetric(f"M steps to {REACH_M:g} m", 1, False),
}


def distance_curve(records: Sequence[dict]) -> np.ndarray:
    """[n, 2] (agent steps, swarm/dist) of the records that logged a finite distance, in step order."""
    pts = [(r["global_step"], r[DIST_KEY]) for r in records
           if r.get(DIST_KEY) is not None and "global_step" in r and np.isfinite(r[DIST_KEY])]
    pts.sort()
    return np.array(pts, dtype=np.float64).reshape(-1, 2)


def curve_summary(records: Sequence[dict], smooth: Callable[[np.ndarray], np.ndarray]) -> Dict[str, float]:
    """{"dist_auc", "steps_to_1m"} of one run's metrics records ({} when it logged fewer than two distances).
    ``smooth`` is the figure's smoothing, so the crossing is the one a reader sees in the figure."""
    c = distance_curve(records)
    if len(c) < 2 or c[-1, 0] <= c[0, 0]:
        return {}
    steps, dist = c[:, 0], c[:, 1]
    auc = float(np.sum((dist[1:] + dist[:-1]) * np.diff(steps)) / 2 / (steps[-1] - steps[0]))
    below = np.nonzero(smooth(dist) < REACH_M)[0]
    reach = steps[below[0]] if len(below) else steps[-1]
    return {"dist_auc": auc, "steps_to_1m": float(reach) / 1e6, "reached": float(len(below) > 0)}


def speed_markdown(labels: Sequence[str], by_seed: Dict[str, Dict[int, Dict[str, float]]]) -> str:
    """Rows x CURVE_METRICS (mean ± std over seeds; how many seeds reached 1 m), then the paired differences."""
    from benchmarks.paired import paired_markdown

    lines = ["| row | seeds | " + " | ".join(m.column for m in CURVE_METRICS.values()) + f" | reached {REACH_M:g} m |",
             "|---|---:|" + "---:|" * (len(CURVE_METRICS) + 1)]
    for label in labels:
        seeds = by_seed.get(label, {})
        if not seeds:
            continue
        cells = []
        for key, m in CURVE_METRICS.items():
            x = np.array([s[key] for s in seeds.values()])
            cells.append(f"{x.mean():.{m.decimals}f} ± {x.std():.{m.decimals}f}")
        reached = int(sum(s["reached"] for s in seeds.values()))
        lines.append(f"| {label} | {len(seeds)} | " + " | ".join(cells) + f" | {reached}/{len(seeds)} |")
    if len(lines) == 2:
        return ""
    paired = paired_markdown(labels, by_seed, metrics=tuple(CURVE_METRICS), specs=CURVE_METRICS)
    return "\n".join(lines) + ("\n\n" + paired if paired else "")


def summaries(curves: Dict[str, Dict[int, List[dict]]], smooth: Callable[[np.ndarray], np.ndarray]
              ) -> Dict[str, Dict[int, Dict[str, float]]]:
    """row -> seed -> curve_summary, leaving out runs without a distance curve."""
    out: Dict[str, Dict[int, Dict[str, float]]] = {}
    for label, runs in curves.items():
        for seed, records in runs.items():
            s = curve_summary(records, smooth)
            if s:
                out.setdefault(label, {})[seed] = s
    return out

