"""benchmarks.bf16_tanh: the native variant really runs torch's tanh modules, and nothing else changes."""
import pytest
import torch
from torch import nn

from benchmarks.bf16_tanh import main, with_native_tanh
from encoders.common import Tanh
from swarm_appo.config import load_config
from swarm_appo.model import model_factory


def test_with_native_tanh_swaps_every_tanh_and_keeps_the_function():
    cfg = load_config(None, ["model.encoder=kattention", "model.size=small"])
    torch.manual_seed(0)
    model = model_factory(cfg.env.obs_layout(), cfg.model)()
    ours = sum(isinstance(m, Tanh) for m in model.modules())
    assert ours > 0
    obs = torch.randn(16, cfg.env.obs_layout().dim)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        before = model.policy(obs)[0]
    keys = set(model.state_dict())
    assert with_native_tanh(model) == ours
    assert not any(isinstance(m, Tanh) for m in model.modules())
    assert sum(type(m) is nn.Tanh for m in model.modules()) == ours
    assert set(model.state_dict()) == keys  # parameter-free swap: the same weights
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.equal(model.policy(obs)[0], before)  # bit-identical: only the tanh kernel differs


def test_rounds_must_be_positive():
    with pytest.raises(SystemExit, match="--rounds"):
        main(["--rounds", "0", "--no-append"])


def test_unknown_encoder_is_a_config_error_before_anything_runs(capsys):
    with pytest.raises(SystemExit, match="config error: .*model.encoder.*deepsets"):
        main(["--encoders", "deepsetz", "--no-append"])
    assert capsys.readouterr().out == ""  # nothing was timed or printed
