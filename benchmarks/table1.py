"""The paper's Table 1 on 2 cores: every row trained with ONE recipe, the same seeds and the same agent-step budget,
then evaluated with ``swarm_appo.evaluate`` (no training aids), as mean +- std over seeds, with learning curves.

    python -m benchmarks.table1                                   # the default experiment (resumes where it stopped)
    python -m benchmarks.table1 --rows deepsets/none,deepsets/se3 --seeds 0,1,2 --agent-steps 3e6
    python -m benchmarks.table1 --train-scenarios static_same_goal,mix --episodes 50
    python -m benchmarks.table1 --rows deepsets/none --compare runner.precision=fp32,bf16   # one recipe change

A row is ``architecture/symmetry`` (``encoders.ARCHITECTURES`` x ``encoders.SYMMETRIES``), or a named baseline of
``PRESETS`` (``rmappo/none``: the mlp encoder with a GRU core and a central critic); only ``model.encoder`` and
``model.symmetry`` (and a preset's own model keys) differ between rows (``--config`` is the recipe, ``--set
key=value`` changes it for every row; ``--compare KEY=V1,V2`` splits every row into one variant per value). Each
training is an ordinary run directory ``<out>/runs/<train scenario>/<arch>-<symmetry>[-<key>-<value>]/seed<k>``;
a finished one holds ``done.json`` and is skipped next time, an interrupted one resumes from its last checkpoint
(one killed before its first checkpoint starts again), and an evaluated one keeps its ``eval_table1/``. So a
killed experiment resumes where it stopped, and the table fills in row by row. Raising ``--agent-steps`` trains
every finished run on from its last checkpoint to the new budget (and evaluates it again); with a budget-tied lr
schedule (``algo.lr_schedule=linear``) that is refused, since the decay would restart mid-run.
``--archive DIR`` keeps slim copies of the evaluated runs there and restores missing ones from it
(``benchmarks.table1_archive``), so an experiment can be filled in across machines. ``--select`` reports, for
every run alike, the checkpoint ``swarm_appo.select_checkpoint`` picks among the run's kept ones on validation
episodes of its training scenario (seeded apart from the evaluation's) instead of the last one; its evaluations
go to ``eval_table1_selected/``, so one experiment can report both.

Output: ``<out>/table1.md`` (also appended to benchmarks/RESULTS.md unless ``--no-results``) with one table
per (training scenario, evaluation scenario): rows x the paper's columns, mean +- std over seeds of each seed's
mean over its evaluation episodes; each row's agent-steps/s; under it each symmetry row paired with its ``none``
row seed by seed (``benchmarks.paired``: the differences and an exact sign-flip test); how fast each row learned
(``benchmarks.learning_speed``: the mean training distance over the run and the agent steps to 1 m, also paired by
seed); and learning curves (training episodes: success, collisions, distance against agent steps, a line per row =
mean over seeds, band = min..max) as PNG.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from benchmarks.common import ROOT, append_results, commit, load_average, machine
from benchmarks.learning_speed import REACH_M, speed_markdown, summaries
from benchmarks.paired import paired_markdown
from benchmarks.table1_archive import archive_run, existing, read_jsonl, restore_runs

DEFAULT_ROWS = ("deepsets/none", "deepsets/se3", "kattention/none", "kattention/se3", "graphormer/none",
                "graphormer/se3")
DEFAULT_RECIPE = ROOT / "configs" / "table1" / "recipe.yaml"
# training-curve metrics of metrics.jsonl (training episodes, with the training aids) -> plot title
# (metric keys, first present wins: runs logged before swarm/collisions_drone existed have drone contacts in
# swarm/collisions) -> plot title
CURVES = ((("swarm/success_rate",), "success rate (Suc)"),
          (("swarm/collisions_drone", "swarm/collisions"), "drone collisions / episode (ColD)"),
          (("swarm/dist",), "distance to goal, last 5 s (m)"))
EVAL_DIR = "eval_table1"
SELECTED_EVAL_DIR = "eval_table1_selected"  # --select: the evaluation of checkpoints/selected.pt
# named baselines that are more than an encoder: row name -> (architecture, the model keys it sets)
PRESETS: Dict[str, Tuple[str, Tuple[str, ...]]] = {
    "rmappo": ("mlp", ("model.core=gru", "model.critic=central")),  # configs/paper/rmappo.yaml's network
}


# ----------------------------------------------------------------------------------------------- plan
Row = Tuple[str, str, Optional[str]]  # (architecture, symmetry, "key=value" of --compare or None)


def parse_compare(text: Optional[str]) -> List[Optional[str]]:
    """``KEY=V1,V2`` -> ["KEY=V1", "KEY=V2"]; None -> [None] (no comparison)."""
    if text is None:
        return [None]
    key, eq, values = text.partition("=")
    vals = [v.strip() for v in values.split(",") if v.strip()]
    if not eq or not key.strip() or len(vals) < 2:
        raise ValueError(f"--compare {text!r} must be KEY=V1,V2[,...] (at least two values)")
    return [f"{key.strip()}={v}" for v in dict.fromkeys(vals)]


def parse_rows(text: str, compare: Optional[str] = None) -> List[Row]:
    import encoders

    rows = []
    for item in (s.strip() for s in text.split(",") if s.strip()):
        arch, _, symmetry = item.partition("/")
        if arch not in (*encoders.ARCHITECTURES, *PRESETS) or symmetry not in encoders.SYMMETRIES:
            raise ValueError(f"row {item!r} must be architecture/symmetry with architecture in "
                             f"{list(encoders.ARCHITECTURES) + list(PRESETS)} and symmetry in "
                             f"{list(encoders.SYMMETRIES)}")
        rows.extend((arch, symmetry, setting) for setting in parse_compare(compare))
    if not rows:
        raise ValueError("--rows names no row")
    return list(dict.fromkeys(rows))


def _short(setting: str) -> Tuple[str, str]:
    key, _, value = setting.partition("=")
    return key.rsplit(".", 1)[-1], value


def row_label(row: Row) -> str:
    label = f"{row[0]}/{row[1]}"
    return label if row[2] is None else label + " {}={}".format(*_short(row[2]))


def row_name(row: Row) -> str:
    """A row as a file name: deepsets-se3, deepsets-none-precision-bf16."""
    name = f"{row[0]}-{row[1]}" if row[2] is None else f"{row[0]}-{row[1]}-" + "-".join(_short(row[2]))
    return name.replace("/", "_")


def run_dir(out: Path, scenario: str, row: Row, seed: int) -> Path:
    return out / "runs" / scenario / row_name(row) / f"seed{seed}"


def row_config(args, scenario: str, row: Row, seed: int):
    """The recipe with this row's encoder, symmetry (and --compare value), scenario, seed and budget (validated,
    nothing written)."""
    from swarm_appo.config import load_config

    rd = run_dir(Path(args.out), scenario, row, seed)
    encoder, preset = PRESETS.get(row[0], (row[0], ()))
    overrides = [*args.set, *preset, *([row[2]] if row[2] else []), f"model.encoder={encoder}",
                 f"model.symmetry={row[1]}",
                 f"env.scenario={scenario}",
                 f"runner.seed={seed}", f"runner.total_agent_steps={args.agent_steps}",
                 f"runner.run_dir={rd.parent}", f"runner.name={rd.name}", "runner.final_eval_episodes=0",
                 f"wandb.group=table1-{scenario}", "wandb.tags=[table1]"]  # the trainer adds architecture/symmetry tags
    return load_config(str(args.config), overrides)


# ----------------------------------------------------------------------------------------------- train
def has_checkpoint(rd: Path) -> bool:
    return any((rd / "checkpoints").glob("ckpt_*.pt"))


def train_run(cfg, rd: Path, progress: bool) -> Optional[dict]:
    """Train (or resume) one run to its budget; returns its done.json record, None if interrupted."""
    from swarm_appo.trainer import train

    if rd.exists() and not has_checkpoint(rd):  # killed before its first checkpoint: nothing worth keeping
        shutil.rmtree(rd)
    resume = str(rd) if rd.exists() else None
    start = time.perf_counter()
    result = train(cfg, resume_dir=resume, progress=progress)
    if result.interrupted:
        return None
    steps_per_s = [r["perf/agent_steps_per_s"] for r in read_metrics(rd) if "perf/agent_steps_per_s" in r]
    record = {"agent_steps": result.agent_steps, "wall_s": time.perf_counter() - start,
              "agent_steps_per_s": float(np.median(steps_per_s)) if steps_per_s else float("nan"),
              "resumed": resume is not None}
    (rd / "done.json").write_text(json.dumps(record, indent=1))
    return record


def is_short(rd: Path, agent_steps: int) -> bool:
    """A finished run trained for less than ``agent_steps`` (the experiment's budget was raised since)."""
    done = rd / "done.json"
    return done.exists() and json.loads(done.read_text())["agent_steps"] < agent_steps


def read_metrics(rd: Path) -> List[dict]:
    """The run's metrics records (a torn last line of a killed run skipped); an archived run's are gzipped."""
    path = existing(rd / "metrics.jsonl")
    return read_jsonl(path) if path else []


# ----------------------------------------------------------------------------------------------- evaluate
def eval_scenarios(train_scenario: str, text: str) -> str:
    if text != "auto":
        return text
    return "all" if train_scenario == "mix" else train_scenario  # mix-trained: every scenario, as the paper


def evaluate_run(rd: Path, scenarios: str, episodes: int, workers: Optional[int],
                 select_on: Optional[str] = None, select_episodes: int = 25) -> Path:
    """``swarm_appo.evaluate`` on the run's last checkpoint (seeded as every run: same episodes for every row),
    or, with ``select_on`` (a scenario), on the checkpoint ``swarm_appo.select_checkpoint`` picks there."""
    from swarm_appo import evaluate

    name = EVAL_DIR if select_on is None else SELECTED_EVAL_DIR
    out = rd / name
    if (out / "episodes.jsonl").exists():
        return out
    checkpoint = rd
    if select_on is not None:
        from swarm_appo import select_checkpoint

        record = select_checkpoint.select(str(rd), episodes=select_episodes, scenarios=[select_on], workers=workers)
        print(f"    selected {record['selected']} on {select_episodes} validation episodes of {select_on}", flush=True)
        checkpoint = rd / "checkpoints" / select_checkpoint.SELECTED_NAME
    tmp = rd / f"{name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    argv = ["--checkpoint", str(checkpoint), "--scenarios", scenarios, "--episodes", str(episodes), "--seed", "2024",
            "--out", str(tmp), "--no-pictures", "--no-progress", "--wandb-mode", "disabled"]
    if workers is not None:
        argv += ["--workers", str(workers)]
    if evaluate.main(argv) != 0:
        raise RuntimeError(f"evaluation of {rd} failed")
    tmp.rename(out)  # complete or absent: a killed evaluation is redone
    return out


