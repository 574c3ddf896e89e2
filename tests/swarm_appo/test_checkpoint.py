"""Checkpoints: round trip, atomicity under a kill mid-write, corruption fallback, retention, RNG states."""
import os
import random
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from swarm_appo.checkpoint import (BEST_NAME, CheckpointCorruptError, capture_rng_states, checkpoint_dir,
                                   list_checkpoints, load_checkpoint, load_latest_checkpoint,
                                   read_checkpoint_header, restore_rng_states, save_checkpoint)

REPO_ROOT = Path(__file__).resolve().parents[2]


def make_state(step):
    model = torch.nn.Linear(3, 2)
    torch.nn.init.constant_(model.weight, float(step))
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model(torch.ones(1, 3)).sum().backward()
    opt.step()
    return {"model": model.state_dict(), "optimizer": opt.state_dict(), "counters": {"step": step, "version": 7},
            "config": {"algo": {"lr": 1e-4, "adam_betas": [0.9, 0.995]}, "run": "x"}}


def step_of(state):
    return state["counters"]["step"]


def test_round_trip(tmp_path):
    state = make_state(5)
    path = save_checkpoint(tmp_path, state, step=5, metric=1.5)
    assert path == tmp_path / "checkpoints" / "ckpt_000000000005.pt"
    loaded, loaded_path = load_latest_checkpoint(tmp_path)
    assert loaded_path == path
    for k, v in state["model"].items():
        assert torch.equal(loaded["model"][k], v)
    assert loaded["optimizer"]["param_groups"] == state["optimizer"]["param_groups"]
    for pid, s in state["optimizer"]["state"].items():
        assert torch.equal(loaded["optimizer"]["state"][pid]["exp_avg"], s["exp_avg"])
    assert loaded["counters"] == state["counters"] and loaded["config"] == state["config"]
    header = read_checkpoint_header(path)
    assert header["step"] == 5 and header["metric"] == 1.5


def test_empty_run_dir_has_no_checkpoint(tmp_path, recwarn):
    assert load_latest_checkpoint(tmp_path) == (None, None)
    assert len(recwarn) == 0


def test_latest_by_step_not_by_write_order(tmp_path):
    save_checkpoint(tmp_path, make_state(20), step=20)
    save_checkpoint(tmp_path, make_state(100), step=100)
    state, path = load_latest_checkpoint(tmp_path)
    assert step_of(state) == 100 and path.name == "ckpt_000000000100.pt"


