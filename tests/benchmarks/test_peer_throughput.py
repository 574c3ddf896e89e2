"""benchmarks.peer_throughput: the peer's log parser, and that both sides of a pair train the same settings."""
import dataclasses

import pytest

from benchmarks import peer_throughput as pt
from swarm_appo.config import load_config


def _report(clock: str, frames: int) -> str:
    return (f"[2026-12-02 {clock}][01234] Fps is (10 sec: 1.0, 60 sec: 2.0, 300 sec: 3.0). Total num frames: "
            f"{frames}. Throughput: 0: 5.0. Samples: {frames}. Policy #0 lag: (min: 0.0, avg: 1.0, max: 2.0)")


def test_peer_log_rate_skips_start_up_and_warm_up():
    lines = ["[2026-12-02 10:00:00,000][01234] Starting all processes...",
             _report("10:00:20,000", 0),  # still compiling: no trained frames
             _report("10:00:30,000", 1_000),  # first trained batch: t0
             _report("10:00:40,000", 50_000),  # inside the 30% warm-up of the 100-s span
             "[2026-12-02 10:00:45,000][01235] some other line mentioning Total num frames: 999999",
             _report("10:01:00,000", 100_000),  # t0 + 30 s: the steady window starts here
             _report("10:01:30,500", 130_500),
             _report("10:02:10,000", 170_000)]  # t1 = t0 + 100 s
    r = pt.parse_peer_log("\n".join(lines))
    assert r["sps"] == pytest.approx((170_000 - 100_000) / 70.0)
    assert r["agent_steps"] == 170_000
    assert r["first_trained_s"] == pytest.approx(30.0)


def test_peer_log_rate_of_a_stepwise_count_runs_between_its_moves():
    # the peer's serial mode: 16,384 frames per training iteration, the unchanged count reported in between
    lines = [_report("10:00:00,000", 0), _report("10:00:40,000", 16_384)]  # first trained iteration: t0
    lines += [_report(f"10:00:{s},000", 16_384) for s in (45, 50, 55)]
    lines += [_report("10:01:10,000", 32_768)] + [_report(f"10:01:{s},000", 32_768) for s in (15, 20, 25)]
    lines += [_report("10:01:40,000", 49_152), _report("10:01:45,000", 49_152), _report("10:01:50,000", 49_152)]
    r = pt.parse_peer_log("\n".join(lines))
    # moves at 40, 70 and 100 s; the window (from 40 + 0.3 x 60 s) holds the moves at 70 and 100 s
    assert r["sps"] == pytest.approx(16_384 / 30.0)
    assert r["first_trained_s"] == pytest.approx(40.0)
    with pytest.raises(RuntimeError, match="1 reports with trained frames"):  # one move only: no rate
        pt.parse_peer_log("\n".join(lines[:5]))


def test_peer_log_without_training_is_an_error():
    with pytest.raises(RuntimeError, match="1 reports with trained frames"):
        pt.parse_peer_log("\n".join([_report("10:00:20,000", 0), _report("10:00:30,000", 1_000)]))


@pytest.mark.parametrize("encoder,epochs", [("attention", 1), ("mean_embed", 5)])
def test_both_sides_train_the_same_settings(encoder, epochs, tmp_path):
    peer = dict(a[2:].split("=", 1) for a in pt.peer_command("py", encoder, epochs, 60, "d", 2, 8) if "=" in a)
    cfg = load_config(str(pt.ROOT / "configs" / "paper.yaml"),
                      pt.our_overrides(encoder, epochs, 60, "fp32") + [f"runner.run_dir={tmp_path}"])
    assert int(peer["batch_size"]) == cfg.algo.batch_size == 1024
    assert int(peer["rollout"]) == cfg.algo.rollout
    assert int(peer["num_epochs"]) == cfg.algo.num_epochs == epochs
    assert float(peer["learning_rate"]) == cfg.algo.lr
    assert float(peer["gamma"]) == cfg.algo.gamma
    assert float(peer["max_grad_norm"]) == cfg.algo.max_grad_norm
    assert int(peer["quads_num_agents"]) == cfg.env.num_agents
    assert peer["quads_mode"] == cfg.env.scenario == "mix"
    assert int(peer["quads_neighbor_visible_num"]) == cfg.env.num_neighbors
    assert peer["quads_neighbor_obs_type"] == cfg.env.neighbor_obs == "pos_vel"
    assert int(peer["quads_neighbor_hidden_size"]) == 256 and int(peer["rnn_size"]) == 256
    assert peer["use_rnn"] == "False" and cfg.model.core == "none"
    assert peer["actor_critic_share_weights"] == "False" and cfg.model.share_encoder is False
    assert peer["normalize_input"] == "False" and cfg.model.normalize_obs is False
    assert cfg.model.head_hidden == 0  # the peer's linear action and value heads
    assert pt.PEER_ENCODERS[peer["quads_neighbor_encoder_type"]] == cfg.model.encoder
    assert cfg.model.symmetry == "none"


