"""K-Attention and DeepSets against per-sample numpy references (float64)."""
import numpy as np
import pytest
import torch

import encoders
from encoders.testing import random_obs
from quad_env.obs_layout import ObsLayout


def dense(params, prefix, x, layers=99):
    """The first ``layers`` Linear layers of an nn.Sequential (indices 0, 2, 4, ...), tanh after each."""
    i = 0
    while f"{prefix}.{i}.weight" in params and i < 2 * layers:
        x = np.tanh(params[f"{prefix}.{i}.weight"] @ x + params[f"{prefix}.{i}.bias"])
        i += 2
    return x


def inputs(layout, o):
    own = np.concatenate([o[f.start:f.stop] for f in layout.fields if f.group in ("self", "obstacle")])
    mask = o[layout.mask_start:layout.mask_start + layout.num_neighbors] > 0.5
    return own, layout.neighbors(o)[mask]  # only the real neighbours


def test_kattention_matches_numpy():
    layout = ObsLayout(4, obstacle_obs=True)
    torch.manual_seed(0)
    enc = encoders.make_encoder("kattention", layout, hidden=8, out_dim=12).double()
    P = {k: v.numpy() for k, v in enc.state_dict().items()}
    obs = random_obs(layout, 5, np.random.default_rng(0), num_real=[4, 2, 1, 0, 3])
    out = enc(torch.as_tensor(obs)).detach().numpy()
    for b in range(5):
        own, nb = inputs(layout, obs[b])
        self_h = dense(P, "net.self_mlp", own)
        neighborhood = np.zeros(8)
        if len(nb):
            e = np.stack([dense(P, "net.embed", np.concatenate([own, o_j])) for o_j in nb])
            h = np.stack([dense(P, "net.value", e_j) for e_j in e])
            e_mean = e.mean(0)
            # 2 tanh layers
            score_hidden = [dense(P, "net.score", np.concatenate([e_j, e_mean]), layers=2) for e_j in e]
            scores = np.array([P["net.score.4.weight"] @ sh + P["net.score.4.bias"] for sh in score_hidden])[:, 0]
            w = np.exp(scores - scores.max())
            neighborhood = (w / w.sum()) @ h
        expected = dense(P, "net.join", np.concatenate([self_h, neighborhood]))
        assert np.abs(out[b] - expected).max() < 1e-12


def test_deepsets_matches_numpy():
    layout = ObsLayout(3, "pos_vel")
    torch.manual_seed(0)
    enc = encoders.make_encoder("deepsets", layout, hidden=8, out_dim=12).double()
    P = {k: v.numpy() for k, v in enc.state_dict().items()}
    obs = random_obs(layout, 4, np.random.default_rng(1), num_real=[3, 2, 1, 0])
    out = enc(torch.as_tensor(obs)).detach().numpy()
    for b in range(4):
        own, nb = inputs(layout, obs[b])
        pooled = np.mean([dense(P, "neighbor_mlp", o_j) for o_j in nb], 0) if len(nb) else np.zeros(8)
        expected = dense(P, "join", np.concatenate([dense(P, "self_mlp", own), pooled]))
        assert np.abs(out[b] - expected).max() < 1e-12


def test_linear_of_concat_is_the_layer_on_the_concatenation():
    from encoders.kattention import _linear_of_concat

    torch.manual_seed(0)
    layer = torch.nn.Linear(3 + 5 + 2, 4).double()
    per_item, per_sample, other = (torch.randn(6, 7, 3, dtype=torch.float64), torch.randn(6, 5, dtype=torch.float64),
                                   torch.randn(6, 7, 2, dtype=torch.float64))
    for parts in ([per_item, per_sample, other], [per_sample, per_item, other]):
        ins = [p.clone().requires_grad_() for p in parts]
        tiled = [x if x.dim() == 3 else x.unsqueeze(1).expand(-1, 7, -1) for x in ins]
        expected = layer(torch.cat(tiled, -1))
        got = _linear_of_concat(layer, ins)
        assert got.shape == (6, 7, 4) and torch.allclose(got, expected, atol=1e-13, rtol=0)
        g = torch.randn(6, 7, 4, dtype=torch.float64)
        want = torch.autograd.grad(expected, ins + list(layer.parameters()), g)
        have = torch.autograd.grad(got, ins + list(layer.parameters()), g)
        for a, b in zip(have, want):
            assert torch.allclose(a, b, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="parts give 8 input features, the layer takes 10"):
        _linear_of_concat(layer, [per_item, per_sample])
