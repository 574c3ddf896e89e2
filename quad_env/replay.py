"""Collision replay (the QuadSwarm simulator's trick): restart some episodes shortly before a past collision.

Every swarm keeps a small ring of its own past states, one every SNAPSHOT_INTERVAL_S of its episode
(drone states, thrust noise and goals). When a swarm has its first collision after the grace period in an
episode (drone-drone or drone-obstacle: what the Col metric counts), the snapshot taken LOOKBACK_S (or at
most one interval more) before it goes into a buffer shared by the env's swarms, with the swarm's obstacle
layout and scenario name; the oldest entry is overwritten when the buffer is full.

At an automatic reset, if the buffer is not empty, a swarm draws u ~ U(0, 1) from its own stream and, if
u < ``replay_prob``, restarts from a uniformly drawn entry (a second draw) instead of a fresh spawn. A
replayed episode is a whole new episode (clock at 0, full length, metrics from scratch, grace period again)
whose goals stay where they were stored (the scenario's goal motion is not replayed). Replayed episodes
do not store new entries, so the buffer holds situations from fresh episodes only.
With ``replay_prob == 0`` nothing is drawn and nothing is stored: the env behaves as without replay.
"""
from __future__ import annotations

from typing import List, Optional

import numpy as np

from quad_env.jit_cache import njit  # numba's njit, cached under the sources' hash
from quad_env.rng import uniform

SNAPSHOT_INTERVAL_S = 0.25  # a swarm's state is kept every this many seconds of its episode ...
LOOKBACK_S = 1.5  # ... and a collision stores the one this long before it (at most one interval earlier)

# Columns of a packed drone state (float64 [..., STATE_WIDTH]).
PACK_SLICES = dict(pos=slice(0, 3), vel=slice(3, 6), rot=slice(6, 15), omega=slice(15, 18), motor=slice(18, 22),
                   thrust_noise=slice(22, 26), goal=slice(26, 29))
STATE_WIDTH = 29


