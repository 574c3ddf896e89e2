"""model.symmetry for every architecture: equivariant under its group (float64, 1e-9), and visibly not under a
transformation outside it, so that each check can fail."""
import numpy as np
import pytest
import torch

import encoders
from encoders.body_frame import FrameInput
from encoders.frames import yaw_frame
from encoders.testing import (TINY_OPTIONS, assert_equivariant, equivariance_error, random_group_element, random_obs,
                              random_rotation, random_tilt, rotation_about_z)
from quad_env.obs_layout import ObsLayout

LAYOUTS = [ObsLayout(5), ObsLayout(3, "pos_vel"), ObsLayout(4, "full", obstacle_obs=True)]
COMBINATIONS = [(arch, sym) for arch in encoders.ARCHITECTURES for sym in encoders.SYMMETRIES]


def tiny(arch, symmetry, layout):
    torch.manual_seed(0)
    options = dict(TINY_OPTIONS[arch])
    if symmetry != "none" and "graphormer" not in arch:
        options["out_vectors"] = 8
    return encoders.make_encoder(arch, layout, symmetry=symmetry, **options).double()


def batch(layout, n=12, seed=0):
    return torch.as_tensor(random_obs(layout, n, np.random.default_rng(seed)))


@pytest.mark.parametrize("layout", LAYOUTS, ids=repr)
@pytest.mark.parametrize("arch,symmetry", COMBINATIONS)
def test_equivariant_under_its_group_and_not_outside_it(arch, symmetry, layout):
    enc = tiny(arch, symmetry, layout)
    obs = batch(layout)
    rng = np.random.default_rng(3)
    if symmetry == "none":
        assert enc.equivariance is None
        # any rotation of the world changes the output, as an invariant and as a typed (all-vector) output
        Q = torch.as_tensor(random_rotation(rng))
        assert equivariance_error(enc, obs, layout, (enc.out_dim, 0), Q) > 1e-2
        if enc.out_dim % 3 == 0:
            assert equivariance_error(enc, obs, layout, (0, enc.out_dim // 3), Q) > 1e-2
        return
    rep = enc.equivariance
    assert assert_equivariant(enc, obs, layout, rep, group=symmetry) < 1e-9
    # the vectors really turn with the group (a merely invariant output would pass the check above vacuously)
    Q = torch.as_tensor(random_group_element(symmetry, rng))
    assert equivariance_error(enc, obs, layout, (enc.out_dim, 0), Q) > 1e-3
    if symmetry == "yaw":  # a tilt is outside the yaw group: gravity's direction is seen
        tilt = torch.as_tensor(random_tilt(rng))
        assert equivariance_error(enc, obs, layout, rep, tilt) > 1e-2


@pytest.mark.parametrize("alias", list(encoders.ALIASES))
def test_aliases_are_the_architecture_with_se3(alias):
    layout = ObsLayout(4)
    arch, symmetry = encoders.ALIASES[alias]
    assert symmetry == "se3" and alias == f"se3_{arch}"
    torch.manual_seed(0)
    a = encoders.make_encoder(alias, layout)
    torch.manual_seed(0)
    b = encoders.make_encoder(arch, layout, symmetry="se3")
    obs = batch(layout).float()
    assert torch.equal(a(obs), b(obs))


def test_yaw_frame_against_numpy():
    rng = np.random.default_rng(0)
    R = random_rotation(rng, (20,))
    F = yaw_frame(torch.as_tensor(R)).numpy()
    for r, f in zip(R, F):
        psi = np.arctan2(r[1, 0], r[0, 0])
        assert np.allclose(f, rotation_about_z(psi), atol=1e-12)
    # heading of a pure yaw attitude is the attitude itself; a global yaw Q moves F to Q F
    Rz = rotation_about_z(0.7)
    assert np.allclose(yaw_frame(torch.as_tensor(Rz)).numpy(), Rz, atol=1e-12)
    Q = rotation_about_z(-2.1)
    assert np.allclose(yaw_frame(torch.as_tensor(Q @ R)).numpy(), Q @ F, atol=1e-12)


@pytest.mark.parametrize("symmetry", ["se3", "yaw"])
def test_frame_input_against_numpy(symmetry):
    layout = ObsLayout(2)
    obs = random_obs(layout, 4, np.random.default_rng(1), num_real=[2, 1, 0, 2])
    got = FrameInput(layout, symmetry).double()(torch.as_tensor(obs)).numpy()
    for b in range(4):
        R = obs[b, 6:15].reshape(3, 3)
        F = R if symmetry == "se3" else rotation_about_z(np.arctan2(R[1, 0], R[0, 0]))
        assert np.allclose(got[b, 0:3], F.T @ obs[b, 0:3]) and np.allclose(got[b, 3:6], F.T @ obs[b, 3:6])
        assert np.allclose(got[b, 6:15].reshape(3, 3), F.T @ R)
        assert np.allclose(got[b, 15:18], obs[b, 15:18])  # body rates unchanged
        s = layout.neighbor_start + layout.neighbor_dim  # neighbour 1
        assert np.allclose(got[b, s:s + 3], F.T @ obs[b, s:s + 3])
        assert np.allclose(got[b, s + 6:s + 15].reshape(3, 3), F.T @ obs[b, s + 6:s + 15].reshape(3, 3))
        assert np.allclose(got[b, layout.mask_start:], obs[b, layout.mask_start:])


def test_body_frame_obs_is_refused_with_a_symmetry():
    with pytest.raises(ValueError, match="body_frame_obs.*'yaw'"):
        encoders.ActorCritic(ObsLayout(2), "deepsets", symmetry="yaw", body_frame_obs=True)
    with pytest.raises(ValueError, match="body_frame_obs.*'se3'"):
        encoders.ActorCritic(ObsLayout(2), "se3_graphormer", body_frame_obs=True)


@pytest.mark.parametrize("symmetry", ["se3", "yaw"])
def test_actor_critic_with_symmetry_trains_and_is_not_equivariant_as_a_whole(symmetry):
    """The head reads the typed features in world axes: the policy itself sees gravity."""
    layout = ObsLayout(3)
    torch.manual_seed(0)
    model = encoders.ActorCritic(layout, "deepsets", symmetry=symmetry, size="small").double()
    assert model.config["symmetry"] == symmetry and model.config["size"] == "small"
    obs = batch(layout)
    Q = torch.as_tensor(random_group_element(symmetry, np.random.default_rng(4)))
    mean, _, value = model(obs)
    mean_moved, _, _ = model(layout.transform(obs, Q))
    assert (mean - mean_moved).abs().max() > 1e-4
    value.sum().backward()
    assert all(p.grad is not None for p in model.critic_encoder.parameters())


@pytest.mark.parametrize("symmetry", ["se3", "yaw"])
def test_actor_and_critic_share_one_frame_map_and_compute_the_same(symmetry):
    """Separate actor and critic encoders map the observation into drone i's frame once per step, not twice,
    and the outputs and gradients equal those of each encoder mapping it itself."""
    layout = ObsLayout(3)
    torch.manual_seed(0)
    model = encoders.ActorCritic(layout, "deepsets", symmetry=symmetry, size="small").double()
    calls = []
    for enc in (model.actor_encoder, model.critic_encoder):
        enc.to_local.register_forward_hook(lambda *_: calls.append(1))
    obs = batch(layout)

    def outputs_and_grads():
        model.zero_grad()
        mean, _, value = model(obs)
        (mean.sum() + value.sum()).backward()
        return [mean.detach(), value.detach()] + [p.grad.clone() for p in model.parameters() if p.grad is not None]

    assert model.one_frame_map
    shared = outputs_and_grads()
    assert len(calls) == 1  # one map for both
    model.one_frame_map = False  # each encoder maps the observation itself
    separate = outputs_and_grads()
    assert len(calls) == 3
    assert len(shared) == len(separate) and all(torch.equal(a, b) for a, b in zip(shared, separate))
    assert not encoders.ActorCritic(layout, "deepsets", symmetry="none", size="small").one_frame_map
    assert not encoders.ActorCritic(layout, "deepsets", symmetry=symmetry, share_encoder=True).one_frame_map


def test_checkpoints_from_before_the_symmetry_option_load():
    """se3_kattention weights were saved at <encoder>.net.* before the canonicalization became a wrapper."""
    layout = ObsLayout(3)
    torch.manual_seed(0)
    model = encoders.ActorCritic(layout, "se3_kattention", TINY_OPTIONS["se3_kattention"]).double()
    old = {k.replace(".inner.net.", ".net."): v.clone() for k, v in model.state_dict().items()}
    assert any(".net." in k and ".inner." not in k for k in old)
    torch.manual_seed(1)
    fresh = encoders.ActorCritic(layout, "se3_kattention", TINY_OPTIONS["se3_kattention"]).double()
    fresh.load_state_dict(old)
    obs = batch(layout)
    assert torch.equal(fresh(obs)[0], model(obs)[0])
