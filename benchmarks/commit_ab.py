"""Before and after: the same training at two commits, alternating, with its speed and whether it learned the same.

    python -m benchmarks.commit_ab --base 81a6ca3                    # base commit vs this working tree
    python -m benchmarks.commit_ab --base 81a6ca3 --head 5925c3d --repeats 3 --agent-steps 2e6
    python -m benchmarks.commit_ab --base HEAD~1 --config configs/table1/quality.yaml --set model.encoder=kattention

A performance change is claimed by end-to-end agent-steps/s, measured alone, old and new interleaved so that a
drift of the machine falls on both. The base (and a ``--head`` commit, if given; default: the working tree as it
is) is checked out with ``git worktree`` into a temporary folder and trained from there with this Python: each
tree imports its own packages (checked before anything trains). Every run is ``python -m launchers.local`` with the
config, ``--set`` overrides, the same seed and agent-step budget, serial by default (deterministic: a change that
should not move the numbers must give the same losses to the last digit, which is reported as such).

Reported per run: agent-steps/s (median of the trainer's ``perf/agent_steps_per_s`` after the warm-up), learner
share, wall seconds; then the head/base ratio of the mean rates and whether every logged loss agrees. Appended to
benchmarks/RESULTS.md with the command, both commits, the machine and load averages (time nothing else meanwhile).
"""
from __future__ import annotations

import argparse
import datetime
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from benchmarks.common import ROOT, load_average, publish, section_header, steady_window
from benchmarks.table1 import read_metrics

LOSS_PREFIX = "losses/"


def git(*args: str, cwd: Path = ROOT) -> str:
    done = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"git {' '.join(args)} failed: {done.stderr.strip()}")
    return done.stdout.strip()


def resolve(rev: str) -> str:
    """A revision's short sha; a clear error for one git does not know."""
    try:
        return git("rev-parse", "--short", "--verify", f"{rev}^{{commit}}")
    except RuntimeError:
        raise SystemExit(f"--base/--head: {rev!r} is not a commit of {ROOT}") from None


def check_imports_from(tree: Path, python: str = sys.executable) -> None:
    """Fail unless ``python -m`` run in ``tree`` imports the trainer from that tree (not from an installed copy)."""
    code = "import swarm_appo, encoders, quad_env; print(swarm_appo.__file__, encoders.__file__, quad_env.__file__)"
    out = subprocess.run([python, "-c", code], cwd=tree, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"cannot import the trainer in {tree}: {out.stderr[-1000:]}")
    files = [Path(f).resolve() for f in out.stdout.split()]
    outside = [str(f) for f in files if tree.resolve() not in f.parents]
    if outside:
        raise RuntimeError(f"in {tree} Python imports {outside} from elsewhere: the comparison would run one code "
                           f"twice (an installed, non-editable copy shadows the tree?)")


def speed(records: Sequence[Dict[str, float]]) -> Dict[str, float]:
    """Median agent-steps/s and learner share of the logged iterations after the warm-up."""
    timed = [r for r in records if "perf/agent_steps_per_s" in r and "time" in r]
    if not timed:
        raise ValueError("no perf/agent_steps_per_s records: the run logged no training iteration")
    steady = steady_window(timed, lambda r: r["time"])
    return {"agent_steps_per_s": statistics.median(r["perf/agent_steps_per_s"] for r in steady),
            "learner_share": statistics.median(r.get("perf/learner_share", float("nan")) for r in steady),
            "agent_steps": float(max(r.get("global_step", 0) for r in records))}


def loss_trace(records: Sequence[Dict[str, float]]) -> List[tuple]:
    """``(global_step, ((loss name, value), ...))`` of every record with losses, in order."""
    return [(r.get("global_step"), tuple(sorted((k, v) for k, v in r.items() if k.startswith(LOSS_PREFIX))))
            for r in records if any(k.startswith(LOSS_PREFIX) for k in r)]


def compare_losses(a: Sequence[tuple], b: Sequence[tuple]) -> str:
    """'identical (n records)' or where the two loss traces first part."""
    if not a or not b:
        return "no losses logged"
    for i, (ra, rb) in enumerate(zip(a, b)):
        if ra != rb:
            names = [ka for (ka, va), (kb, vb) in zip(ra[1], rb[1]) if ka != kb or va != vb] or ["(keys differ)"]
            return f"differ from record {i} (agent step {ra[0]} vs {rb[0]}; first: {names[0]})"
    if len(a) != len(b):
        return f"the first {min(len(a), len(b))} records identical, then one run logged more ({len(a)} vs {len(b)})"
    return f"identical ({len(a)} records)"


