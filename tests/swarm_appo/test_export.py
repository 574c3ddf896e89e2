"""The exported actor (TorchScript, ONNX through onnxruntime) acts as the PyTorch policy: every encoder, a
batch size other than the traced one, swarms smaller and larger than the K neighbour slots."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from encoders import ENCODERS, ActorCritic
from encoders.testing import TINY_OPTIONS, random_obs
from quad_env import EnvConfig, ObsLayout, VecQuadEnv
from swarm_appo import export
from swarm_appo.testing import untrained_checkpoint

K = 3


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


def tiny_model(encoder: str, seed: int = 0, **kwargs) -> ActorCritic:
    layout = ObsLayout(K, "full")
    torch.manual_seed(seed)
    model = ActorCritic(layout, encoder, TINY_OPTIONS[encoder], head_hidden=16, normalize_obs=True, **kwargs)
    obs = random_obs(layout, 64, np.random.default_rng(seed))
    model.obs_norm.update(torch.as_tensor(obs * np.linspace(0.5, 4.0, layout.dim)))  # scales other than 1
    return model.eval()


def policy_actions(model: ActorCritic, obs: np.ndarray) -> np.ndarray:
    """The reference: the policy's deterministic action, as training and evaluation compute it."""
    with torch.no_grad():
        return model.act(torch.from_numpy(obs), deterministic=True)[0].numpy()


def observations() -> dict:
    """Random observations with 0..K real neighbours (21 rows; the export traced 8), and the simulator's
    own observations of a swarm smaller (N = 2: one real slot) and larger (N = 9) than K + 1."""
    layout = ObsLayout(K, "full")
    rows = 21
    out = {"random": random_obs(layout, rows, np.random.default_rng(7), num_real=np.arange(rows) % (K + 1))}
    for n in (2, 9):
        env = VecQuadEnv(EnvConfig(num_agents=n, num_neighbors=K), num_envs=2, seed=n)
        for _ in range(3):
            obs, *_ = env.step(np.full((2 * n, 4), 0.1, np.float32))
        out[f"N={n}"] = obs.copy()
    return {k: v.astype(np.float32) for k, v in out.items()}


@pytest.mark.parametrize("encoder", ENCODERS)
def test_exported_actor_gives_the_policys_actions(tmp_path, encoder):
    model = tiny_model(encoder)
    paths = export.export_actor(model, tmp_path, EnvConfig(num_neighbors=K))
    assert set(paths) == {"torchscript", "onnx", "sidecar"}
    for name, obs in observations().items():
        expected = policy_actions(model, obs)
        assert expected.shape == (obs.shape[0], 4)
        for fmt in ("torchscript", "onnx"):
            actions = export.run_exported(fmt, paths[fmt], obs)
            np.testing.assert_allclose(actions, expected, rtol=0, atol=1e-5, err_msg=f"{fmt}, {name}")


def test_clipped_export_applies_the_simulators_clip(tmp_path):
    model = tiny_model("deepsets", init_action_mean=1.5)  # means mostly beyond the [-1, 1] range
    obs = observations()["random"]
    expected = policy_actions(model, obs)
    assert (np.abs(expected) > 1).mean() > 0.5
    raw = export.export_actor(model, tmp_path / "raw", EnvConfig(num_neighbors=K), formats=["onnx"])
    clipped = export.export_actor(model, tmp_path / "clip", EnvConfig(num_neighbors=K), clip_actions=True)
    np.testing.assert_allclose(export.run_exported("onnx", raw["onnx"], obs), expected, atol=1e-5)
    for fmt in ("torchscript", "onnx"):
        np.testing.assert_allclose(export.run_exported(fmt, clipped[fmt], obs), np.clip(expected, -1, 1), atol=1e-5)
    assert "torchscript" not in raw and not (tmp_path / "raw" / "actor.pt").exists()


