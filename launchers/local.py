"""Train on this machine: a local Ray with all its cores, a learner and rollout actors sized to fit.

    python -m launchers.local                                   # embedded quickstart config
    python -m launchers.local --config configs/paper.yaml model.encoder=se3_graphormer env.num_agents=16
    python -m launchers.local --resume runs/quickstart          # continue a run (same counters, same wandb run)

Ctrl-C stops cleanly and writes a final checkpoint.
"""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from typing import List, Optional

os.environ.setdefault("WANDB_SILENT", "true")


def parse_args(argv: Optional[List[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="swarm-train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=None, help="YAML config (default: the embedded quickstart config)")
    p.add_argument("--resume", default=None, metavar="RUN_DIR", help="resume this run directory")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. env.num_agents=16")
    return p.parse_args(argv)


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def main(argv: Optional[List[str]] = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    import encoders
    from swarm_appo.config import ConfigError, load_config, validate
    from swarm_appo.trainer import train

    try:
        if args.resume:
            cfg = None
            if args.overrides or args.config:
                base = args.config or os.path.join(args.resume, "config.yaml")
                cfg = load_config(base, args.overrides)
        else:
            cfg = load_config(args.config, args.overrides)
        if cfg is not None:
            validate(cfg, known_encoders=encoders.ENCODERS)
    except (ConfigError, FileNotFoundError) as exc:
        print(f"config error: {exc}", file=sys.stderr)
        return 2
    # SIGTERM (a scheduler, `kill`) stops like Ctrl-C: a final checkpoint, then a clean exit.
    signal.signal(signal.SIGTERM, _interrupt)
    result = train(cfg, resume_dir=args.resume, progress=not args.no_progress)
    print(f"run directory: {result.run_dir}")
    print(f"agent steps: {result.agent_steps}  policy version: {result.policy_version}  "
          f"worker restarts: {result.worker_restarts}")
    print(f"checkpoint: {result.checkpoint}")
    print(f"metrics: {result.run_dir / 'metrics.jsonl'}")
    if result.final_eval:
        ev = result.final_eval
        print(f"final evaluation (mean actions): "
              f"distance to goal {ev.get('eval/dist', float('nan')):.2f} m (last 5 s) vs "
              f"{ev.get('eval_random/dist', float('nan')):.2f} m for random actions "
              f"(ratio {ev.get('eval/dist_ratio_to_random', float('nan')):.2f}); "
              f"collisions/episode {ev.get('eval/collisions', float('nan')):.2f}")
    return 130 if result.interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
