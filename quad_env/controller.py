"""A hand-written goal-seeking controller (geometric position + attitude control), for demos and tests.

Not a learned policy: it reads the true state (``VecQuadEnv.get_state``) and returns actions in [-1, 1]^4.
Position PD -> desired acceleration -> collective thrust along the body z axis and a desired attitude
(keeping the current heading) -> attitude PD on SO(3) -> body torques -> per-motor thrusts through the
inverse of the motor mixing matrix.
"""
from __future__ import annotations

import numpy as np

from quad_env.config import EnvConfig
from quad_env.vec_env import DroneState


def mixing_matrix(cfg: EnvConfig) -> np.ndarray:
    """[4, 4] map from motor thrusts (T0..T3) to (total thrust, tau_x, tau_y, tau_z) in the body frame."""
    arm, k = cfg.physics.arm_xy, cfg.physics.torque_to_thrust
    return np.array([
        [1.0, 1.0, 1.0, 1.0],
        [-arm, -arm, arm, arm],  # tau_x = sum y_m T_m; motors (+x,-y), (-x,-y), (-x,+y), (+x,+y)
        [-arm, arm, arm, -arm],  # tau_y = -sum x_m T_m
        [-k, k, -k, k],  # tau_z from the spin signs [-1, +1, -1, +1]
    ])


class GoalSeekingController:
    """Vectorised over all drones. Gains are per unit mass / inertia (natural frequencies in rad/s)."""

    def __init__(self, cfg: EnvConfig, kp: float = 4.0, kd: float = 3.5, k_att: float = 144.0,
                 k_rate: float = 20.0, max_tilt_accel: float = 5.0):
        self.cfg = cfg
        p = cfg.physics
        self.mass, self.g = p.mass, p.gravity
        self.inertia = np.asarray(p.inertia)
        self.tmax = p.thrust_to_weight * p.mass * p.gravity / 4.0
        self.unmix = np.linalg.inv(mixing_matrix(cfg))
        self.kp, self.kd, self.k_att, self.k_rate = kp, kd, k_att, k_rate
        self.max_tilt_accel = max_tilt_accel

    def __call__(self, s: DroneState) -> np.ndarray:
        R = s.rot  # [M, 3, 3]
        a_des = -self.kp * (s.pos - s.goal) - self.kd * s.vel  # [M, 3]
        horiz = np.linalg.norm(a_des[:, :2], axis=1, keepdims=True)
        a_des[:, :2] *= np.minimum(1.0, self.max_tilt_accel / np.maximum(horiz, 1e-9))
        a_des[:, 2] = np.clip(a_des[:, 2], -0.5 * self.g, 0.8 * self.g) + self.g
        z_d = a_des / np.linalg.norm(a_des, axis=1, keepdims=True)
        thrust = self.mass * np.einsum("mi,mi->m", a_des, R[:, :, 2])  # along the current body z

        heading = np.stack([R[:, 0, 0], R[:, 1, 0], np.zeros(len(R))], axis=1)
        heading /= np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), 1e-9)
        y_d = np.cross(z_d, heading)
        y_d /= np.maximum(np.linalg.norm(y_d, axis=1, keepdims=True), 1e-9)
        x_d = np.cross(y_d, z_d)
        R_d = np.stack([x_d, y_d, z_d], axis=2)  # columns

        E = np.einsum("mji,mjk->mik", R_d, R) - np.einsum("mji,mjk->mik", R, R_d)  # R_d^T R - R^T R_d
        e_rot = 0.5 * np.stack([E[:, 2, 1], E[:, 0, 2], E[:, 1, 0]], axis=1)
        tau = self.inertia * (-self.k_att * e_rot - self.k_rate * s.omega)
        wrench = np.concatenate([thrust[:, None], tau], axis=1)  # [M, 4]
        motor_thrust = wrench @ self.unmix.T
        cmd = np.clip(motor_thrust / self.tmax, 0.0, 1.0)
        return (2.0 * cmd - 1.0).astype(np.float32)
