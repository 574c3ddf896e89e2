"""Render an episode of any scenario: a 3-D trajectory PNG and an animated GIF (top and side views).

    python -m quad_env.render --scenario NAME --out DIR [--policy controller|random] [--steps 1500]
                              [--seed 0] [--num-agents 8] [--frame-every 5] [--obstacles]

Headless (matplotlib Agg, Pillow for the GIF). ``controller`` is the hand-written goal-seeking controller,
``random`` uniform actions. A trained policy plugs in through ``record_episode(cfg, policy=callable)``,
where ``callable(obs [N, D] float32, state: DroneState) -> actions [N, 4]`` (quad_env knows nothing of
the trainer). Collisions (new drone-drone contacts) are marked with black crosses in both pictures;
with obstacles (``--obstacles``, implied by the o_* scenarios) the cylinders are drawn (gray) and new
drone-obstacle contacts marked with orange crosses at the drone.
"""
from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field
from typing import Callable, List, Optional, Union

import numpy as np

from quad_env.config import EnvConfig
from quad_env.controller import GoalSeekingController
from quad_env.demo import plot
from quad_env.obstacles import obstacle_centers
from quad_env.scenarios import SCENARIO_REGISTRY, SCENARIOS
from quad_env.vec_env import DroneState, VecQuadEnv

Policy = Callable[[np.ndarray, DroneState], np.ndarray]


@dataclass
class Episode:
    """Stored states of one swarm episode (T control steps, N drones)."""

    pos: np.ndarray  # [T+1, N, 3] positions, row 0 = after reset
    goal: np.ndarray  # [T+1, N, 3] goals
    collisions: np.ndarray  # [C, 4] (step, x, y, z): midpoints of new drone-drone contacts
    stats: dict  # episode_stats at the end
    dt: float  # control step, s
    title: str
    cylinders: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # [K, 2] axes (x, y) of the obstacles
    cylinder_radius: float = 0.0
    obstacle_hits: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # [H, 4] (step, x, y, z): drones
    # at new obstacle contacts


def make_policy(name: str, cfg: EnvConfig, seed: int) -> Policy:
    if name == "controller":
        ctrl = GoalSeekingController(cfg)
        return lambda obs, state: ctrl(state)
    if name == "random":
        rng = np.random.default_rng(seed)
        return lambda obs, state: rng.uniform(-1, 1, (state.pos.shape[0], 4)).astype(np.float32)
    raise ValueError(f"unknown policy {name!r}; valid: ['controller', 'random'] or a callable")


def record_episode(cfg: EnvConfig, policy: Union[str, Policy] = "controller", steps: Optional[int] = None,
                   seed: int = 0) -> Episode:
    """Fly one swarm for ``steps`` control steps (default: the whole episode) and store its states."""
    env = VecQuadEnv(cfg, num_envs=1, seed=seed, auto_reset=False)
    act = make_policy(policy, cfg, seed) if isinstance(policy, str) else policy
    steps = cfg.episode_steps if steps is None else min(steps, cfg.episode_steps)
    obs = env.observe()
    state = env.get_state()
    pos, goal, hits = [state.pos], [state.goal], []
    touching = env._contact[0].copy()  # [N, N] pairs a < b in contact (the simulator's memory)
    on_cylinder, obstacle_hits = env._obst_contact.copy(), []  # [N] drones touching a cylinder
    for t in range(steps):
        obs, _, _, _ = env.step(act(obs, state))
        state = env.get_state()
        pos.append(state.pos)
        goal.append(state.goal)
        for a, b in zip(*np.nonzero(env._contact[0] > touching)):  # new contacts: mark the pair's midpoint
            hits.append([t + 1, *(0.5 * (state.pos[a] + state.pos[b]))])
        touching = env._contact[0].copy()
        for a in np.flatnonzero(env._obst_contact > on_cylinder):  # new obstacle contacts: mark the drone
            obstacle_hits.append([t + 1, *state.pos[a]])
        on_cylinder = env._obst_contact.copy()
    name = env.scenario.episode_name(0)
    policy_name = policy if isinstance(policy, str) else getattr(policy, "__name__", "policy")
    title = f"{name}, {cfg.num_agents} drones, {policy_name}, {steps * cfg.control_dt:.1f} s"
    cylinders = obstacle_centers(env.obstacle_grid[0], cfg) if cfg.obstacles else np.zeros((0, 2))
    return Episode(np.stack(pos), np.stack(goal), np.array(hits).reshape(-1, 4), env.episode_stats(0),
                   cfg.control_dt, title, cylinders, 0.5 * cfg.obstacle_diameter,
                   np.array(obstacle_hits).reshape(-1, 4))


