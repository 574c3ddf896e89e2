"""Where and how a trained swarm collides: evidence for the quality goal (issue 15, item 6).

    python -m benchmarks.collision_anatomy --checkpoint runs/quality3_deepsets_se3 [--episodes 20] [--append]
    python -m benchmarks.collision_anatomy --checkpoint none=runs/a --checkpoint se3=runs/b --scenario static_same_goal

Several ``--checkpoint [LABEL=]RUN`` are flown on the same episodes (same seed and scenario) and compared in one
table, a row per checkpoint.

Flies the checkpoint in its evaluation environment (``swarm_appo.evaluation.evaluation_env``: no training aids,
mean actions, the ``swarm_appo.evaluate`` seed by default) and records, from the public ``VecQuadEnv.get_state``
after every control step, each new drone-drone contact (centre distance below ``physics.collision_dist``, a pair
that was not touching at the step before): when it happens, how far from the pair's goals, whether the pair was
stacked (vertical offset larger than horizontal: downwash) or side by side, and how fast the two closed in.
It also reports how the swarm sits once it has arrived (t >= 5 s): the nearest-neighbour distance of each drone
and the share of drone-steps with a neighbour inside the proximity distance ``reward.proximity_dist``.

This is a measurement, not a timing: it may run while other work shares the cores.
"""
from __future__ import annotations

import argparse
import os
from typing import Dict, List, Optional, Tuple

import numpy as np

from benchmarks.common import load_average, publish, section_header

TIME_BINS = (0.0, 1.5, 3.0, 5.0, 10.0, np.inf)  # s: the grace period, the approach, the hover


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="collision_anatomy", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, action="append",
                   help="checkpoint file or run directory, optionally LABEL=PATH; repeat it to compare runs")
    p.add_argument("--episodes", type=int, default=20, help="swarm episodes, flown in parallel")
    p.add_argument("--seed", type=int, default=None, help="episode seed (default: swarm_appo.evaluate's)")
    p.add_argument("--scenario", default=None, help="scenario (default: the training scenario)")
    p.add_argument("--append", action="store_true", help="append the figures to benchmarks/RESULTS.md")
    return p


def new_contacts(pos: np.ndarray, touching: np.ndarray, num_agents: int, dist: float) -> List[tuple]:
    """Pairs (e, a, b) with a < b whose centres are closer than ``dist`` now and were not at the last call;
    ``touching`` [E, N, N] bool is updated in place. ``pos`` [E * N, 3]."""
    p = pos.reshape(-1, num_agents, 3)  # [E, N, 3]
    d = np.linalg.norm(p[:, :, None, :] - p[:, None, :, :], axis=-1)  # [E, N, N]
    now = d < dist
    now &= np.triu(np.ones((num_agents, num_agents), bool), 1)[None]
    fresh = now & ~touching
    touching[:] = now
    return [tuple(int(x) for x in ix) for ix in np.argwhere(fresh)]


def nearest_neighbour(pos: np.ndarray, num_agents: int) -> np.ndarray:
    """[E * N] centre distance of every drone to its nearest swarm mate."""
    p = pos.reshape(-1, num_agents, 3)
    d = np.linalg.norm(p[:, :, None, :] - p[:, None, :, :], axis=-1)
    d[:, np.arange(num_agents), np.arange(num_agents)] = np.inf
    return d.min(axis=2).reshape(-1)


