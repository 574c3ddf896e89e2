"""The fast Graphormer layer equals the paper's update rule written out pair by pair (float64 numpy)."""
import numpy as np
import pytest
import torch

import encoders
from encoders.graphormer import NODE_INPUTS, EquivariantGraphormerLayer, Graph, build_graph
from encoders.common import read_obs
from encoders.testing import TINY_OPTIONS, random_obs, random_rotation
from quad_env.obs_layout import ObsLayout


def layer_norm(x, weight, bias, eps=1e-5):
    return (x - x.mean()) / np.sqrt(x.var() + eps) * weight + bias


def reference_layer(layer, f, R, x, node_mask, edge_radius):
    """f_v <- phi_{g_v}[mu(f_v' + attn_v(phi_{g_v^-1}[F]))], returned in v's frame like the module.

    ``f`` [B, N, 4m] holds each node's features in its own frame; world-frame vectors are R_p V_p.
    """
    P = {k: v.detach().numpy() for k, v in layer.state_dict().items()}
    m, H, d = layer.m, layer.heads, layer.head_dim
    B, N, _ = f.shape
    out = np.zeros_like(f)
    for b in range(B):
        s = f[b, :, :m]
        V_world = [R[b, p] @ f[b, p, m:].reshape(3, m) for p in range(N)]
        for v in range(N):
            Rv, xv = R[b, v], x[b, v]
            neighbours = [p for p in range(N) if p == v or (node_mask[b, v] and node_mask[b, p] and (
                edge_radius is None or np.linalg.norm(x[b, p] - xv) <= edge_radius))]
            pairs = []
            for p in neighbours:  # node p seen from v's frame: phi_{g_v^-1}[(g_p, f_p)]
                vec = np.concatenate([(Rv.T @ (x[b, p] - xv))[:, None], Rv.T @ R[b, p], Rv.T @ V_world[p]], 1)
                pairs.append(np.concatenate([[np.linalg.norm(x[b, p] - xv)], s[p], vec.reshape(-1)]))
            pairs = np.array(pairs)  # [|N_v|, X]
            q = P["W_Q.weight"] @ f[b, v]
            keys = pairs @ P["W_K.weight"].T
            values = pairs @ P["W_V.weight"].T + P["W_V.bias"]
            attn = np.zeros(4 * m)
            for h in range(H):
                hs = slice(h * d, (h + 1) * d)
                logits = keys[:, hs] @ q[hs] / np.sqrt(d)
                alpha = np.exp(logits - logits.max())
                alpha /= alpha.sum()
                attn[hs] = alpha @ values[:, hs]
            u = layer_norm(f[b, v] + attn, P["norm_attn.weight"], P["norm_attn.bias"])
            hidden = np.maximum(P["ffn.0.weight"] @ u + P["ffn.0.bias"], 0.0)
            ffn = P["ffn.2.weight"] @ hidden + P["ffn.2.bias"]
            out[b, v] = layer_norm(u + ffn, P["norm_ffn.weight"], P["norm_ffn.bias"])
    return out


@pytest.mark.parametrize("heads,edge_radius", [(1, None), (2, None), (4, 1.2)])
def test_layer_matches_pairwise_reference(heads, edge_radius):
    torch.manual_seed(0)
    m, B, N = 4, 3, 5
    layer = EquivariantGraphormerLayer(m, heads, ffn_dim=12, act="relu").double()
    rng = np.random.default_rng(0)
    R = random_rotation(rng, (B, N))
    x = rng.standard_normal((B, N, 3))
    x[:, 0] = 0.0  # node 0 is drone i, the origin
    node_mask = np.ones((B, N), bool)
    node_mask[1, 3:] = False
    node_mask[2, 1:] = False
    f = rng.standard_normal((B, N, 4 * m))
    graph = Graph(torch.as_tensor(R), torch.as_tensor(x), torch.as_tensor(node_mask), edge_radius)
    fast = layer(torch.as_tensor(f), graph).detach().numpy()
    slow = reference_layer(layer, f, R, x, node_mask, edge_radius)
    assert np.abs(fast - slow).max() < 1e-10
    if edge_radius is not None:  # the radius really removed edges
        assert np.abs(reference_layer(layer, f, R, x, node_mask, None) - slow).max() > 1e-3


def layer_inputs(heads=2, m=2, B=2, N=4, seed=3):
    torch.manual_seed(seed)
    layer = EquivariantGraphormerLayer(m, heads, ffn_dim=6, act="relu").double()
    rng = np.random.default_rng(seed)
    R = random_rotation(rng, (B, N))
    x = rng.standard_normal((B, N, 3))
    x[:, 0] = 0.0
    node_mask = np.ones((B, N), bool)
    node_mask[1, 2:] = False
    graph = Graph(torch.as_tensor(R), torch.as_tensor(x), torch.as_tensor(node_mask), None)
    return layer, graph, rng.standard_normal((B, N, 4 * m)), (R, x, node_mask)


def test_layer_gradients_match_finite_differences():
    """The layer cuts its tensors with split and casts nothing in float64: autograd's gradients with respect
    to the features and to every weight agree with central differences."""
    layer, graph, f, _ = layer_inputs()
    f = torch.as_tensor(f).requires_grad_(True)
    params = tuple(layer.parameters())

    def fn(feat, *weights):
        named = dict(zip([k for k, _ in layer.named_parameters()], weights))
        return torch.func.functional_call(layer, named, (feat, graph))

    assert torch.autograd.gradcheck(fn, (f, *[p.detach().clone().requires_grad_(True) for p in params]),
                                    eps=1e-6, atol=1e-7, rtol=1e-5)


