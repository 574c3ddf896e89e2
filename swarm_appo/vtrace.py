"""V-trace off-policy value targets and policy-gradient advantages (Espeholt et al. 2018, IMPALA, Sec. 4).

Everything is time-major: ``[T, B]`` where T is the fragment length (rollout) and B the number of
trajectories (one per drone). For a step s, with ``rho_t = pi(a_t|x_t) / mu(a_t|x_t)``:

    delta_t V = min(rho_bar, rho_t) * (r_t + gamma_t * V(x_{t+1}) - V(x_t))
    v_s       = V(x_s) + sum_{t>=s} (prod_{i=s}^{t-1} gamma_i) (prod_{i=s}^{t-1} c_i) delta_t V,
                with c_i = min(c_bar, rho_i)
    A_s       = min(rho_pg_bar, rho_s) * (r_s + gamma_s * v_{s+1} - V(x_s))

computed with the equivalent backward recursion ``v_s - V(x_s) = delta_s V + gamma_s c_s (v_{s+1} - V(x_{s+1}))``.
``gamma_t`` is the per-step discount, so episode ends inside a fragment are handled through it:

- termination at step t (the episode really ended): ``discount_t = 0``.
- truncation at step t (time limit; the state is not terminal): the episode goes on in principle, so the
  target must bootstrap from ``V(true final observation of that episode)``, not from ``V(x_{t+1})``, which
  belongs to the next episode after the reset. The caller folds that bootstrap into the reward:
  ``reward_t := reward_t + gamma * V(final obs)`` and ``discount_t := 0`` (see ``fold_truncation_bootstrap``).
  The result is what V-trace does at the end of a fragment: the trace stops, and the last TD error
  bootstraps from the value of the state that followed.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import torch


class VTraceReturns(NamedTuple):
    vs: torch.Tensor  # [T, B] value targets v_s
    pg_advantages: torch.Tensor  # [T, B] advantages for the policy gradient


def _clip_above(x: torch.Tensor, threshold: Optional[float]) -> torch.Tensor:
    return x if threshold is None else torch.clamp(x, max=threshold)


@torch.no_grad()
def vtrace(
    log_rhos: torch.Tensor,
    discounts: torch.Tensor,
    rewards: torch.Tensor,
    values: torch.Tensor,
    bootstrap_value: torch.Tensor,
    clip_rho_threshold: Optional[float] = 1.0,
    clip_c_threshold: Optional[float] = 1.0,
    clip_pg_rho_threshold: Optional[float] = 1.0,
    lambda_: float = 1.0,
) -> VTraceReturns:
    """V-trace targets for one batch of fragments (no gradients flow through the result).

    Args:
        log_rhos: ``[T, B]`` log pi(a|x) - log mu(a|x) (target policy minus behaviour policy).
        discounts: ``[T, B]`` per-step discount: ``gamma * (1 - terminated_t)``, and 0 at truncated steps
            after ``fold_truncation_bootstrap``.
        rewards: ``[T, B]`` rewards (with truncation bootstraps folded in).
        values: ``[T, B]`` V(x_t) from the current critic.
        bootstrap_value: ``[B]`` V(x_T), the value of the observation after the fragment's last step.
        clip_rho_threshold: rho_bar, clips the importance weight inside delta_t V (None = no clipping).
        clip_c_threshold: c_bar, clips the trace coefficients c_i (None = no clipping).
        clip_pg_rho_threshold: clips the importance weight of the policy-gradient advantage (None = none).
        lambda_: trace-cutting factor of IMPALA's Remark 2, ``c_i = lambda * min(c_bar, rho_i)``: 1 is plain
            V-trace; below 1 trades bias for variance like GAE(lambda) (on-policy, ``vs - V`` is exactly the
            GAE(lambda) advantage).

    Returns:
        ``VTraceReturns(vs [T, B], pg_advantages [T, B])`` in the dtype of ``values``.
    """
    if log_rhos.dim() != 2:
        raise ValueError(f"log_rhos must be time-major [T, B], got shape {tuple(log_rhos.shape)}")
    for name, t in (("discounts", discounts), ("rewards", rewards), ("values", values)):
        if t.shape != log_rhos.shape:
            raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {tuple(log_rhos.shape)} like log_rhos")
    if bootstrap_value.shape != log_rhos.shape[1:]:
        raise ValueError(f"bootstrap_value has shape {tuple(bootstrap_value.shape)}, expected [{log_rhos.shape[1]}]")

    log_rhos, discounts, rewards, values, bootstrap_value = (
        t.detach() for t in (log_rhos, discounts, rewards, values, bootstrap_value))
    rhos = torch.exp(log_rhos)  # [T, B]
    clipped_rhos = _clip_above(rhos, clip_rho_threshold)  # [T, B]
    if not 0.0 <= lambda_ <= 1.0:
        raise ValueError(f"lambda_ must be in [0, 1], got {lambda_}")
    cs = lambda_ * _clip_above(rhos, clip_c_threshold)  # [T, B]

    values_next = torch.cat([values[1:], bootstrap_value.unsqueeze(0)], dim=0)  # [T, B] V(x_{t+1})
    deltas = clipped_rhos * (rewards + discounts * values_next - values)  # [T, B]

    # Backward recursion over time, vectorised over the B trajectories.
    vs_minus_v = torch.empty_like(values)  # [T, B]
    acc = torch.zeros_like(bootstrap_value)  # [B] v_{t+1} - V(x_{t+1}), zero past the end
    for t in range(values.shape[0] - 1, -1, -1):
        acc = deltas[t] + discounts[t] * cs[t] * acc
        vs_minus_v[t] = acc
    vs = vs_minus_v + values  # [T, B]

    vs_next = torch.cat([vs[1:], bootstrap_value.unsqueeze(0)], dim=0)  # [T, B] v_{t+1}
    pg_rhos = _clip_above(rhos, clip_pg_rho_threshold)  # [T, B]
    pg_advantages = pg_rhos * (rewards + discounts * vs_next - values)  # [T, B]
    return VTraceReturns(vs=vs, pg_advantages=pg_advantages)


def fold_truncation_bootstrap(
    rewards: torch.Tensor,
    discounts: torch.Tensor,
    truncated: torch.Tensor,
    final_values: torch.Tensor,
    gamma: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fold the bootstrap of time-limit truncations into rewards and discounts (returns new tensors).

    At a truncated step t: ``reward_t + gamma * V(final obs)`` and ``discount_t = 0``, so the target stops
    at the episode end but still counts the value of the state the drone was left in.

    Args:
        rewards: ``[T, B]`` raw rewards.
        discounts: ``[T, B]`` ``gamma * (1 - terminated)``. A step that is both terminated and truncated
            counts as terminated (no bootstrap), as in Gymnasium: it is recognised by its zero discount.
        truncated: ``[T, B]`` bool (or 0/1) truncation flags.
        final_values: ``[T, B]`` V(true final observation) from the current critic; only read where
            ``truncated`` (other entries may hold anything, NaN included).
        gamma: the discount factor.

    Returns:
        ``(rewards [T, B], discounts [T, B])``.
    """
    if not (rewards.shape == discounts.shape == truncated.shape == final_values.shape):
        raise ValueError(
            "rewards, discounts, truncated and final_values must share one [T, B] shape, got "
            f"{tuple(rewards.shape)}, {tuple(discounts.shape)}, {tuple(truncated.shape)}, {tuple(final_values.shape)}")
    bootstrap = truncated.bool() & (discounts != 0)  # [T, B] truncated and not terminated
    folded_rewards = torch.where(bootstrap, rewards + gamma * final_values.detach(), rewards)
    folded_discounts = torch.where(truncated.bool(), torch.zeros_like(discounts), discounts)
    return folded_rewards, folded_discounts
