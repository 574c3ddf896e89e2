"""The paper's evaluation tables from episode stats: Table 1 (per scenario) and Table 2 (per swarm size).

Input: ``EpisodeGroup``s, the episodes of one (policy, swarm size N, scenario) as the dicts that
``VecQuadEnv.pop_episode_stats`` returns. Every cell is the mean ± std over episodes (population std,
ddof = 0: the spread of the episodes, not the error of the mean; the CSV carries the episode count to
compute either). Table 2 pools the episodes of all scenarios of one N, as the paper does.

Columns (the paper's names; ``METRICS`` says which episode stats make each; all after the 1.5 s grace
period where contacts are counted):

    Rew      episode reward per drone, the paper's terms c1..c5 only (``PAPER_REWARD_TERMS``)
    Shaping  the reward terms that are not the paper's (``SHAPING_REWARD_TERMS``), per drone; in the
             Markdown table only when some row has them
    Dist     mean distance to goal over the last 5 s, m
    Col      new contacts per episode with the environment or other drones: drone-drone pairs,
             drone-obstacle and drone-room (floor, walls, ceiling) contacts
    ColD     new drone-drone contacts (pairs) per episode
    Suc %    drones within 0.5 m of their goal during the whole last 1 s and without a collision, percent
    IColR    share of drones with a drone-drone contact
    (CSV only, when the stats carry ``reached_rate``: ``reached_pct``, drones that came within 0.5 m of
    their goal at some time, percent)

With several policies the best mean of each column among the rows of one scenario (Table 1) or one
N (Table 2) is printed in bold in the Markdown table, as in the paper.
"""
from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from typing import Dict, List, Sequence, Tuple

import numpy as np

from quad_env.params import REWARD_TERMS

PAPER_REWARD_TERMS = ("pos", "collision", "proximity", "omega", "action")  # the paper's c1..c5
# floor, tilt, goal, height, centre, crash
SHAPING_REWARD_TERMS = tuple(t for t in REWARD_TERMS if t not in PAPER_REWARD_TERMS)


@dataclass(frozen=True)
class Metric:
    """One swarm metric, the single definition that training (``swarm/<name>``), the end-of-run evaluation
    (``eval/<name>``, ``eval_random/<name>``), the tables and the metric docs all read."""

    column: str  # header in the Markdown table
    csv_name: str  # prefix of the CSV columns <csv_name>_mean, <csv_name>_std
    stats: Tuple[str, ...]  # keys in the episode stats dict, summed ...
    scale: float  # ... and the table shows (sum - sum of ``minus``) * scale
    decimals: int
    higher_is_better: bool
    name: str  # logged as swarm/<name> (training episodes), eval/<name>, eval_random/<name> (unscaled)
    description: str  # what it measures, in the metric docs (swarm_appo.metrics.METRICS)
    minus: Tuple[str, ...] = ()  # keys subtracted
    markdown: str = "always"  # in the Markdown table: "always", "nonzero" (when some row is not 0) or "never"
    optional: bool = False  # computed only when every episode has the stats (else the column is left out)
    zero_if_absent: Tuple[str, ...] = ()  # stats that count 0 in episodes written before they existed

    def value(self, episode: dict) -> float:
        """The metric of one episode, unscaled (Suc as a share)."""
        get = lambda k: float(episode.get(k, 0.0) if k in self.zero_if_absent else episode[k])  # noqa: E731
        return sum(get(k) for k in self.stats) - sum(get(k) for k in self.minus)

    def available(self, episode: dict) -> bool:
        return all(k in episode or k in self.zero_if_absent for k in self.stats + self.minus)


