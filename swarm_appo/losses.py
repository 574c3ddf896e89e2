"""The APPO loss: PPO's clipped surrogate on V-trace advantages, a value loss to the V-trace targets and an
entropy bonus, all as masked means over the valid samples.

Inputs are flat ``[N]`` tensors (a minibatch of time steps). ``valid_mask`` drops samples from every term
and every statistic, e.g. steps whose policy lag exceeds ``max_policy_lag``. Masked samples may hold
anything (huge log-prob differences, NaN): they are replaced before any arithmetic, so neither the loss nor
its gradient can be poisoned by them. With no valid sample the loss is a zero that still has a graph.
"""
from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` over ``mask`` (bool, same shape); 0 when the mask is empty."""
    return torch.where(mask, x, torch.zeros_like(x)).sum() / mask.sum().clamp(min=1)


def explained_variance(pred: torch.Tensor, target: torch.Tensor, mask: Optional[torch.Tensor] = None) -> float:
    """1 - Var(target - pred) / Var(target) over the (masked) samples.

    1 is a perfect critic, 0 one no better than the mean of the targets, negative is worse.
    Returns 0.0 when it is undefined (fewer than 2 samples or targets without variance) so logs stay finite.
    """
    pred, target = pred.detach().double().flatten(), target.detach().double().flatten()
    if mask is not None:
        keep = mask.detach().bool().flatten()
        pred, target = pred[keep], target[keep]
    if target.numel() < 2:
        return 0.0
    var_target = target.var(unbiased=False)
    if var_target <= 1e-12:
        return 0.0
    return float(1.0 - (target - pred).var(unbiased=False) / var_target)


def appo_loss(
    new_log_prob: torch.Tensor,
    old_log_prob: torch.Tensor,
    advantages: torch.Tensor,
    values: torch.Tensor,
    value_targets: torch.Tensor,
    entropy: torch.Tensor,
    valid_mask: torch.Tensor,
    clip_ratio: float,
    value_coeff: float,
    entropy_coeff: float,
    old_values: Optional[torch.Tensor] = None,
    value_clip: Optional[float] = None,
    normalize_advantages: bool = False,
) -> Tuple[torch.Tensor, Dict[str, float]]:
    """APPO loss for one minibatch.

    total = policy_loss + value_coeff * value_loss - entropy_coeff * entropy, where (masked means)

    - policy_loss = -mean(min(ratio * A, clip(ratio, 1 - clip_ratio, 1 + clip_ratio) * A)),
      ratio = exp(new_log_prob - old_log_prob) against the behaviour policy;
    - value_loss = mean((values - value_targets)^2); with ``value_clip`` (and ``old_values``) the pessimistic
      max of that and ((old_values + clip(values - old_values, -value_clip, value_clip)) - value_targets)^2
      (an absolute clip range around the behaviour-time value, as in Sample Factory);
    - entropy = mean(entropy).

    Args:
        new_log_prob: ``[N]`` log pi(a|x) under the current policy (with gradient).
        old_log_prob: ``[N]`` log mu(a|x) under the behaviour policy.
        advantages: ``[N]`` V-trace policy-gradient advantages (no gradient).
        values: ``[N]`` V(x) from the current critic (with gradient).
        value_targets: ``[N]`` V-trace targets v_s (no gradient).
        entropy: ``[N]`` entropy of the current policy at x (with gradient).
        valid_mask: ``[N]`` bool or 0/1 float; False/0 drops the sample everywhere.
        clip_ratio: PPO's epsilon (> 0).
        value_coeff: weight of the value loss.
        entropy_coeff: weight of the entropy bonus.
        old_values: ``[N]`` critic values at behaviour time; needed when ``value_clip`` is set.
        value_clip: absolute clip range of the value update; None disables value clipping.
        normalize_advantages: standardise the advantages over the valid samples first.

    Returns:
        ``(total_loss, stats)``; stats are Python floats: ``policy_loss``, ``value_loss``, ``entropy``,
        ``approx_kl`` (the non-negative estimator mean((ratio - 1) - log ratio)), ``clip_fraction``
        (share of valid samples whose ratio is outside the clip range), ``explained_variance``,
        ``total_loss``, ``valid_fraction``.
    """
    n = new_log_prob.shape
    for name, t in (("old_log_prob", old_log_prob), ("advantages", advantages), ("values", values),
                    ("value_targets", value_targets), ("entropy", entropy), ("valid_mask", valid_mask)):
        if t.shape != n:
            raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {tuple(n)} like new_log_prob")
    if value_clip is not None and old_values is None:
        raise ValueError("value_clip needs old_values (the critic's values at behaviour time)")
    if old_values is not None and old_values.shape != n:
        raise ValueError(f"old_values has shape {tuple(old_values.shape)}, expected {tuple(n)}")

    mask = valid_mask.bool()  # [N]
    zeros = torch.zeros_like(new_log_prob)
    # Replace masked entries before arithmetic: exp() of a stale log-ratio can overflow, and 0 * inf = NaN
    # would otherwise leak into the gradient.
    log_ratio = torch.where(mask, new_log_prob - old_log_prob.detach(), zeros)  # [N]
    advantages = torch.where(mask, advantages.detach(), zeros)
    values = torch.where(mask, values, zeros)
    value_targets = torch.where(mask, value_targets.detach(), zeros)
    entropy = torch.where(mask, entropy, zeros)

    if normalize_advantages:
        mean = masked_mean(advantages, mask)
        var = masked_mean((advantages - mean) ** 2, mask)
        advantages = torch.where(mask, (advantages - mean) / (var.sqrt() + 1e-8), zeros)

    ratio = torch.exp(log_ratio)  # [N]
    surrogate = torch.min(ratio * advantages, torch.clamp(ratio, 1.0 - clip_ratio, 1.0 + clip_ratio) * advantages)
    policy_loss = -masked_mean(surrogate, mask)

    value_error = (values - value_targets) ** 2  # [N]
    if value_clip is not None:
        old_values = torch.where(mask, old_values.detach(), zeros)
        clipped_values = old_values + torch.clamp(values - old_values, -value_clip, value_clip)
        value_error = torch.max(value_error, (clipped_values - value_targets) ** 2)
    value_loss = masked_mean(value_error, mask)

    entropy_mean = masked_mean(entropy, mask)
    total_loss = policy_loss + value_coeff * value_loss - entropy_coeff * entropy_mean

    with torch.no_grad():
        approx_kl = masked_mean((ratio - 1.0) - log_ratio, mask)
        clipped = (ratio - 1.0).abs() > clip_ratio
        clip_fraction = masked_mean(clipped.to(ratio.dtype), mask)
        stats = {
            "policy_loss": float(policy_loss),
            "value_loss": float(value_loss),
            "entropy": float(entropy_mean),
            "approx_kl": float(approx_kl),
            "clip_fraction": float(clip_fraction),
            "explained_variance": explained_variance(values, value_targets, mask),
            "total_loss": float(total_loss),
            "valid_fraction": float(mask.float().mean()) if mask.numel() else 0.0,
        }
    return total_loss, stats
