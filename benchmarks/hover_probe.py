"""How a trained swarm sits at its goals: the offset in each drone's own frame, and whether it holds still or
circles (the Graphormer `se3` rows' low success on `mix`, RESULTS.md notes of 2026-12-05).

    python -m benchmarks.hover_probe --checkpoint se3=RUN --checkpoint none=RUN [--scenario static_diff_goal]
                                     [--num-agents 1] [--episodes 10] [--window 3] [--stochastic] [--append]

Flies each checkpoint in its evaluation environment (``swarm_appo.evaluation.evaluation_env``: no training aids,
mean actions unless ``--stochastic`` (then sampled, as in training), the ``swarm_appo.evaluate`` seed by
default; ``--num-agents`` replaces N, e.g. 1 for a drone
without neighbours) and, over the last ``--window`` seconds of every episode, reads each drone's position,
velocity and attitude from ``VecQuadEnv.get_state``:

- Dist: median distance to the goal; body offset: the mean of R^T (x - x^d), the offset in the drone's own axes
  (a steady bias of the policy in its frame shows here whatever the drone's heading);
- yaw turned: |heading change| over the window; speed; path: the distance flown in the window; net move: the
  distance between the window's first and last positions (path >> net move: the drone circles);
- swarm centre: the swarm's common offset c = mean over its drones of the window-mean offset x - x^d (median |c|
  over swarms), and the spread: each drone's distance from its goal shifted by c (median |x - x^d - c|); within
  0.5 m: the share of drones whose window-mean offset is shorter than 0.5 m as flown, and if the swarm were shifted
  by -c (a swarm whose drones ring their shared goal at 0.35 m but whose centre sits 0.2 m off it loses the far side
  of the ring to Suc's radius, while the paper's c1 summed over the swarm hardly changes: the mean distance of a
  ring of radius r from a point c off its centre grows only as c^2 / 4r for c in the ring's plane); c split
  into its vertical part c_z (world z, signed: + above the goal; median over swarms) and its horizontal length;
- Col: new contacts per episode after the 1.5-s grace period (the evaluation's Col); touched: the share of drones
  with a drone-drone contact after it (IColR);
- Suc: the environment's success (within 0.5 m during the whole last second, no collision).

``--env-change KEY=VALUE[,KEY=VALUE]`` flies every row once more in a changed evaluation environment (top-level
``env`` keys, e.g. ``downwash=false``: does the policy lean on an effect of the simulator it trained with?).

A measurement, not a timing: it may run while other work shares the cores.
"""
from __future__ import annotations

import argparse
import datetime
from typing import Dict, List, Optional, Tuple

import numpy as np

from benchmarks.collision_anatomy import checked_checkpoints
from benchmarks.common import load_average, publish, section_header
from quad_env.kernels import SUCCESS_RADIUS


def hover_stats(pos: np.ndarray, goal: np.ndarray, rot: np.ndarray, vel: np.ndarray, dt: float,
                num_agents: Optional[int] = None) -> Dict[str, float]:
    """Statistics of a window of T control steps for M drones: ``pos``, ``goal``, ``vel`` [T, M, 3], ``rot``
    [T, M, 3, 3] (body -> world), ``dt`` the control step (s); ``num_agents``: drones per swarm (M = swarms x N,
    swarm by swarm; default: one swarm of M). Medians over drones unless named a mean."""
    off = pos - goal  # [T, M, 3] world
    n = off.shape[1] if num_agents is None else num_agents
    if off.shape[1] % n:
        raise ValueError(f"{off.shape[1]} drones are not whole swarms of {n}")
    mean_off = off.mean(0).reshape(-1, n, 3)  # [E, N, 3] each drone's window-mean offset, by swarm
    centre = mean_off.mean(1, keepdims=True)  # [E, 1, 3] the swarm's common offset
    about = np.linalg.norm(mean_off - centre, axis=-1)  # [E, N]
    body = np.einsum("tmji,tmj->tmi", rot, off)  # R^T off: [T, M, 3] in the drone's axes
    yaw = np.unwrap(np.arctan2(rot[..., 1, 0], rot[..., 0, 0]), axis=0)  # [T, M] heading of the body x axis
    path = np.linalg.norm(np.diff(pos, axis=0), axis=-1).sum(0)  # [M]
    return {
        "dist": float(np.median(np.linalg.norm(off, axis=-1))),
        "body_offset": body.mean(axis=(0, 1)).tolist(),  # mean over drones and steps [3]
        "body_offset_norm": float(np.median(np.linalg.norm(body.mean(0), axis=-1))),  # |per-drone mean|
        "yaw_turned_deg": float(np.degrees(np.median(np.abs(yaw[-1] - yaw[0])))),
        "speed": float(np.mean(np.linalg.norm(vel, axis=-1))),
        "path": float(np.median(path)),
        "net_move": float(np.median(np.linalg.norm(pos[-1] - pos[0], axis=-1))),
        "window_s": float((pos.shape[0] - 1) * dt),
        "centre_offset": float(np.median(np.linalg.norm(centre[:, 0], axis=-1))),
        "centre_vertical": float(np.median(centre[:, 0, 2])),  # signed: + above the goal
        "centre_horizontal": float(np.median(np.linalg.norm(centre[:, 0, :2], axis=-1))),
        "spread": float(np.median(about)),
        "within_pct": float(100.0 * np.mean(np.linalg.norm(mean_off, axis=-1) < SUCCESS_RADIUS)),
        "within_centred_pct": float(100.0 * np.mean(about < SUCCESS_RADIUS)),
    }


