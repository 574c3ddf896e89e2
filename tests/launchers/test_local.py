"""The launcher's command line: config errors, a short serial run end to end, and evaluation of its result."""
from __future__ import annotations

import csv
import json

import pytest

from launchers.local import main
from swarm_appo import evaluate


def tiny_args(tmp_path, name="cli"):
    return ["--no-progress", "env.num_agents=2", "env.num_neighbors=1", "env.episode_duration=0.3",
            "runner.serial=true", "runner.num_workers=1", "runner.envs_per_worker=2", "algo.rollout=16",
            "algo.batch_size=64", "algo.num_epochs=1", "runner.total_agent_steps=128",
            "runner.final_eval_episodes=2", f"runner.run_dir={tmp_path}", f"runner.name={name}",
            "wandb.mode=disabled", "model.encoder=deepsets"]


def test_unknown_key_names_the_key(tmp_path, capsys):
    assert main(tiny_args(tmp_path) + ["env.num_agentz=3"]) == 2
    err = capsys.readouterr().err
    assert "env.num_agentz" in err and "num_agents" in err
    assert not (tmp_path / "cli").exists(), "a config error must not create a run directory"


def test_a_ray_address_without_a_cluster_fails_before_the_run_directory(tmp_path, capsys):
    assert main(tiny_args(tmp_path) + ["runner.serial=false", "runner.ray_address=127.0.0.1:9"]) == 1
    err = capsys.readouterr().err
    assert "cannot join the Ray cluster of runner.ray_address" in err and "127.0.0.1:9" in err
    assert not (tmp_path / "cli").exists(), "nothing to record: no run directory"


def test_unknown_encoder_lists_the_valid_ones(tmp_path, capsys):
    assert main(tiny_args(tmp_path) + ["model.encoder=transformer"]) == 2
    err = capsys.readouterr().err
    assert "model.encoder" in err and "se3_graphormer" in err and "deepsets" in err


def test_wrong_type_names_key_and_type(tmp_path, capsys):
    assert main(tiny_args(tmp_path) + ["algo.lr=fast"]) == 2
    err = capsys.readouterr().err
    assert "algo.lr" in err and "float" in err


def test_short_run_then_evaluate(tmp_path, capsys):
    assert main(tiny_args(tmp_path)) == 0
    out = capsys.readouterr().out
    run_dir = tmp_path / "cli"
    assert f"run directory: {run_dir}" in out and "final evaluation" in out
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["global_step"] >= 128 and "eval/dist" in records[-1]

    out = tmp_path / "eval"
    assert evaluate.main(["--checkpoint", str(run_dir), "--episodes", "2", "--scenarios", "static_same_goal",
                          "--random-baseline", "--workers", "0", "--out", str(out), "--no-pictures",
                          "--wandb-mode", "disabled", "--no-progress"]) == 0
    assert "| static_same_goal | cli (deepsets) |" in capsys.readouterr().out
    with open(out / "table1_scenarios.csv", newline="") as f:
        trained, random = csv.DictReader(f)
    # the CLI evaluates the same policy on the same seeded episodes as the end-of-run evaluation
    assert float(trained["dist_mean"]) == pytest.approx(records[-1]["eval/dist"], abs=1e-4)
    assert float(random["dist_mean"]) == pytest.approx(records[-1]["eval_random/dist"], abs=1e-4)


@pytest.mark.parametrize("make,message", [
    (lambda root: root / "nonexistent", "does not exist"),
    (lambda root: root, "not a run directory (no config.yaml"),
    (lambda root: _checkpoint_file(root), "is a file, not a run directory; did you mean its run directory"),
])
def test_resume_of_something_that_is_not_a_run_dir_is_one_line(tmp_path, capsys, make, message):
    assert main(["--resume", str(make(tmp_path)), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("--resume: ") and message in err and "Traceback" not in err


def _checkpoint_file(root):
    path = root / "run" / "checkpoints" / "ckpt_000000001000.pt"
    path.parent.mkdir(parents=True)
    (root / "run" / "config.yaml").write_text("{}\n")
    path.write_bytes(b"x")
    return path


def test_resume_before_the_first_checkpoint_starts_afresh_with_one_history(tmp_path):
    from swarm_appo.config import load_config, save_config

    overrides = [a for a in tiny_args(tmp_path, "nc") if "=" in a]
    run_dir = tmp_path / "nc"
    run_dir.mkdir()
    save_config(load_config(None, overrides), run_dir / "config.yaml")
    # what a run killed before its first checkpoint leaves: records, a wandb id, no checkpoint
    (run_dir / "metrics.jsonl").write_text('{"global_step": 16384}\n{"global_step": 32768}\n')
    (run_dir / "wandb_id.txt").write_text("deadrun\n")
    assert main(["--resume", str(run_dir), "--no-progress"]) == 0
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    steps = [r["global_step"] for r in records if not any(k.startswith("eval") for k in r)]  # iterations
    assert steps[0] < 16384 and steps == sorted(steps) and len(set(steps)) == len(steps)
    assert 16384 not in steps and 32768 not in steps
    assert any((run_dir / "checkpoints").glob("ckpt_*.pt"))


def test_time_limit_is_reported_with_the_share_of_the_plan(tmp_path, capsys):
    args = [a for a in tiny_args(tmp_path, "tl") if not a.startswith("runner.total_agent_steps")]
    assert main(args + ["runner.total_agent_steps=1e9", "runner.time_limit_s=0.5", "runner.final_eval_episodes=0"]) == 0
    out = capsys.readouterr().out
    assert "stopped by the time limit" in out and "of the planned 1,000,000,000 agent steps" in out
    assert f"--resume {tmp_path / 'tl'}" in out and "python -m swarm_appo.evaluate --checkpoint" in out


def test_progress_counts_toward_whichever_limit_comes_first():
    from swarm_appo.config import load_config
    from swarm_appo.trainer import PROGRESS_UNITS, progress_units

    steps_only = load_config(None, ["runner.time_limit_s=0", "runner.total_agent_steps=1000"])
    assert progress_units(steps_only, 250, elapsed_s=1e6) == PROGRESS_UNITS // 4
    both = load_config(None, ["runner.time_limit_s=100", "runner.total_agent_steps=1000"])
    assert progress_units(both, 100, elapsed_s=50) == PROGRESS_UNITS // 2  # time binds
    assert progress_units(both, 900, elapsed_s=50) == PROGRESS_UNITS * 9 // 10  # steps bind
    assert progress_units(both, 5000, elapsed_s=500) == PROGRESS_UNITS


def test_ctrl_c_during_start_up_is_one_line_and_exit_130(tmp_path, monkeypatch, capsys):
    import swarm_appo.trainer

    def interrupted_start(*args, **kwargs):
        raise KeyboardInterrupt  # e.g. Ctrl-C while Ray starts

    monkeypatch.setattr(swarm_appo.trainer, "train", interrupted_start)
    assert main(["--no-progress", f"runner.run_dir={tmp_path}"]) == 130
    err = capsys.readouterr().err
    assert "interrupted during start-up" in err and "Traceback" not in err
