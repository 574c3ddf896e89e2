"""Every parameter learns: gradients reach it, and a tiny supervised fit drops the loss 10x."""
import numpy as np
import pytest
import torch

import encoders
from encoders.testing import TINY_OPTIONS, random_obs
from quad_env.obs_layout import ObsLayout


@pytest.mark.parametrize("layout", [ObsLayout(4), ObsLayout(3, "pos_vel", True)], ids=repr)
@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_gradients_reach_every_parameter(name, layout):
    torch.manual_seed(0)
    enc = encoders.make_encoder(name, layout, **TINY_OPTIONS[name]).double()
    obs = torch.as_tensor(random_obs(layout, 16, np.random.default_rng(0)))
    weights = torch.randn(16, enc.out_dim, dtype=torch.float64)
    (enc(obs) * weights).sum().backward()
    for pname, p in enc.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), pname
        assert p.grad.abs().max() > 0, f"no gradient reaches {pname}"


def equivariant_target(layout, obs):
    """0.5 x (goal offset) + mean position of the real neighbours: a world vector needing the mask."""
    f = layout.split(obs)
    mask = f["mask"].unsqueeze(-1)
    mean_pos = (f["neighbor.rel_pos"] * mask).sum(1) / mask.sum(1).clamp(min=1.0)
    return 0.5 * f["self.rel_goal"] + mean_pos  # [B, 3]


@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_tiny_supervised_fit(name):
    layout = ObsLayout(4)
    torch.manual_seed(0)
    obs = torch.as_tensor(random_obs(layout, 64, np.random.default_rng(0)), dtype=torch.float32)
    target = equivariant_target(layout, obs)
    enc = encoders.make_encoder(name, layout, **TINY_OPTIONS[name])
    model = torch.nn.Sequential(enc, torch.nn.Linear(enc.out_dim, 3))
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(60):
        loss = (model(obs) - target).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])
