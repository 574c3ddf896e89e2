"""How a run stops: SIGTERM / Ctrl-C at an iteration boundary (the final checkpoint is a state the run really
passed through), and a run that cannot learn stops loudly instead of exiting 0."""
from __future__ import annotations

import os
import random
import signal
import threading

import pytest

from launchers import local
from swarm_appo.checkpoint import load_checkpoint
from swarm_appo.trainer import train

from .test_training import read_metrics, tiny_config, tiny_overrides

# tiny_config: 2 swarms x 2 drones x 16 steps = 64 agent steps per fragment; batch 128 = 2 fragments per
# iteration; 8 trajectories per batch, 8 per minibatch -> 1 minibatch x 2 epochs = 2 updates per iteration
STEPS_PER_ITERATION = 128
UPDATES_PER_ITERATION = 2


def run_launcher(argv) -> int:
    """``launchers.local.main(argv)``, then the SIGTERM handler it installs is put back."""
    previous = signal.getsignal(signal.SIGTERM)
    try:
        return local.main(argv)
    finally:
        signal.signal(signal.SIGTERM, previous)


@pytest.fixture
def sigterm_as_interrupt():
    """What the launchers do (``stop_on_sigterm``): a SIGTERM outside the loop must not kill pytest."""
    previous = signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    yield
    signal.signal(signal.SIGTERM, previous)


@pytest.mark.parametrize("seed", range(6))
def test_sigterm_at_a_random_moment_stops_at_an_iteration_boundary(tmp_path, sigterm_as_interrupt, seed):
    cfg = tiny_config(tmp_path, f"t{seed}", **{"algo.batch_size": 128, "runner.total_agent_steps": 10**7,
                                                "runner.final_eval_episodes": 0})
    rng = random.Random(seed)
    timer = []
    sigint_before = signal.getsignal(signal.SIGINT)  # default_int_handler, or SIG_IGN in a background job

    def on_iteration(version, sampler):  # once the loop runs: a SIGTERM 0-150 ms later, anywhere in the loop
        if not timer:
            timer.append(threading.Timer(rng.uniform(0.0, 0.15), os.kill, (os.getpid(), signal.SIGTERM)))
            timer[0].start()

    result = train(cfg, progress=False, on_iteration=on_iteration)
    timer[0].join()
    assert result.interrupted and result.stopped_by == "interrupted"
    state = load_checkpoint(result.checkpoint)
    version = state["learner"]["version"]
    assert version >= 1
    # every counter describes the same whole number of iterations: no partial update, no untrained fragment
    assert state["learner"]["num_updates"] == UPDATES_PER_ITERATION * version
    assert state["agent_steps"] == STEPS_PER_ITERATION * version == result.agent_steps
    logged = [r["global_step"] for r in read_metrics(result.run_dir) if "losses/total_loss" in r]
    assert logged[-1] == state["agent_steps"]
    assert signal.getsignal(signal.SIGINT) is sigint_before  # handlers restored after the run


def test_a_run_that_cannot_learn_stops_with_an_error_naming_the_checkpoint(tmp_path, monkeypatch, capsys):
    from swarm_appo import learner as learner_module

    real_appo_loss = learner_module.appo_loss

    def nan_loss(*args, **kwargs):  # e.g. a reward term that became inf: every loss is non-finite
        loss, stats = real_appo_loss(*args, **kwargs)
        return loss * float("nan"), stats

    monkeypatch.setattr(learner_module, "appo_loss", nan_loss)
    argv = ["--no-progress", *tiny_overrides(tmp_path, "nan", **{"algo.max_consecutive_skips": 6,
                                                                   "runner.total_agent_steps": 10**6})]
    with pytest.warns(UserWarning, match="skipped"):
        code = run_launcher(argv)
    assert code == 1
    err = capsys.readouterr().err
    assert "6 consecutive updates skipped" in err and "algo.max_consecutive_skips=6" in err
    assert f"--resume {tmp_path / 'nan'}" in err
    records = [r for r in read_metrics(tmp_path / "nan") if "losses/skipped_updates" in r]
    assert records and records[-1]["losses/skipped_updates"] >= 6  # counted in the metrics


def test_skips_below_the_limit_do_not_stop_a_run(tmp_path, monkeypatch):
    from swarm_appo import learner as learner_module

    real_appo_loss = learner_module.appo_loss
    calls = []

    def sometimes_nan(*args, **kwargs):  # every third update is non-finite: never 3 in a row
        loss, stats = real_appo_loss(*args, **kwargs)
        calls.append(1)
        return (loss * float("nan") if len(calls) % 3 == 0 else loss), stats

    monkeypatch.setattr(learner_module, "appo_loss", sometimes_nan)
    cfg = tiny_config(tmp_path, "some", **{"algo.max_consecutive_skips": 2, "runner.final_eval_episodes": 0})
    with pytest.warns(UserWarning, match="skipped"):
        result = train(cfg, progress=False)
    assert result.agent_steps >= cfg.runner.total_agent_steps
    assert load_checkpoint(result.checkpoint)["learner"]["skipped_updates"] >= 1


def test_max_consecutive_skips_is_checked(tmp_path):
    from swarm_appo.config import ConfigError

    with pytest.raises(ConfigError, match=r"algo\.max_consecutive_skips"):
        tiny_config(tmp_path, "x", **{"algo.max_consecutive_skips": -1})


