"""Fly a trained policy and draw it: a 3-D trajectory PNG and an animated GIF (top and side views, legend).

    python -m swarm_appo.render --checkpoint runs/quickstart [--scenario NAME] [--num-agents N] [--seed S]
                                [--steps T] [--out DIR] [--stochastic] [--frame-every 5]

The checkpoint (a file, or a run directory's newest valid one) flies in its evaluation environment
(``swarm_appo.evaluation.evaluation_env``: the training environment without the training aids), with the
scenario and N replaced when given; the pictures are ``quad_env.render``'s (goals, drones, collisions
marked). Output: ``<run dir>/render`` (``render_2``, ... if it exists), or ``--out``. Arguments are checked
before torch loads.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import List, Optional


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="swarm-render", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, metavar="PATH", help="checkpoint file or run directory")
    p.add_argument("--scenario", default=None, help="scenario to fly (default: the training scenario)")
    p.add_argument("--num-agents", type=int, default=None, help="swarm size (default: as trained)")
    p.add_argument("--seed", type=int, default=0, help="episode seed")
    p.add_argument("--steps", type=int, default=None, help="control steps (100 per second; default: the episode)")
    p.add_argument("--out", default=None, help="output folder (default: <run dir>/render, numbered if it exists)")
    p.add_argument("--stochastic", action="store_true", help="sample actions instead of the mean action")
    p.add_argument("--frame-every", type=int, default=5, help="control steps per GIF frame")
    return p


def main(argv: Optional[List[str]] = None) -> List[str]:
    p = build_parser()
    args = p.parse_args(argv)
    if args.steps is not None and args.steps < 1:
        p.error("--steps must be >= 1")
    if args.frame_every < 1:
        p.error("--frame-every must be >= 1")
    if args.num_agents is not None and args.num_agents < 1:
        p.error("--num-agents must be >= 1")
    if not os.path.exists(args.checkpoint):
        p.error(f"--checkpoint {args.checkpoint} does not exist")

    import torch

    from quad_env.render import record_episode, save_animation_gif, save_trajectory_png
    from quad_env.scenarios import SCENARIO_REGISTRY, SCENARIOS
    from swarm_appo import evaluation
    from swarm_appo.checkpoint import CheckpointCorruptError

    if args.scenario is not None and (args.scenario not in SCENARIO_REGISTRY or args.scenario == "mix"):
        p.error(f"unknown --scenario {args.scenario!r}; valid: {[s for s in SCENARIOS if s != 'mix']}")
    try:
        loaded = evaluation.load_checkpoint_policy(args.checkpoint)
    except (ValueError, FileNotFoundError, CheckpointCorruptError) as exc:
        p.error(str(exc))
    train_env = loaded.cfg.env
    scenario = args.scenario or (train_env.scenario if train_env.scenario != "mix" else "static_same_goal")
    env_cfg = evaluation.evaluation_env(train_env, args.num_agents, scenario)
    if SCENARIO_REGISTRY[scenario].needs_obstacles and not env_cfg.obstacles:
        p.error(f"--scenario {scenario} flies through obstacles, but this policy was trained without the obstacle "
                f"field in its observation (env.obstacles=false)")
    generator = torch.Generator().manual_seed(args.seed) if args.stochastic else None
    act = evaluation.model_policy(loaded.model, deterministic=not args.stochastic, generator=generator)

    def policy(obs, state):  # quad_env.render's policy signature: (obs [N, D], DroneState) -> actions [N, 4]
        return act(obs)

    policy.__name__ = f"{loaded.run_name} at {loaded.agent_steps:,} steps ({'sampled' if args.stochastic else 'mean'})"
    torch.set_num_threads(1)
    episode = record_episode(env_cfg, policy, args.steps, args.seed)
    out = Path(args.out) if args.out else evaluation.numbered_dir(evaluation.run_dir_of(args.checkpoint) / "render")
    out.mkdir(parents=True, exist_ok=True)
    stem = str(out / f"{scenario}_n{env_cfg.num_agents}_seed{args.seed}")
    paths = [save_trajectory_png(episode, stem + ".png"),
             save_animation_gif(episode, stem + ".gif", args.frame_every, env_cfg.physics.room_half_width)]
    s = episode.stats
    for path in paths:
        print(path)
    print(f"{scenario}, {env_cfg.num_agents} drones: reward per agent {s['return']:.3f}, distance to goal over the "
          f"last 5 s {s['dist_last_5s']:.2f} m, collisions {s['collisions_after_grace']} after the grace period, "
          f"success {s['success_rate']:.0%}", file=sys.stdout)
    return paths


if __name__ == "__main__":
    main()
