"""APPO loss on a tiny batch whose numbers are worked out by hand below."""
import math

import numpy as np
import pytest
import torch

from swarm_appo.losses import appo_loss, explained_variance

CLIP, VALUE_COEFF, ENTROPY_COEFF = 0.2, 0.5, 0.01


def tiny_batch():
    """Four samples. ratio = exp(new - old) = [1, e^0.3 = 1.3499, e^-0.4 = 0.6703, 1]."""
    return dict(
        new_log_prob=torch.tensor([0.0, 0.3, -0.4, 0.1], dtype=torch.float64, requires_grad=True),
        old_log_prob=torch.tensor([0.0, 0.0, 0.0, 0.1], dtype=torch.float64),
        advantages=torch.tensor([1.0, 2.0, -1.0, 0.5], dtype=torch.float64),
        values=torch.tensor([0.5, 1.0, -0.5, 2.0], dtype=torch.float64, requires_grad=True),
        value_targets=torch.tensor([1.0, 0.0, 0.0, 2.0], dtype=torch.float64),
        entropy=torch.tensor([1.0, 1.2, 0.8, 1.0], dtype=torch.float64, requires_grad=True),
    )


def call(batch, mask, **kw):
    args = dict(clip_ratio=CLIP, value_coeff=VALUE_COEFF, entropy_coeff=ENTROPY_COEFF)
    args.update(kw)
    return appo_loss(**batch, valid_mask=mask, **args)


# Surrogates min(r A, clip(r) A): s0 1*1 = 1; s1 min(1.3499*2, 1.2*2) = 2.4; s2 min(-0.6703, 0.8*-1) = -0.8;
# s3 1*0.5 = 0.5.
HAND_POLICY_LOSS = -(1.0 + 2.4 - 0.8 + 0.5) / 4  # -0.775
HAND_VALUE_LOSS = (0.25 + 1.0 + 0.25 + 0.0) / 4  # squared errors of values vs targets: 0.375
HAND_ENTROPY = (1.0 + 1.2 + 0.8 + 1.0) / 4  # 1.0
HAND_TOTAL = HAND_POLICY_LOSS + VALUE_COEFF * HAND_VALUE_LOSS - ENTROPY_COEFF * HAND_ENTROPY  # -0.5975
# Targets [1, 0, 0, 2]: mean 0.75, variance 2.75 / 4; residuals [0.5, -1, 0.5, 0]: variance 1.5 / 4.
HAND_EXPLAINED_VARIANCE = 1.0 - (1.5 / 4) / (2.75 / 4)  # 5 / 11


def test_hand_computed_loss_and_stats():
    batch = tiny_batch()
    total, stats = call(batch, torch.ones(4, dtype=torch.bool))
    assert total.item() == pytest.approx(HAND_TOTAL, abs=1e-12)
    assert stats["total_loss"] == pytest.approx(HAND_TOTAL, abs=1e-12)
    assert stats["policy_loss"] == pytest.approx(HAND_POLICY_LOSS, abs=1e-12)
    assert stats["value_loss"] == pytest.approx(HAND_VALUE_LOSS, abs=1e-12)
    assert stats["entropy"] == pytest.approx(HAND_ENTROPY, abs=1e-12)
    assert stats["clip_fraction"] == pytest.approx(0.5)  # samples 1 and 2 leave [0.8, 1.2]
    kl = ((math.exp(0.3) - 1 - 0.3) + (math.exp(-0.4) - 1 + 0.4)) / 4
    assert stats["approx_kl"] == pytest.approx(kl, abs=1e-12)
    assert stats["explained_variance"] == pytest.approx(HAND_EXPLAINED_VARIANCE, abs=1e-12)
    assert stats["valid_fraction"] == 1.0
    assert all(isinstance(v, float) for v in stats.values())


def test_hand_computed_gradients():
    batch = tiny_batch()
    total, _ = call(batch, torch.ones(4))
    total.backward()
    # Only unclipped samples carry a policy gradient: d(-r A / 4)/d log pi = -r A / 4 with r = 1.
    np.testing.assert_allclose(batch["new_log_prob"].grad.numpy(), [-0.25, 0.0, 0.0, -0.125], atol=1e-12)
    # value_coeff * d(mean (v - t)^2)/dv = 0.5 * 2 (v - t) / 4.
    np.testing.assert_allclose(batch["values"].grad.numpy(), [-0.125, 0.25, -0.125, 0.0], atol=1e-12)
    np.testing.assert_allclose(batch["entropy"].grad.numpy(), [-ENTROPY_COEFF / 4] * 4, atol=1e-12)


