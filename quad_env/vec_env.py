"""VecQuadEnv: E independent swarms of N drones, stepped together by one numba kernel.

Rows: drone a of swarm e is row ``e * N + a`` of every per-drone array. Swarms auto-reset when their
episode ends (a truncation: ``terminated`` is always False). The arrays that ``reset``/``step`` return
(and ``final_obs``, ``reward_terms``) are preallocated buffers that the next call overwrites: copy what
you keep.

Seeding: ``seed`` makes one SplitMix64 stream per swarm (``quad_env.rng``); every random draw (obstacles,
spawn, goals, thrust noise, sensor noise, collision kicks, replay choices) comes from the swarm's stream in
a fixed order, so the same seed and the same actions give bit-identical transitions.

Obstacles (``cfg.obstacles``): a new cylinder layout per swarm and episode (``quad_env.obstacles``);
``obstacle_grid`` / ``set_obstacles`` read and write it. Collision replay (``cfg.replay_prob > 0``): see
``quad_env.replay``; only automatic resets replay.

Non-finite states: the kernel checks every drone after its physics. With ``cfg.nan_policy == "raise"``
(default) ``step`` raises ``FloatingPointError`` naming the swarms, and the env must be ``reset()``.
With ``"reset"`` the swarm's rows are reported truncated with reward 0, ``final_obs`` holds the last
finite observation, a ``RuntimeWarning`` is issued, the episode stats carry ``diverged=True`` and the
swarm restarts.

Low-level state API (model validation against flight logs)::

    env = VecQuadEnv(EnvConfig(num_agents=1, sim_dtype="float64"), num_envs=1, seed=0)
    env.set_state(pos=[[0, 0, 1]], vel=[[0, 0, 0]], rot=[np.eye(3)], omega=[[0, 0, 0]],
                  motor=[[0.7, 0.7, 0.7, 0.7]])
    s = env.simulate(actions)          # one control step, no noise, no auto-reset
    s.pos, s.vel, s.rot, s.omega, s.motor  # float64 copies
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np

from quad_env.actions import check_actions
from quad_env.config import EnvConfig
from quad_env.kernels import (
    ACC_COLL_GRACE, ACC_COLLISIONS, ACC_DIST_FINAL, ACC_DIST_TAIL, ACC_DIST_TAIL1, ACC_DIST_TAIL3, ACC_OBST,
    ACC_OBST_GRACE, ACC_RESPAWNS, ACC_RETURN, ACC_ROOM, ACC_ROOM_GRACE, ACC_TAIL1_STEPS, ACC_TAIL3_STEPS,
    ACC_TAIL_STEPS, ACC_TERMS, AG_COLL_GRACE, AG_LAST_OUT, AG_OBST_GRACE, AG_REACHED, NUM_ACC, NUM_AGENT_ACC,
    SUCCESS_HOLD_S, EpisodeMetrics, Obstacles, SpawnBox, StepOutput, SwarmState, all_finite, observe_kernel,
    refresh_contacts_kernel, respawn_kernel, spawn_kernel, step_with_metrics_kernel,
)
from quad_env.obstacles import (
    INDEX_SLOTS, OBSTACLE_CLEARANCE, clear_spawns_and_goals, draw_obstacles, grid_origin, index_obstacles, index_spec,
    lookup_pad,
)
from quad_env.params import (
    F_C_COLL, F_C_OBST, F_C_PROX, I_EP_STEPS, REWARD_TERMS, SDF_SPACING, T_CRASH, pack_params,
)
from quad_env.replay import CollisionReplay
from quad_env.rng import seed_streams
from quad_env.scenarios import SPAWN_HALF, SPAWN_MIN_SEP, SPAWN_MIN_Z, make_scenario

_NEVER = np.iinfo(np.int64).max // 2  # episode length used by ``simulate`` (no episode end)


@dataclass
class DroneState:
    """Full simulator state of all M = E * N drones (float64 copies; row e * N + a)."""

    pos: np.ndarray  # [M, 3] world position, m
    vel: np.ndarray  # [M, 3] world velocity, m/s
    rot: np.ndarray  # [M, 3, 3] body -> world rotation
    omega: np.ndarray  # [M, 3] body rates, rad/s
    motor: np.ndarray  # [M, 4] normalised rotor speed in [0, 1] (thrust fraction = motor ** 2)
    thrust_noise: np.ndarray  # [M, 4] Ornstein-Uhlenbeck thrust-noise state
    goal: np.ndarray  # [M, 3] goal position, m


class VecQuadEnv:
    """E swarms x N drones. See the module docstring for rows, buffers, seeding and the NaN policy.

    Args:
        cfg: environment config (validated here).
        num_envs: E, the number of independent swarms.
        seed: one integer seed for every random draw.
        auto_reset: restart a swarm as soon as its episode ends (rollout workers). With False a
            finished swarm must be ``reset()`` before the next ``step`` (the single-swarm adapters).
    """

    def __init__(self, cfg: EnvConfig, num_envs: int, seed: int = 0, auto_reset: bool = True):
        if not isinstance(cfg, EnvConfig):
            raise TypeError(f"cfg must be an EnvConfig, got {type(cfg).__name__}")
        cfg.validate()
        if not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be an int >= 1, got {num_envs!r}")
        self.cfg = cfg
        self.scenario = make_scenario(cfg.scenario, cfg)
        if self.scenario.needs_obstacles and not cfg.obstacles:
            raise ValueError(f"scenario {cfg.scenario!r} flies through obstacles: set env.obstacles=True "
                             "(which also adds the 9-entry obstacle field to the observation)")
        self.layout = cfg.obs_layout()
        self.num_envs = E = int(num_envs)
        self.num_agents = N = cfg.num_agents
        self.num_drones = M = E * N
        self.obs_dim = D = self.layout.dim
        self.auto_reset = auto_reset
        self.scenario.allocate(E)

        dt = np.float32 if cfg.sim_dtype == "float32" else np.float64
        # ---- simulator state (structure of arrays)
        self._pos = np.zeros((M, 3), dt)
        self._vel = np.zeros((M, 3), dt)
        self._rot = np.zeros((M, 3, 3), dt)
        self._omega = np.zeros((M, 3), dt)
        self._motor = np.zeros((M, 4), dt)
        self._ou = np.zeros((M, 4), dt)
        self._goal = np.zeros((M, 3), dt)
        self._center = np.zeros((E, 3), np.float64)
        self._contact = np.zeros((E, N, N), np.uint8)
        self._room_contact = np.zeros(M, np.uint8)
        self._step_count = np.zeros(E, np.int64)
        self._acc = np.zeros((E, NUM_ACC), np.float64)
        self._agent_acc = np.zeros((M, NUM_AGENT_ACC), np.float64)
        G = cfg.obstacle_grid_cells if cfg.obstacles else 1
        self._obst = np.zeros((E, G, G), np.uint8)  # 1 = a cylinder in cell (ix, iy) (quad_env.obstacles)
        L = G + 2 * lookup_pad(cfg) if cfg.obstacles else 1
        self._obst_index = np.zeros((E, L, L, INDEX_SLOTS + 1 if cfg.obstacles else 1), index_spec(cfg)[0])
        self._obst_contact = np.zeros(M, np.uint8)
        self._rng = seed_streams(seed, E)
        self._fp, self._ip = pack_params(cfg, D, noise=True)
        self._fp_quiet, self._ip_quiet = pack_params(cfg, D, noise=False)
        self._collision_scale = 1.0
        self._ip_quiet[I_EP_STEPS] = _NEVER

        # ---- output buffers (overwritten by every call)
        self._obs = np.zeros((M, D), np.float32)
        self._rew = np.zeros(M, np.float32)
        self._terms = np.zeros((len(REWARD_TERMS), M), np.float32)
        self._terminated = np.zeros(M, bool)  # never set: the episode end is a truncation
        self._truncated = np.zeros(M, bool)
        self._final_obs = np.zeros((M, D), np.float32)
        self._done = np.zeros(E, bool)
        self._diverged = np.zeros(E, bool)
        self._needs_reset = np.zeros(E, bool)
        self._action_buf = np.zeros((M, 4), np.float64)  # exact for float32 and float64 inputs
        self.reward_terms: Dict[str, np.ndarray] = {name: self._terms[k] for k, name in enumerate(REWARD_TERMS)}
        self._episode_stats: List[dict] = []
        # ---- floor contacts: reward.crash and the respawn_on_floor training aid (off in the paper's setting)
        self._floor_on = cfg.respawn_on_floor or cfg.reward.crash > 0
        self._on_floor = np.zeros(M, bool)  # touching the floor after the previous step
        self._replay = (CollisionReplay(E, N, self._obst.shape[1:], cfg.control_dt, cfg.replay_buffer_size,
                                        cfg.replay_prob) if cfg.replay_prob > 0 else None)
        self._replayed_name: List[Optional[str]] = [None] * E  # scenario name of a replayed episode
        self._everyone = np.ones(E, bool)
        # ---- the kernels' argument bundles (views of the arrays above, built once: keep the arrays, never rebind)
        self._state = SwarmState(pos=self._pos, vel=self._vel, rot=self._rot, omega=self._omega, motor=self._motor,
                                 ou=self._ou, goal=self._goal, contact=self._contact, room_contact=self._room_contact,
                                 rng=self._rng, step_count=self._step_count)
        self._out = StepOutput(obs=self._obs, rew=self._rew, terms=self._terms, done=self._done,
                               diverged=self._diverged)
        self._metrics = EpisodeMetrics(acc=self._acc, agent_acc=self._agent_acc, jumped=self.scenario.jumped)
        self._obstacles = Obstacles(grid=self._obst, index=self._obst_index, contact=self._obst_contact)
        self._spawn_box = SpawnBox(center=self._center, half=self.scenario.spawn_half, min_z=SPAWN_MIN_Z,
                                   min_sep=SPAWN_MIN_SEP)
        self._hold_steps = max(1, int(round(SUCCESS_HOLD_S / cfg.control_dt)))  # success: the last 1 s
        self.reset()

    # ------------------------------------------------------------------ public buffers
    @property
    def final_obs(self) -> np.ndarray:
        """float32 [M, D]: for rows whose episode ended at the last step, the true last observation.
        Other rows hold stale values."""
        return self._final_obs

    # ------------------------------------------------------------------ episode API
    def seed(self, seed: int) -> None:
        """Restart every swarm's random stream from ``seed`` (takes effect from the next draw)."""
        self._rng[:] = seed_streams(seed, self.num_envs)

    def reset(self, seed: Optional[int] = None) -> np.ndarray:
        """Start a new episode in every swarm; returns obs float32 [E*N, D] (a reused buffer).
        Episodes in progress are dropped without stats."""
        if seed is not None:
            self.seed(seed)
        self._reset_swarms(self._everyone.copy())
        self._truncated[:] = False
        self._rew[:] = 0.0
        self._terms[:] = 0.0
        return self._obs

    def step(self, actions: np.ndarray):
        """Advance every swarm by one control step.

        Args:
            actions: [E*N, 4] float array; clipped to [-1, 1]; motor command = (a + 1) / 2.
        Returns:
            obs float32 [E*N, D], rew float32 [E*N], terminated bool [E*N] (always False),
            truncated bool [E*N] (reused buffers). Rows that ended hold the first observation of the
            next episode in ``obs`` and the true last one in ``final_obs``.
        """
        act = self._check_actions(actions)
        if self._needs_reset.any():
            raise RuntimeError(f"swarms {np.flatnonzero(self._needs_reset).tolist()} finished their episode "
                               "(auto_reset=False): call reset() before step()")
        if self.scenario.dynamic:
            self.scenario.update(self._goal, self._step_count, self._rng)
        self._done[:] = False
        n_done = step_with_metrics_kernel(act, self._state, self._fp, self._ip, self._out, self._metrics,
                                          self._obstacles)
        if self._floor_on:
            self._floor_contacts()
        if self._replay is not None:
            self._replay.after_step(self._state, self._acc[:, ACC_COLL_GRACE] + self._acc[:, ACC_OBST_GRACE],
                                    self._obst, self._episode_name)
        if n_done:
            self._finish_episodes()
        else:
            self._truncated[:] = False
        return self._obs, self._rew, self._terminated, self._truncated

    def pop_episode_stats(self) -> List[dict]:
        """One dict per swarm episode finished since the last call (then forgotten).

        Keys: ``scenario``; ``return`` (episode reward, mean per agent); ``length`` (control steps);
        ``dist_final`` (mean distance to goal after the last step); ``dist_last_5s``, ``dist_last_3s``,
        ``dist_last_1s`` (mean over the last 5 / 3 / 1 s, or the whole episode if shorter);
        ``collisions`` (new drone-drone contacts, pairs); ``room_contacts`` (new floor/wall/ceiling
        contacts, drones); ``collisions_after_grace``, ``room_contacts_after_grace`` (the same, counted
        only after the first 1.5 s); ``inter_collision_rate`` (share of drones with at least one new
        drone-drone contact after the grace period); ``success_rate`` (the paper's Suc: share of drones
        that were within 0.5 m of their goal after every control step of the episode's last 1 s, or of the
        whole episode if it is shorter, and had no drone-drone contact after the grace period);
        ``reached_rate`` (the earlier success: share of drones that reached their goal -- mean distance over
        5 consecutive steps < 0.5 m at some step after the last goal jump -- and had no drone-drone contact
        after the grace period); ``agent_success``, ``agent_reached``, ``agent_collided`` (bool [N]: the same
        per drone); ``agent_dist_final`` (float [N]: each drone's distance to its goal after the last step);
        ``rew_<term>`` (per-term episode reward, mean per agent: they sum
        to ``return``); ``diverged`` (the episode ended on a non-finite state).
        With obstacles, ``collisions`` and ``collisions_after_grace`` count drone-drone contacts (pairs) plus
        new drone-obstacle contacts (drones): the paper's Col; ``obstacle_collisions`` and
        ``obstacle_collisions_after_grace`` count the latter alone, ``agent_hit_obstacle`` (bool [N]) marks
        the drones with one after the grace period, and success and reached also need no obstacle contact
        after the grace period (``inter_collision_rate`` stays drone-drone only). ``replayed``: the episode restarted
        from a stored pre-collision state (``env.replay_prob``); ``respawns``: drones put back in the air by
        ``env.respawn_on_floor``.
        """
        out, self._episode_stats = self._episode_stats, []
        return out

    def observe(self) -> np.ndarray:
        """Rebuild the observation of the current state (sensor noise as configured) and return the
        obs buffer float32 [E*N, D]."""
        observe_kernel(self._everyone, self._state, self._fp, self._ip, self._obs, self._obstacles)
        return self._obs

    # ------------------------------------------------------------------ reward schedule
    @property
    def collision_scale(self) -> float:
        """The factor on the collision penalties (c2, c3, obstacle contacts) now in force; 1 = as configured."""
        return self._collision_scale

    def set_collision_scale(self, scale: float) -> None:
        """Scale the collision penalties (``reward.collision``, ``proximity``, ``obstacle_collision``) by
        ``scale`` in [0, 1] from the next step on (``reward.collision_anneal_steps``: the trainer's annealing)."""
        scale = float(scale)
        if not 0.0 <= scale <= 1.0:
            raise ValueError(f"collision scale must be in [0, 1], got {scale!r}")
        r = self.cfg.reward
        for fp in (self._fp, self._fp_quiet):
            fp[F_C_COLL], fp[F_C_PROX], fp[F_C_OBST] = (r.collision * scale, r.proximity * scale,
                                                        r.obstacle_collision * scale)
        self._collision_scale = scale

    def replay_info(self) -> Optional[dict]:
        """Collision replay (``env.replay_prob``) as it stands, None when off: ``stored`` (entries held),
        ``next_slot`` (written next; the oldest once full) and ``replaying`` (bool [E]: the swarm's current
        episode restarted from a stored state)."""
        if self._replay is None:
            return None
        return {"stored": int(self._replay.count), "next_slot": int(self._replay.next),
                "replaying": self._replay.replayed.copy()}

    # ------------------------------------------------------------------ obstacles
    @property
    def obstacle_grid(self) -> np.ndarray:
        """uint8 [E, G, G]: 1 where a grid cell holds a cylinder (``quad_env.obstacles``). The env's own
        array: change it through ``set_obstacles``."""
        return self._obst

    def set_obstacles(self, grid) -> None:
        """Replace the cylinder layout of every swarm (bool/int [E, G, G]) for the rest of the episode; the
        drones' obstacle-contact memory is cleared and the observation rebuilt."""
        if not self.cfg.obstacles:
            raise ValueError("set_obstacles: this env has no obstacles (env.obstacles=False)")
        grid = np.asarray(grid)
        if grid.shape != self._obst.shape:
            raise ValueError(f"set_obstacles: grid must have shape {self._obst.shape}, got {grid.shape}")
        self._obst[...] = grid != 0
        self._index_obstacles(self._everyone)
        self._obst_contact[:] = 0
        self.observe()

    # ------------------------------------------------------------------ low-level state API
    def get_state(self) -> DroneState:
        """Copy of the full state of every drone (float64)."""
        f = lambda x: np.array(x, dtype=np.float64)  # noqa: E731
        return DroneState(pos=f(self._pos), vel=f(self._vel), rot=f(self._rot), omega=f(self._omega),
                          motor=f(self._motor), thrust_noise=f(self._ou), goal=f(self._goal))

    def set_state(self, pos=None, vel=None, rot=None, omega=None, motor=None, thrust_noise=None,
                  goal=None) -> None:
        """Overwrite any part of the state of all drones (arrays shaped as in ``DroneState``).

        Rotations must be orthonormal with det +1 (to 1e-6), motor speeds in [0, 1]. Afterwards the
        contact memory is set to the pairs touching now (they do not count as new collisions), the room and
        obstacle contact memories are cleared and the observation buffer is rebuilt.
        """
        M = self.num_drones
        spec = dict(pos=(pos, (M, 3), self._pos), vel=(vel, (M, 3), self._vel), rot=(rot, (M, 3, 3), self._rot),
                    omega=(omega, (M, 3), self._omega), motor=(motor, (M, 4), self._motor),
                    thrust_noise=(thrust_noise, (M, 4), self._ou), goal=(goal, (M, 3), self._goal))
        checked = {}
        for name, (value, shape, _) in spec.items():
            if value is None:
                continue
            arr = np.asarray(value, dtype=np.float64)
            if arr.shape != shape:
                raise ValueError(f"set_state: {name} must have shape {shape}, got {arr.shape}")
            if not np.isfinite(arr).all():
                raise ValueError(f"set_state: {name} contains NaN or inf")
            checked[name] = arr
        if "rot" in checked:
            r = checked["rot"]
            err = np.abs(np.einsum("mji,mjk->mik", r, r) - np.eye(3)).max()
            if err > 1e-6 or (np.linalg.det(r) < 0).any():
                raise ValueError(f"set_state: rot must be rotation matrices (|R^T R - I| = {err:.2e}, det > 0)")
        if "motor" in checked and ((checked["motor"] < 0) | (checked["motor"] > 1)).any():
            raise ValueError("set_state: motor speeds must be in [0, 1]")
        for name, arr in checked.items():
            spec[name][2][...] = arr
        refresh_contacts_kernel(self._everyone, self._state, self._fp, self._ip)
        self._room_contact[:] = 0
        self._on_floor[:] = self._pos[:, 2] <= self.cfg.physics.floor_z  # resting drones are no new contact
        self._obst_contact[:] = 0
        self.observe()

    def simulate(self, actions: np.ndarray, noise: bool = False) -> DroneState:
        """One control step of every drone with the given actions and return the new state.

        With ``noise=False`` there is no thrust noise, no sensor noise and no random collision kick; the
        step is deterministic. No episode ends and nothing auto-resets (the episode clock still advances,
        which sets the re-orthonormalisation schedule, and the episode metrics accumulate: see
        ``episode_stats``; the last-N-seconds distances never count, the episode never nearing its end).
        Observation, reward and ``reward_terms`` buffers are updated as in ``step``.
        """
        act = self._check_actions(actions)
        fp, ip = (self._fp, self._ip.copy()) if noise else (self._fp_quiet, self._ip_quiet)
        ip[I_EP_STEPS] = _NEVER
        done = np.zeros(self.num_envs, bool)
        diverged = np.zeros(self.num_envs, bool)
        out = self._out._replace(done=done, diverged=diverged)
        step_with_metrics_kernel(act, self._state, fp, ip, out, self._metrics, self._obstacles)
        if diverged.any():
            raise FloatingPointError(f"simulate: non-finite state in swarms {np.flatnonzero(diverged).tolist()}")
        return self.get_state()

    # ------------------------------------------------------------------ internals
    def _check_actions(self, actions) -> np.ndarray:
        a = actions
        if (isinstance(a, np.ndarray) and a.dtype in (np.float32, np.float64) and a.flags.c_contiguous
                and a.shape == (self.num_drones, 4) and all_finite(a)):
            return a  # the step loop's path: no copy, no allocation
        return check_actions(actions, (self.num_drones, 4), "actions (one row of 4 per drone, E*N rows)",
                             out=self._action_buf)

    def _index_obstacles(self, selected: np.ndarray) -> None:
        """Rebuild the obstacle field's lookup index of the selected swarms (after their layout changed)."""
        cfg = self.cfg
        index_obstacles(selected, self._obst, self._obst_index, grid_origin(cfg), cfg.obstacle_cell_size,
                        0.5 * cfg.obstacle_diameter, cfg.obstacle_sdf_max, lookup_pad(cfg), SDF_SPACING + 1e-6,
                        index_spec(cfg)[1])

    def _episode_name(self, e: int) -> str:
        name = self._replayed_name[e]
        return self.scenario.episode_name(e) if name is None else name

    def _reset_swarms(self, selected: np.ndarray, allow_replay: bool = False) -> None:
        """Start new episodes in the selected swarms. Draw order per swarm: replay choice (automatic resets
        with replay on), obstacles, scenario goals, spawn points."""
        fresh = selected
        replayed = np.zeros_like(selected)
        if allow_replay and self._replay is not None:
            choice = self._replay.draw(selected, self._rng)
            replayed = selected & (choice >= 0)
            fresh = selected & ~replayed
        cfg = self.cfg
        if cfg.obstacles:
            draw_obstacles(fresh, self._obst, self._rng, cfg.obstacle_density)
        self.scenario.spawn_half[fresh] = SPAWN_HALF
        self.scenario.set_active(fresh, True)
        self.scenario.reset(fresh, self._goal, self._center, self._rng)
        spawn_kernel(fresh, self._state, self._spawn_box, self._fp, self._ip)
        if cfg.obstacles:
            clear_spawns_and_goals(fresh, self._obst, self._pos, self._goal, self.num_agents, grid_origin(cfg),
                                   cfg.obstacle_cell_size, 0.5 * cfg.obstacle_diameter, OBSTACLE_CLEARANCE)
        for e in np.flatnonzero(fresh):
            self._replayed_name[e] = None
        if replayed.any():
            arrays = dict(pos=self._pos, vel=self._vel, rot=self._rot, omega=self._omega, motor=self._motor,
                          thrust_noise=self._ou, goal=self._goal)
            for e in np.flatnonzero(replayed):
                name = self._replay.restore(int(e), int(self._replay.choice[e]), arrays, self._obst, self.num_agents)
                self._replayed_name[e] = name
                self._room_contact[e * self.num_agents:(e + 1) * self.num_agents] = 0
            self.scenario.set_active(replayed, False)  # the stored goals stay put
        if cfg.obstacles:
            self._index_obstacles(selected)
        self._obst_contact[np.repeat(selected, self.num_agents)] = 0
        refresh_contacts_kernel(selected, self._state, self._fp, self._ip)
        self._step_count[selected] = 0
        self._on_floor[np.repeat(selected, self.num_agents)] = False
        self._acc[selected] = 0.0
        self._agent_acc[np.repeat(selected, self.num_agents)] = 0.0
        self.scenario.jumped[selected] = 0
        self._diverged[selected] = False
        self._needs_reset[selected] = False
        if self._replay is not None:
            self._replay.start_episodes(selected, replayed)
            self._replay.snapshot(selected, self._state)
        observe_kernel(selected, self._state, self._fp, self._ip, self._obs, self._obstacles)

    def _floor_contacts(self) -> None:
        """After a step: ``reward.crash`` for every new floor contact, then (``respawn_on_floor``) those
        drones go back to the scenario's spawn box. Swarms that diverged or just ended are left alone."""
        E, N = self.num_envs, self.num_agents
        live = ~np.repeat(self._done | self._diverged, N)  # [M]
        on_floor = self._pos[:, 2] <= self.cfg.physics.floor_z  # [M]
        new = on_floor & ~self._on_floor & live  # [M]
        crash = self._terms[T_CRASH]  # [M] view
        crash[:] = 0.0
        c = self.cfg.reward.crash
        if c > 0 and new.any():
            crash[new] = -c
            self._rew[new] -= c
            per_swarm = c * new.reshape(E, N).sum(axis=1)  # [E]
            self._acc[:, ACC_TERMS + T_CRASH] -= per_swarm
            self._acc[:, ACC_RETURN] -= per_swarm
        self._on_floor[:] = on_floor
        if not self.cfg.respawn_on_floor:
            return
        rows = np.flatnonzero(on_floor & live)
        if rows.size == 0:
            return
        respawn_kernel(rows, self._state, self._spawn_box, self._fp, self._ip)
        self._on_floor[rows] = False
        swarms = np.zeros(E, bool)
        swarms[rows // N] = True
        self._acc[:, ACC_RESPAWNS] += np.bincount(rows // N, minlength=E)
        refresh_contacts_kernel(swarms, self._state, self._fp, self._ip)
        observe_kernel(swarms, self._state, self._fp, self._ip, self._obs, self._obstacles)

    def _finish_episodes(self) -> None:
        """Record stats, save final observations and restart the swarms that finished."""
        done, N = self._done, self.num_agents
        rows = np.repeat(done, N)
        self._truncated[:] = rows
        diverged = self._diverged & done
        if diverged.any():
            bad = np.flatnonzero(diverged).tolist()
            if self.cfg.nan_policy == "raise":
                self._needs_reset[:] = True
                raise FloatingPointError(f"non-finite drone state in swarms {bad} (env.nan_policy='raise'); "
                                         "call reset() to continue")
            warnings.warn(f"non-finite drone state in swarms {bad}: resetting them (env.nan_policy='reset')",
                          RuntimeWarning, stacklevel=3)
        self._final_obs[rows] = self._obs[rows]
        for e in np.flatnonzero(done):
            self._episode_stats.append(self.episode_stats(int(e)))
        if self.auto_reset:
            self._reset_swarms(done.copy(), allow_replay=True)
        else:
            self._needs_reset |= done

    def episode_stats(self, e: int) -> dict:
        """Stats of swarm ``e``'s episode so far (the dict ``pop_episode_stats`` returns at its end; mid-episode,
        success looks at the last 1 s so far)."""
        acc, N = self._acc[e], self.num_agents
        rows = slice(e * N, (e + 1) * N)  # swarm e's drones
        agents = self._agent_acc[rows]
        collided = agents[:, AG_COLL_GRACE] > 0  # [N] drone-drone
        hit_obstacle = agents[:, AG_OBST_GRACE] > 0  # [N]
        clean = ~collided & ~hit_obstacle  # [N]
        n_steps = int(self._step_count[e])
        hold_start = max(n_steps - self._hold_steps, 0)  # the hold covers steps hold_start + 1 .. n_steps
        success = (agents[:, AG_LAST_OUT] <= hold_start) & clean & (n_steps > 0)  # [N]
        reached = (agents[:, AG_REACHED] > 0) & clean  # [N]
        mean_of = lambda total, steps: total / steps if steps > 0 else float("nan")  # noqa: E731
        stats = {
            "scenario": self._episode_name(e),
            "return": acc[ACC_RETURN] / N,
            "length": int(self._step_count[e]),
            "dist_final": acc[ACC_DIST_FINAL],
            "dist_last_5s": mean_of(acc[ACC_DIST_TAIL], acc[ACC_TAIL_STEPS]),
            "dist_last_3s": mean_of(acc[ACC_DIST_TAIL3], acc[ACC_TAIL3_STEPS]),
            "dist_last_1s": mean_of(acc[ACC_DIST_TAIL1], acc[ACC_TAIL1_STEPS]),
            "collisions": int(acc[ACC_COLLISIONS] + acc[ACC_OBST]),
            "room_contacts": int(acc[ACC_ROOM]),
            "collisions_after_grace": int(acc[ACC_COLL_GRACE] + acc[ACC_OBST_GRACE]),
            "obstacle_collisions": int(acc[ACC_OBST]),
            "obstacle_collisions_after_grace": int(acc[ACC_OBST_GRACE]),
            "room_contacts_after_grace": int(acc[ACC_ROOM_GRACE]),
            "inter_collision_rate": float(collided.mean()),
            "success_rate": float(success.mean()),
            "reached_rate": float(reached.mean()),
            "agent_success": success.copy(),
            "agent_reached": reached.copy(),
            "agent_collided": collided.copy(),
            "agent_hit_obstacle": hit_obstacle.copy(),
            "agent_dist_final": np.linalg.norm(self._pos[rows].astype(np.float64) - self._goal[rows], axis=1),  # [N]
            "diverged": bool(self._diverged[e]),
            "respawns": int(acc[ACC_RESPAWNS]),
            "replayed": bool(self._replay is not None and self._replay.replayed[e]),
        }
        for k, name in enumerate(REWARD_TERMS):
            stats[f"rew_{name}"] = acc[ACC_TERMS + k] / N
        return stats