METRICS: Dict[str, Metric] = {
    "rew": Metric("Rew", "reward", tuple(f"rew_{t}" for t in PAPER_REWARD_TERMS), 1.0, 2, True, "reward",
                  "Rew: mean per-agent episode reward of the paper's terms c1..c5 (pos, collision, proximity, omega, "
                  "action)"),
    "shaping": Metric("Shaping", "reward_shaping", tuple(f"rew_{t}" for t in SHAPING_REWARD_TERMS), 1.0, 2, True,
                      "reward_shaping", "per-agent episode sum of the training-only shaping terms (floor, tilt, "
                      "goal, height, centre, crash), not in Rew", markdown="nonzero",
                      # terms added after the first evaluation files
                      zero_if_absent=("rew_goal", "rew_height", "rew_centre")),
    "dist": Metric("Dist", "dist", ("dist_last_5s",), 1.0, 2, False, "dist",
                   "Dist: mean distance of a drone to its goal over the last 5 s of the episode (m)"),
    "dist_final": Metric("Dist end", "dist_final", ("dist_final",), 1.0, 2, False, "dist_final",
                         "mean distance of a drone to its goal at the end of the episode (m)", markdown="never"),
    "col": Metric("Col", "collisions", ("collisions_after_grace", "room_contacts_after_grace"), 1.0, 2, False,
                  "collisions", "Col: new contacts per episode after the 1.5 s grace period with other drones "
                  "(pairs), obstacles and the room (floor, walls, ceiling)"),
    "cold": Metric("ColD", "collisions_drone", ("collisions_after_grace",), 1.0, 2, False, "collisions_drone",
                   "ColD: new drone-drone contacts (pairs) per episode after the grace period",
                   minus=("obstacle_collisions_after_grace",)),
    "room": Metric("Room", "room_contacts", ("room_contacts_after_grace",), 1.0, 2, False, "room_contacts",
                   "new floor/wall/ceiling contacts per episode after the grace period (part of Col)",
                   markdown="never"),
    "suc": Metric("Suc %", "success_pct", ("success_rate",), 100.0, 1, True, "success_rate",
                  "Suc: share of drones within 0.5 m of their goal during the whole last 1 s of the episode and "
                  "without a collision after the grace period (0-1)"),
    "reached": Metric("Reached %", "reached_pct", ("reached_rate",), 100.0, 1, True, "reached_rate",
                      "share of drones that came within 0.5 m of their goal at some time (when the episode stats "
                      "carry reached_rate)", markdown="never", optional=True),
    "icolr": Metric("IColR", "inter_collision_rate", ("inter_collision_rate",), 1.0, 3, False,
                    "inter_collision_rate", "IColR: share of drones with a drone-drone collision after the grace "
                    "period"),
}
TABLE1_METRICS = ("rew", "shaping", "dist", "col", "cold", "suc", "reached", "icolr")
TABLE2_METRICS = ("rew", "shaping", "col", "cold", "suc", "reached", "icolr")


@dataclass
class EpisodeGroup:
    """The evaluation episodes of one policy, at one swarm size, in one scenario."""

    policy: str  # label, e.g. "quickstart (deepsets)"
    num_agents: int
    scenario: str
    episodes: List[dict]  # episode stats, in episode order


@dataclass
class Row:
    """One table row: its labels (in column order), the episode count and (mean, std) per metric."""

    labels: Dict[str, str]
    episodes: int
    values: Dict[str, Tuple[float, float]]


def summarize_episodes(episodes: Sequence[dict], metrics: Sequence[str]) -> Dict[str, Tuple[float, float]]:
    """``{metric: (mean, std)}`` over episodes, in table units (Suc in percent); an optional metric only
    when every episode has its stats."""
    if not episodes:
        raise ValueError("no episodes to summarize")
    out = {}
    for name in metrics:
        m = METRICS[name]
        if m.optional and not all(m.available(e) for e in episodes):
            continue
        x = np.array([m.value(e) for e in episodes], dtype=np.float64) * m.scale  # [episodes]
        out[name] = (float(x.mean()), float(x.std()))
    return out


def shown_metrics(rows: Sequence[Row], metrics: Sequence[str], markdown: bool) -> List[str]:
    """The metrics every row has, in order; for the Markdown table without the CSV-only ones and without
    those shown only when nonzero (Shaping) where every row is 0 ± 0."""
    shown = [m for m in metrics if all(m in r.values for r in rows)]
    if markdown:
        shown = [m for m in shown if METRICS[m].markdown == "always" or
                 (METRICS[m].markdown == "nonzero" and any(v != 0 for r in rows for v in r.values[m]))]
    return shown


def episode_columns(episode: dict, metrics: Sequence[str] = TABLE1_METRICS) -> Dict[str, float]:
    """``{csv_name: value}`` of one episode in table units, for the metrics whose stats it has (the
    table's columns of a single episode: episodes.jsonl carries them as ``table_<csv_name>``)."""
    return {METRICS[m].csv_name: METRICS[m].value(episode) * METRICS[m].scale for m in metrics
            if METRICS[m].available(episode)}


