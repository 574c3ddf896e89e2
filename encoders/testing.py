"""Test helpers: random valid observations (through the layout) and an equivariance check.

``random_obs`` fills every field of a layout with a valid random value (rotations from QR, masks with a
chosen number of real neighbours). ``random_swarm`` + ``swarm_observations`` build the observations of
a whole swarm of N drones from world states (K nearest neighbours, sorted, padded and masked), so that
moving the world by (Q, t) can be checked end to end. Neither uses the simulator.
"""
from __future__ import annotations

from typing import Callable, Dict, Optional, Sequence, Tuple

import numpy as np
import torch

from quad_env.obs_layout import ObsLayout

# max |error| allowed by ``assert_equivariant`` per dtype (float64 per the spec; float32 for O(1) outputs)
EQUIVARIANCE_TOLERANCE = {torch.float64: 1e-9, torch.float32: 1e-4}


def random_rotation(rng: np.random.Generator, size: Tuple[int, ...] = ()) -> np.ndarray:
    """Uniform random rotations [*size, 3, 3] (QR of a Gaussian matrix, signs fixed, det +1)."""
    A = rng.standard_normal((*size, 3, 3))
    Q, Rr = np.linalg.qr(A)
    Q = Q * np.sign(np.diagonal(Rr, axis1=-2, axis2=-1))[..., None, :]
    Q[..., :, 0] *= np.sign(np.linalg.det(Q))[..., None]  # a reflection becomes a rotation
    return Q


def rotation_about_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def random_group_element(group: str, rng: np.random.Generator) -> np.ndarray:
    """A random rotation of ``group``: "se3" any rotation (Haar), "yaw" a rotation about the world z axis,
    "none" the identity (only translations act, and every position in an observation is relative)."""
    if group == "se3":
        return random_rotation(rng)
    if group == "yaw":
        return rotation_about_z(rng.uniform(-np.pi, np.pi))
    if group == "none":
        return np.eye(3)
    raise ValueError(f"unknown group {group!r}; valid: ['none', 'se3', 'yaw']")


def random_tilt(rng: np.random.Generator, min_angle: float = 0.5) -> np.ndarray:
    """A rotation about a random horizontal axis by at least ``min_angle`` rad: outside the yaw group."""
    phi = rng.uniform(0, 2 * np.pi)
    axis = np.array([np.cos(phi), np.sin(phi), 0.0])
    angle = rng.uniform(min_angle, np.pi - 0.1)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K  # Rodrigues


def random_obs(layout: ObsLayout, batch: int, rng: np.random.Generator,
               num_real: Optional[Sequence[int]] = None, garbage: float = 0.0) -> np.ndarray:
    """A batch [B, D] of valid observations: Gaussian vectors, random rotations, a mask whose first
    ``num_real[b]`` slots are real (default: random in 0..K); padded slots hold zeros or, if ``garbage``
    is not 0, values of that scale (a valid env would write zeros)."""
    K = layout.num_neighbors
    obs = np.zeros((batch, layout.dim))
    if num_real is None:
        num_real = rng.integers(0, K + 1, size=batch)
    num_real = np.broadcast_to(np.asarray(num_real), (batch,))
    for f in layout.fields:
        copies = K if f.group == "neighbor" else 1
        for k in range(copies):
            off = k * layout.neighbor_dim if f.group == "neighbor" else 0
            s = slice(f.start + off, f.stop + off)
            if f.kind == "rotation":
                obs[:, s] = random_rotation(rng, (batch,)).reshape(batch, 9)
            elif f.kind == "mask":
                obs[:, s] = (np.arange(K)[None, :] < num_real[:, None]).astype(float)
            else:
                obs[:, s] = rng.standard_normal((batch, f.size))
    if K:
        mask = obs[:, layout.mask_start:layout.mask_start + K] > 0.5
        nb = layout.neighbors(obs)  # [B, K, F] view
        nb[~mask] = garbage * rng.standard_normal(nb[~mask].shape) if garbage else 0.0
    return obs


def random_swarm(num_drones: int, rng: np.random.Generator, spread: float = 1.0) -> Dict[str, np.ndarray]:
    """World states of N drones: positions, velocities, attitudes (body -> world), body rates, goals."""
    N = num_drones
    return {"pos": spread * rng.standard_normal((N, 3)), "vel": rng.standard_normal((N, 3)),
            "rot": random_rotation(rng, (N,)), "omega": rng.standard_normal((N, 3)),
            "goal": spread * rng.standard_normal((N, 3))}