def anatomy(checkpoint: str, episodes: int = 20, seed: Optional[int] = None,
            scenario: Optional[str] = None) -> Dict:
    from quad_env import VecQuadEnv
    from swarm_appo.evaluation import default_eval_seed, evaluation_env, load_checkpoint_policy, model_policy

    loaded = load_checkpoint_policy(checkpoint)
    env_cfg = evaluation_env(loaded.cfg.env, scenario=scenario)
    seed = default_eval_seed(loaded.cfg.runner.seed) if seed is None else seed
    policy = model_policy(loaded.model)
    N, dt = env_cfg.num_agents, env_cfg.control_dt
    coll_dist, prox_dist = env_cfg.physics.collision_dist, env_cfg.reward.proximity_dist
    env = VecQuadEnv(env_cfg, num_envs=episodes, seed=seed, auto_reset=False)
    obs = env.reset()
    touching = np.zeros((episodes, N, N), bool)
    events, nn_hover, nn_late = [], [], []
    prev = env.get_state()
    for step in range(1, env_cfg.episode_steps + 1):
        obs, _, term, trunc = env.step(policy(obs))
        s = env.get_state()
        for e, a, b in new_contacts(s.pos, touching, N, coll_dist):
            i, j = e * N + a, e * N + b
            rel = s.pos[j] - s.pos[i]
            prel, dv = prev.pos[j] - prev.pos[i], prev.vel[j] - prev.vel[i]  # before the contact's response
            events.append({
                "t": step * dt,
                "stacked": abs(rel[2]) > np.hypot(rel[0], rel[1]),
                "closing_speed": float(max(0.0, -(dv @ prel) / max(np.linalg.norm(prel), 1e-9))),
                "goal_dist": float(0.5 * (np.linalg.norm(s.pos[i] - s.goal[i]) + np.linalg.norm(s.pos[j] - s.goal[j]))),
            })
        if step * dt >= 5.0:
            (nn_late if step * dt >= 10.0 else nn_hover).append(nearest_neighbour(s.pos, N))
        prev = s
        if (term | trunc).all():
            break
    stats = env.pop_episode_stats()
    nn_mid = np.concatenate(nn_hover) if nn_hover else np.zeros(0)
    nn_end = np.concatenate(nn_late) if nn_late else np.zeros(0)
    nn = np.concatenate([nn_mid, nn_end])
    t = np.array([ev["t"] for ev in events])
    counts = np.histogram(t, bins=TIME_BINS)[0] if len(t) else np.zeros(len(TIME_BINS) - 1, int)
    return {
        "run": loaded.run_name, "agent_steps": loaded.agent_steps, "scenario": env_cfg.scenario, "N": N,
        "episodes": episodes, "seed": seed, "coll_dist": coll_dist, "prox_dist": prox_dist,
        "contacts_per_episode": len(events) / episodes,
        "env_collisions_per_episode": float(np.mean([st["collisions"] for st in stats])),
        "success_pct": 100.0 * float(np.mean([st["success_rate"] for st in stats])),
        "time_bins": TIME_BINS, "per_bin_per_episode": (counts / episodes).tolist(),
        "stacked_share": float(np.mean([ev["stacked"] for ev in events])) if events else float("nan"),
        "closing_speed_median": float(np.median([ev["closing_speed"] for ev in events])) if events else float("nan"),
        "goal_dist_median": float(np.median([ev["goal_dist"] for ev in events])) if events else float("nan"),
        "hover_nn_median": float(np.median(nn)) if nn.size else float("nan"),
        "hover_nn_p05": float(np.percentile(nn, 5)) if nn.size else float("nan"),
        "hover_inside_prox_pct": 100.0 * float(np.mean(nn < prox_dist)) if nn.size else float("nan"),
        "nn_median_5_10": float(np.median(nn_mid)) if nn_mid.size else float("nan"),
        "nn_median_10_end": float(np.median(nn_end)) if nn_end.size else float("nan"),
    }


def parse_checkpoint(text: str) -> Tuple[str, str]:
    """``LABEL=PATH`` or ``PATH`` (labelled by itself) -> (label, path). A path that exists as given wins over a
    split at ``=``, so a run folder with ``=`` in its name still works."""
    label, sep, path = text.partition("=")
    if sep and label and path and not os.path.exists(text):
        return label, path
    return text, text


def checked_checkpoints(parser: argparse.ArgumentParser, texts: List[str]) -> List[Tuple[str, str]]:
    """``--checkpoint`` values as (label, path), every path checked before anything is flown (a usage error)."""
    runs = [parse_checkpoint(c) for c in texts]
    for _, path in runs:
        if not os.path.exists(path):
            parser.error(f"--checkpoint: {path} does not exist (give a checkpoint file or a run directory)")
    return runs