def test_sidecar_slices_read_the_observation_as_the_layout_does(tmp_path):
    layout = ObsLayout(K, "full")
    paths = export.export_actor(tiny_model("mlp"), tmp_path, EnvConfig(num_neighbors=K), formats=["torchscript"])
    side = json.loads(paths["sidecar"].read_text())
    assert side["input"]["shape"] == ["batch", layout.dim] and side["output"]["shape"] == ["batch", 4]
    assert side["files"] == {"torchscript": "actor.pt"} and side["check"]["max_abs_error"]["torchscript"] == 0.0
    obs = random_obs(layout, 5, np.random.default_rng(0))
    split = layout.split(obs)
    fields = side["observation"]["fields"]
    assert sum(f["size"] * len(f.get("slices", [0])) for f in fields) == layout.dim  # every entry, once
    for f in fields:
        key = "mask" if f["group"] == "mask" else f"{f['group']}.{f['name']}"
        if f["group"] == "neighbor":
            got = np.stack([obs[:, a:b] for a, b in f["slices"]], axis=1)  # [B, K, size]
        else:
            got = obs[:, f["slice"][0]:f["slice"][1]]
        np.testing.assert_array_equal(got, split[key])
    action = side["action"]
    assert action["max_thrust_per_motor_N"] == pytest.approx(1.9 * 0.028 * 9.81 / 4)  # 0.1305 N (Crazyflie)
    assert action["control_rate_hz"] == pytest.approx(100.0) and action["clipped"] is False
    assert action["hover_action"] == pytest.approx(2 / 1.9 - 1)


def test_export_command_on_a_checkpoint(tmp_path, capsys):
    run = untrained_checkpoint(tmp_path, "q", ["env.num_agents=4", f"env.num_neighbors={K}",
                                               "model.encoder=se3_kattention", "model.body_frame_obs=false"],
                               TINY_OPTIONS["se3_kattention"])
    assert export.main(["--checkpoint", str(run), "--out", str(tmp_path / "out")]) == 0
    assert "max |error|" in capsys.readouterr().out
    side = json.loads((tmp_path / "out" / "actor.json").read_text())
    assert side["policy"]["encoder"] == "se3_kattention" and side["policy"]["trained_num_agents"] == 4
    assert side["policy"]["run"] == "q" and side["policy"]["agent_steps"] == 1000
    from swarm_appo.evaluate import load_policy_from_checkpoint

    _, model = load_policy_from_checkpoint(str(run))
    obs = observations()["N=9"]
    np.testing.assert_allclose(export.run_exported("onnx", tmp_path / "out" / "actor.onnx", obs),
                               policy_actions(model, obs), atol=1e-5)
    with pytest.raises(SystemExit):
        export.main(["--checkpoint", str(run), "--out", str(tmp_path / "x"), "--format", "tflite"])
    err = capsys.readouterr().err
    assert "tflite" in err and "'torchscript', 'onnx'" in err  # the valid formats are listed


def test_export_of_a_truncated_checkpoint_is_one_clear_error(tmp_path, capsys):
    """A damaged checkpoint file is a usage error (exit 2) naming the file, no traceback and no output folder."""
    run = untrained_checkpoint(tmp_path, "q", ["env.num_agents=4", f"env.num_neighbors={K}"],
                               TINY_OPTIONS["deepsets"])
    ckpt = sorted((run / "checkpoints").glob("*.pt"))[-1]
    broken = tmp_path / "broken.pt"
    broken.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
    with pytest.raises(SystemExit) as exit_info:
        export.main(["--checkpoint", str(broken), "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "broken.pt" in err and "truncated" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("core", ["gru", "lstm"])
def test_recurrent_actor_exports_with_its_state_in_and_out(tmp_path, core):
    """TorchScript and ONNX take (obs, state) and return (actions, state_out); three steps of feeding state_out
    back (from zeros, as at an episode start) reproduce the policy's own recurrence, and the state matters."""
    model = tiny_model("deepsets", core=core, core_size=8)
    paths = export.export_actor(model, tmp_path, EnvConfig(num_neighbors=K))
    sidecar = json.loads(paths["sidecar"].read_text())
    S = model.state_sizes[0]
    assert S == (8 if core == "gru" else 16) and sidecar["state"]["shape"] == ["batch", S]
    obs = random_obs(ObsLayout(K, "full"), 3 * 5, np.random.default_rng(1)).astype(np.float32).reshape(3, 5, -1)
    for fmt in ("torchscript", "onnx"):
        state, ref_state = np.zeros((5, S), np.float32), model.initial_state(5)
        for k in range(3):
            actions, state = export.run_exported(fmt, paths[fmt], obs[k], state)
            with torch.no_grad():
                ref, _, _, ref_state = model.act(torch.from_numpy(obs[k]), True, with_value=False, state=ref_state)
            np.testing.assert_allclose(actions, ref.numpy(), atol=1e-5)
            np.testing.assert_allclose(state, ref_state[:, :S].numpy(), atol=1e-5)
        fresh, _ = export.run_exported(fmt, paths[fmt], obs[2], np.zeros((5, S), np.float32))
        assert np.abs(fresh - actions).max() > 1e-4  # the same observation from a zero state acts differently
