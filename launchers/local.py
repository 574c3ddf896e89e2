"""Train on this machine: a local Ray with all its cores, a learner and rollout actors sized to fit.

    python -m launchers.local                                   # embedded quickstart config
    python -m launchers.local --config configs/paper.yaml model.encoder=se3_graphormer env.num_agents=16
    python -m launchers.local --resume runs/quickstart          # continue a run (same counters, one history)

Ctrl-C stops cleanly and writes a final checkpoint.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import List, Optional

os.environ.setdefault("WANDB_SILENT", "true")

from launchers.common import (add_config_arguments, load_cli_config, print_result, report_training_error,  # noqa: E402
                              stop_on_sigterm)


def parse_args(argv: Optional[List[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="swarm-train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resume", default=None, metavar="RUN_DIR", help="resume this run directory")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_config_arguments(p)
    return p.parse_args(argv)


def resume_problem(path: str) -> Optional[str]:
    """Why ``path`` cannot be resumed (one line), or None: it must be a run directory (it holds config.yaml)."""
    p = Path(path)
    if not p.exists():
        return f"{path} does not exist"
    if p.is_file():
        parent = p.parent.parent if p.parent.name == "checkpoints" else p.parent
        hint = f"; did you mean its run directory {parent}?" if (parent / "config.yaml").exists() else ""
        return f"{path} is a file, not a run directory{hint}"
    if not (p / "config.yaml").exists():
        return f"{path} is not a run directory (no config.yaml in it)"
    return None


def main(argv: Optional[List[str]] = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return _train(args)
    except KeyboardInterrupt:  # Ctrl-C before the training loop (imports, Ray, workers): no traceback
        print("interrupted during start-up; a run directory made so far holds no checkpoint and starts afresh "
              "on --resume", file=sys.stderr)
        return 130


def _train(args: argparse.Namespace) -> int:
    from swarm_appo.config import ConfigError
    from swarm_appo.trainer import TrainingError, train

    if args.resume:
        problem = resume_problem(args.resume)
        if problem:
            print(f"--resume: {problem}", file=sys.stderr)
            return 2
    try:
        cfg = None
        if not args.resume:
            cfg = load_cli_config(args.config, args.overrides)
        elif args.overrides or args.config:
            cfg = load_cli_config(args.config or os.path.join(args.resume, "config.yaml"), args.overrides)
    except (ConfigError, FileNotFoundError) as exc:
        print(f"config error: {exc}", file=sys.stderr)
        return 2
    stop_on_sigterm()
    try:
        result = train(cfg, resume_dir=args.resume, progress=not args.no_progress)
    except ConnectionError as exc:  # runner.ray_address: no cluster there
        print(f"cannot join the Ray cluster of runner.ray_address: {exc}", file=sys.stderr)
        return 1
    except TrainingError as exc:
        return report_training_error(exc)
    except ConfigError as exc:  # what only this machine can tell, e.g. runner.device=cuda without a GPU
        print(f"config error: {exc}", file=sys.stderr)
        return 2
    print_result(result)
    return 130 if result.interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