def _time_bins_header(bins) -> str:
    return " | ".join(f"{lo:g}-{hi:g} s" if np.isfinite(hi) else f">= {lo:g} s" for lo, hi in zip(bins[:-1], bins[1:]))


def compare(results: List[Tuple[str, Dict]]) -> str:
    """One table, a row per checkpoint: contacts by time bin, how they happen, and how the swarm sits afterwards."""
    bins = results[0][1]["time_bins"]
    head = _time_bins_header(bins)
    lines = [f"new drone-drone contacts per episode by time, how they happen, and the nearest-neighbour distance from "
             f"t = 5 s on (contact at {results[0][1]['coll_dist']:.3f} m; proximity distance "
             f"{results[0][1]['prox_dist']:.3f} m)", "",
             f"| run | agent steps | scenario, N, episodes, seed | contacts | {head} | stacked % | "
             f"closing speed (m/s) | pair's goal distance (m) | NN median (m) | NN inside proximity % | Suc % |",
             "|---|---:|---|---:|" + "---:|" * (len(bins) - 1) + "---:|---:|---:|---:|---:|---:|"]
    for label, r in results:
        cells = " | ".join(f"{c:.2f}" for c in r["per_bin_per_episode"])
        lines.append(f"| {label} | {r['agent_steps']:,} | {r['scenario']}, {r['N']}, {r['episodes']}, {r['seed']} | "
                     f"{r['contacts_per_episode']:.2f} | {cells} | {100 * r['stacked_share']:.0f} | "
                     f"{r['closing_speed_median']:.2f} | {r['goal_dist_median']:.2f} | {r['hover_nn_median']:.3f} | "
                     f"{r['hover_inside_prox_pct']:.0f} | {r['success_pct']:.1f} |")
    return "\n".join(lines)


def report(r: Dict) -> str:
    bins = r["time_bins"]
    head = _time_bins_header(bins)
    cells = " | ".join(f"{c:.2f}" for c in r["per_bin_per_episode"])
    return "\n".join([
        f"{r['run']} ({r['agent_steps']:,} agent steps), {r['scenario']}, N = {r['N']}, {r['episodes']} episodes, "
        f"seed {r['seed']}: {r['contacts_per_episode']:.2f} new contacts per episode (the env's Col: "
        f"{r['env_collisions_per_episode']:.2f}), Suc {r['success_pct']:.1f} %",
        "",
        f"| new contacts per episode, by time | {head} |",
        "|---|" + "---:|" * (len(bins) - 1),
        f"| {r['run']} | {cells} |",
        "",
        f"- stacked pairs (vertical offset > horizontal): {100 * r['stacked_share']:.0f} % of contacts; median closing "
        f"speed {r['closing_speed_median']:.2f} m/s;"
        f" median distance of the pair to its goals {r['goal_dist_median']:.2f} m",
        f"- from t = 5 s on: median nearest-neighbour distance {r['hover_nn_median']:.3f} m (5th percentile "
        f"{r['hover_nn_p05']:.3f} m; contact at {r['coll_dist']:.3f} m); {r['hover_inside_prox_pct']:.0f} % of "
        f"drone-steps have a neighbour inside the proximity distance {r['prox_dist']:.3f} m; median nearest-neighbour "
        f"distance {r['nn_median_5_10']:.3f} m over 5-10 s and {r['nn_median_10_end']:.3f} m from 10 s on",
    ])


def main(argv=None) -> Dict:
    import datetime

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error("--episodes must be >= 1")
    runs = checked_checkpoints(parser, args.checkpoint)
    started, load_before = datetime.datetime.now().isoformat(timespec="seconds"), load_average()
    results = [(label, anatomy(path, args.episodes, args.seed, args.scenario)) for label, path in runs]
    header = section_header("collision_anatomy", started, argv, ["quad_env", "swarm_appo", "encoders"], load_before)
    body = report(results[0][1]) if len(results) == 1 else compare(results)
    publish("\n".join(header + ["", body]), args.append)
    return results[0][1] if len(results) == 1 else dict(results)


if __name__ == "__main__":
    main()