def train(tree: Path, run_root: Path, name: str, args) -> Dict[str, float]:
    serial = ["runner.serial=true"] if args.serial else []  # before --set, which may override it
    cmd = [sys.executable, "-m", "launchers.local", "--config", str(Path(args.config).resolve()), *serial, *args.set,
           f"runner.total_agent_steps={int(args.agent_steps)}", f"runner.seed={args.seed}",
           f"runner.run_dir={run_root}", f"runner.name={name}", "runner.final_eval_episodes=0",
           "wandb.mode=disabled", "--no-progress"]
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=tree, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} (in {tree}) failed ({done.returncode}):\n{done.stderr[-2000:]}")
    records = read_metrics(run_root / name)
    return {**speed(records), "wall_s": wall, "losses": loss_trace(records)}


def parse_args(argv: Optional[Sequence[str]]):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--base", required=True, help="the commit before the change")
    p.add_argument("--head", default=None, help="the commit after it (default: the working tree as it is)")
    p.add_argument("--config", default="configs/table1/quality.yaml", help="config trained at both commits")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override (repeatable)")
    p.add_argument("--agent-steps", type=float, default=1e6, help="agent steps per run")
    p.add_argument("--repeats", type=int, default=2, help="runs per commit, alternating base, head, base, ...")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-serial", dest="serial", action="store_false",
                   help="train asynchronously (default: runner.serial=true, deterministic)")
    p.add_argument("--no-results", action="store_true", help="print only, do not append to RESULTS.md")
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error("--repeats must be >= 1")
    if not Path(args.config).is_file() and (ROOT / args.config).is_file():
        args.config = str(ROOT / args.config)  # a path relative to the project, run from elsewhere
    if not Path(args.config).is_file():
        p.error(f"--config: no file {args.config}")
    bad = [s for s in args.set if "=" not in s]
    if bad:
        p.error(f"--set takes KEY=VALUE, got {bad}")
    return args


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parse_args(argv)
    started = datetime.datetime.now().isoformat(timespec="seconds")
    load_before = load_average()
    base = resolve(args.base)
    head = resolve(args.head) if args.head else None
    with tempfile.TemporaryDirectory(prefix="commit_ab_") as tmp:
        tmp = Path(tmp)
        trees = {}
        try:
            for label, rev in (("base", base), ("head", head)):
                if rev is None:
                    trees[label] = ROOT
                    continue
                trees[label] = tmp / label
                git("worktree", "add", "--detach", str(trees[label]), rev)
            for tree in trees.values():
                check_imports_from(tree)
            runs: Dict[str, List[Dict]] = {"base": [], "head": []}
            for i in range(args.repeats):
                for label in ("base", "head"):
                    print(f"[{label} {i + 1}/{args.repeats}] training in {trees[label]}", flush=True)
                    runs[label].append(train(trees[label], tmp / "runs", f"{label}{i}", args))
        finally:
            for label, tree in trees.items():
                if tree != ROOT:
                    subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT,
                                   capture_output=True)
    if head:
        head_name = head
    else:
        dirty = " + uncommitted changes" if git("status", "--porcelain") else ""
        head_name = f"the working tree ({git('rev-parse', '--short', 'HEAD')}{dirty})"
    lines = section_header("commit_ab", started, argv, (), load_before)
    lines += [f"- base: {base}; head: {head_name}; config: {args.config} {' '.join(args.set)}; "
              f"{int(args.agent_steps):,} agent steps per run, seed {args.seed}, "
              f"{'serial' if args.serial else 'asynchronous'}; runs alternate base, head", "",
              "| run | agent steps | agent-steps/s (median after warm-up) | learner share | wall (s) |",
              "|---|---:|---:|---:|---:|"]
    for i in range(args.repeats):
        for label in ("base", "head"):
            r = runs[label][i]
            lines.append(f"| {label} {i + 1} | {r['agent_steps']:,.0f} | {r['agent_steps_per_s']:,.0f} | "
                         f"{r['learner_share']:.3f} | {r['wall_s']:.0f} |")
    mean = {k: statistics.mean(r["agent_steps_per_s"] for r in v) for k, v in runs.items()}
    losses = compare_losses(runs["base"][0]["losses"], runs["head"][0]["losses"])
    lines += ["", f"- head / base, mean agent-steps/s: **{mean['head'] / mean['base']:.2f}x** "
                  f"({mean['base']:,.0f} -> {mean['head']:,.0f})",
              f"- losses of the first base and head runs (same seed): {losses}"]
    publish("\n".join(lines), append=not args.no_results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