def test_a_run_dir_that_cannot_be_written_is_one_line_and_exit_2(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    argv = ["--no-progress", *tiny_overrides(blocker / "runs", "x")]
    assert run_launcher(argv) == 2
    err = capsys.readouterr().err
    assert "runner.run_dir: cannot write the run directory" in err and "Traceback" not in err


def test_a_full_disk_says_free_space_first_once_without_a_traceback(tmp_path, monkeypatch, capsys):
    import errno

    import swarm_appo.checkpoint as checkpoint_module

    real_save = checkpoint_module.save_checkpoint
    calls = []

    def filling_disk(*args, **kwargs):
        calls.append(1)
        if len(calls) >= 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_save(*args, **kwargs)

    monkeypatch.setattr(checkpoint_module, "save_checkpoint", filling_disk)  # under TrainingState.save
    argv = ["--no-progress", *tiny_overrides(tmp_path, "full", **{"runner.checkpoint_every_updates": 1,
                                                                    "runner.final_eval_episodes": 0})]
    assert run_launcher(argv) == 1
    err = capsys.readouterr().err
    assert err.count("is full") == 1 and "Free space there first" in err and "Traceback" not in err
    assert f"--resume {tmp_path / 'full'}" in err
    kept = sorted((tmp_path / "full" / "checkpoints").glob("ckpt_*.pt"))
    assert len(kept) == 2 and all(load_checkpoint(p)["agent_steps"] > 0 for p in kept)  # the earlier ones intact


def test_a_failing_end_of_run_evaluation_still_closes_the_metrics(tmp_path, monkeypatch):
    import swarm_appo.trainer as trainer_module
    from swarm_appo.metrics import MetricsLogger

    closed = []
    real_close = MetricsLogger.close
    monkeypatch.setattr(MetricsLogger, "close", lambda self: (closed.append(1), real_close(self))[1])

    def broken_evaluation(*args, **kwargs):
        raise RuntimeError("evaluation broke")

    monkeypatch.setattr(trainer_module, "compare_with_random", broken_evaluation)
    with pytest.raises(RuntimeError, match="evaluation broke"):
        train(tiny_config(tmp_path, "ev"), progress=False)
    assert closed
    assert any((tmp_path / "ev" / "checkpoints").glob("ckpt_*.pt"))  # the final checkpoint came first


def test_sigterm_during_start_up_stops_before_the_first_iteration_with_everything_closed(tmp_path, monkeypatch,
                                                                                         sigterm_as_interrupt):
    """A resume stopped while it starts (e.g. while Ray starts) keeps its counters, and its new wandb run already
    holds the replayed history (the run is finished, not abandoned)."""
    import swarm_appo.trainer as trainer_module
    from swarm_appo.metrics import read_metrics, wait_for_wandb_history

    first = train(tiny_config(tmp_path, "s", **{"wandb.mode": "offline", "runner.final_eval_episodes": 0}),
                  progress=False)
    real_start = trainer_module._start_sampling

    def interrupted_start(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)  # arrives while the samplers start
        return real_start(*args, **kwargs)

    monkeypatch.setattr(trainer_module, "_start_sampling", interrupted_start)
    resumed = train(tiny_config(tmp_path, "s", **{"wandb.mode": "offline", "runner.total_agent_steps": 10**6}),
                    resume_dir=str(first.run_dir), progress=False)
    assert resumed.interrupted and resumed.agent_steps == first.agent_steps
    assert load_checkpoint(resumed.checkpoint)["agent_steps"] == first.agent_steps
    run_id = (first.run_dir / "wandb_id.txt").read_text().strip()
    newest, = (first.run_dir / "wandb").glob(f"offline-run-*-{run_id}")
    expected = [r["global_step"] for r in read_metrics(first.run_dir)]
    assert [h["global_step"] for h in wait_for_wandb_history(newest / f"run-{run_id}.wandb", len(expected))] == expected


@pytest.mark.parametrize("wandb_mode", ["disabled", "offline"])
def test_a_fresh_run_that_fails_to_start_removes_what_it_made(tmp_path, monkeypatch, wandb_mode):
    """Ray failing to start (here: the samplers raise) leaves no half-made run dir behind; a folder that was
    already there keeps what it held."""
    import swarm_appo.trainer as trainer_module

    def failing_start(*args, **kwargs):
        raise RuntimeError("raylet did not start in time")

    monkeypatch.setattr(trainer_module, "_start_sampling", failing_start)
    with pytest.raises(RuntimeError, match="raylet"):
        train(tiny_config(tmp_path, "new", **{"wandb.mode": wandb_mode}), progress=False)
    assert not (tmp_path / "new").exists()

    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "notes.txt").write_text("mine")
    with pytest.raises(RuntimeError, match="raylet"):
        train(tiny_config(tmp_path, "old", **{"wandb.mode": wandb_mode}), progress=False)
    assert [p.name for p in (tmp_path / "old").iterdir()] == ["notes.txt"]


def test_trainer_close_is_idempotent_and_closes_everything(tmp_path):
    """Trainer.close (what __exit__ calls after any ending) closes the samplers, the signal handlers and the
    metrics, and a second call does nothing."""
    from swarm_appo.trainer import Trainer

    before = signal.getsignal(signal.SIGTERM)
    with Trainer(tiny_config(tmp_path, "c", **{"runner.final_eval_episodes": 0}), progress=False) as trainer:
        trainer.start()
        assert signal.getsignal(signal.SIGTERM) != before  # GracefulStop active
        assert trainer.sampler is not None and trainer.logger is not None
    assert trainer.sampler is None and signal.getsignal(signal.SIGTERM) == before
    assert trainer.logger._file.closed  # metrics.jsonl
    trainer.close()  # again: nothing to do, no error
