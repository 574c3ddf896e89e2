"""SIGTERM (a scheduler, `kill`) stops a Ray run like Ctrl-C: a final checkpoint and exit status 130.

Ray's driver installs its own SIGTERM handler, which exits at once; the launcher's must survive it.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_sigterm_writes_a_final_checkpoint_in_a_ray_run(tmp_path):
    args = ["--no-progress", "env.num_agents=2", "env.num_neighbors=1", "env.episode_duration=0.3",
            "runner.num_workers=1", "runner.envs_per_worker=2", "algo.rollout=16", "algo.batch_size=64",
            "algo.num_epochs=1", "runner.total_agent_steps=100000000", "runner.checkpoint_every_s=0",
            "runner.final_eval_episodes=2", f"runner.run_dir={tmp_path}", "runner.name=term",
            "wandb.mode=disabled", "model.encoder=deepsets"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "launchers.local", *args], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    metrics = tmp_path / "term" / "metrics.jsonl"
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:
            if metrics.exists() and metrics.read_text().strip():
                break  # the learner has trained: Ray and the rollout actor are up
            time.sleep(0.5)
        assert proc.poll() is None, proc.stdout.read()
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, out
    assert "SIGTERM received" not in out  # Ray's handler did not take over
    checkpoints = sorted((tmp_path / "term" / "checkpoints").glob("ckpt_*.pt"))
    assert checkpoints, out
    steps = [json.loads(line)["global_step"] for line in metrics.read_text().splitlines()]
    assert f"checkpoint: {checkpoints[-1]}" in out and int(checkpoints[-1].stem.split("_")[1]) >= max(steps)