@njit(cache=True)
def snapshot_kernel(selected, state, interval, ring, ring_step):
    """Pack the state (``quad_env.kernels.SwarmState``) of every selected swarm whose clock is a multiple of
    ``interval`` into its ring ``ring [E, R, N, STATE_WIDTH]`` (slot (step / interval) mod R; ``ring_step [E, R]``
    = the step)."""
    step_count, pos, vel, rot, omega = state.step_count, state.pos, state.vel, state.rot, state.omega
    motor, ou, goal = state.motor, state.ou, state.goal
    num_slots, n_agents = ring.shape[1], ring.shape[2]
    for e in range(selected.shape[0]):
        s = step_count[e]
        if not selected[e] or s % interval != 0:
            continue
        slot = (s // interval) % num_slots
        ring_step[e, slot] = s
        for a in range(n_agents):
            i = e * n_agents + a
            dst = ring[e, slot, a]
            for k in range(3):
                dst[k] = pos[i, k]
                dst[3 + k] = vel[i, k]
                dst[15 + k] = omega[i, k]
                dst[26 + k] = goal[i, k]
                for c in range(3):
                    dst[6 + 3 * k + c] = rot[i, k, c]
            for k in range(4):
                dst[18 + k] = motor[i, k]
                dst[22 + k] = ou[i, k]


@njit(cache=True)
def find_new_collisions(collisions_after_grace, eligible, step_count, lookback, interval, ring_step, out_slot):
    """Swarms with a collision after the grace period that may still store one: ``out_slot[e]`` = the ring
    slot holding their state ``lookback`` steps (or at most one interval more) before now, else -1.
    Returns how many were found."""
    num_slots = ring_step.shape[1]
    found = 0
    for e in range(step_count.shape[0]):
        out_slot[e] = -1
        if not eligible[e] or collisions_after_grace[e] <= 0.0:
            continue
        target = step_count[e] - lookback
        if target < 0:
            continue
        s = (target // interval) * interval
        slot = (s // interval) % num_slots
        if ring_step[e, slot] == s:
            out_slot[e] = slot
            found += 1
    return found


@njit(cache=True)
def draw_replays(selected, rng, prob, count, choice):
    """``choice[e]`` = the buffer entry the selected swarm e restarts from, or -1 for a fresh spawn."""
    for e in range(selected.shape[0]):
        choice[e] = -1
        if selected[e] and count > 0 and uniform(rng, e) < prob:
            choice[e] = min(int(uniform(rng, e) * count), count - 1)


class CollisionReplay:
    """Snapshot rings, the shared buffer of pre-collision states and the replay draw of one VecQuadEnv."""

    def __init__(self, num_envs: int, num_agents: int, grid_shape, control_dt: float, capacity: int, prob: float):
        self.prob = float(prob)
        self.interval = max(1, int(round(SNAPSHOT_INTERVAL_S / control_dt)))
        self.lookback = int(round(LOOKBACK_S / control_dt))
        slots = -(-(self.lookback + self.interval - 1) // self.interval) + 1  # enough to reach back that far
        self.ring = np.zeros((num_envs, slots, num_agents, STATE_WIDTH))
        self.ring_step = np.full((num_envs, slots), -1, np.int64)
        self.states = np.zeros((capacity, num_agents, STATE_WIDTH))  # the buffer
        self.obstacles = np.zeros((capacity,) + tuple(grid_shape), np.uint8)
        self.names: List[Optional[str]] = [None] * capacity
        self.count = 0  # entries held
        self.next = 0  # entry written next (oldest first once full)
        self.eligible = np.zeros(num_envs, bool)  # may still store an entry this episode
        self.replayed = np.zeros(num_envs, bool)  # this episode is a replay
        self.choice = np.zeros(num_envs, np.int64)
        self._slot = np.zeros(num_envs, np.int64)
        self._everyone = np.ones(num_envs, bool)

    def snapshot(self, selected, state) -> None:
        snapshot_kernel(selected, state, self.interval, self.ring, self.ring_step)

    def after_step(self, state, collisions_after_grace, obst, episode_name) -> None:
        """Store the pre-collision states of swarms that just collided, then snapshot the current step.
        ``state``: the env's ``quad_env.kernels.SwarmState``; ``episode_name(e)`` names the scenario."""
        if find_new_collisions(collisions_after_grace, self.eligible, state.step_count, self.lookback,
                               self.interval, self.ring_step, self._slot):
            for e in np.flatnonzero(self._slot >= 0):
                k = self.next
                self.states[k] = self.ring[e, self._slot[e]]
                self.obstacles[k] = obst[e]
                self.names[k] = episode_name(int(e))
                self.next = (k + 1) % len(self.states)
                self.count = min(self.count + 1, len(self.states))
                self.eligible[e] = False
        self.snapshot(self._everyone, state)

    def draw(self, selected, rng) -> np.ndarray:
        """Entry index per swarm (-1: fresh spawn) for an automatic reset of the selected swarms."""
        draw_replays(selected, rng, self.prob, self.count, self.choice)
        return self.choice

    def restore(self, e: int, k: int, arrays: dict, obst, num_agents: int) -> str:
        """Write entry ``k`` into swarm ``e``'s rows of ``arrays`` (DroneState field name -> array) and its
        obstacle grid; returns the stored scenario name."""
        rows = slice(e * num_agents, (e + 1) * num_agents)
        for name, cols in PACK_SLICES.items():
            target = arrays[name]
            target[rows] = self.states[k][:, cols].reshape(target[rows].shape)
        obst[e] = self.obstacles[k]
        return self.names[k]

    def start_episodes(self, selected, replayed) -> None:
        """Bookkeeping at a reset: fresh episodes may store an entry, replayed ones may not."""
        self.replayed[selected] = replayed[selected]
        self.eligible[selected] = ~replayed[selected]
