import math
import subprocess
import sys

import numpy as np
import pytest
import torch

import encoders
from encoders import ActorCritic
from encoders.testing import TINY_OPTIONS, random_obs
from quad_env.obs_layout import ObsLayout


def model_and_obs(name="deepsets", share=False, batch=8, **kw):
    layout = ObsLayout(3)
    torch.manual_seed(0)
    model = ActorCritic(layout, encoder=name, encoder_kwargs=TINY_OPTIONS[name], share_encoder=share, **kw)
    obs = torch.as_tensor(random_obs(layout, batch, np.random.default_rng(0)), dtype=torch.float32)
    return model.double(), obs.double()


@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_shapes(name):
    model, obs = model_and_obs(name)
    mean, log_std, value = model(obs)
    assert mean.shape == (8, 4) and log_std.shape == (4,) and value.shape == (8,)
    actions, log_prob, value2 = model.act(obs)
    assert actions.shape == (8, 4) and log_prob.shape == (8,) and torch.equal(value, value2)
    log_prob2, entropy, value3 = model.evaluate(obs, actions)
    assert log_prob2.shape == entropy.shape == value3.shape == (8,)
    assert torch.allclose(log_prob, log_prob2) and torch.equal(model.get_value(obs), value)
    mean_p, log_std_p = model.policy(obs)  # the actor alone gives the same distribution
    assert torch.equal(mean_p, mean) and torch.equal(log_std_p, log_std)


def test_log_prob_and_entropy_match_numpy():
    model, obs = model_and_obs(init_log_std=-0.3)
    with torch.no_grad():
        model.log_std.copy_(torch.tensor([-0.3, 0.1, -1.0, 0.5]))
    actions = torch.randn(8, 4, dtype=torch.float64)
    log_prob, entropy, _ = model.evaluate(obs, actions)
    mean = model(obs)[0].detach().numpy()
    std = np.exp([-0.3, 0.1, -1.0, 0.5])
    a = actions.numpy()
    expected = np.sum(-0.5 * ((a - mean) / std) ** 2 - np.log(std * math.sqrt(2 * math.pi)), axis=1)
    assert np.allclose(log_prob.detach().numpy(), expected, atol=1e-12)
    assert np.allclose(entropy.detach().numpy(), np.sum(0.5 * np.log(2 * math.pi * math.e * std ** 2)))


def test_sampling():
    model, obs = model_and_obs(batch=1, init_log_std=-0.5)
    det, log_prob_det, _ = model.act(obs, deterministic=True)
    assert torch.equal(det, model(obs)[0])
    assert torch.allclose(log_prob_det, -4 * (-0.5 + 0.5 * math.log(2 * math.pi)) * torch.ones(1, dtype=det.dtype))
    many = obs.expand(20000, -1)
    gen = torch.Generator().manual_seed(3)
    actions, _, _ = model.act(many, generator=gen)
    assert torch.allclose(actions.mean(0), det[0], atol=0.02)
    assert torch.allclose(actions.std(0), torch.full((4,), math.exp(-0.5), dtype=det.dtype), atol=0.02)
    again, _, _ = model.act(many, generator=torch.Generator().manual_seed(3))
    assert torch.equal(actions, again)  # same seed, same actions


def test_shared_encoder():
    separate, obs = model_and_obs("se3_kattention")
    shared, _ = model_and_obs("se3_kattention", share=True)
    enc_params = sum(p.numel() for p in shared.actor_encoder.parameters())
    n = lambda m: sum(p.numel() for p in m.parameters())
    assert n(separate) - n(shared) == enc_params
    assert shared.critic_encoder is None
    log_prob, _, value = shared.evaluate(obs, torch.zeros(8, 4, dtype=obs.dtype))
    (value.sum() + log_prob.sum()).backward()
    assert all(p.grad is not None for p in shared.parameters())


def test_separate_critic_does_not_touch_actor():
    model, obs = model_and_obs()
    model.get_value(obs).sum().backward()
    assert all(p.grad is None for p in model.actor_encoder.parameters())
    assert all(p.grad is None for p in model.actor_head.parameters())


def test_xavier_uniform_init():
    model, _ = model_and_obs("kattention")
    for name, m in model.named_modules():
        if isinstance(m, torch.nn.Linear):
            bound = math.sqrt(6.0 / (m.in_features + m.out_features))
            assert m.weight.abs().max() <= bound and m.weight.abs().max() > 0.8 * bound, name
            assert torch.all(m.bias == 0), name
    assert torch.all(model.log_std == 0)


def test_small_actor_output_init_starts_at_the_constant_mean_action():
    layout = ObsLayout(3)
    obs = torch.as_tensor(random_obs(layout, 64, np.random.default_rng(0)), dtype=torch.float32)
    torch.manual_seed(0)
    wide = ActorCritic(layout, encoder="deepsets", head_hidden=16, init_action_mean=0.053)
    torch.manual_seed(0)
    narrow = ActorCritic(layout, encoder="deepsets", head_hidden=16, init_action_mean=0.053,
                         init_actor_out_scale=0.01)
    np.testing.assert_allclose(narrow.actor_head[-1].weight.detach(), 0.01 * wide.actor_head[-1].weight.detach())
    with torch.no_grad():
        spread_wide = (wide.policy(obs)[0] - 0.053).abs().max().item()
        spread_narrow = (narrow.policy(obs)[0] - 0.053).abs().max().item()
    assert spread_narrow == pytest.approx(0.01 * spread_wide, rel=1e-4)  # the output is linear in that layer
    assert narrow.config["init_actor_out_scale"] == 0.01  # rebuilt identically from a checkpoint


def test_head_hidden_zero_gives_linear_heads():
    layout = ObsLayout(3)
    model = ActorCritic(layout, encoder="deepsets", head_hidden=0, init_action_mean=0.053)
    out_dim = model.actor_encoder.out_dim
    for head, width in ((model.actor_head, 4), (model.critic_head, 1)):
        assert [type(m) for m in head] == [torch.nn.Linear]
        assert (head[0].in_features, head[0].out_features) == (out_dim, width)
    obs = torch.as_tensor(random_obs(layout, 8, np.random.default_rng(0)), dtype=torch.float32)
    mean, _, value = model(obs)
    assert mean.shape == (8, 4) and value.shape == (8,)
    assert torch.all(model.actor_head[0].bias == 0.053)


def test_unknown_encoder_in_actor_critic():
    with pytest.raises(ValueError, match="deepsets"):
        ActorCritic(ObsLayout(), encoder="nope")
    with pytest.raises(TypeError, match="widht"):
        ActorCritic(ObsLayout(), encoder="mlp", encoder_kwargs={"widht": 3})


def test_param_count_command():
    out = subprocess.run([sys.executable, "-m", "encoders.param_count", "--num-neighbors", "2"],
                         capture_output=True, text=True, check=True).stdout
    layout = ObsLayout(2)
    for name in encoders.ENCODERS:
        row = next(line for line in out.splitlines() if line.startswith(name + " "))
        enc_params = sum(p.numel() for p in encoders.make_encoder(name, layout).parameters())
        ac_params = sum(p.numel() for p in ActorCritic(layout, encoder=name).parameters())
        assert f"{enc_params:,}" in row and f"{ac_params:,}" in row
