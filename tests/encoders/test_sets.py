"""Neighbour slots form a set: order, padding contents and swarm size do not matter."""
import numpy as np
import pytest
import torch

import encoders
from encoders.testing import TINY_OPTIONS, random_obs, random_swarm, swarm_observations
from quad_env.obs_layout import ObsLayout

SET_ENCODERS = [n for n in encoders.ENCODERS if n != "mlp"]  # weights independent of K


def tiny(name, layout):
    torch.manual_seed(0)
    return encoders.make_encoder(name, layout, **TINY_OPTIONS[name]).double()


def permute_neighbors(layout, obs, perm):
    out = obs.clone()
    K, F = layout.num_neighbors, layout.neighbor_dim
    nb = layout.neighbors(obs)[:, perm]
    out[:, layout.neighbor_start:layout.neighbor_start + K * F] = nb.reshape(obs.shape[0], K * F)
    out[:, layout.mask_start:layout.mask_start + K] = obs[:, layout.mask_start + perm]
    return out


@pytest.mark.parametrize("layout", [ObsLayout(5), ObsLayout(4, "pos_vel", True)], ids=repr)
@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_neighbor_permutation_invariance(name, layout):
    enc = tiny(name, layout)
    obs = torch.as_tensor(random_obs(layout, 16, np.random.default_rng(0)))
    out = enc(obs)
    K = layout.num_neighbors
    perms = [np.arange(K)[::-1].copy(), np.roll(np.arange(K), 1), np.array([2, 0, 3, 1] + list(range(4, K)))]
    for perm in map(torch.as_tensor, perms):
        assert (enc(permute_neighbors(layout, obs, perm)) - out).abs().max() < 1e-12


@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_padded_slots_are_ignored_even_if_nan(name):
    layout = ObsLayout(5)
    enc = tiny(name, layout)
    num_real = [0, 1, 2, 3, 4, 5] * 2
    clean = torch.as_tensor(random_obs(layout, 12, np.random.default_rng(1), num_real=num_real))
    garbage = torch.as_tensor(random_obs(layout, 12, np.random.default_rng(1), num_real=num_real, garbage=1e3))
    assert not torch.equal(clean, garbage)
    nb = layout.neighbors(garbage).clone()
    nb[0, 0, 0], nb[1, 3, 2], nb[2, 4, 5] = float("nan"), float("inf"), -float("inf")
    garbage[:, layout.neighbor_start:layout.mask_start] = nb.flatten(1)
    out = enc(clean)
    out_garbage = enc(garbage)
    assert torch.isfinite(out_garbage).all()
    assert torch.equal(out, out_garbage)
    out_garbage.square().sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in enc.parameters())
    # and the real neighbours do matter (so the comparison above is not vacuous)
    moved = clean.clone()
    moved[:, layout.neighbor_start] += 1.0  # neighbour 0's first field; real in rows with num_real >= 1
    changed = (enc(moved) - out).abs().amax(1) > 1e-6
    assert not changed[0] and changed[1:6].all()


@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_zero_neighbors(name):
    """A K = 0 layout works; with set encoders an all-masked K = 6 observation gives the same output."""
    empty, padded = ObsLayout(0), ObsLayout(6)
    enc0 = tiny(name, empty)
    own = torch.as_tensor(random_obs(empty, 8, np.random.default_rng(2)))
    out0 = enc0(own)
    assert out0.shape == (8, enc0.out_dim) and torch.isfinite(out0).all()
    obs = torch.as_tensor(random_obs(padded, 8, np.random.default_rng(3), num_real=0, garbage=5.0))
    obs[:, :padded.self_dim] = own
    enc6 = tiny(name, padded)
    out6 = enc6(obs)
    assert torch.isfinite(out6).all()
    if name in SET_ENCODERS:
        enc6.load_state_dict(enc0.state_dict())
        assert (enc6(obs) - out0).abs().max() < 1e-12


@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_swarm_size_independence(name):
    """One set of weights runs on observations of swarms of 2, 8 and 128 drones (1, 6 and 6 real
    neighbours of K = 6); for set encoders the padding is irrelevant: a 2-drone swarm gives the same
    output under a K = 1 layout with the same weights."""
    layout = ObsLayout(6)
    enc = tiny(name, layout)
    rng = np.random.default_rng(4)
    for n in (2, 8, 128):
        obs = torch.as_tensor(swarm_observations(layout, random_swarm(n, rng)))
        out = enc(obs)
        assert out.shape == (n, enc.out_dim) and torch.isfinite(out).all()
        assert (obs[:, layout.mask_start:] .sum(1) == min(n - 1, 6)).all()
    if name in SET_ENCODERS:
        small = ObsLayout(1)
        state = random_swarm(2, rng)
        enc_small = tiny(name, small)
        enc_small.load_state_dict(enc.state_dict())
        out6 = enc(torch.as_tensor(swarm_observations(layout, state)))
        out1 = enc_small(torch.as_tensor(swarm_observations(small, state)))
        assert (out6 - out1).abs().max() < 1e-12


@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_samples_are_independent_in_a_batch(name):
    """Each row's output depends on that row only (the reference K-Attention tiles the batch wrongly)."""
    layout = ObsLayout(4)
    enc = tiny(name, layout)
    obs = torch.as_tensor(random_obs(layout, 6, np.random.default_rng(5), num_real=[4, 3, 4, 2, 4, 1]))
    out = enc(obs)
    for b in range(6):
        assert (enc(obs[b:b + 1]) - out[b:b + 1]).abs().max() < 1e-12
