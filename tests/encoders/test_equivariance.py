"""SE(3) encoders transform by their declared representation; the baselines do not."""
import numpy as np
import pytest
import torch

import encoders
from encoders.frames import canonicalize, typed_to_world
from encoders.common import read_obs
from encoders.testing import (EQUIVARIANCE_TOLERANCE, TINY_OPTIONS, assert_equivariant, equivariance_error,
                              move_swarm, random_obs, random_rotation, random_swarm, swarm_observations)
from quad_env.obs_layout import ObsLayout

SE3 = [n for n in encoders.ENCODERS if n.startswith("se3_")]
BASELINES = [n for n in encoders.ENCODERS if not n.startswith("se3_")]
LAYOUTS = [ObsLayout(6), ObsLayout(3, "pos_vel"), ObsLayout(4, "full", obstacle_obs=True)]


def tiny(name, layout, **extra):
    torch.manual_seed(0)
    return encoders.make_encoder(name, layout, **{**TINY_OPTIONS[name], **extra}).double()


def batch(layout, n=12, seed=0, **kw):
    return torch.as_tensor(random_obs(layout, n, np.random.default_rng(seed), **kw))


def test_random_rotation_is_uniform_so3():
    Q = random_rotation(np.random.default_rng(1), (2000,))
    assert np.allclose(Q @ np.swapaxes(Q, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(Q), 1.0)
    assert np.abs(Q.mean(0)).max() < 0.05  # Haar measure: E[Q] = 0


def test_assert_equivariant_catches_a_non_equivariant_function():
    layout = ObsLayout(2)
    obs = batch(layout)
    goal = layout.field("rel_goal")
    as_vector = lambda o: o[:, goal.start:goal.stop]  # a world vector: equivariant as one 3-vector
    assert assert_equivariant(as_vector, obs, layout, (0, 1)) < 1e-14
    with pytest.raises(AssertionError, match="equivariance error"):
        assert_equivariant(as_vector, obs, layout, (3, 0))  # but not invariant
    first_x = lambda o: o[:, goal.start:goal.start + 1] * torch.ones(1, 3, dtype=o.dtype)
    with pytest.raises(AssertionError):
        assert_equivariant(first_x, obs, layout, (0, 1))
    assert EQUIVARIANCE_TOLERANCE[torch.float64] == 1e-9


def test_canonicalize_matches_numpy():
    layout = ObsLayout(2)
    obs = batch(layout, n=3, num_real=2)
    fields = read_obs(layout, obs)
    R = layout.as_matrix(fields["self.rot"])
    canon = canonicalize(layout, fields, R)
    o, Rn = obs.numpy(), R.numpy()

    def nb_field(b, k, name):
        f = layout.field(name, "neighbor")
        start = f.start - layout.neighbor_start
        return layout.neighbors(o)[b, k, start:start + f.size]

    goal = layout.field("rel_goal")
    for b in range(3):
        assert np.allclose(canon["self.rel_goal"][b].numpy(), Rn[b].T @ o[b, goal.start:goal.stop])
        assert np.allclose(canon["self.rot"][b].numpy().reshape(3, 3), np.eye(3))
        assert np.allclose(canon["neighbor.rel_pos"][b, 1].numpy(), Rn[b].T @ nb_field(b, 1, "rel_pos"))
        assert np.allclose(canon["neighbor.rot"][b, 1].numpy().reshape(3, 3),
                           Rn[b].T @ nb_field(b, 1, "rot").reshape(3, 3))
        assert np.allclose(canon["neighbor.omega"][b, 1].numpy(), nb_field(b, 1, "omega"))  # body: unchanged
    out = torch.arange(7.0, dtype=torch.float64).expand(3, 7)  # 1 scalar + 2 vectors
    back = typed_to_world(out, R, 2).numpy()
    assert np.allclose(back[:, 0], 0.0) and np.allclose(back[0, 4:7], Rn[0] @ np.array([4.0, 5.0, 6.0]))


def test_typed_to_world_against_numpy_per_row_and_broadcast_frames():
    """Scalars pass, every 3-vector of every row turns by its own frame: one frame per row (the batched product)
    and one frame shared along a leading axis (the broadcast path) against a float64 numpy reference."""
    rng = np.random.default_rng(3)
    S, V = 2, 3
    out = rng.normal(size=(4, 5, S + 3 * V))
    R = random_rotation(rng, (4, 5))
    for frames in (R, R[:, :1]):  # [4, 5, 3, 3] per row, [4, 1, 3, 3] shared along axis 1
        back = typed_to_world(torch.as_tensor(out), torch.as_tensor(frames), V).numpy()
        Rb = np.broadcast_to(frames, (4, 5, 3, 3))
        vectors = out[..., S:].reshape(4, 5, V, 3)
        expected = np.einsum("abij,abvj->abvi", Rb, vectors).reshape(4, 5, 3 * V)
        assert np.allclose(back[..., :S], out[..., :S], atol=0, rtol=0)
        assert np.allclose(back[..., S:], expected, atol=1e-12)
    assert not np.allclose(typed_to_world(torch.as_tensor(out), torch.as_tensor(R), V).numpy()[..., S:],
                           out[..., S:])  # the frames are not the identity: the check above can fail


@pytest.mark.parametrize("layout", LAYOUTS, ids=repr)
@pytest.mark.parametrize("name", SE3)
def test_se3_encoders_are_equivariant(name, layout):
    enc = tiny(name, layout)
    obs = batch(layout)
    error = assert_equivariant(enc, obs, layout, enc.equivariance)  # raises above 1e-9
    assert error < 1e-9
    # the vectors do rotate: the output is not merely invariant (else the check above would be vacuous)
    Q = torch.as_tensor(random_rotation(np.random.default_rng(5)))
    assert equivariance_error(enc, obs, layout, (enc.out_dim, 0), Q) > 1e-3


@pytest.mark.parametrize("name", SE3)
def test_se3_encoders_equivariant_with_edge_radius_and_heads(name):
    layout = ObsLayout(5)
    extra = {"edge_radius": 1.5, "num_heads": 2} if name == "se3_graphormer" else {}
    enc = tiny(name, layout, **extra)
    assert assert_equivariant(enc, batch(layout, seed=3), layout, enc.equivariance) < 1e-9


@pytest.mark.parametrize("name", SE3)
def test_moving_the_whole_swarm_moves_the_outputs(name):
    """End to end: rotate and translate the world, rebuild every drone's observation."""
    layout = ObsLayout(4)
    enc = tiny(name, layout)
    rng = np.random.default_rng(7)
    state = random_swarm(9, rng)
    Q, t = random_rotation(rng), 10.0 * rng.standard_normal(3)
    out = enc(torch.as_tensor(swarm_observations(layout, state)))
    moved = enc(torch.as_tensor(swarm_observations(layout, move_swarm(state, Q, t))))
    s, v = enc.equivariance
    expected = torch.cat([out[:, :s], (out[:, s:].reshape(-1, v, 3) @ torch.as_tensor(Q).T).flatten(1)], 1)
    assert (moved - expected).abs().max() < 1e-9


@pytest.mark.parametrize("name", BASELINES)
def test_baselines_are_not_equivariant(name):
    layout = ObsLayout(4)
    enc = tiny(name, layout)
    obs = batch(layout, num_real=3)
    Q = torch.as_tensor(random_rotation(np.random.default_rng(2)))
    assert equivariance_error(enc, obs, layout, (enc.out_dim, 0), Q) > 1e-2
    with pytest.raises(AssertionError):
        assert_equivariant(enc, obs, layout, (enc.out_dim, 0))


def test_policy_is_deliberately_not_equivariant():
    """h_p reads the equivariant features in world axes, so the action depends on the world's orientation."""
    layout = ObsLayout(3)
    torch.manual_seed(0)
    model = encoders.ActorCritic(layout, "se3_kattention", TINY_OPTIONS["se3_kattention"]).double()
    obs = batch(layout)
    Q = torch.as_tensor(random_rotation(np.random.default_rng(4)))
    mean, _, _ = model(obs)
    mean_moved, _, _ = model(layout.transform(obs, Q))
    assert (mean - mean_moved).abs().max() > 1e-3


@pytest.mark.parametrize("name", SE3)
def test_paper_sizes_equivariant_in_both_dtypes(name):
    layout = ObsLayout(6)
    torch.manual_seed(0)
    enc = encoders.make_encoder(name, layout)  # default (paper) sizes
    obs = batch(layout, n=8, seed=9)
    assert assert_equivariant(enc, obs.float(), layout, enc.equivariance, rotations=2) < 1e-4
    assert assert_equivariant(enc.double(), obs, layout, enc.equivariance, rotations=2) < 1e-9
