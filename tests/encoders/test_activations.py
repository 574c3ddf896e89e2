"""encoders.common.Tanh: the fp32 path for low-precision CPU tensors must be torch.tanh, bit for bit."""
import numpy as np
import pytest
import torch

from encoders.common import Tanh, _TanhViaFloat32, activation, mlp


def _inputs(shape, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (3.0 * torch.randn(*shape, generator=g)).to(dtype)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
@pytest.mark.parametrize("shape", [(0, 4), (7,), (3, 5, 11), (2, _TanhViaFloat32.CHUNK // 2 + 5)])
def test_low_precision_tanh_matches_torch_bitwise(dtype, shape):
    # shapes: empty, 1-D, 3-D, and one spanning several chunks with a partial last one
    x = _inputs(shape, dtype).requires_grad_()
    grad_out = _inputs(shape, dtype, seed=1)
    ours = Tanh()(x)
    ref = torch.tanh(x)
    assert ours.dtype == dtype and ours.shape == ref.shape
    assert torch.equal(ours, ref)
    (g_ours,) = torch.autograd.grad(ours, x, grad_out)
    (g_ref,) = torch.autograd.grad(ref, x, grad_out)
    assert torch.equal(g_ours, g_ref)


def test_low_precision_tanh_takes_the_fp32_path_and_agrees_with_float64():
    x64 = np.linspace(-6.0, 6.0, 4001)
    x = torch.from_numpy(x64).to(torch.bfloat16)
    y = Tanh()(x)
    x_req = x.clone().requires_grad_()
    assert "TanhViaFloat32" in type(Tanh()(x_req).grad_fn).__name__
    # the bf16 result is tanh of the bf16 input rounded once: within half a bf16 ulp (2^-9 relative)
    exact = np.tanh(x.double().numpy())
    err = np.abs(y.double().numpy() - exact)
    assert np.all(err <= np.abs(exact) * 2.0 ** -8 + 1e-30)


def test_non_contiguous_input():
    x = _inputs((40, 30), torch.bfloat16).t()  # a transposed view
    assert not x.is_contiguous()
    assert torch.equal(Tanh()(x), torch.tanh(x))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_full_precision_runs_torch_tanh(dtype):
    x = _inputs((5, 9), dtype).requires_grad_()
    y = Tanh()(x)
    assert "TanhBackward" in type(y.grad_fn).__name__  # torch.tanh's own node: export and tracing see aten::tanh
    assert torch.equal(y, torch.tanh(x))


def test_registry_and_mlp_use_it_under_autocast():
    assert isinstance(activation("tanh"), Tanh)
    net = mlp([6, 16, 4], "tanh", last_act=False)
    x = _inputs((32, 6), torch.float32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = net(x)
        h = net[0](x)
        ref = net[2](torch.tanh(h))
    assert out.dtype == torch.bfloat16
    assert torch.equal(out, ref)


def test_torch_compile_sees_plain_tanh():
    # under torch.compile the chunk loop would be unrolled per shape: the module hands the op to the compiler
    graphs = []

    def backend(gm, example_inputs):
        graphs.append(gm)
        return gm.forward

    fn = torch.compile(Tanh(), backend=backend, fullgraph=True)
    x = _inputs((3, 7), torch.bfloat16)
    assert torch.equal(fn(x), torch.tanh(x))
    ops = [n.target for g in graphs for n in g.graph.nodes if n.op == "call_function"]
    assert torch.tanh in ops and len(ops) == 1