def test_layer_pair_work_runs_in_bf16_under_autocast_and_stays_near_the_reference():
    """Under bf16 autocast every batched product of the layer (frame rotations of features, pair products) reads
    bf16 operands, i.e. each is cast once rather than per product; the output stays within bf16 accuracy of
    the float64 pairwise reference, and the residual stream (LayerNorm output) stays float32."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class BmmDtypes(TorchDispatchMode):  # the operand dtypes of every bmm the layer runs
        def __init__(self):
            super().__init__()
            self.seen = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func is torch.ops.aten.bmm.default:
                self.seen.append(tuple(a.dtype for a in args))
            return func(*args, **(kwargs or {}))

    layer64, _, f, (R, x, node_mask) = layer_inputs(heads=1, m=4, B=3, N=5)
    layer = EquivariantGraphormerLayer(4, 1, ffn_dim=6, act="relu")
    layer.load_state_dict({k: v.float() for k, v in layer64.state_dict().items()})
    graph = Graph(torch.as_tensor(R).float(), torch.as_tensor(x).float(), torch.as_tensor(node_mask), None)
    with torch.autocast("cpu", dtype=torch.bfloat16), BmmDtypes() as mode:
        out = layer(torch.as_tensor(f).float(), graph)
    assert out.dtype == torch.float32
    assert len(mode.seen) >= 5  # rotations of f and of the keys, logits, values, rotation back
    assert all(d == (torch.bfloat16, torch.bfloat16) for d in mode.seen), mode.seen
    reference = reference_layer(layer64, f, R, x, node_mask, None)
    error = np.abs(out.detach().double().numpy() - reference).max()
    assert 1e-5 < error < 0.1, error  # bf16's rounding is visible, and small next to features of size ~1


def test_graph_nodes_from_layout():
    """Node 0 is drone i at the origin with R_i; node 1 + k is neighbour slot k with its own attitude;
    node inputs are velocity and goal offset in the node's own frame, body rates, is-self flag."""
    layout = ObsLayout(3)
    obs = torch.as_tensor(random_obs(layout, 2, np.random.default_rng(1), num_real=[3, 1]))
    fields = read_obs(layout, obs)
    graph, inputs = build_graph(layout, fields, edge_radius=None)
    assert inputs.shape == (2, 4, NODE_INPUTS)
    Ri = fields["self.rot"][0].reshape(3, 3).numpy()
    Rj = fields["neighbor.rot"][0, 1].reshape(3, 3).numpy()
    v_i, v_rel = fields["self.vel"][0].numpy(), fields["neighbor.rel_vel"][0, 1].numpy()
    assert np.allclose(graph.R[0, 2].numpy(), Rj) and np.allclose(graph.x[0, 0].numpy(), 0.0)
    assert np.allclose(graph.x[0, 2].numpy(), fields["neighbor.rel_pos"][0, 1].numpy())
    node_j = inputs[0, 2].numpy()
    assert np.allclose(node_j[0:6:2], Rj.T @ (v_i + v_rel))  # velocity (interleaved with goal offset)
    assert np.allclose(node_j[1:6:2], Rj.T @ fields["neighbor.goal_offset"][0, 1].numpy())
    assert np.allclose(node_j[6:9], fields["neighbor.omega"][0, 1].numpy()) and node_j[9] == 0.0
    node_i = inputs[0, 0].numpy()
    assert np.allclose(node_i[1:6:2], -Ri.T @ fields["self.rel_goal"][0].numpy()) and node_i[9] == 1.0
    assert graph.node_mask.tolist() == [[True] * 4, [True, True, False, False]]
    assert not graph.edges[1, 0, 2] and graph.edges[1, 2, 2] and graph.edges[0].all()


def test_encoder_readout_matches_reference():
    """zeta(canonical own state (+) mean_j R_i^T f_j^L), mapped back by R_i, from the module's own pieces."""
    layout = ObsLayout(3)
    torch.manual_seed(1)
    enc = encoders.make_encoder("se3_graphormer", layout, **TINY_OPTIONS["se3_graphormer"]).double()
    obs = torch.as_tensor(random_obs(layout, 4, np.random.default_rng(2), num_real=[3, 2, 1, 0]))
    f, graph, fields = enc.node_features(obs)
    m, n_vec = enc.m, enc.out_vectors
    out = enc(obs).detach().numpy()
    for b in range(4):
        Ri = fields["self.rot"][b].reshape(3, 3).numpy()
        real = [j for j in range(4) if graph.node_mask[b, j]]
        feats = [np.concatenate([f[b, j, :m].detach().numpy(),
                                 (Ri.T @ graph.R[b, j].numpy() @ f[b, j, m:].detach().numpy().reshape(3, m))
                                 .reshape(-1)]) for j in real]
        state = np.concatenate([Ri.T @ fields["self.rel_goal"][b].numpy(), Ri.T @ fields["self.vel"][b].numpy(),
                                np.eye(3).reshape(-1), fields["self.omega"][b].numpy()])
        h = enc.zeta_state(torch.as_tensor(state))
        z = enc.zeta_joint(torch.cat([h, torch.as_tensor(np.mean(feats, 0))])).detach().numpy()
        s = enc.out_dim - 3 * n_vec
        expected = np.concatenate([z[:s], (z[s:].reshape(n_vec, 3) @ Ri.T).reshape(-1)])
        assert np.abs(out[b] - expected).max() < 1e-12