@pytest.mark.parametrize("damage", ["truncate", "flip_byte", "empty", "garbage_header"])
def test_corrupt_latest_falls_back_to_previous_with_warning(tmp_path, damage):
    save_checkpoint(tmp_path, make_state(1), step=1)
    latest = save_checkpoint(tmp_path, make_state(2), step=2)
    raw = latest.read_bytes()
    if damage == "truncate":
        latest.write_bytes(raw[: len(raw) // 2])
    elif damage == "flip_byte":
        latest.write_bytes(raw[:-10] + bytes([raw[-10] ^ 0xFF]) + raw[-9:])
    elif damage == "empty":
        latest.write_bytes(b"")
    else:
        latest.write_bytes(b"{not json\n" + raw)
    with pytest.raises(CheckpointCorruptError):
        load_checkpoint(latest)
    with pytest.warns(RuntimeWarning, match="ckpt_000000000002.pt"):
        state, path = load_latest_checkpoint(tmp_path)
    assert step_of(state) == 1 and path.name == "ckpt_000000000001.pt"


def test_all_corrupt_returns_none_with_warnings(tmp_path):
    for step in (1, 2):
        save_checkpoint(tmp_path, make_state(step), step=step).write_bytes(b"junk")
    with pytest.warns(RuntimeWarning) as record:
        assert load_latest_checkpoint(tmp_path) == (None, None)
    named = " ".join(str(w.message) for w in record)
    assert "ckpt_000000000001.pt" in named and "ckpt_000000000002.pt" in named


def test_crash_before_rename_leaves_no_partial_checkpoint(tmp_path, monkeypatch):
    save_checkpoint(tmp_path, make_state(1), step=1)

    def crash(*args):
        raise KeyboardInterrupt("killed")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(tmp_path, make_state(2), step=2)
    monkeypatch.undo()
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt_000000000001.pt"]
    assert sorted(p.name for p in checkpoint_dir(tmp_path).iterdir()) == ["ckpt_000000000001.pt"]
    state, _ = load_latest_checkpoint(tmp_path)
    assert step_of(state) == 1


def test_process_killed_mid_write_leaves_previous_checkpoint(tmp_path):
    """A real SIGKILL while the new file's bytes are on disk but before the rename."""
    script = textwrap.dedent(f"""
        import os, sys, time, torch
        from swarm_appo.checkpoint import save_checkpoint
        run = {str(tmp_path)!r}
        save_checkpoint(run, {{"counters": {{"step": 1}}, "w": torch.zeros(3)}}, step=1)
        def hang(fd):
            print("writing", flush=True)
            time.sleep(120)
        os.fsync = hang  # the temp file is written; block before it can be renamed
        save_checkpoint(run, {{"counters": {{"step": 2}}, "w": torch.ones(200_000)}}, step=2)
    """)
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, env=env, cwd=REPO_ROOT)
    try:
        assert proc.stdout.readline().strip() == b"writing"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    leftovers = [p for p in checkpoint_dir(tmp_path).iterdir() if p.name.startswith(".tmp-")]
    assert len(leftovers) == 1 and leftovers[0].stat().st_size > 0  # the partial write exists, hidden
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt_000000000001.pt"]
    state, _ = load_latest_checkpoint(tmp_path)
    assert step_of(state) == 1 and torch.equal(state["w"], torch.zeros(3))
    # The next save cleans the leftover temp file up.
    save_checkpoint(tmp_path, make_state(3), step=3)
    assert not [p for p in checkpoint_dir(tmp_path).iterdir() if p.name.startswith(".tmp-")]


def test_retention_keeps_last_n_plus_best(tmp_path):
    metrics = {10: 1.0, 20: 5.0, 30: 2.0, 40: float("nan"), 50: 3.0, 60: None}
    for step, metric in metrics.items():
        save_checkpoint(tmp_path, make_state(step), step=step, metric=metric, keep_last=2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt_000000000050.pt", "ckpt_000000000060.pt"]
    best = checkpoint_dir(tmp_path) / BEST_NAME
    assert read_checkpoint_header(best)["metric"] == 5.0
    assert step_of(load_checkpoint(best)) == 20


def test_best_respects_direction(tmp_path):
    for step, metric in ((1, 0.5), (2, 0.2), (3, 0.9)):
        save_checkpoint(tmp_path, make_state(step), step=step, metric=metric, higher_is_better=False)
    assert step_of(load_checkpoint(checkpoint_dir(tmp_path) / BEST_NAME)) == 2


def test_best_is_the_fallback_when_it_is_newer_than_the_valid_ones(tmp_path):
    save_checkpoint(tmp_path, make_state(1), step=1, metric=0.0)
    save_checkpoint(tmp_path, make_state(2), step=2, metric=1.0).write_bytes(b"junk")  # best.pt = step 2
    with pytest.warns(RuntimeWarning, match="ckpt_000000000002.pt"):
        state, path = load_latest_checkpoint(tmp_path)
    assert path.name == BEST_NAME and step_of(state) == 2


def test_resuming_from_an_earlier_step_drops_the_abandoned_future(tmp_path):
    for step in (1, 2, 3):
        save_checkpoint(tmp_path, make_state(step), step=step)
    save_checkpoint(tmp_path, make_state(2), step=2)  # resumed from 2 (say 3 was unusable), saved again
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt_000000000001.pt", "ckpt_000000000002.pt"]


def test_rng_states_round_trip_through_a_checkpoint(tmp_path):
    gen = np.random.default_rng(123)
    random.seed(1), np.random.seed(2), torch.manual_seed(3)
    save_checkpoint(tmp_path, {"rng": capture_rng_states({"env": gen})}, step=1)
    draws = (random.random(), np.random.rand(3), np.random.randn(), torch.rand(3), gen.random(2))
    random.seed(99), np.random.seed(99), torch.manual_seed(99)
    gen2 = np.random.default_rng(0)
    state, _ = load_latest_checkpoint(tmp_path)  # weights_only loading accepts the captured states
    restore_rng_states(state["rng"], {"env": gen2})
    again = (random.random(), np.random.rand(3), np.random.randn(), torch.rand(3), gen2.random(2))
    assert draws[0] == again[0]
    np.testing.assert_array_equal(draws[1], again[1])
    assert draws[2] == again[2]
    assert torch.equal(draws[3], again[3])
    np.testing.assert_array_equal(draws[4], again[4])
    with pytest.raises(KeyError, match="other"):
        restore_rng_states(state["rng"], {"other": gen2})


def test_training_state_is_the_one_payload_definition(tmp_path):
    """TrainingState writes and reads the payload with the format version of the file header; a payload of
    another version or without the training keys is refused by name."""
    from swarm_appo.checkpoint import FORMAT_VERSION, TrainingState

    state = TrainingState(learner={"model": {"w": torch.ones(2)}, "version": 3}, agent_steps=4096,
                          config={"env": {"num_agents": 2}}, rng=None, wandb_id="abc")
    path = state.save(tmp_path, metric=1.5)
    assert path.name == "ckpt_000000004096.pt"
    assert load_checkpoint(path)["format"] == FORMAT_VERSION == read_checkpoint_header(path)["version"]
    back = TrainingState.load(path)
    assert (back.agent_steps, back.config, back.wandb_id, back.learner["version"]) == (4096, state.config, "abc", 3)
    assert torch.equal(back.learner["model"]["w"], torch.ones(2))
    latest, latest_path = TrainingState.load_latest(tmp_path)
    assert latest_path == path and latest.agent_steps == 4096
    assert TrainingState.load_latest(tmp_path / "empty") == (None, None)
    with pytest.raises(CheckpointCorruptError, match="payload format 99"):
        TrainingState.from_payload({**state.payload(), "format": 99}, source="x.pt")
    with pytest.raises(CheckpointCorruptError, match="not a training checkpoint .no config"):
        TrainingState.from_payload({"format": FORMAT_VERSION, "learner": {}}, source="x.pt")