def _ordered(values) -> list:
    """Distinct values in order of first appearance."""
    return list(dict.fromkeys(values))


def table1_rows(groups: Sequence[EpisodeGroup]) -> List[Row]:
    """Table 1: one row per scenario (x N when there are several) x policy, in the order the groups came."""
    several_n = len({g.num_agents for g in groups}) > 1
    rows = []
    for scenario in _ordered(g.scenario for g in groups):
        for n in _ordered(g.num_agents for g in groups):
            for g in groups:
                if g.scenario == scenario and g.num_agents == n:
                    labels = {"scenario": scenario, **({"N": str(n)} if several_n else {}), "policy": g.policy}
                    rows.append(Row(labels, len(g.episodes), summarize_episodes(g.episodes, TABLE1_METRICS)))
    return rows


def table2_rows(groups: Sequence[EpisodeGroup]) -> List[Row]:
    """Table 2 (zero-shot scaling): one row per N x policy, the episodes of all scenarios pooled."""
    rows = []
    for n in _ordered(g.num_agents for g in groups):
        for policy in _ordered(g.policy for g in groups):
            episodes = [e for g in groups if g.num_agents == n and g.policy == policy for e in g.episodes]
            if episodes:
                rows.append(Row({"N": str(n), "policy": policy}, len(episodes),
                                summarize_episodes(episodes, TABLE2_METRICS)))
    return rows


def _best_rows(rows: Sequence[Row], metric: str) -> set:
    """Indices of the rows with the best mean of ``metric`` as printed (rounded) among the rows sharing
    all labels but the policy; none where all those rows tie (or there is one: nothing to compare)."""
    blocks: Dict[tuple, List[int]] = {}
    for i, r in enumerate(rows):
        blocks.setdefault(tuple((k, v) for k, v in r.labels.items() if k != "policy"), []).append(i)
    m = METRICS[metric]
    sign = 1.0 if m.higher_is_better else -1.0
    best = set()
    for members in blocks.values():
        shown = {i: sign * round(rows[i].values[metric][0], m.decimals) for i in members
                 if math.isfinite(rows[i].values[metric][0])}
        if len(set(shown.values())) < 2:
            continue
        top = max(shown.values())
        best.update(i for i, v in shown.items() if v == top)
    return best


def to_markdown(rows: Sequence[Row], metrics: Sequence[str]) -> str:
    """A GitHub Markdown table: the label columns, then ``mean ± std`` per shown metric (``shown_metrics``;
    best in bold)."""
    if not rows:
        raise ValueError("no rows")
    metrics = shown_metrics(rows, metrics, markdown=True)
    label_cols = list(rows[0].labels)
    header = label_cols + [METRICS[m].column for m in metrics]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(label_cols) + "---:|" * len(metrics)]
    best = {m: _best_rows(rows, m) for m in metrics}
    for i, r in enumerate(rows):
        cells = [r.labels[c] for c in label_cols]
        for m in metrics:
            d = METRICS[m].decimals
            mean, std = r.values[m]
            cell = f"{mean:.{d}f} ± {std:.{d}f}"
            cells.append(f"**{cell}**" if i in best[m] else cell)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def csv_header(rows: Sequence[Row], metrics: Sequence[str]) -> List[str]:
    """Label columns, ``episodes``, then ``<csv_name>_mean``, ``<csv_name>_std`` of every metric all rows have."""
    label_cols = ["num_agents" if c == "N" else c for c in rows[0].labels]
    stats = [f"{METRICS[m].csv_name}_{s}" for m in shown_metrics(rows, metrics, markdown=False)
             for s in ("mean", "std")]
    return label_cols + ["episodes"] + stats


def csv_records(rows: Sequence[Row], metrics: Sequence[str]) -> List[list]:
    """One list per row, in ``csv_header`` order, numbers at full precision (also the wandb Table data)."""
    metrics = shown_metrics(rows, metrics, markdown=False)
    return [list(r.labels.values()) + [r.episodes] + [v for m in metrics for v in r.values[m]] for r in rows]


def to_csv(rows: Sequence[Row], metrics: Sequence[str]) -> str:
    """CSV with one column per label, the episode count, and ``<metric>_mean``, ``<metric>_std``."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(csv_header(rows, metrics))
    writer.writerows(csv_records(rows, metrics))
    return buf.getvalue()
