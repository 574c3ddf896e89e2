"""runner.precision: bf16 mixed precision agrees with fp32 on a fixed batch, keeps fp32 where it must, and
"auto" follows the hardware and the model size."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from encoders import ActorCritic
from encoders.body_frame import FrameInput
from encoders.testing import random_obs
from quad_env import ObsLayout
from swarm_appo import precision as prec
from swarm_appo.checkpoint import load_checkpoint
from swarm_appo.config import ConfigError, load_config
from swarm_appo.learner import Learner
from swarm_appo.model import model_factory
from swarm_appo.rollout import RolloutWorker
from swarm_appo.trainer import train

from .test_training import fixed_fragments, tiny_config

CPU = torch.device("cpu")

# Stated tolerances of bf16 (8 mantissa bits, relative rounding 2^-9 = 0.2 %) against fp32 on one batch:
# (measured on the tiny batch below: loss within 0.8-1.5 %, cosine 0.9997, norms within 0.8 %)
LOSS_RTOL = 0.05  # |loss_bf16 - loss_fp32| <= 5 % of |loss_fp32| + 1e-4
GRAD_COSINE = 0.995  # cosine similarity of the flattened gradients
GRAD_NORM_RTOL = 0.05  # relative difference of the gradient norms


# ----------------------------------------------------------------------------------------- resolving "auto"
@pytest.mark.parametrize("flags, size, device, expected", [
    ({"amx_bf16", "avx512_bf16"}, "paper", CPU, "bf16"),
    ({"avx512_bf16"}, "paper", CPU, "bf16"),
    ({"amx_bf16"}, "small", CPU, "fp32"),  # narrow layers: bf16 does not pay on a CPU
    ({"avx2", "avx512f"}, "paper", CPU, "fp32"),  # no native bf16
    (set(), "paper", CPU, "fp32"),
])
def test_auto_follows_the_cpu_flags_and_the_model_size(monkeypatch, flags, size, device, expected):
    monkeypatch.setattr(prec, "cpu_flags", lambda: frozenset(flags))
    chosen, why = prec.resolve_precision("auto", device, size)
    assert chosen == expected
    assert why.startswith("auto:")


@pytest.mark.parametrize("supports", [True, False])
def test_auto_is_fp32_on_cuda_where_the_learner_is_launch_bound(monkeypatch, supports):
    # measured on an H200 (RESULTS.md, gpu_check): bf16 0.79x fp32 at the paper's batch, 1.20x at 16384
    monkeypatch.setattr(prec, "native_bf16", lambda device: (supports, f"GPU {'supports' if supports else 'lacks'}"))
    chosen, why = prec.resolve_precision("auto", torch.device("cuda"), "paper")
    assert chosen == "fp32"
    assert why.startswith("auto: GPU")
    assert ("launch-bound" in why) == supports
    assert prec.resolve_precision("bf16", torch.device("cuda"), "paper")[0] == "bf16"


def test_explicit_precision_is_kept_and_unknown_ones_are_refused():
    assert prec.resolve_precision("fp32", CPU, "paper")[0] == "fp32"
    assert prec.resolve_precision("bf16", CPU, "small")[0] == "bf16"
    with pytest.raises(ValueError, match="fp16"):
        prec.resolve_precision("fp16", CPU)
    with pytest.raises(ValueError, match="resolved"):
        prec.autocast("auto", CPU)


@pytest.mark.parametrize("key", ["runner.precision", "runner.inference_precision"])
def test_config_names_the_precision_key(key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(None, [f"{key}=half"])


# ----------------------------------------------------------------------------------------- fp32 where it must be
def test_frame_maps_stay_float32_under_bf16_autocast():
    """Canonicalization is exact under autocast: the same bits as without it, and float32."""
    layout = ObsLayout(num_neighbors=3)
    obs = torch.as_tensor(random_obs(layout, 64, np.random.default_rng(0)), dtype=torch.float32)
    frame = FrameInput(layout, "se3")
    plain = frame(obs)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        cast = frame(obs)
        bare_matmul = obs[:, :9].reshape(-1, 3, 3) @ obs[:, 9:18].reshape(-1, 3, 3)
    assert bare_matmul.dtype == torch.bfloat16  # what an unguarded rotation would do
    assert cast.dtype == torch.float32
    torch.testing.assert_close(cast, plain, rtol=0, atol=0)


@pytest.mark.parametrize("encoder, symmetry", [("deepsets", "none"), ("kattention", "se3"), ("graphormer", "se3")])
def test_model_outputs_are_float32_under_bf16(encoder, symmetry):
    layout = ObsLayout(num_neighbors=3)
    torch.manual_seed(0)
    model = ActorCritic(layout, encoder=encoder, symmetry=symmetry, size="small")
    obs = torch.as_tensor(random_obs(layout, 32, np.random.default_rng(1)), dtype=torch.float32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mean, log_std, value = model(obs)
        log_prob, entropy, value2 = model.evaluate(obs, torch.zeros(32, 4))
    for t in (mean, log_std, value, log_prob, entropy, value2):
        assert t.dtype == torch.float32
    fp32_mean = model(obs)[0]
    # bf16 matmuls: close to fp32, yet not the same computation
    torch.testing.assert_close(mean, fp32_mean, rtol=0.05, atol=0.02)
    assert not torch.equal(mean, fp32_mean)


# ----------------------------------------------------------------------------------------- learner agreement
@pytest.mark.parametrize("encoder", ["deepsets", "se3_kattention", "se3_graphormer"])
def test_bf16_loss_and_gradients_agree_with_fp32_on_a_fixed_batch(tmp_path, encoder):
    cfg = tiny_config(tmp_path, "p", **{"model.encoder": encoder, "model.size": "small",
                                        "model.body_frame_obs": "false"})
    fragments = fixed_fragments(cfg)
    layout = cfg.env.obs_layout()
    grads, losses = {}, {}
    for precision in ("fp32", "bf16"):
        torch.manual_seed(0)
        learner = Learner(model_factory(layout, cfg.model)(), cfg.algo, CPU, seed=0, precision=precision)
        t, _, valid = learner._to_tensors(fragments)
        cols = torch.arange(t["rewards"].shape[1])
        loss, _ = learner._loss(t, cols, valid, t["final_idx"])
        assert loss.dtype == torch.float32
        learner.model.zero_grad()
        loss.backward()
        params = list(learner.model.parameters())
        assert all(p.dtype == torch.float32 and p.grad is None or p.grad.dtype == torch.float32 for p in params)
        grads[precision] = torch.cat([p.grad.flatten() for p in params if p.grad is not None])
        losses[precision] = float(loss.detach())
    assert abs(losses["bf16"] - losses["fp32"]) <= LOSS_RTOL * abs(losses["fp32"]) + 1e-4, losses
    g32, g16 = grads["fp32"], grads["bf16"]
    cosine = float(torch.dot(g32, g16) / (g32.norm() * g16.norm()))
    assert cosine >= GRAD_COSINE, cosine
    assert abs(float(g16.norm() / g32.norm()) - 1) <= GRAD_NORM_RTOL


def test_bf16_worker_log_probs_match_the_fp32_learner_at_lag_zero(tmp_path):
    """A bf16 rollout worker's behaviour log-probs are those the fp32 learner computes, to bf16 accuracy:
    the importance ratios of fresh data stay near 1."""
    cfg = tiny_config(tmp_path, "w", **{"model.encoder": "se3_kattention", "model.size": "small",
                                        "model.body_frame_obs": "false"})
    layout = cfg.env.obs_layout()
    make = model_factory(layout, cfg.model)
    torch.manual_seed(0)
    weights = make().state_dict()
    worker = RolloutWorker(cfg.env, make, 2, 16, seed=3, precision="bf16")
    assert worker.precision == "bf16"
    worker.set_weights(0, weights)
    frag = worker.collect()
    model = make()
    model.load_state_dict(weights)
    T, B, D = frag["obs"].shape
    with torch.no_grad():
        log_prob, _, _ = model.evaluate(torch.from_numpy(frag["obs"]).reshape(T * B, D),
                                        torch.from_numpy(frag["actions"]).reshape(T * B, -1))
    ratio = torch.exp(log_prob - torch.from_numpy(frag["log_probs"]).reshape(-1))
    assert float((ratio - 1).abs().max()) < 0.05  # PPO clips at 0.2
    assert float((ratio - 1).abs().max()) > 0  # really computed in bf16


def test_a_bf16_run_trains_fp32_weights_and_says_so(tmp_path):
    cfg = tiny_config(tmp_path, "bf", **{"runner.precision": "bf16", "runner.inference_precision": "bf16"})
    result = train(cfg)
    header = (result.run_dir / "config.yaml").read_text().splitlines()[:3]
    assert any("learner precision bf16 (set by runner.precision)" in line for line in header), header
    state = load_checkpoint(result.checkpoint)
    dtypes = {v.dtype for v in state["learner"]["model"].values() if v.is_floating_point()}
    assert dtypes <= {torch.float32, torch.float64}, dtypes  # fp32 weights (fp64 observation statistics)
    moments = [s["exp_avg"] for s in state["learner"]["optimizer"]["state"].values()]
    assert moments and all(m.dtype == torch.float32 for m in moments)
    assert result.agent_steps >= cfg.runner.total_agent_steps
