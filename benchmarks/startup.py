"""Start-up time: seconds from ``python -m launchers.local`` to the first fragment in the learner, cold and warm.

    python -m benchmarks.startup                          # quickstart and mix (the paper's scenarios), cold + warm
    python -m benchmarks.startup --configs quickstart --repeats 3

For each config the real command line runs as a subprocess until its first learner iteration
(``runner.total_agent_steps`` = one batch, no final evaluation, wandb offline), and the trainer's own
``perf/startup_s`` is read from the run's first metrics record: process start -> first fragment (imports, config,
numba kernel compilation, Ray and rollout-worker start-up, one rollout). **cold**: an empty numba cache
(``NUMBA_CACHE_DIR`` in a fresh temporary folder: every kernel compiles); **warm**: the same folder again (every
kernel loads from disk). The wall time of the whole command is printed too (it adds one learner iteration,
the checkpoint, and the shutdown of Ray and wandb). Issue 16's targets: <= 30 s cold, <= 10 s warm on 2 cores.
Figures are appended to benchmarks/RESULTS.md with the command, commit, machine and load.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List

from benchmarks.common import ROOT, load_average, publish, section_header

CONFIGS = {"quickstart": None, "mix": "configs/paper.yaml"}
# the paper config at laptop size: the point is the start-up, not the model
MIX_OVERRIDES = ["model.size=small", "model.encoder=deepsets", "runner.envs_per_worker=4"]


def start_once(config: str, cache_dir: Path, run_root: Path, name: str) -> Dict[str, float]:
    """One start of the command line; returns ``startup_s`` (the trainer's) and ``wall_s`` (the whole command)."""
    cmd = [sys.executable, "-m", "launchers.local", "--no-progress"]
    if CONFIGS[config]:
        cmd += ["--config", CONFIGS[config], *MIX_OVERRIDES]
    cmd += ["runner.total_agent_steps=1", "runner.final_eval_episodes=0", f"runner.run_dir={run_root}",
            f"runner.name={name}"]
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir), WANDB_MODE="offline", WANDB_SILENT="true")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    first = json.loads((run_root / name / "metrics.jsonl").read_text().splitlines()[0])
    if "perf/startup_s" not in first:
        raise RuntimeError(f"no perf/startup_s in the first record of {run_root / name}")
    return {"startup_s": float(first["perf/startup_s"]), "wall_s": wall}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--configs", default=",".join(CONFIGS), help=f"comma-separated, of {list(CONFIGS)}")
    p.add_argument("--repeats", type=int, default=2, help="warm starts per config (after one cold start)")
    p.add_argument("--no-append", action="store_true", help="do not append to benchmarks/RESULTS.md")
    args = p.parse_args(argv)
    configs = [c.strip() for c in args.configs.split(",") if c.strip()]
    unknown = [c for c in configs if c not in CONFIGS]
    if unknown or not configs:
        p.error(f"--configs: unknown {unknown or configs}; valid: {list(CONFIGS)}")
    if args.repeats < 1:
        p.error("--repeats must be >= 1")

    started, load_before = datetime.datetime.now().isoformat(timespec="seconds"), load_average()
    rows: List[str] = ["| config | start | perf/startup_s (s) | whole command (s) |", "|---|---|---:|---:|"]
    with tempfile.TemporaryDirectory(prefix="startup_") as tmp:
        for config in configs:
            cache = Path(tmp) / f"numba_{config}"  # empty: the first start compiles every kernel it needs
            for k in range(1 + args.repeats):
                kind = "cold" if k == 0 else "warm"
                r = start_once(config, cache, Path(tmp) / "runs", f"{config}_{k}")
                print(f"{config:10s} {kind}: first fragment after {r['startup_s']:.1f} s "
                      f"(whole command {r['wall_s']:.1f} s)", flush=True)
                rows.append(f"| {config} | {kind} | {r['startup_s']:.1f} | {r['wall_s']:.1f} |")
    header = section_header("startup", started, argv, ["quad_env", "swarm_appo", "launchers"], load_before)
    publish("\n".join([*header, "", *rows]), append=not args.no_append)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