# ----------------------------------------------------------------------------------------------- aggregate
def seed_means(episodes_file: Path) -> Dict[str, Dict[str, float]]:
    """{eval scenario: {metric: mean over the run's episodes}} in table units, plus "episodes" (their count)."""
    from swarm_appo.eval_tables import TABLE1_METRICS, summarize_episodes

    by_scenario: Dict[str, List[dict]] = {}
    for e in read_jsonl(episodes_file):
        by_scenario.setdefault(e["eval_scenario"], []).append(e)
    return {s: {**{m: v[0] for m, v in summarize_episodes(eps, TABLE1_METRICS).items()}, "episodes": len(eps)}
            for s, eps in by_scenario.items()}


POOLED = "all scenarios (mean)"  # the row of a seed pooled over the evaluation scenarios, each weighted equally


def pooled_means(per_scenario: Dict[str, Dict[str, float]]) -> Dict[str, float]:
    """One seed's metrics averaged over its evaluation scenarios (each scenario one vote)."""
    keys = set.intersection(*(set(m) for m in per_scenario.values()))
    return {k: float(np.mean([m[k] for m in per_scenario.values()])) for k in keys}


def episodes_label(by_row: Dict[str, List[Dict[str, float]]]) -> str:
    counts = sorted({int(c["episodes"]) for cells in by_row.values() for c in cells if "episodes" in c})
    return "-".join(str(c) for c in counts[::max(1, len(counts) - 1)]) if counts else "?"


