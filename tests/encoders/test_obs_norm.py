import numpy as np
import pytest
import torch

from encoders import ActorCritic, make_encoder
from encoders.obs_norm import FieldScaleNorm
from encoders.testing import TINY_OPTIONS, assert_equivariant, random_obs
from quad_env.obs_layout import ObsLayout


def numpy_mean_sq_norms(layout, obs):
    """E||v||^2 per scaled field, from scratch in float64 numpy (neighbour fields over real slots only)."""
    K, F = layout.num_neighbors, layout.neighbor_dim
    real = obs[:, layout.mask_start:layout.mask_start + K] > 0.5
    out = {}
    for f in layout.fields:
        if f.kind not in ("world_vector", "body", "scalar"):
            continue
        if f.group == "neighbor":
            sq = [np.sum(obs[:, f.start + k * F:f.stop + k * F] ** 2, axis=1)[real[:, k]] for k in range(K)]
            out[f"neighbor.{f.name}"] = np.concatenate(sq).mean()
        else:
            out[f"{f.group}.{f.name}"] = np.sum(obs[:, f.start:f.stop] ** 2, axis=1).mean()
    return out


def scaled_obs(layout, batch, rng):
    """Observations whose fields have clearly different magnitudes."""
    obs = random_obs(layout, batch, rng)
    for i, f in enumerate(layout.fields):
        if f.kind in ("world_vector", "body", "scalar"):
            copies = layout.num_neighbors if f.group == "neighbor" else 1
            for k in range(copies):
                off = k * layout.neighbor_dim if f.group == "neighbor" else 0
                obs[:, f.start + off:f.stop + off] *= 0.5 + 3.0 * i
    return obs


def test_statistics_match_numpy_over_several_batches():
    layout = ObsLayout(3, obstacle_obs=True)
    rng = np.random.default_rng(1)
    batches = [scaled_obs(layout, n, rng) for n in (17, 5, 40)]
    norm = FieldScaleNorm(layout)
    for b in batches:
        norm.update(torch.as_tensor(b))
    expected = numpy_mean_sq_norms(layout, np.concatenate(batches))
    assert norm.field_names == list(expected)
    assert np.allclose(norm.mean_sq_norm.numpy(), list(expected.values()), rtol=1e-12)
    # forward: scaled fields divided by their RMS norm, rotations and mask unchanged
    obs = batches[0]
    out = norm(torch.as_tensor(obs)).numpy()
    scale = {k: 1.0 / np.sqrt(v) for k, v in expected.items()}
    for f in layout.fields:
        copies = layout.num_neighbors if f.group == "neighbor" else 1
        for k in range(copies):
            off = k * layout.neighbor_dim if f.group == "neighbor" else 0
            s = slice(f.start + off, f.stop + off)
            factor = scale.get(f"{f.group}.{f.name}" if f.group != "mask" else "mask", 1.0)
            assert np.allclose(out[:, s], obs[:, s] * factor, rtol=1e-12), f.name


def test_unseen_fields_keep_scale_one_and_tiny_fields_are_floored():
    layout = ObsLayout(2)
    norm = FieldScaleNorm(layout, min_rms=1e-3)
    obs = torch.as_tensor(random_obs(layout, 4, np.random.default_rng(0)))
    assert torch.equal(norm(obs), obs)  # no statistics yet: identity
    no_neighbors = obs.clone()
    no_neighbors[:, layout.mask_start:layout.mask_start + 2] = 0.0
    no_neighbors[:, layout.field("rel_goal").start:layout.field("rel_goal").stop] = 1e-6
    norm.update(no_neighbors)
    scales = dict(zip(norm.field_names, norm.field_scales().tolist()))
    assert scales["neighbor.rel_pos"] == 1.0  # no real neighbour seen
    assert scales["self.rel_goal"] == pytest.approx(1e3)  # RMS 1.7e-6 floored at 1e-3


@pytest.mark.parametrize("name", ["se3_kattention", "se3_graphormer"])
def test_equivariance_survives_normalisation(name):
    layout = ObsLayout(3)
    rng = np.random.default_rng(2)
    torch.manual_seed(0)
    norm = FieldScaleNorm(layout).double()
    norm.update(torch.as_tensor(scaled_obs(layout, 64, rng)))
    assert not torch.allclose(norm.field_scales(), torch.ones(len(norm.fields), dtype=torch.float64))
    encoder = make_encoder(name, layout, **TINY_OPTIONS[name]).double()
    obs = torch.as_tensor(scaled_obs(layout, 8, rng))
    assert_equivariant(lambda o: encoder(norm(o)), obs, layout, encoder.equivariance)


def test_statistics_travel_in_the_state_dict_and_forward_does_not_move_them():
    layout = ObsLayout(2)
    torch.manual_seed(0)
    model = ActorCritic(layout, encoder="deepsets", encoder_kwargs=TINY_OPTIONS["deepsets"], normalize_obs=True)
    obs = torch.as_tensor(scaled_obs(layout, 32, np.random.default_rng(3)), dtype=torch.float32)
    model.obs_norm.update(obs)
    before = model.obs_norm.mean_sq_norm.clone()
    model(obs)
    model.get_value(obs)
    assert torch.equal(model.obs_norm.mean_sq_norm, before)
    state = model.state_dict()
    assert {"obs_norm.count", "obs_norm.mean_sq_norm"} <= set(state)
    copy = ActorCritic(layout, encoder="deepsets", encoder_kwargs=TINY_OPTIONS["deepsets"], normalize_obs=True)
    copy.load_state_dict(state)
    assert torch.equal(copy.obs_norm.mean_sq_norm, before)
    for a, b in zip(copy(obs), model(obs)):
        assert torch.equal(a, b)


def test_initial_action_mean_is_the_actor_bias():
    layout = ObsLayout(2)
    model = ActorCritic(layout, encoder="deepsets", encoder_kwargs=TINY_OPTIONS["deepsets"], init_action_mean=0.053)
    assert torch.equal(model.actor_head[-1].bias, torch.full((4,), 0.053))
    model_zero = ActorCritic(layout, encoder="deepsets", encoder_kwargs=TINY_OPTIONS["deepsets"])
    assert torch.equal(model_zero.actor_head[-1].bias, torch.zeros(4))
