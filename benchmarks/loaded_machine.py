"""The quickstart on a quiet and on a busy machine: agent-steps/s per ``runner.learner_threads`` setting.

    python -m benchmarks.loaded_machine                        # 90 s per run, 2 busy processes as the "load"
    python -m benchmarks.loaded_machine --seconds 60 --hogs 2 --threads 0,all

A laptop that trains is rarely idle. This runs the README's main job (the embedded quickstart config, as
``python -m launchers.local`` runs it) for ``--seconds`` of training per case, for each learner-thread setting
(``0`` = the default: the cores left after the rollout workers; ``all`` = every core, the old default that
oversubscribed the cores) on a quiet machine and with ``--hogs`` busy-looping processes running. The hogs start
in their own session (``setsid``), so on a kernel that groups processes per session (autogroup) they compete as
another user's work would. Reported: agent steps trained, agent-steps/s (steps / training time, from
metrics.jsonl), and the ratio of each setting to the default under the same load. Appended to
benchmarks/RESULTS.md with the command, commit, machine and load averages.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Dict, List, Sequence

from benchmarks.common import ROOT, load_average, publish, section_header

HOG = "while True: pass"


def start_hogs(count: int) -> List[subprocess.Popen]:
    """``count`` busy-looping Python processes, each in a new session (its own autogroup)."""
    return [subprocess.Popen([sys.executable, "-c", HOG], start_new_session=True) for _ in range(count)]


def stop_hogs(hogs: Sequence[subprocess.Popen]) -> None:
    for h in hogs:
        h.send_signal(signal.SIGKILL)
        h.wait()


def learner_threads_value(setting: str) -> int:
    """``all`` -> every core; else the number (0 = the trainer's default)."""
    return (os.cpu_count() or 1) if setting == "all" else int(setting)


def train_for(run_root: Path, name: str, seconds: float, threads: int) -> Dict[str, float]:
    """The quickstart trained for ``seconds`` (runner.time_limit_s) with ``learner_threads``: steps and rate."""
    cmd = [sys.executable, "-m", "launchers.local", "--no-progress", f"runner.run_dir={run_root}",
           f"runner.name={name}", f"runner.time_limit_s={seconds}", "runner.final_eval_episodes=0",
           "runner.checkpoint_every_s=3600", "wandb.mode=disabled", f"runner.learner_threads={threads}"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    rows = [json.loads(line) for line in (run_root / name / "metrics.jsonl").read_text().splitlines() if line]
    rows = [r for r in rows if "charts/elapsed_s" in r]
    steps, elapsed = rows[-1]["global_step"], rows[-1]["charts/elapsed_s"]
    return {"agent_steps": steps, "elapsed_s": elapsed, "agent_steps_per_s": steps / elapsed}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=90.0, help="training time per run")
    p.add_argument("--hogs", type=int, default=2, help="busy processes of the loaded case")
    p.add_argument("--threads", default="0,all", help="learner_threads settings (0 = default, all = every core)")
    p.add_argument("--no-append", action="store_true")
    args = p.parse_args(argv)
    settings = [s.strip() for s in args.threads.split(",") if s.strip()]
    if not settings or any(s != "all" and not (s.isdigit()) for s in settings):
        p.error(f"--threads: comma-separated learner_threads values (0 = default, a number, or all), "
                f"got {args.threads!r}")
    root = Path(tempfile.mkdtemp(prefix="loaded_machine_"))
    started, load_before = datetime.datetime.now().isoformat(timespec="seconds"), load_average()
    results = {}
    for load in ("quiet", "loaded"):
        for setting in settings:
            hogs = start_hogs(args.hogs) if load == "loaded" else []
            try:
                results[load, setting] = train_for(root, f"{load}_{setting}", args.seconds,
                                                   learner_threads_value(setting))
            finally:
                stop_hogs(hogs)
            r = results[load, setting]
            print(f"{load:6s} learner_threads={setting:4s} {r['agent_steps']:>10,} steps in {r['elapsed_s']:.0f} s: "
                  f"{r['agent_steps_per_s']:,.0f} agent-steps/s", flush=True)
    lines = []
    for (load, setting), r in results.items():
        base = results[load, settings[0]]["agent_steps_per_s"]
        lines.append(f"| {load} | {setting} ({learner_threads_value(setting)}) | {r['agent_steps']:,} | "
                     f"{r['agent_steps_per_s']:,.0f} | {r['agent_steps_per_s'] / base:.2f} |")
    section = "\n".join([
        *section_header("loaded_machine", started, argv, ["swarm_appo", "launchers", "quad_env", "encoders"],
                        load_before),
        f"- the quickstart (embedded default config) trained {args.seconds:.0f} s per row; loaded = {args.hogs} "
        f"busy-looping processes in their own session; ratio = agent-steps/s over the first setting's "
        f"({settings[0]}) under the same load",
        "", "| machine | runner.learner_threads | agent steps | agent-steps/s | ratio |", "|---|---|---:|---:|---:|",
        *lines])
    publish(section, not args.no_append)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