def table_markdown(rows: Sequence[str], cells: Dict[str, List[Dict[str, float]]], speeds: Dict[str, List[float]],
                   n_seeds: Dict[str, int]) -> str:
    """Rows x the paper's columns, mean +- std over seeds (the best mean of each column in bold)."""
    from swarm_appo.eval_tables import METRICS

    metrics = [m for m in ("rew", "shaping", "dist", "col", "cold", "suc", "icolr")
               if any(m in c for r in rows for c in cells.get(r, []))]
    stats = {}
    for r in rows:
        for m in metrics:
            x = np.array([c[m] for c in cells.get(r, []) if m in c])
            stats[r, m] = (float(x.mean()), float(x.std())) if len(x) else None
    best = {}
    for m in metrics:
        vals = [(round(stats[r, m][0], METRICS[m].decimals), r) for r in rows if stats[r, m] is not None]
        if len(vals) > 1 and len({v for v, _ in vals}) > 1:
            target = max(vals)[0] if METRICS[m].higher_is_better else min(vals)[0]
            best[m] = {r for v, r in vals if v == target}
    head = "| row | seeds | " + " | ".join(METRICS[m].column for m in metrics) + " | agent-steps/s |"
    lines = [head, "|---|---:|" + "---:|" * len(metrics) + "---:|"]
    for r in rows:
        parts = []
        for m in metrics:
            s = stats[r, m]
            if s is None:
                parts.append("-")
                continue
            d = METRICS[m].decimals
            text = f"{s[0]:.{d}f} ± {s[1]:.{d}f}"
            parts.append(f"**{text}**" if r in best.get(m, ()) else text)
        sps = speeds.get(r, [])
        speed = f"{np.mean(sps):,.0f}" if sps else "-"
        lines.append(f"| {r} | {n_seeds.get(r, 0)} | " + " | ".join(parts) + f" | {speed} |")
    return "\n".join(lines)