@pytest.mark.parametrize("option,message", [
    (["--encoders", "attn"], "unknown encoder 'attn'; valid: attention, mean_embed"),
    (["--precisions", "fp16"], "--precisions: unknown 'fp16'; valid: fp32, bf16"),
    (["--epochs", "1,five"], "--epochs and --peer-envs take comma-separated integers"),
    (["--peer-envs", "0"], "--epochs and --peer-envs must be >= 1"),
    (["--layouts", "async,parallel"], "--layouts: unknown 'parallel'; valid: async, serial"),
    (["--compile", "off,max-autotune"], "--compile: unknown 'max-autotune'; valid: off, default"),
    ([], "--peer-python must exist and --peer-src must hold swarm_rl/"),
])
def test_bad_options_are_usage_errors(option, message, capsys, tmp_path):
    with pytest.raises(SystemExit) as e:
        pt.main(["--peer-python", str(tmp_path / "no_python"), "--peer-src", str(tmp_path), *option])
    assert e.value.code == 2 and message in capsys.readouterr().err


def test_steady_window_drops_the_warm_up_and_keeps_at_least_two():
    from benchmarks.common import steady_window
    times = [0.0, 10.0, 29.0, 30.0, 70.0, 100.0]
    assert steady_window(times, float) == [30.0, 70.0, 100.0]  # from 0 + 0.3 x 100 s on
    assert steady_window(times, float, warmup_fraction=0.95) == [70.0, 100.0]  # one left: the last two


@pytest.mark.parametrize("layout,serial", [("async", False), ("serial", True)])
def test_layouts_change_only_the_process_layout(layout, serial, tmp_path):
    base = load_config(str(pt.ROOT / "configs" / "paper.yaml"),
                       pt.our_overrides("attention", 5, 60, "bf16") + [f"runner.run_dir={tmp_path}"])
    cfg = load_config(str(pt.ROOT / "configs" / "paper.yaml"),
                      pt.our_overrides("attention", 5, 60, "bf16", layout) + [f"runner.run_dir={tmp_path}"])
    assert cfg.runner.serial is serial
    assert cfg.algo == base.algo and cfg.model == base.model and cfg.env == base.env


def test_compile_mode_changes_only_the_learner_compilation(tmp_path):
    base = load_config(str(pt.ROOT / "configs" / "paper.yaml"),
                       pt.our_overrides("attention", 5, 60, "bf16", "serial") + [f"runner.run_dir={tmp_path}"])
    cfg = load_config(str(pt.ROOT / "configs" / "paper.yaml"), pt.our_overrides(
        "attention", 5, 60, "bf16", "serial", "default") + [f"runner.run_dir={tmp_path}"])
    assert base.runner.compile == "off" and cfg.runner.compile == "default"
    assert dataclasses.replace(cfg.runner, compile="off") == base.runner
    assert cfg.algo == base.algo and cfg.model == base.model and cfg.env == base.env
    assert pt.our_label("serial", "off") == "serial"
    assert pt.our_label("serial", "default") == "serial compiled (default)"


def test_our_cell_names_layouts_and_rates_the_best():
    one = {"async": {"sps": 1500.0}}
    assert pt.our_cell(one, 600.0) == "1,500 (**2.50x**)"
    two = {"async": {"sps": 1500.0}, "serial": {"sps": 1950.0}}
    assert pt.our_cell(two, 600.0) == "async: 1,500, serial: 1,950 (best **3.25x**)"


def test_peer_serial_mode_is_its_only_difference():
    asynchronous = pt.peer_command("py", "attention", 5, 60, "d", 2, 8)
    serial = pt.peer_command("py", "attention", 5, 60, "d", 2, 8, serial=True)
    assert serial[:3] == ["py", "-m", "swarm_rl.train"]  # flags go to the peer's trainer, not to python
    assert sorted(set(serial) - set(asynchronous)) == ["--async_rl=False", "--num_batches_per_epoch=16",
                                                       "--serial_mode=True"]
    # sample-factory's synchronous mode needs samples per rollout = batches per epoch x batch size
    flags = dict(a[2:].split("=", 1) for a in serial if "=" in a)
    per_rollout = (int(flags["num_workers"]) * int(flags["num_envs_per_worker"]) * int(flags["quads_num_agents"])
                   * int(flags["rollout"]))
    assert per_rollout == int(flags["num_batches_per_epoch"]) * int(flags["batch_size"])
    assert set(asynchronous) <= set(serial)
