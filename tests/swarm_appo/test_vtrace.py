"""V-trace against an independent float64 double-sum implementation of the IMPALA formula."""
import math

import numpy as np
import pytest
import torch

from swarm_appo.vtrace import fold_truncation_bootstrap, vtrace


def reference_vtrace(log_rhos, discounts, rewards, values, bootstrap, rho_bar, c_bar, pg_bar):
    """IMPALA eq. (1) written as the explicit double sum, float64, one trajectory column at a time.

    v_s = V(x_s) + sum_{t=s}^{T-1} (prod_{i=s}^{t-1} gamma_i c_i) delta_t V
    """
    T, B = log_rhos.shape
    clip = (lambda x, bar: x if bar is None else min(bar, x))
    vs = np.zeros((T, B))
    adv = np.zeros((T, B))
    for b in range(B):
        rho = [math.exp(x) for x in log_rhos[:, b]]
        v_ext = list(values[:, b]) + [bootstrap[b]]  # V(x_0) .. V(x_T)
        delta = [clip(rho[t], rho_bar) * (rewards[t, b] + discounts[t, b] * v_ext[t + 1] - v_ext[t]) for t in range(T)]
        for s in range(T):
            total = v_ext[s]
            for t in range(s, T):
                weight = 1.0
                for i in range(s, t):
                    weight *= discounts[i, b] * clip(rho[i], c_bar)
                total += weight * delta[t]
            vs[s, b] = total
        vs_ext = list(vs[:, b]) + [bootstrap[b]]
        for s in range(T):
            adv[s, b] = clip(rho[s], pg_bar) * (rewards[s, b] + discounts[s, b] * vs_ext[s + 1] - v_ext[s])
    return vs, adv


def random_batch(rng, T=9, B=6, rho_scale=1.0, p_done=0.15, gamma=0.9):
    log_rhos = rng.normal(0.0, rho_scale, size=(T, B))
    discounts = gamma * (rng.random((T, B)) > p_done)
    rewards = rng.normal(size=(T, B))
    values = rng.normal(size=(T, B))
    bootstrap = rng.normal(size=B)
    return log_rhos, discounts, rewards, values, bootstrap


def run_torch(batch, dtype=torch.float64, **clips):
    out = vtrace(*(torch.tensor(x, dtype=dtype) for x in batch), **clips)
    return out.vs.double().numpy(), out.pg_advantages.double().numpy()


