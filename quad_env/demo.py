"""Fly one swarm for a short episode and save a 3-D trajectory plot.

    python -m quad_env.demo --out runs/demo [--scenario static_diff_goal] [--steps 500] [--seed 0]
                            [--num-agents 8] [--policy controller|random]

``controller`` is the hand-written goal-seeking controller (``quad_env.controller``); ``random`` draws
uniform actions. Prints the path of the PNG and a one-line summary.
"""
from __future__ import annotations

import argparse
import os
from typing import List, Optional

import numpy as np

from quad_env.config import EnvConfig
from quad_env.controller import GoalSeekingController
from quad_env.scenarios import SCENARIOS
from quad_env.vec_env import VecQuadEnv


def fly(cfg: EnvConfig, steps: int, seed: int, policy: str):
    """Returns positions [T+1, N, 3], goals [N, 3] (at the end) and the episode's reward per agent."""
    env = VecQuadEnv(cfg, num_envs=1, seed=seed, auto_reset=False)
    controller = GoalSeekingController(cfg)
    rng = np.random.default_rng(seed)
    steps = min(steps, cfg.episode_steps)
    track = [env.get_state().pos]
    total = 0.0
    for _ in range(steps):
        if policy == "controller":
            actions = controller(env.get_state())
        else:
            actions = rng.uniform(-1, 1, (env.num_drones, 4)).astype(np.float32)
        _, rew, _, _ = env.step(actions)
        total += float(rew.mean())
        track.append(env.get_state().pos)
    return np.stack(track), env.get_state().goal, total


def plot(track: np.ndarray, goals: np.ndarray, path: str, title: str, goal_track: Optional[np.ndarray] = None,
         collisions: Optional[np.ndarray] = None, cylinders: Optional[np.ndarray] = None,
         cylinder_radius: float = 0.3, obstacle_hits: Optional[np.ndarray] = None) -> None:
    """3-D trajectory PNG. track [T+1, N, 3]; goals [N, 3] (at the end); goal_track [T+1, N, 3] draws the
    goals' paths (moving goals); collisions [C, 3] marks where drones collided; cylinders [K, 2] (axes x, y)
    draws obstacles of ``cylinder_radius`` from the floor to just above the highest point drawn;
    obstacle_hits [H, 3] marks where drones hit them."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    colors = plt.cm.viridis(np.linspace(0, 1, track.shape[1]))
    for a in range(track.shape[1]):
        ax.plot(track[:, a, 0], track[:, a, 1], track[:, a, 2], color=colors[a], lw=1)
        ax.scatter(*track[0, a], color=colors[a], marker="o", s=12)
    if goal_track is not None and np.ptp(goal_track, axis=0).max() > 0:
        for a in range(goal_track.shape[1]):
            ax.plot(goal_track[:, a, 0], goal_track[:, a, 1], goal_track[:, a, 2], color="red", lw=0.6, ls="--",
                    alpha=0.5, label="goal paths" if a == 0 else None)
    if cylinders is not None and len(cylinders):
        top = max(track[..., 2].max(), goals[:, 2].max()) + 0.5
        ang, height = np.linspace(0, 2 * np.pi, 24), np.array([0.0, top])
        for cx, cy in cylinders:
            ax.plot_surface(cx + cylinder_radius * np.cos(ang)[None], cy + cylinder_radius * np.sin(ang)[None],
                            np.repeat(height[:, None], len(ang), 1), color="gray", alpha=0.25, linewidth=0)
        ax.plot([], [], color="gray", lw=6, alpha=0.4, label=f"obstacles ({len(cylinders)})")
    ax.scatter(goals[:, 0], goals[:, 1], goals[:, 2], color="red", marker="*", s=60, label="goals")
    ax.scatter([], [], color="gray", marker="o", s=12, label="start")
    if collisions is not None and len(collisions):
        ax.scatter(collisions[:, 0], collisions[:, 1], collisions[:, 2], color="black", marker="x", s=50,
                   label=f"collisions ({len(collisions)})")
    if obstacle_hits is not None and len(obstacle_hits):
        ax.scatter(obstacle_hits[:, 0], obstacle_hits[:, 1], obstacle_hits[:, 2], color="darkorange", marker="X",
                   s=50, label=f"obstacle hits ({len(obstacle_hits)})")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_title(title)
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Optional[List[str]] = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="output folder (created)")
    ap.add_argument("--scenario", default="static_diff_goal", choices=SCENARIOS)
    ap.add_argument("--steps", type=int, default=500, help="control steps (100 per second)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--num-agents", type=int, default=8)
    ap.add_argument("--policy", default="controller", choices=("controller", "random"))
    args = ap.parse_args(argv)
    if args.steps < 1:
        ap.error("--steps must be >= 1")

    cfg = EnvConfig(num_agents=args.num_agents, scenario=args.scenario)
    track, goals, total = fly(cfg, args.steps, args.seed, args.policy)
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, f"trajectory_{args.scenario}_seed{args.seed}.png")
    dist = np.linalg.norm(track[-1] - goals, axis=1).mean()
    plot(track, goals, path, f"{args.scenario}, {args.num_agents} drones, {args.policy}, "
                             f"{(len(track) - 1) * cfg.control_dt:.1f} s")
    print(path)
    print(f"reward per agent {total:.3f}, final mean distance to goal {dist:.3f} m")
    return path


if __name__ == "__main__":
    main()