def parse_env_change(spec: str) -> Dict[str, object]:
    """``"downwash=false,drag_coeff=1e-2"`` -> {"downwash": False, "drag_coeff": 0.01}: top-level ``env`` keys,
    values read as YAML as in the trainer's overrides (``swarm_appo.config.yaml_load``: ``1e-2`` is a number).
    Unknown keys raise ValueError naming them and the valid ones."""
    import dataclasses

    from quad_env.config import EnvConfig
    from swarm_appo.config import yaml_load

    valid = [f.name for f in dataclasses.fields(EnvConfig)]
    changes = {}
    for item in spec.split(","):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"--env-change {spec!r}: expected KEY=VALUE[,KEY=VALUE]")
        if key not in valid:
            raise ValueError(f"--env-change: unknown env key {key!r}; valid: {valid}")
        changes[key] = yaml_load(value)
    return changes


def probe(loaded, episodes: int = 10, window_s: float = 3.0, seed: Optional[int] = None,
          scenario: Optional[str] = None, num_agents: Optional[int] = None, stochastic: bool = False,
          env_change: Optional[Dict[str, object]] = None) -> Dict:
    """Fly ``loaded`` (``swarm_appo.evaluation.load_checkpoint_policy``) and measure the window (module docstring);
    ``stochastic``: sampled actions (a generator seeded with the episode seed) instead of the mean action;
    ``env_change``: top-level ``env`` keys replaced in the evaluation environment (``parse_env_change``), type-checked
    and validated as a config file's would be."""
    import torch

    from quad_env import VecQuadEnv
    from quad_env.config import EnvConfig
    from swarm_appo.config import config_from_dict, config_to_dict
    from swarm_appo.evaluation import default_eval_seed, evaluation_env, model_policy

    env_cfg = evaluation_env(loaded.cfg.env, num_agents=num_agents, scenario=scenario)
    if env_change:
        env_cfg = config_from_dict({**config_to_dict(env_cfg), **env_change}, EnvConfig, "env.").validate()
    seed = default_eval_seed(loaded.cfg.runner.seed) if seed is None else seed
    policy = model_policy(loaded.model, not stochastic, torch.Generator().manual_seed(seed))
    steps, dt = env_cfg.episode_steps, env_cfg.control_dt
    first = steps - int(round(window_s / dt))  # the window: steps first..steps (its first state included)
    if first < 0:
        raise ValueError(f"--window {window_s} s is longer than the episode ({steps * dt:g} s)")
    env = VecQuadEnv(env_cfg, num_envs=episodes, seed=seed, auto_reset=False)
    obs = env.reset()
    frames: List = []
    for step in range(1, steps + 1):
        obs, _, term, trunc = env.step(policy(obs))
        if step >= first:
            frames.append(env.get_state())
        if (term | trunc).all():
            break
    episode_stats = env.pop_episode_stats()
    stack = lambda k: np.stack([getattr(s, k) for s in frames])  # noqa: E731
    out = hover_stats(stack("pos"), stack("goal"), stack("rot"), stack("vel"), dt, env_cfg.num_agents)
    out.update({"run": loaded.run_name, "agent_steps": loaded.agent_steps, "scenario": env_cfg.scenario,
                "N": env_cfg.num_agents, "episodes": episodes, "seed": seed, "stochastic": stochastic,
                "env_change": dict(env_change or {}), "episode_s": steps * dt,
                "success_pct": 100.0 * float(np.mean([st["success_rate"] for st in episode_stats])),
                "col": float(np.mean([st["collisions_after_grace"] for st in episode_stats])),
                "touched_pct": 100.0 * float(np.mean([st["inter_collision_rate"] for st in episode_stats]))})
    return out


