"""What an evaluation leaves behind: the tables as Markdown and CSV, every episode's stats, trajectory
pictures, and the same tables and pictures in a wandb run (offline by default).

Output folder::

    table1_scenarios.md / .csv   the paper's Table 1: per scenario (x N), per policy
    table2_scaling.md / .csv     the paper's Table 2 (only with several N): per N, scenarios pooled
    episodes.jsonl               one record per episode: policy, N, scenario, seed, every stat, and the
                                 tables' columns of the episode as table_<csv column> (table_reward: the
                                 paper's reward terms, table_reward_shaping: the others, table_collisions:
                                 Col, table_collisions_drone: ColD, ...)
    placement.json               (Ray runs) actors, and tasks and episodes per Ray node
    trajectories/*.png           the first episode of every (policy, N, scenario)
    wandb/                       offline wandb run (``wandb sync`` uploads it)
"""
from __future__ import annotations

import json
import re
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import numpy as np

from quad_env.render import save_trajectory_png
from swarm_appo.eval_tables import (
    TABLE1_METRICS, TABLE2_METRICS, EpisodeGroup, csv_header, csv_records, episode_columns, table1_rows,
    table2_rows, to_csv, to_markdown,
)


@dataclass
class EvalSetup:
    """What was evaluated and how (written next to the tables and into the wandb run's config)."""

    policies: List[Tuple[str, str, int]]  # (label, checkpoint path, agent steps)
    num_agents: List[int]
    scenarios: List[str]
    episodes: int  # per (policy, N, scenario)
    seed: int
    deterministic: bool
    workers: int
    wall_s: float = 0.0


@dataclass
class Report:
    text: str  # the tables with their captions, as printed
    files: List[Path] = field(default_factory=list)
    tables: Dict[str, Tuple[List[str], List[list]]] = field(default_factory=dict)  # name -> (columns, rows)
    images: Dict[str, Tuple[Path, str]] = field(default_factory=dict)  # name -> (png, caption)


def group_results(results, labels: Sequence[str]) -> List[EpisodeGroup]:
    """Chunks of one (policy, N, scenario) joined in chunk order; groups in task (table) order."""
    groups: Dict[tuple, EpisodeGroup] = {}
    for r in sorted(results, key=lambda r: r.task.index):
        t = r.task
        key = (t.policy, t.num_agents, t.scenario)
        if key not in groups:
            groups[key] = EpisodeGroup(labels[t.policy], t.num_agents, t.scenario, [])
        groups[key].episodes.extend(r.episodes)
    return list(groups.values())


def caption(setup: EvalSetup, table: str) -> str:
    actions = "deterministic mean actions" if setup.deterministic else "sampled actions"
    sizes = ", ".join(map(str, setup.num_agents))
    if table == "table1":
        what = f"Table 1: {setup.episodes} episodes per scenario, N = {sizes} drones"
    else:
        what = (f"Table 2 (zero-shot scaling, same room): {setup.episodes} episodes x {len(setup.scenarios)} "
                f"scenarios per N ({', '.join(setup.scenarios)})")
    return f"{what}; seed {setup.seed}; {actions}; mean ± std over episodes."


def _policy_lines(setup: EvalSetup) -> str:
    return "\n".join(f"- {label}: {source}" + (f" ({step:,} agent steps)" if step else "")
                     for label, source, step in setup.policies)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def write_report(out: Path, setup: EvalSetup, results, labels: Sequence[str]) -> Report:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    groups = group_results(results, labels)
    report = Report(text="")
    sections = []
    tables = [("table1", "table1_scenarios", table1_rows(groups), TABLE1_METRICS)]
    if len(setup.num_agents) > 1:
        tables.append(("table2", "table2_scaling", table2_rows(groups), TABLE2_METRICS))
    for name, stem, rows, metrics in tables:
        text = f"{caption(setup, name)}\n\n{to_markdown(rows, metrics)}"
        sections.append(text)
        (out / f"{stem}.md").write_text(f"# Evaluation\n\n{text}\nPolicies:\n\n{_policy_lines(setup)}\n")
        (out / f"{stem}.csv").write_text(to_csv(rows, metrics))
        report.files += [out / f"{stem}.md", out / f"{stem}.csv"]
        report.tables[stem] = (csv_header(rows, metrics), csv_records(rows, metrics))
    report.text = "\n".join(sections)

    with open(out / "episodes.jsonl", "w", encoding="utf-8") as f:
        done: Dict[tuple, int] = {}  # episodes written per (policy, N, scenario): chunks come in order
        for r in sorted(results, key=lambda r: r.task.index):
            t = r.task
            key = (t.policy, t.num_agents, t.scenario)
            first = done.get(key, 0)
            done[key] = first + len(r.episodes)
            for i, e in enumerate(r.episodes):
                record = {"policy": labels[t.policy], "num_agents": t.num_agents, "eval_scenario": t.scenario,
                          "episode": first + i, "task_seed": t.seed, **{k: _jsonable(v) for k, v in e.items()},
                          **{f"table_{k}": v for k, v in episode_columns(e).items()}}
                f.write(json.dumps(record) + "\n")
    report.files.append(out / "episodes.jsonl")

    for r in results:
        if r.trajectory is None:
            continue
        t = r.task
        png = out / "trajectories" / f"{_slug(labels[t.policy])}_{t.scenario}_n{t.num_agents}.png"
        png.parent.mkdir(exist_ok=True)
        save_trajectory_png(r.trajectory, str(png))
        report.files.append(png)
        report.images[png.stem] = (png, r.trajectory.title)
    return report


def write_placement(out: Path, results, address, workers: int, ray_cpus: int) -> Path:
    """``placement.json``: where the tasks of a Ray evaluation ran (tasks and episodes per node)."""
    tasks: Dict[str, int] = {}
    episodes: Dict[str, int] = {}
    for r in results:
        tasks[r.node_id] = tasks.get(r.node_id, 0) + 1
        episodes[r.node_id] = episodes.get(r.node_id, 0) + len(r.episodes)
    path = Path(out) / "placement.json"
    path.write_text(json.dumps({"address": address, "workers": workers, "ray_cpus": ray_cpus,
                                "tasks_per_node": tasks, "episodes_per_node": episodes}, indent=1))
    return path


def log_to_wandb(out: Path, report: Report, setup: EvalSetup, mode: str = "offline",
                 project: str = "swarm-appo") -> None:
    """The tables as wandb Tables (``eval/<table>``) and the pictures as images (``eval/trajectory/<name>``)
    in a new wandb run under ``out/wandb``; ``mode="disabled"`` does nothing."""
    if mode == "disabled":
        return
    import wandb

    try:
        run = wandb.init(dir=str(out), mode=mode, project=project, job_type="eval",
                         name="eval " + " vs ".join(label for label, _, _ in setup.policies),
                         config=asdict(setup), settings=wandb.Settings(console="off", silent=True))
    except Exception as e:  # e.g. "online" without a network: the files are written anyway
        warnings.warn(f"wandb ({mode}) failed to start: {e}; the results are in {out} only", RuntimeWarning)
        return
    record = {f"eval/{name}": wandb.Table(columns=cols, data=rows) for name, (cols, rows) in report.tables.items()}
    record.update({f"eval/trajectory/{name}": wandb.Image(str(png), caption=text)
                   for name, (png, text) in report.images.items()})
    run.log(record)
    run.finish()