def move_swarm(state: Dict[str, np.ndarray], Q: np.ndarray, t: np.ndarray) -> Dict[str, np.ndarray]:
    """The same swarm after the world is rotated by Q and translated by t."""
    return {"pos": state["pos"] @ Q.T + t, "vel": state["vel"] @ Q.T, "rot": Q @ state["rot"],
            "omega": state["omega"].copy(), "goal": state["goal"] @ Q.T + t}


def swarm_observations(layout: ObsLayout, state: Dict[str, np.ndarray]) -> np.ndarray:
    """Observation [N, D] of every drone: own state, then its K nearest other drones (nearest first)
    written field by field in the layout's order, padded and masked when N - 1 < K."""
    pos, vel, rot, omega, goal = (state[k] for k in ("pos", "vel", "rot", "omega", "goal"))
    N, K = pos.shape[0], layout.num_neighbors
    obs = np.zeros((N, layout.dim))
    own = {"rel_goal": pos - goal, "vel": vel, "rot": rot.reshape(N, 9), "omega": omega}
    for f in layout.fields_of("self"):
        obs[:, f.start:f.stop] = own[f.name]
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.diag(np.full(N, np.inf))
    for i in range(N):
        nearest = np.argsort(d[i], kind="stable")[:min(K, N - 1)]
        for k, j in enumerate(nearest):
            values = {"rel_pos": pos[j] - pos[i], "rel_vel": vel[j] - vel[i], "rot": rot[j].reshape(9),
                      "omega": omega[j], "goal_offset": goal[j] - pos[j]}
            for f in layout.fields_of("neighbor"):
                s = f.start + k * layout.neighbor_dim
                obs[i, s:s + f.size] = values[f.name]
            obs[i, layout.mask_start + k] = 1.0
    return obs


def rotate_output(out: torch.Tensor, Q: torch.Tensor, rep: Tuple[int, int]) -> torch.Tensor:
    """Apply Q to a typed output ``[num_scalars | num_vectors x 3]``: scalars fixed, vectors rotated."""
    num_scalars, num_vectors = rep
    if out.shape[-1] != num_scalars + 3 * num_vectors:
        raise ValueError(f"output width {out.shape[-1]} does not match representation {rep}")
    vectors = out[..., num_scalars:].reshape(*out.shape[:-1], num_vectors, 3) @ Q.T
    return torch.cat([out[..., :num_scalars], vectors.flatten(-2)], dim=-1)


def equivariance_error(fn: Callable[[torch.Tensor], torch.Tensor], obs: torch.Tensor, layout: ObsLayout,
                       rep: Tuple[int, int], Q: torch.Tensor) -> float:
    """max |fn(Q . obs) - Q . fn(obs)| for one rotation Q (a matrix of obs's dtype)."""
    with torch.no_grad():
        moved = fn(layout.transform(obs, Q))
        expected = rotate_output(fn(obs), Q, rep)
    return float((moved - expected).abs().max())


def assert_equivariant(fn: Callable[[torch.Tensor], torch.Tensor], obs: torch.Tensor, layout: ObsLayout,
                       rep: Tuple[int, int], rotations: int = 4, seed: int = 0,
                       tolerance: Optional[float] = None, group: str = "se3") -> float:
    """Check ``fn(Q . obs) == Q . fn(obs)`` for ``rotations`` random Q of ``group`` ("se3": SO(3), "yaw":
    rotations about z), where Q acts on the observation through ``layout.transform`` and on the output by
    ``rep = (num_scalars, num_vectors)``.

    Returns the largest error; raises AssertionError if it exceeds ``tolerance`` (default: per dtype,
    ``EQUIVARIANCE_TOLERANCE``).
    """
    if tolerance is None:
        tolerance = EQUIVARIANCE_TOLERANCE[obs.dtype]
    rng = np.random.default_rng(seed)
    error = 0.0
    for _ in range(rotations):
        Q = torch.as_tensor(random_group_element(group, rng), dtype=obs.dtype, device=obs.device)
        error = max(error, equivariance_error(fn, obs, layout, rep, Q))
    assert error <= tolerance, f"equivariance error {error:.3e} > tolerance {tolerance:.1e} for rep {rep}"
    return error


# small sizes of every encoder for fast tests (the defaults are the paper's)
TINY_OPTIONS = {
    "se3_graphormer": dict(multiplicity=4, zeta_sizes=(32, 16, 32, 32), out_vectors=8),
    "graphormer": dict(multiplicity=4, zeta_sizes=(32, 16, 32, 32)),
    "se3_kattention": dict(hidden=16, out_dim=32, out_vectors=8),
    "kattention": dict(hidden=16, out_dim=32),
    "deepsets": dict(hidden=16, out_dim=32),
    "mlp": dict(hidden=16, out_dim=32),
    "infomarl": dict(hidden=8, embedding_size=2, num_heads=2, out_dim=32),
}