def table(results: List[Tuple[str, Dict]]) -> str:
    lines = ["| run | scenario, N, episodes, seed | window (s) | Dist (m) | body offset x, y, z (m) | "
             "per-drone body offset (m) | yaw turned (deg) | speed (m/s) | path (m) | net move (m) | "
             "swarm centre offset (m) | of it: vertical, horizontal (m) | spread about it (m) | "
             f"within {SUCCESS_RADIUS:g} m %: as flown / centred | Col | touched % | Suc % |",
             "|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|"]
    for label, r in results:
        bx, by, bz = r["body_offset"]
        actions = ", sampled actions" if r.get("stochastic") else ""
        lines.append(f"| {label} | {r['scenario']}, {r['N']}, {r['episodes']}, {r['seed']}{actions} | "
                     f"{r['window_s']:.1f} | "
                     f"{r['dist']:.2f} | {bx:+.2f}, {by:+.2f}, {bz:+.2f} | {r['body_offset_norm']:.2f} | "
                     f"{r['yaw_turned_deg']:.0f} | {r['speed']:.2f} | {r['path']:.2f} | {r['net_move']:.2f} | "
                     f"{r['centre_offset']:.2f} | {r['centre_vertical']:+.2f}, {r['centre_horizontal']:.2f} | "
                     f"{r['spread']:.2f} | {r['within_pct']:.0f} / {r['within_centred_pct']:.0f} | "
                     f"{r['col']:.2f} | {r['touched_pct']:.0f} | {r['success_pct']:.1f} |")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hover_probe", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, action="append",
                   help="checkpoint file or run directory, optionally LABEL=PATH; repeat it to compare runs")
    p.add_argument("--scenario", action="append", default=None,
                   help="scenario (default: the training scenario); repeat it for several")
    p.add_argument("--num-agents", type=int, action="append", default=None,
                   help="swarm size N (default: the training N); repeat it for several")
    p.add_argument("--episodes", type=int, default=10, help="swarm episodes per row, flown in parallel")
    p.add_argument("--window", type=float, default=3.0, help="the last seconds of each episode that are measured")
    p.add_argument("--seed", type=int, default=None, help="episode seed (default: swarm_appo.evaluate's)")
    p.add_argument("--stochastic", action="store_true",
                   help="sample actions as in training (seeded) instead of the mean action")
    p.add_argument("--env-change", action="append", default=None, metavar="KEY=VALUE[,KEY=VALUE]",
                   help="also fly every row with these top-level env keys changed, e.g. downwash=false; repeatable")
    p.add_argument("--append", action="store_true", help="append the table to benchmarks/RESULTS.md")
    return p


def main(argv=None) -> List[Tuple[str, Dict]]:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error("--episodes must be >= 1")
    if args.window <= 0:
        parser.error("--window must be > 0 s")
    if any(n < 1 for n in args.num_agents or []):
        parser.error("--num-agents must be >= 1")
    from quad_env.scenarios import SCENARIOS

    unknown = [name for name in args.scenario or [] if name not in SCENARIOS]
    if unknown:
        parser.error(f"--scenario: unknown {unknown}; valid: {sorted(SCENARIOS)}")
    changes = [None]
    for spec in args.env_change or []:
        try:
            changes.append(parse_env_change(spec))
        except ValueError as err:
            parser.error(str(err))
    runs = checked_checkpoints(parser, args.checkpoint)
    started, load_before = datetime.datetime.now().isoformat(timespec="seconds"), load_average()
    from swarm_appo.evaluation import load_checkpoint_policy

    policies = [(label, load_checkpoint_policy(path)) for label, path in runs]  # each loaded once
    results = []
    for scenario in args.scenario or [None]:
        for n in args.num_agents or [None]:
            for label, loaded in policies:
                for change in changes:
                    shown = label + (" [" + ", ".join(f"{k}={v}" for k, v in change.items()) + "]" if change else "")
                    results.append((shown, probe(loaded, args.episodes, args.window, args.seed, scenario, n,
                                                 args.stochastic, change)))
    header = section_header("hover_probe", started, argv, ["quad_env", "swarm_appo", "encoders"], load_before)
    publish("\n".join(header + ["", table(results)]), args.append)
    return results


if __name__ == "__main__":
    main()