@pytest.mark.parametrize("clips", [
    dict(clip_rho_threshold=1.0, clip_c_threshold=1.0, clip_pg_rho_threshold=1.0),
    dict(clip_rho_threshold=2.0, clip_c_threshold=0.5, clip_pg_rho_threshold=1.5),
    dict(clip_rho_threshold=None, clip_c_threshold=None, clip_pg_rho_threshold=None),
])
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_double_sum_reference(clips, seed):
    batch = random_batch(np.random.default_rng(seed), rho_scale=1.0)
    vs, adv = run_torch(batch, **clips)
    ref_vs, ref_adv = reference_vtrace(*batch, clips["clip_rho_threshold"], clips["clip_c_threshold"],
                                       clips["clip_pg_rho_threshold"])
    np.testing.assert_allclose(vs, ref_vs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(adv, ref_adv, rtol=1e-10, atol=1e-10)


def test_float32_close_to_float64_reference():
    batch = random_batch(np.random.default_rng(3), T=32, B=4, rho_scale=0.3, gamma=0.99)
    vs, adv = run_torch(batch, dtype=torch.float32)
    ref_vs, ref_adv = reference_vtrace(*batch, 1.0, 1.0, 1.0)
    np.testing.assert_allclose(vs, ref_vs, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(adv, ref_adv, rtol=1e-4, atol=1e-4)


def test_on_policy_gives_discounted_n_step_returns():
    rng = np.random.default_rng(4)
    T, B, gamma = 7, 3, 0.95
    rewards, values, bootstrap = rng.normal(size=(T, B)), rng.normal(size=(T, B)), rng.normal(size=B)
    vs, adv = run_torch((np.zeros((T, B)), np.full((T, B), gamma), rewards, values, bootstrap))
    for s in range(T):
        n_step = sum(gamma ** (t - s) * rewards[t] for t in range(s, T)) + gamma ** (T - s) * bootstrap
        np.testing.assert_allclose(vs[s], n_step, rtol=1e-12)
    # With rho = 1 the advantage is the one-step TD error towards the next target.
    vs_next = np.concatenate([vs[1:], bootstrap[None]])
    np.testing.assert_allclose(adv, rewards + gamma * vs_next - values, rtol=1e-12)


def test_rho_clipping_caps_large_weights_and_ignores_small_ones():
    rng = np.random.default_rng(5)
    T, B, gamma = 6, 4, 0.9
    rewards, values, bootstrap = rng.normal(size=(T, B)), rng.normal(size=(T, B)), rng.normal(size=B)
    discounts = np.full((T, B), gamma)
    on_policy = run_torch((np.zeros((T, B)), discounts, rewards, values, bootstrap))
    # Every rho = e^2 > 1: clipping at 1 makes all weights 1, i.e. the on-policy result.
    clipped = run_torch((np.full((T, B), 2.0), discounts, rewards, values, bootstrap))
    np.testing.assert_allclose(clipped[0], on_policy[0], rtol=1e-12)
    np.testing.assert_allclose(clipped[1], on_policy[1], rtol=1e-12)
    # Without clipping the same weights change the targets.
    unclipped = run_torch((np.full((T, B), 2.0), discounts, rewards, values, bootstrap),
                          clip_rho_threshold=None, clip_c_threshold=None, clip_pg_rho_threshold=None)
    assert np.abs(unclipped[0] - on_policy[0]).max() > 1e-3
    # Every rho < 1: a threshold of 1 has no effect.
    small = (np.full((T, B), -0.5), discounts, rewards, values, bootstrap)
    a, b = run_torch(small), run_torch(small, clip_rho_threshold=None, clip_c_threshold=None,
                                       clip_pg_rho_threshold=None)
    np.testing.assert_allclose(a[0], b[0], rtol=1e-12)
    np.testing.assert_allclose(a[1], b[1], rtol=1e-12)


def test_pg_clip_affects_only_advantages():
    batch = random_batch(np.random.default_rng(6), rho_scale=1.5)
    vs_a, adv_a = run_torch(batch, clip_pg_rho_threshold=0.5)
    vs_b, adv_b = run_torch(batch, clip_pg_rho_threshold=5.0)
    np.testing.assert_allclose(vs_a, vs_b, rtol=1e-12)
    assert np.abs(adv_a - adv_b).max() > 1e-3


def test_termination_mid_fragment_cuts_the_trace():
    rng = np.random.default_rng(7)
    T, B, gamma, k = 8, 2, 0.9, 3
    rewards, values, bootstrap = rng.normal(size=(T, B)), rng.normal(size=(T, B)), rng.normal(size=B)
    discounts = np.full((T, B), gamma)
    discounts[k, 0] = 0.0  # drone 0 terminates after step k
    log_rhos = rng.normal(0, 0.5, size=(T, B))
    vs, adv = run_torch((log_rhos, discounts, rewards, values, bootstrap))
    # Perturb everything after the terminal step of column 0: its earlier targets must not move.
    rewards2, values2, bootstrap2 = rewards.copy(), values.copy(), bootstrap.copy()
    rewards2[k + 1:, 0] += 10.0
    values2[k + 1:, 0] -= 10.0
    bootstrap2[0] += 10.0
    vs2, adv2 = run_torch((log_rhos, discounts, rewards2, values2, bootstrap2))
    np.testing.assert_allclose(vs2[:k + 1, 0], vs[:k + 1, 0], rtol=1e-12)
    np.testing.assert_allclose(adv2[:k + 1, 0], adv[:k + 1, 0], rtol=1e-12)
    assert np.abs(vs2[k + 1:, 0] - vs[k + 1:, 0]).min() > 1e-3  # the new episode did change
    # On-policy, the terminal step's target is its reward.
    on = run_torch((np.zeros((T, B)), discounts, rewards, values, bootstrap))
    np.testing.assert_allclose(on[0][k, 0], rewards[k, 0], rtol=1e-12)


def test_truncation_bootstraps_from_true_final_observation():
    rng = np.random.default_rng(8)
    T, B, gamma, k = 6, 2, 0.9, 2
    rewards, values, bootstrap = rng.normal(size=(T, B)), rng.normal(size=(T, B)), rng.normal(size=B)
    discounts = np.full((T, B), gamma)
    truncated = np.zeros((T, B), dtype=bool)
    truncated[k, 0] = True
    final_values = np.full((T, B), np.nan)  # only read at truncated steps
    final_values[k, 0] = 3.0  # V(true last obs of the episode)
    t = lambda x: torch.tensor(x, dtype=torch.float64)
    r2, d2 = fold_truncation_bootstrap(t(rewards), t(discounts), torch.tensor(truncated), t(final_values), gamma)
    assert torch.isfinite(r2).all()
    vs = vtrace(torch.zeros(T, B, dtype=torch.float64), d2, r2, t(values), t(bootstrap)).vs.numpy()
    # On-policy targets before the truncation: n-step returns ending in gamma * V(final obs) ...
    for s in range(k + 1):
        expected = sum(gamma ** (j - s) * rewards[j, 0] for j in range(s, k + 1)) + gamma ** (k + 1 - s) * 3.0
        np.testing.assert_allclose(vs[s, 0], expected, rtol=1e-12)
    # ... and never the value of the reset observation that follows (values[k + 1]).
    values_moved = values.copy()
    values_moved[k + 1, 0] += 100.0
    vs_moved = vtrace(torch.zeros(T, B, dtype=torch.float64), d2, r2, t(values_moved), t(bootstrap)).vs.numpy()
    np.testing.assert_allclose(vs_moved[:k + 1, 0], vs[:k + 1, 0], rtol=1e-12)
    # The untouched column equals the plain computation.
    plain = vtrace(torch.zeros(T, B, dtype=torch.float64), t(discounts), t(rewards), t(values), t(bootstrap)).vs
    np.testing.assert_allclose(vs[:, 1], plain[:, 1].numpy(), rtol=1e-12)


def test_truncated_and_terminated_step_does_not_bootstrap():
    gamma = 0.9
    rewards = torch.tensor([[1.0], [2.0]], dtype=torch.float64)
    discounts = torch.tensor([[gamma], [0.0]], dtype=torch.float64)  # step 1 terminated
    truncated = torch.tensor([[False], [True]])
    final_values = torch.tensor([[0.0], [5.0]], dtype=torch.float64)
    r2, d2 = fold_truncation_bootstrap(rewards, discounts, truncated, final_values, gamma)
    np.testing.assert_array_equal(r2.numpy(), [[1.0], [2.0]])
    np.testing.assert_array_equal(d2.numpy(), [[gamma], [0.0]])
    truncated_only = torch.tensor([[gamma], [gamma]], dtype=torch.float64)
    r3, d3 = fold_truncation_bootstrap(rewards, truncated_only, truncated, final_values, gamma)
    np.testing.assert_allclose(r3.numpy(), [[1.0], [2.0 + gamma * 5.0]])
    np.testing.assert_array_equal(d3.numpy(), [[gamma], [0.0]])


def test_no_gradient_flows_through_targets():
    values = torch.randn(4, 3, requires_grad=True)
    out = vtrace(torch.zeros(4, 3), torch.full((4, 3), 0.9), torch.randn(4, 3), values, torch.randn(3))
    assert not out.vs.requires_grad and not out.pg_advantages.requires_grad
    assert out.vs.shape == (4, 3) and out.pg_advantages.shape == (4, 3)


def test_shape_errors_name_the_argument():
    z = torch.zeros(4, 3)
    with pytest.raises(ValueError, match="rewards"):
        vtrace(z, z, torch.zeros(4, 2), z, torch.zeros(3))
    with pytest.raises(ValueError, match="bootstrap_value"):
        vtrace(z, z, z, z, torch.zeros(4))
    with pytest.raises(ValueError, match="time-major"):
        vtrace(torch.zeros(12), z, z, z, torch.zeros(3))


def test_lambda_on_policy_gives_gae_returns():
    """On-policy, V-trace with lambda is GAE(lambda): vs - V equals the GAE advantage (forward-view sum)."""
    rng = np.random.default_rng(5)
    T, B, gamma, lam = 8, 4, 0.9, 0.7
    discounts = gamma * (rng.random((T, B)) > 0.2)  # episode ends inside the fragment
    rewards, values, bootstrap = rng.normal(size=(T, B)), rng.normal(size=(T, B)), rng.normal(size=B)
    vs, _ = run_torch((np.zeros((T, B)), discounts, rewards, values, bootstrap), lambda_=lam)
    v_ext = np.concatenate([values, bootstrap[None]])
    deltas = rewards + discounts * v_ext[1:] - values
    for s in range(T):
        gae = np.zeros(B)
        weight = np.ones(B)
        for t in range(s, T):
            gae += weight * deltas[t]
            weight = weight * discounts[t] * lam
        np.testing.assert_allclose(vs[s] - values[s], gae, rtol=1e-12, atol=1e-12)
    # lambda = 0 is TD(0): one-step targets
    vs0, _ = run_torch((np.zeros((T, B)), discounts, rewards, values, bootstrap), lambda_=0.0)
    np.testing.assert_allclose(vs0, rewards + discounts * v_ext[1:], rtol=1e-12)
    with pytest.raises(ValueError, match="lambda_"):
        run_torch((np.zeros((T, B)), discounts, rewards, values, bootstrap), lambda_=1.5)
