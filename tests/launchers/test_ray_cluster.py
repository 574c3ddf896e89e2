"""The cluster launcher: config errors fail before anything is sent, where the learner is placed, and a real
submission through the Ray Jobs API to a two-node Ray cluster on this machine (a head and a worker node,
each its own raylet and object store, on 127.0.0.1), which must spread the rollout actors over both nodes
and leave a checkpoint and metrics.jsonl in the run directory."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from launchers.local_cluster import LocalCluster
from launchers.ray_cluster import cluster_run_root, entrypoint_options, main

ROOT = Path(__file__).resolve().parents[2]

TINY = ["env.num_agents=2", "env.num_neighbors=1", "env.episode_duration=0.3", "runner.envs_per_worker=2",
        "algo.rollout=16", "algo.batch_size=64", "algo.num_epochs=1", "model.encoder=deepsets",
        "wandb.mode=disabled", "runner.checkpoint_every_s=0", "runner.final_eval_episodes=2"]


# --------------------------------------------------------------------------- no cluster needed
@pytest.mark.parametrize("override, names", [
    ("env.num_agentz=3", ["env.num_agentz", "num_agents"]),
    ("model.encoder=transformer", ["model.encoder", "se3_graphormer"]),
    ("algo.lr=fast", ["algo.lr", "float"]),
    ("runner.serial=true", ["runner.serial", "runner.ray_address"]),
])
def test_config_errors_fail_before_contacting_the_cluster(override, names, capsys):
    # Port 9 (discard) has no Jobs API: a config error must be reported before any connection is tried.
    assert main(["submit", "--address", "http://127.0.0.1:9", *TINY, override]) == 2
    err = capsys.readouterr().err
    assert err.startswith("config error:") and all(n in err for n in names), err
    assert "cannot reach" not in err


def test_unreachable_address_is_reported(capsys):
    assert main(["submit", "--address", "http://127.0.0.1:9", *TINY]) == 1
    assert "cannot reach the Ray Jobs API at http://127.0.0.1:9" in capsys.readouterr().err


def test_learner_goes_to_a_gpu_node_when_the_cluster_has_one():
    head = {"node_id": "h", "head": True, "cpus": 4, "gpus": 0}
    gpu_node = {"node_id": "g", "head": False, "cpus": 8, "gpus": 1}
    opts, _ = entrypoint_options([head, gpu_node], "auto", "auto")
    assert opts == {"entrypoint_num_cpus": 1, "entrypoint_num_gpus": 1}
    # no GPU anywhere: the head node, one CPU reserved (the workers get the others)
    opts, _ = entrypoint_options([head, dict(gpu_node, gpus=0)], "auto", "auto")
    assert opts == {"entrypoint_num_cpus": 1, "entrypoint_label_selector": {"ray.io/node-id": "h"}}
    # the config asks for the CPU: no GPU is reserved even though there is one
    opts, _ = entrypoint_options([head, gpu_node], "auto", "cpu")
    assert "entrypoint_num_gpus" not in opts
    # runner.device=cuda or --learner-gpus 1 ask for a GPU even if none is up yet (an autoscaler adds one)
    assert entrypoint_options([head], "auto", "cuda")[0]["entrypoint_num_gpus"] == 1
    assert entrypoint_options([head], "1", "auto")[0]["entrypoint_num_gpus"] == 1
    assert "entrypoint_num_gpus" not in entrypoint_options([head, gpu_node], "0", "auto")[0]
    # a head without CPUs (a common setup for large clusters) cannot reserve one: Ray's default (the head)
    assert entrypoint_options([dict(head, cpus=0)], "auto", "auto")[0] == {}


def test_relative_run_dirs_go_under_the_home_directory(tmp_path):
    assert cluster_run_root("runs", home=tmp_path) == tmp_path / "runs"
    assert cluster_run_root("/data/runs", home=tmp_path) == Path("/data/runs")
    assert cluster_run_root("~/x", home=tmp_path) == Path(os.path.expanduser("~/x"))


# --------------------------------------------------------------------------- a real two-node cluster
def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1][0] != "Z"  # a zombie has exited
    except OSError:
        return False


def _still_alive(pids, timeout_s: float = 20.0) -> list:
    """The pids still running after up to ``timeout_s`` (workers exit shortly after their raylet)."""
    deadline = time.monotonic() + timeout_s
    while [p for p in pids if _alive(p)] and time.monotonic() < deadline:
        time.sleep(0.5)
    return [p for p in pids if _alive(p)]


def test_submit_to_a_two_node_cluster_spreads_rollout_actors(tmp_path):
    run_root = tmp_path / "runs"
    cluster = LocalCluster(nodes=2, cpus_per_node=2)
    with cluster:
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        cmd = [sys.executable, "-m", "launchers.ray_cluster", "submit", "--address", cluster.dashboard_url,
               "--follow", "--log-every-s", "5", *TINY, "runner.num_workers=0", "runner.total_agent_steps=960",
               f"runner.run_dir={run_root}", "runner.name=two_nodes"]
        done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
        logs = done.stdout + done.stderr
        assert done.returncode == 0, logs[-4000:]
        job_id = done.stdout.splitlines()[0]
        status = subprocess.run([sys.executable, "-m", "launchers.ray_cluster", "status", job_id, "--address",
                                 cluster.dashboard_url], cwd=ROOT, env=env, capture_output=True, text=True)
        assert f"{job_id}: SUCCEEDED" in status.stdout, status.stdout + status.stderr
        node_ids = set(cluster.node_ids)

    run_dir = run_root / "two_nodes"
    assert list((run_dir / "checkpoints").glob("ckpt_*.pt")), logs[-3000:]
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["global_step"] >= 960
    placement = json.loads((run_dir / "cluster.json").read_text())
    # 2 nodes x 2 CPUs, one CPU for the learner: three rollout actors, spread over both nodes
    assert {n["node_id"] for n in placement["nodes"]} == node_ids
    assert len(placement["rollout_workers"]) == 3
    assert {w["node_id"] for w in placement["rollout_workers"]} == node_ids
    # ... and both nodes produced fragments, which the learner fetched across nodes
    assert set(placement["fragments_per_node"]) == node_ids and min(placement["fragments_per_node"].values()) > 0
    assert placement["learner"]["node_id"] in node_ids and placement["learner"]["device"] == "cpu"
    assert any(r.get("perf/remote_fragment_fraction", 0) > 0 for r in records)

    # every process the cluster ran is gone: its nodes' own processes and the rollout actors
    pids = cluster.node_pids + [w["pid"] for w in placement["rollout_workers"]] + [cluster.info["keeper_pid"]]
    assert not _still_alive(pids)
    assert not os.path.exists(cluster.temp_dir)


def test_example_cluster_yaml_is_a_valid_ray_cluster_config():
    """configs/cluster/example.yaml passes the schema `ray up` checks (Ray's autoscaler validator)."""
    import yaml
    from ray.autoscaler._private.util import prepare_config, validate_config

    config = yaml.safe_load((ROOT / "configs" / "cluster" / "example.yaml").read_text())
    validate_config(prepare_config(config))
    config["max_wrkers"] = 3  # the validator is strict: a typo is caught
    with pytest.raises(Exception, match="max_wrkers"):
        validate_config(prepare_config(config))
