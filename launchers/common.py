"""What the launchers share: the config arguments (``--config`` + ``key=value``), loading and validating
them, the summary printed at the end of a run, SIGTERM as Ctrl-C, and Ray's token authentication."""
from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path
from typing import List, MutableMapping, Optional


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default=None, help="YAML config (default: the embedded quickstart config)")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. env.num_agents=16")


def load_cli_config(path: Optional[str], overrides: List[str]):
    """The validated config (scenario, encoder, symmetry and its options included); raises ConfigError naming
    the offending key."""
    from swarm_appo.config import load_config
    return load_config(path, overrides)


def print_result(result) -> None:
    """Where a finished run left its files, its end-of-run evaluation and what to run next."""
    print(f"run directory: {result.run_dir}")
    print(f"agent steps: {result.agent_steps:,}  policy version: {result.policy_version}  "
          f"worker restarts: {result.worker_restarts}")
    if result.stopped_by == "time":
        share = 100 * result.agent_steps / result.planned_agent_steps
        print(f"stopped by the time limit (runner.time_limit_s) at {result.agent_steps:,} of the planned "
              f"{result.planned_agent_steps:,} agent steps ({share:.0f}%); continue with "
              f"--resume {result.run_dir} runner.time_limit_s=0")
    print(f"checkpoint: {result.checkpoint}")
    print(f"metrics: {result.run_dir / 'metrics.jsonl'}")
    if result.final_eval:
        ev = result.final_eval
        print(f"final evaluation (mean actions): "
              f"distance to goal {ev.get('eval/dist', float('nan')):.2f} m (last 5 s) vs "
              f"{ev.get('eval_random/dist', float('nan')):.2f} m for random actions "
              f"(ratio {ev.get('eval/dist_ratio_to_random', float('nan')):.2f}); "
              f"collisions/episode {ev.get('eval/collisions', float('nan')):.2f}; "
              f"success {100 * ev.get('eval/success_rate', float('nan')):.0f}% "
              f"(random {100 * ev.get('eval_random/success_rate', float('nan')):.0f}%)")
    if not result.interrupted:
        run = result.run_dir
        print("next:")
        print(f"  python -m swarm_appo.evaluate --checkpoint {run} --random-baseline   # the paper's Table 1")
        print(f"  python -m swarm_appo.select_checkpoint --run {run}   # final policy chosen on validation episodes")
        print(f"  python -m swarm_appo.export --checkpoint {run} --out export/{run.name}   # actor for a robot")
        print(f"  python -m swarm_appo.render --checkpoint {run}                       # PNG + GIF of the swarm")
        print(f"  python -m launchers.local --resume {run}                             # train on")


def report_training_error(exc: BaseException) -> int:
    """Print why training stopped (the cause's traceback for a learner bug; one paragraph for a run that cannot
    learn or a system error such as a full disk) and return the exit code 1."""
    import traceback

    if exc.__cause__ is not None and not isinstance(exc.__cause__, OSError):  # a bug: show where (once)
        traceback.print_exception(exc.__cause__, file=sys.stderr)
    print(f"error: {exc}", file=sys.stderr)
    return 1


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def stop_on_sigterm() -> None:
    """SIGTERM (a scheduler, `kill`, `ray job stop`) stops like Ctrl-C: a final checkpoint, then a clean exit."""
    signal.signal(signal.SIGTERM, _interrupt)


def token_available() -> bool:
    """Whether a Ray auth token can be found where Ray looks for one."""
    return bool(os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
                or (Path.home() / ".ray" / "auth_token").exists())


def enable_token_auth_if_available(env: MutableMapping[str, str]) -> None:
    """RAY_AUTH_MODE=token when a token exists and the mode is not set (what ``ray start`` does)."""
    if "RAY_AUTH_MODE" not in env and token_available():
        env["RAY_AUTH_MODE"] = "token"