def save_trajectory_png(ep: Episode, path: str) -> str:
    plot(ep.pos, ep.goal[-1], path, ep.title, goal_track=ep.goal, collisions=ep.collisions[:, 1:],
         cylinders=ep.cylinders, cylinder_radius=ep.cylinder_radius, obstacle_hits=ep.obstacle_hits[:, 1:])
    return path


def save_animation_gif(ep: Episode, path: str, frame_every: int = 5, room_half: float = 5.0) -> str:
    """Top (x-y) and side (x-z) views, one frame every ``frame_every`` control steps, real-time speed."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter
    from matplotlib.patches import Circle, Rectangle

    frames = list(range(0, len(ep.pos), frame_every))
    lo = np.minimum(ep.pos.min((0, 1)), ep.goal.min((0, 1))) - 0.5
    hi = np.maximum(ep.pos.max((0, 1)), ep.goal.max((0, 1))) + 0.5
    if len(ep.cylinders):  # show the whole obstacle course
        lo[:2] = np.minimum(lo[:2], ep.cylinders.min(0) - ep.cylinder_radius)
        hi[:2] = np.maximum(hi[:2], ep.cylinders.max(0) + ep.cylinder_radius)
    lo, hi = np.maximum(lo, [-room_half, -room_half, 0.0]), np.minimum(hi, [room_half, room_half, 2 * room_half])
    fig, axes = plt.subplots(1, 2, figsize=(9, 4.5))
    views = ((0, 1, "top view", "y (m)"), (0, 2, "side view", "z (m)"))
    colors = plt.cm.viridis(np.linspace(0, 1, ep.pos.shape[1]))
    artists = []
    for ax, (u, v, name, ylabel) in zip(axes, views):
        ax.set_xlim(lo[u], hi[u])
        ax.set_ylim(lo[v], hi[v])
        ax.set_aspect("equal")
        ax.set_title(name)
        ax.set_xlabel("x (m)")
        ax.set_ylabel(ylabel)
        for cx, cy in ep.cylinders:  # floor to ceiling: a disc from above, a band from the side
            r = ep.cylinder_radius
            ax.add_patch(Circle((cx, cy), r, color="gray", alpha=0.35) if v == 1 else
                         Rectangle((cx - r, 0.0), 2 * r, 2 * room_half, color="gray", alpha=0.2))
        goals = ax.scatter([], [], color="red", marker="*", s=40, label="goals")
        drones = ax.scatter(ep.pos[0][:, u], ep.pos[0][:, v], c=colors, s=14, label="drones (1 s trails)")
        hits = ax.scatter([], [], color="black", marker="x", s=40, label="drone-drone collision")
        obstacle_hits = ax.scatter([], [], color="darkorange", marker="X", s=40, label="obstacle collision")
        trails = [ax.plot([], [], color=c, lw=0.6, alpha=0.6)[0] for c in colors]
        artists.append((u, v, goals, drones, (hits, obstacle_hits), trails))
    _, _, goals0, drones0, (hits0, obstacle_hits0), _ = artists[0]
    handles = [goals0, drones0, hits0] + ([obstacle_hits0] if len(ep.cylinders) else [])
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.subplots_adjust(bottom=0.16)
    text = fig.suptitle("")

    def draw(t):
        for u, v, goals, drones, marks, trails in artists:
            goals.set_offsets(ep.goal[t][:, [u, v]])
            drones.set_offsets(ep.pos[t][:, [u, v]])
            for events, scatter in zip((ep.collisions, ep.obstacle_hits), marks):
                recent = events[(events[:, 0] <= t) & (events[:, 0] > t - 50)]  # the last 0.5 s
                scatter.set_offsets(recent[:, [1 + u, 1 + v]] if len(recent) else np.zeros((0, 2)))
            start = max(0, t - 100)  # 1 s trails
            for a, line in enumerate(trails):
                line.set_data(ep.pos[start:t + 1, a, u], ep.pos[start:t + 1, a, v])
        text.set_text(f"{ep.title}   t = {t * ep.dt:.2f} s")
        return []

    anim = FuncAnimation(fig, draw, frames=frames, blit=False)
    anim.save(path, writer=PillowWriter(fps=max(1, round(1.0 / (ep.dt * frame_every)))))
    plt.close(fig)
    return path


class SwarmRecorder:
    """Stores one swarm of a running ``VecQuadEnv`` (one of many, e.g. in a batched evaluation) for pictures.

    Create it after ``reset``, call ``record()`` after every ``step``, then ``episode(stats, title)``. The
    env must not auto-reset (``auto_reset=False``), or an episode's end would be followed by the next one.
    """

    def __init__(self, env: VecQuadEnv, swarm: int = 0):
        N = env.num_agents
        self.env, self.swarm, self.rows = env, swarm, slice(swarm * N, (swarm + 1) * N)
        self.pos, self.goal, self.hits = [], [], []
        self.record()

    def record(self) -> None:
        env, rows = self.env, self.rows
        self.pos.append(np.array(env._pos[rows], dtype=np.float64))
        self.goal.append(np.array(env._goal[rows], dtype=np.float64))
        touching = env._contact[self.swarm].copy()  # [N, N] pairs a < b in contact
        if len(self.pos) > 1:
            for a, b in zip(*np.nonzero(touching > self._touching)):  # new contacts: the pair's midpoint
                self.hits.append([len(self.pos) - 1, *(0.5 * (self.pos[-1][a] + self.pos[-1][b]))])
        self._touching = touching

    def episode(self, stats: dict, title: str) -> Episode:
        return Episode(pos=np.stack(self.pos), goal=np.stack(self.goal), collisions=np.array(self.hits).reshape(-1, 4),
                       stats=stats, dt=self.env.cfg.control_dt, title=title)


def main(argv: Optional[List[str]] = None) -> List[str]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", required=True, choices=SCENARIOS)
    ap.add_argument("--out", required=True, help="output folder (created)")
    ap.add_argument("--policy", default="controller", choices=("controller", "random"))
    ap.add_argument("--steps", type=int, default=None, help="control steps (100 per second; default: episode)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--num-agents", type=int, default=8)
    ap.add_argument("--frame-every", type=int, default=5, help="control steps per GIF frame")
    ap.add_argument("--obstacles", action="store_true", help="cylinders in the room (implied by o_* scenarios)")
    args = ap.parse_args(argv)
    if args.steps is not None and args.steps < 1:
        ap.error("--steps must be >= 1")
    if args.frame_every < 1:
        ap.error("--frame-every must be >= 1")
    obstacles = args.obstacles or SCENARIO_REGISTRY[args.scenario].needs_obstacles
    cfg = EnvConfig(num_agents=args.num_agents, scenario=args.scenario, obstacles=obstacles)
    ep = record_episode(cfg, args.policy, args.steps, args.seed)
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, f"{args.scenario}_{args.policy}_seed{args.seed}")
    paths = [save_trajectory_png(ep, stem + ".png"), save_animation_gif(ep, stem + ".gif", args.frame_every,
                                                                         cfg.physics.room_half_width)]
    for p in paths:
        print(p)
    s = ep.stats
    print(f"reward per agent {s['return']:.3f}, final mean distance {s['dist_final']:.3f} m, "
          f"collisions {s['collisions']} (obstacles {s['obstacle_collisions']}), success {s['success_rate']:.0%}")
    return paths


if __name__ == "__main__":
    main()