SMOOTH_RECORDS = 9  # learning curves: running mean over this many logged iterations (a few thousand episodes)


def smooth(y: np.ndarray, window: int) -> np.ndarray:
    """Centred running mean, the window shrinking at the ends (no lag, no padding artefacts)."""
    c = np.concatenate([[0.0], np.cumsum(y)])
    half = window // 2
    lo = np.clip(np.arange(len(y)) - half, 0, len(y))
    hi = np.clip(np.arange(len(y)) + half + 1, 0, len(y))
    return (c[hi] - c[lo]) / (hi - lo)


def plot_curves(curves: Dict[str, List[List[dict]]], path: Path, title: str) -> Optional[Path]:
    """One panel per CURVES metric: a line per row (mean over seeds on a common step grid), band min..max."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(CURVES), figsize=(5 * len(CURVES), 3.6))
    drawn = False
    for ax, (keys, name) in zip(axes, CURVES):
        for label, runs in curves.items():
            series = []
            for records in runs:
                key = next((k for k in keys if any(k in r for r in records)), keys[0])
                pts = [(r["global_step"], r[key]) for r in records if r.get(key) is not None and np.isfinite(r[key])]
                if len(pts) >= 2:
                    pts = np.array(pts, dtype=float)
                    pts[:, 1] = smooth(pts[:, 1], SMOOTH_RECORDS)
                    series.append(pts)
            if not series:
                continue
            end = min(s[-1, 0] for s in series)
            grid = np.linspace(max(s[0, 0] for s in series), end, 60)
            ys = np.stack([np.interp(grid, s[:, 0], s[:, 1]) for s in series])  # [seeds, 60]
            line, = ax.plot(grid / 1e6, ys.mean(0), label=f"{label} ({len(series)} seed{'s' * (len(series) > 1)})")
            if len(series) > 1:
                ax.fill_between(grid / 1e6, ys.min(0), ys.max(0), alpha=0.2, color=line.get_color())
            drawn = True
        ax.set_xlabel("agent steps (M)")
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)
    if not drawn:
        plt.close(fig)
        return None
    axes[0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def budget_label(agent_steps: int) -> str:
    """A budget as a figure name shows it: 768, 50k, 3M, 1.5M."""
    for scale, unit in ((1_000_000, "M"), (1_000, "k")):
        if agent_steps >= scale and agent_steps % (scale // 10) == 0:
            return f"{agent_steps / scale:g}{unit}"
    return str(agent_steps)


def seeds_label(seeds: Sequence[int]) -> str:
    """Seeds as a figure name shows them: seeds0-3 for a range, seeds0+2+5 otherwise."""
    s = sorted(set(seeds))
    if len(s) > 2 and s == list(range(s[0], s[-1] + 1)):
        return f"seeds{s[0]}-{s[-1]}"
    return "seeds" + "+".join(map(str, s))


def figure_name(out_name: str, scenario: str, agent_steps: int, rows: Sequence[Row], seeds: Sequence[int]) -> str:
    """The curves figure of one report: experiment, training scenario, budget, rows and seeds are all in the name,
    so a later report with other rows or seeds draws its own file and never redraws the one an earlier entry links."""
    return (f"{out_name}_{scenario}_{budget_label(agent_steps)}_{'+'.join(row_name(r) for r in rows)}_"
            f"{seeds_label(seeds)}.png")


def _link(path: Path) -> str:
    """``path`` as RESULTS.md (in benchmarks/) links to it."""
    base = ROOT / "benchmarks"
    return str(path.relative_to(base)) if path.resolve().is_relative_to(base) else str(path)


# ----------------------------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.table1", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="runs/table1", help="experiment folder (runs, evaluations, table)")
    p.add_argument("--config", default=str(DEFAULT_RECIPE), help="the recipe shared by every row")
    p.add_argument("--rows", default=",".join(DEFAULT_ROWS), help="architecture/symmetry,...")
    p.add_argument("--train-scenarios", default="static_same_goal", help="comma-separated, e.g. static_same_goal,mix")
    p.add_argument("--seeds", default="0,1", help="comma-separated seeds, the same for every row")
    p.add_argument("--agent-steps", type=float, default=3e6, help="training budget of every run")
    p.add_argument("--episodes", type=int, default=50, help="evaluation episodes per scenario")
    p.add_argument("--eval-scenarios", default="auto",
                   help="'auto' (the training scenario; every scenario for mix), 'all' or a comma-separated list")
    p.add_argument("--workers", type=int, default=0,
                   help="evaluation workers (swarm_appo.evaluate --workers; 0 = in-process, no Ray start-up)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a config override applied to every row (repeatable)")
    p.add_argument("--compare", default=None, metavar="KEY=V1,V2",
                   help="one config key to compare: every row is trained once per value (e.g. runner.precision)")
    p.add_argument("--figures", default=None,
                   help="where the PNGs go (default: benchmarks/figures, or <out>/figures with --no-results, so that a "
                        "report kept out of RESULTS.md leaves no figure in the repository either)")
    p.add_argument("--no-results", action="store_true", help="do not append to benchmarks/RESULTS.md")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--report-only", action="store_true", help="train nothing: table and curves of what exists")
    p.add_argument("--select", action="store_true",
                   help="report each run's checkpoint chosen on validation episodes (swarm_appo.select_checkpoint) "
                        "instead of its last one")
    p.add_argument("--select-episodes", type=int, default=25, help="validation episodes per checkpoint (--select)")
    p.add_argument("--archive", default=None, metavar="DIR",
                   help="slim copies of finished runs (benchmarks.table1_archive): runs missing from --out are "
                        "restored from DIR if their recipe matches, and every evaluated run is copied into DIR")
    return p


def figures_dir(args, out: Path) -> Path:
    """``--figures``, else benchmarks/figures beside RESULTS.md, or the experiment's folder with ``--no-results``."""
    if args.figures:
        return Path(args.figures)
    return out / "figures" if args.no_results else ROOT / "benchmarks" / "figures"


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    from swarm_appo.config import ConfigError

    args.agent_steps = int(args.agent_steps)
    if args.select_episodes < 1:
        p.error(f"--select-episodes must be >= 1, got {args.select_episodes}")
    eval_dir = SELECTED_EVAL_DIR if args.select else EVAL_DIR
    try:
        rows = parse_rows(args.rows, args.compare)
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
        scenarios = [s.strip() for s in args.train_scenarios.split(",") if s.strip()]
        plan = [(sc, row, seed, row_config(args, sc, row, seed)) for sc in scenarios for seed in seeds
                for row in rows]  # every config checked before anything trains
    except (ConfigError, ValueError) as exc:
        p.error(str(exc))
    out = Path(args.out)
    archive = Path(args.archive) if args.archive else None
    if archive is not None and archive.resolve() == out.resolve():
        p.error("--archive must be another folder than --out (report on an archive with --out DIR --report-only)")
    if archive is not None:
        from swarm_appo.config import config_to_dict

        items = [(run_dir(archive, sc, row, seed), run_dir(out, sc, row, seed), config_to_dict(cfg))
                 for sc, row, seed, cfg in plan]
        try:
            restored = restore_runs(items, eval_dir)
        except ValueError as exc:
            p.error(str(exc))
        for i in restored:
            sc, row, seed, _ = plan[i]
            print(f"restored {row_label(row)} on {sc}, seed {seed} from {archive}", flush=True)
    decaying = [str(run_dir(out, sc, row, seed)) for sc, row, seed, cfg in plan
                if cfg.algo.lr_schedule != "constant" and is_short(run_dir(out, sc, row, seed), args.agent_steps)]
    if decaying and not args.report_only:  # its lr reached ~0 at the old budget: training on restarts the decay
        p.error(f"--agent-steps {args.agent_steps:,} raises the budget of finished runs whose algo.lr_schedule "
                f"ties the lr to their budget ({', '.join(decaying)}): training them on would restart the decay "
                f"mid-run, unlike a fresh run at that budget. Use another --out (fresh runs) or a constant lr.")
    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    load_before = load_average()

    for k, (sc, row, seed, cfg) in enumerate(plan):  # seeds outer: a partial experiment has every row once
        rd = run_dir(out, sc, row, seed)
        if not args.report_only and is_short(rd, args.agent_steps):  # a larger budget: train on from the end
            (rd / "done.json").unlink()
            for name in (EVAL_DIR, SELECTED_EVAL_DIR):
                shutil.rmtree(rd / name, ignore_errors=True)
        if not args.report_only and not (rd / "done.json").exists():
            print(f"[{k + 1}/{len(plan)}] training {row_label(row)} on {sc}, seed {seed} -> {rd}", flush=True)
            record = train_run(cfg, rd, progress=not args.no_progress)
            if record is None:
                print("interrupted: run the same command again to resume", file=sys.stderr)
                return 130
            print(f"    {record['agent_steps']:,} agent steps, {record['agent_steps_per_s']:,.0f} agent-steps/s "
                  f"(median over the run), {record['wall_s']:.0f} s", flush=True)
        if (rd / "done.json").exists() and not args.report_only:
            evaluate_run(rd, eval_scenarios(sc, args.eval_scenarios), args.episodes, args.workers,
                         select_on=sc if args.select else None, select_episodes=args.select_episodes)
        if archive is not None and archive_run(rd, run_dir(archive, sc, row, seed), eval_dir):
            print(f"archived {row_label(row)} on {sc}, seed {seed} -> {run_dir(archive, sc, row, seed)}", flush=True)

    sections = []
    figures = []
    for sc in scenarios:
        by_seed: Dict[str, Dict[str, Dict[int, Dict[str, float]]]] = {}  # eval scenario -> row -> seed -> means
        speeds: Dict[str, List[float]] = {}
        curves: Dict[str, List[List[dict]]] = {}
        curves_by_seed: Dict[str, Dict[int, List[dict]]] = {}  # the same records, keyed by seed for the pairing
        for row in rows:
            label = row_label(row)
            for seed in seeds:
                rd = run_dir(out, sc, row, seed)
                if not (rd / "done.json").exists():
                    continue
                speeds.setdefault(label, []).append(json.loads((rd / "done.json").read_text())["agent_steps_per_s"])
                records = read_metrics(rd)
                curves.setdefault(label, []).append(records)
                curves_by_seed.setdefault(label, {})[seed] = records
                ep = existing(rd / eval_dir / "episodes.jsonl")
                if ep is not None:
                    per_scenario = seed_means(ep)
                    if len(per_scenario) > 1:
                        per_scenario = {**per_scenario, POOLED: pooled_means(per_scenario)}
                    for es, means in per_scenario.items():
                        by_seed.setdefault(es, {}).setdefault(label, {})[seed] = means
        labels = [row_label(r) for r in rows]
        for es in sorted(by_seed, key=lambda name: name != POOLED):  # the pooled table first
            by_row = {r: list(per_seed.values()) for r, per_seed in by_seed[es].items()}  # row -> per-seed means
            n = {r: len(v) for r, v in by_row.items()}
            where = f"`{es}`" if es != POOLED else f"{POOLED} of the {len(by_seed) - 1} below"
            sections.append(f"**trained on `{sc}`, evaluated on {where}** ({episodes_label(by_row)} episodes per "
                            f"scenario and seed, mean actions, no training aids)\n\n"
                            + table_markdown(labels, by_row, speeds, n))
            paired = paired_markdown(labels, by_seed[es])
            if paired:
                sections.append(paired)
        speed = speed_markdown(labels, summaries(curves_by_seed, lambda y: smooth(y, SMOOTH_RECORDS)))
        if speed:
            sections.append(f"**learning speed, trained on `{sc}`** (training curves: the training swarm's distance "
                            f"to its goals, stochastic actions, with the training aids; Dist AUC = its mean over "
                            f"the run's agent steps; M steps to {REACH_M:g} m = where the curve, smoothed as in the "
                            f"figure, first falls below {REACH_M:g} m, a run that never does counted at its last "
                            f"step)\n\n" + speed)
        fig = plot_curves(curves, figures_dir(args, out) / figure_name(out.name, sc, args.agent_steps, rows, seeds),
                          f"training curves, {sc} (training episodes, with the training aids; running mean over "
                          f"{SMOOTH_RECORDS} iterations); mean over seeds, band min..max")
        if fig is not None:
            figures.append(fig)

    done = sum((run_dir(out, sc, r, s) / "done.json").exists() for sc in scenarios for r in rows for s in seeds)
    text = "\n".join([
        f"## table1 — {started}",
        "",
        f"- command: `python -m benchmarks.table1 {' '.join(argv if argv is not None else sys.argv[1:])}`",
        f"- commit: {commit(['encoders', 'swarm_appo', 'quad_env', 'configs'])}",
        f"- machine: {machine()}; load average before: {load_before}, after: {load_average()}",
        f"- recipe: `{Path(args.config).relative_to(ROOT) if Path(args.config).is_relative_to(ROOT) else args.config}`"
        + (f" with {' '.join(args.set)}" if args.set else "")
        + (f"; compared: {args.compare}" if args.compare else "") + f"; {args.agent_steps:,} agent steps per run; "
        f"seeds {seeds}; {done} of {len(plan)} runs trained",
        "- final policy: " + (f"each run's checkpoint chosen by `swarm_appo.select_checkpoint` among its kept ones "
                              f"({args.select_episodes} validation episodes of the training scenario, seeded apart "
                              f"from the evaluation's; by Suc, then Col, then Dist)" if args.select
                              else "each run's last checkpoint"),
        "- cells: mean ± std over seeds (population std) of each seed's mean over its evaluation episodes; Rew = the "
        "paper's terms c1..c5, Shaping = the training-only terms; Col = drone, obstacle and room contacts after the "
        "1.5 s grace period, ColD = drone-drone only; Suc = within 0.5 m of the goal during the whole last second "
        "and no collision after the grace period; agent-steps/s = median over each run's iterations, mean over seeds",
        "",
        *(s + "\n" for s in sections),
        *(f"![{f.stem}]({_link(f)})" for f in figures),
    ])
    out.mkdir(parents=True, exist_ok=True)
    (out / "table1.md").write_text(text + "\n")
    print(text)
    if not args.no_results:
        append_results(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
