"""BodyFrameInput against a per-sample float64 numpy reference, and its invariance to a global rotation."""
import numpy as np
import torch

from encoders import ActorCritic
from encoders.body_frame import BodyFrameInput
from encoders.testing import random_obs
from quad_env.obs_layout import ObsLayout


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def reference(layout, obs):
    """Loop over samples and fields: world vectors R^T v, non-own rotations R^T M, the rest copied."""
    out = obs.copy()
    for b in range(obs.shape[0]):
        R = obs[b, layout.field("rot").start:layout.field("rot").stop].reshape(3, 3)
        blocks = [(0, f) for f in layout.fields if f.group in ("self", "obstacle")]
        blocks += [(k * layout.neighbor_dim, f) for k in range(layout.num_neighbors)
                   for f in layout.fields if f.group == "neighbor"]
        for off, f in blocks:
            s = slice(f.start + off, f.stop + off)
            if f.kind == "world_vector":
                out[b, s] = R.T @ obs[b, s]
            elif f.kind == "rotation" and not (f.group == "self" and f.name == "rot"):
                out[b, s] = (R.T @ obs[b, s].reshape(3, 3)).reshape(9)
    return out


def test_matches_the_numpy_reference_for_both_neighbour_layouts():
    rng = np.random.default_rng(0)
    for layout in (ObsLayout(3, "full"), ObsLayout(4, "pos_vel"), ObsLayout(0)):
        obs = random_obs(layout, 32, rng)
        got = BodyFrameInput(layout).double()(torch.as_tensor(obs, dtype=torch.float64)).numpy()
        np.testing.assert_allclose(got, reference(layout, obs), rtol=0, atol=1e-12)
        rel_goal = layout.field("rel_goal")
        assert not np.allclose(got[:, rel_goal.start:rel_goal.stop], obs[:, rel_goal.start:rel_goal.stop])


def test_body_frame_vectors_are_invariant_to_a_global_rotation():
    layout = ObsLayout(3, "full")
    rng = np.random.default_rng(1)
    obs = random_obs(layout, 16, rng, num_real=[3] * 16)
    Q = random_rotation(rng)
    moved = layout.transform(obs, Q)
    f = BodyFrameInput(layout).double()
    a = f(torch.as_tensor(obs, dtype=torch.float64)).numpy()
    b = f(torch.as_tensor(moved, dtype=torch.float64)).numpy()
    rot = layout.field("rot")
    keep = np.ones(layout.dim, bool)
    keep[rot.start:rot.stop] = False  # the own rotation is kept (it carries "up"), so it moves with Q
    np.testing.assert_allclose(a[:, keep], b[:, keep], rtol=0, atol=1e-10)
    assert not np.allclose(a[:, rot.start:rot.stop], b[:, rot.start:rot.stop])


def test_actor_critic_option_feeds_body_frame_inputs():
    layout = ObsLayout(2)
    obs = torch.as_tensor(random_obs(layout, 8, np.random.default_rng(2)), dtype=torch.float32)
    torch.manual_seed(0)
    plain = ActorCritic(layout, encoder="deepsets", head_hidden=16)
    torch.manual_seed(0)
    body = ActorCritic(layout, encoder="deepsets", head_hidden=16, body_frame_obs=True)
    with torch.no_grad():
        expected = plain.policy(BodyFrameInput(layout)(obs))[0]
        np.testing.assert_allclose(body.policy(obs)[0], expected, rtol=1e-6, atol=1e-6)
    assert body.config["body_frame_obs"] is True