def test_value_clipping_takes_the_pessimistic_error():
    batch = tiny_batch()
    old_values = torch.tensor([2.0, 1.0, -0.5, 2.0], dtype=torch.float64)
    total, stats = call(batch, torch.ones(4, dtype=torch.bool), old_values=old_values, value_clip=0.2)
    # s0: v 0.5 moved 1.5 from old 2.0 -> clipped 1.8, error (1.8 - 1)^2 = 0.64 > 0.25. Others unchanged.
    assert stats["value_loss"] == pytest.approx((0.64 + 1.0 + 0.25 + 0.0) / 4, abs=1e-12)
    total.backward()
    # The clipped branch is constant in v, so sample 0 gets no value gradient.
    np.testing.assert_allclose(batch["values"].grad.numpy(), [0.0, 0.25, -0.125, 0.0], atol=1e-12)
    with pytest.raises(ValueError, match="old_values"):
        call(tiny_batch(), torch.ones(4), value_clip=0.2)


def test_advantage_normalisation_matches_numpy():
    batch = tiny_batch()
    _, stats = call(batch, torch.ones(4, dtype=torch.bool), normalize_advantages=True)
    adv = np.array([1.0, 2.0, -1.0, 0.5])
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    ratio = np.exp([0.0, 0.3, -0.4, 0.0])
    expected = -np.mean(np.minimum(ratio * adv, np.clip(ratio, 1 - CLIP, 1 + CLIP) * adv))
    assert stats["policy_loss"] == pytest.approx(expected, abs=1e-9)


def with_garbage_sample(batch):
    """Append a fifth sample full of values that would poison an unmasked mean."""
    extra = dict(new_log_prob=400.0, old_log_prob=-400.0, advantages=float("nan"), values=float("inf"),
                 value_targets=1e30, entropy=float("nan"))
    out = {}
    for key, t in batch.items():
        data = torch.cat([t.detach(), torch.tensor([extra[key]], dtype=t.dtype)])
        out[key] = data.requires_grad_(t.requires_grad)
    return out


@pytest.mark.parametrize("normalize", [False, True])
def test_masked_samples_change_nothing(normalize):
    ref_total, ref_stats = call(tiny_batch(), torch.ones(4, dtype=torch.bool), normalize_advantages=normalize)
    batch = with_garbage_sample(tiny_batch())
    for mask in (torch.tensor([1, 1, 1, 1, 0], dtype=torch.bool), torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0])):
        b = {k: v.detach().clone().requires_grad_(v.requires_grad) for k, v in batch.items()}
        total, stats = call(b, mask, normalize_advantages=normalize)
        assert total.item() == pytest.approx(ref_total.item(), abs=1e-12)
        for key in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction", "explained_variance"):
            assert stats[key] == pytest.approx(ref_stats[key], abs=1e-12), key
        assert stats["valid_fraction"] == pytest.approx(0.8)
        total.backward()
        for key in ("new_log_prob", "values", "entropy"):
            grad = b[key].grad
            assert torch.isfinite(grad).all(), key
            assert grad[4].item() == 0.0, key


def test_masking_a_real_sample_removes_it():
    batch = tiny_batch()
    _, stats = call(batch, torch.tensor([True, False, True, True]))
    assert stats["policy_loss"] == pytest.approx(-(1.0 - 0.8 + 0.5) / 3, abs=1e-12)
    assert stats["value_loss"] == pytest.approx((0.25 + 0.25 + 0.0) / 3, abs=1e-12)
    assert stats["clip_fraction"] == pytest.approx(1 / 3)


def test_all_masked_is_a_finite_zero():
    batch = with_garbage_sample(tiny_batch())
    total, stats = call(batch, torch.zeros(5), old_values=torch.zeros(5, dtype=torch.float64), value_clip=0.2,
                        normalize_advantages=True)
    assert total.item() == 0.0
    total.backward()
    for key in ("new_log_prob", "values", "entropy"):
        assert torch.equal(batch[key].grad, torch.zeros(5, dtype=torch.float64)), key
    assert all(math.isfinite(v) for v in stats.values())
    assert stats["valid_fraction"] == 0.0


def test_explained_variance_cases():
    t = torch.tensor([1.0, 0.0, 0.0, 2.0])
    assert explained_variance(t, t) == pytest.approx(1.0)
    assert explained_variance(torch.full((4,), 0.75), t) == pytest.approx(0.0, abs=1e-12)
    assert explained_variance(torch.tensor([0.5, 1.0, -0.5, 2.0]), t) == pytest.approx(5 / 11)
    assert explained_variance(-t, t) < 0
    assert explained_variance(torch.zeros(3), torch.ones(3)) == 0.0  # undefined: constant target
    assert explained_variance(t, t, torch.tensor([True, False, False, False])) == 0.0  # one sample


def test_shape_mismatch_is_an_error():
    batch = tiny_batch()
    batch["advantages"] = torch.zeros(3, dtype=torch.float64)
    with pytest.raises(ValueError, match="advantages"):
        call(batch, torch.ones(4))
