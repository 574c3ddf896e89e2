"""metrics.jsonl records, offline wandb runs, resume reuses the run id, disabled mode, LagStats."""
import json
import math
import warnings

import numpy as np
import pytest
import torch

from swarm_appo.metrics import (METRIC_GROUPS, METRICS, WANDB_ID_FILE, LagStats, MetricsLogger, read_metrics,
                                swarm_metric, system_metrics)

CFG = {"algo": {"lr": 1e-4}, "env": {"num_agents": 8}}


@pytest.fixture(autouse=True)
def quiet_offline_wandb(monkeypatch, tmp_path):
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "wandb_config"))
    monkeypatch.setenv("WANDB_CACHE_DIR", str(tmp_path / "wandb_cache"))


def offline_runs(run_dir):
    return sorted((run_dir / "wandb").glob("offline-run-*"))


def test_jsonl_records_are_flushed_and_typed(tmp_path):
    run = tmp_path / "run"
    logger = MetricsLogger(run, CFG, wandb_mode="disabled", project="p", run_name="r")
    logger.log(100, {"losses/policy_loss": torch.tensor(0.5), "charts/sps": np.float32(2.0),
                     "lag/max": np.int64(3), "losses/value_loss": float("nan")})
    logger.log(200, {"charts/episode_reward": -1.25, "swarm/static_same_goal/dist": 0.4})
    records = read_metrics(run)  # readable before close: each line is flushed
    assert [r["global_step"] for r in records] == [100, 200]
    assert records[0]["losses/policy_loss"] == 0.5 and records[0]["charts/sps"] == 2.0
    assert records[0]["lag/max"] == 3 and isinstance(records[0]["lag/max"], int)
    assert records[0]["losses/value_loss"] is None  # NaN -> null keeps the file strict JSON
    assert records[1]["swarm/static_same_goal/dist"] == 0.4
    assert all(isinstance(r["time"], float) for r in records)
    logger.close()
    for line in (run / "metrics.jsonl").read_text().splitlines():
        json.loads(line, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    with pytest.raises(ValueError, match="reserved"):
        MetricsLogger(run, CFG, wandb_mode="disabled").log(1, {"global_step": 5})
    with pytest.raises(ValueError, match="scalar"):
        MetricsLogger(run, CFG, wandb_mode="disabled").log(1, {"losses/x": torch.zeros(2)})


def test_disabled_mode_creates_no_wandb_files(tmp_path):
    with MetricsLogger(tmp_path, CFG, wandb_mode="disabled") as logger:
        logger.log(1, {"charts/sps": 1.0})
        assert logger.run_id is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.jsonl"]


def test_offline_run_is_written_and_resume_reuses_its_id(tmp_path):
    run = tmp_path / "run"
    first = MetricsLogger(run, CFG, wandb_mode="offline", project="swarm-appo", run_name="run")
    sent = []  # what reached the wandb run (wandb flushes its own file asynchronously: spy, don't read it)
    real_log = first._wandb_run.log
    first._wandb_run.log = lambda data, *a, **k: (sent.append(dict(data)), real_log(data, *a, **k))
    first.log(10, {"charts/sps": 1.0, "losses/approx_kl": 0.01})
    first.close()
    assert sent == [{"global_step": 10, "charts/sps": 1.0, "losses/approx_kl": 0.01}]
    run_id = first.run_id
    assert run_id and (run / WANDB_ID_FILE).read_text().strip() == run_id
    runs = offline_runs(run)
    assert len(runs) == 1 and run_id in runs[0].name
    assert (runs[0] / f"run-{run_id}.wandb").exists()

    second = MetricsLogger(run, CFG, wandb_mode="offline", project="swarm-appo", run_name="run")
    second.log(20, {"charts/sps": 2.0})
    second.close()
    assert second.run_id == run_id
    runs = offline_runs(run)
    # wandb names a second offline directory of the same run id and second "<...>-<id>-1"
    assert len(runs) == 2 and all(run_id in r.name for r in runs)
    assert [r["global_step"] for r in read_metrics(run)] == [10, 20]


def test_explicit_resume_id_wins_and_is_stored(tmp_path):
    (tmp_path / WANDB_ID_FILE).write_text("oldid123\n")
    logger = MetricsLogger(tmp_path, CFG, wandb_mode="offline", resume_id="fromckpt1")
    logger.close()
    assert logger.run_id == "fromckpt1"
    assert (tmp_path / WANDB_ID_FILE).read_text().strip() == "fromckpt1"
    assert offline_runs(tmp_path)[0].name.endswith("fromckpt1")


def test_resume_drops_records_after_the_checkpoint_and_torn_lines(tmp_path):
    with MetricsLogger(tmp_path, CFG, wandb_mode="disabled") as logger:
        for step in (100, 200, 300):
            logger.log(step, {"charts/sps": float(step)})
    with open(tmp_path / "metrics.jsonl", "a") as f:
        f.write('{"global_step": 400, "charts/s')  # the process died mid-write
    with MetricsLogger(tmp_path, CFG, wandb_mode="disabled") as logger:  # plain reopen: only the torn line goes
        assert [r["global_step"] for r in read_metrics(tmp_path)] == [100, 200, 300]
    with MetricsLogger(tmp_path, CFG, wandb_mode="disabled", resume_step=200) as logger:
        logger.log(250, {"charts/sps": 1.0})
    assert [r["global_step"] for r in read_metrics(tmp_path)] == [100, 200, 250]


def test_names_outside_the_groups_warn_once(tmp_path):
    with MetricsLogger(tmp_path, CFG, wandb_mode="disabled") as logger:
        with pytest.warns(RuntimeWarning, match="'learner/version'"):
            logger.log(1, {"learner/version": 1.0})
        with pytest.warns(RuntimeWarning, match="'loss'"):
            logger.log(2, {"loss": 1.0})
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            logger.log(3, {"learner/version": 2.0, "losses/policy_loss": 0.1})


def test_standard_names_are_grouped():
    assert all(name.split("/")[0] in METRIC_GROUPS for name in METRICS)
    assert {name.split("/")[0] for name in METRICS} == set(METRIC_GROUPS)
    assert swarm_metric("swap_goals", "dist") == "swarm/swap_goals/dist"
    stats = system_metrics()
    assert stats["system/max_rss_mb"] > 1.0 and all(k.startswith("system/") for k in stats)


def test_system_metrics_report_the_gpu_of_a_cuda_learner_only(monkeypatch):
    """The CUDA branch without a GPU: torch.cuda's counters faked, so the names, units and the fallback
    without NVML are checked here; the real figures come from a GPU run (benchmarks/gpu_check.sh)."""
    import torch

    assert not any(k.startswith("system/gpu") for k in system_metrics(torch.device("cpu")))
    monkeypatch.setattr(torch.cuda, "memory_allocated", lambda device=None: 3 * 2**20)
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda device=None: 5 * 2**20)
    monkeypatch.setattr(torch.cuda, "utilization", lambda device=None: 87)
    stats = system_metrics(torch.device("cuda", 0))
    assert (stats["system/gpu_mem_mb"], stats["system/gpu_max_mem_mb"], stats["system/gpu_util"]) == (3.0, 5.0, 87.0)
    assert {k for k in stats if k.startswith("system/gpu")} <= set(METRICS)

    def no_nvml(device=None):
        raise ModuleNotFoundError("pynvml")

    monkeypatch.setattr(torch.cuda, "utilization", no_nvml)
    stats = system_metrics(torch.device("cuda", 0))
    assert "system/gpu_util" not in stats and stats["system/gpu_max_mem_mb"] == 5.0


def test_every_end_of_run_evaluation_metric_is_documented():
    from swarm_appo.evaluate import SUMMARY_METRICS

    names = {f"{prefix}/{name}" for name in SUMMARY_METRICS for prefix in ("eval", "eval_random")}
    assert names <= set(METRICS), sorted(names - set(METRICS))
    assert "eval/collisions_drone" in names and "eval/reward_shaping" in names


def test_lag_stats_match_numpy():
    rng = np.random.default_rng(0)
    chunks = [rng.integers(0, 20, size=(8, 5)), rng.integers(3, 40, size=7), torch.tensor([[2, 50], [1, 0]])]
    stats = LagStats()
    assert math.isnan(stats.mean) and math.isnan(stats.min)
    for chunk in chunks:
        stats.update(chunk, max_policy_lag=25)
    everything = np.concatenate([np.asarray(c).ravel() for c in chunks]).astype(float)
    assert stats.min == everything.min() and stats.max == everything.max()
    assert stats.mean == pytest.approx(everything.mean())
    assert stats.masked_fraction == pytest.approx(np.mean(everything > 25))
    assert stats.summary() == {"lag/min": stats.min, "lag/mean": stats.mean, "lag/max": stats.max,
                               "lag/masked_fraction": stats.masked_fraction}
    stats.reset()
    stats.update(np.array([4]))
    assert (stats.min, stats.mean, stats.max) == (4.0, 4.0, 4.0)


def test_resume_gives_one_wandb_history_read_back_from_the_wandb_file(tmp_path):
    """A run logs 100..400 (its .wandb file misses 400: it died right after writing metrics.jsonl), then resumes
    from a checkpoint at 300 and logs 400..600 again: the newest wandb run holds 100..600, each step once."""
    from swarm_appo.metrics import wait_for_wandb_history

    first = MetricsLogger(tmp_path, CFG, wandb_mode="offline", run_name="r")
    for step in (100, 200, 300):
        first.log(step, {"charts/sps": float(step)})
    first.close()
    with open(tmp_path / "metrics.jsonl", "a") as f:  # logged to the file, never reached wandb
        f.write(json.dumps({"global_step": 400, "time": 0.0, "charts/sps": 400.0}) + "\n")
    old_id = first.run_id

    second = MetricsLogger(tmp_path, CFG, wandb_mode="offline", run_name="r", resume_id=old_id, resume_step=300)
    for step in (400, 500, 600):
        second.log(step, {"charts/sps": float(step) + 0.5})
    second.close()
    assert second.run_id != old_id and (tmp_path / WANDB_ID_FILE).read_text().strip() == second.run_id
    newest, = [r for r in offline_runs(tmp_path) if r.name.endswith(second.run_id)]
    history = wait_for_wandb_history(newest / f"run-{second.run_id}.wandb", 6)
    assert [h["global_step"] for h in history] == [100, 200, 300, 400, 500, 600]
    assert [h["charts/sps"] for h in history][3:] == [400.5, 500.5, 600.5]  # the redone steps, not the lost ones
    oldest, = [r for r in offline_runs(tmp_path) if r.name.endswith(old_id)]
    assert [h["global_step"] for h in wait_for_wandb_history(oldest / f"run-{old_id}.wandb", 3)] == [100, 200, 300]
    assert [r["global_step"] for r in read_metrics(tmp_path)] == [100, 200, 300, 400, 500, 600]


def test_read_wandb_history_refuses_other_files(tmp_path):
    from swarm_appo.metrics import read_wandb_history

    (tmp_path / "x.wandb").write_bytes(b"not wandb")
    with pytest.raises(ValueError, match="not a wandb run file"):
        read_wandb_history(tmp_path / "x.wandb")


def test_process_age_counts_from_the_process_start():
    """A child that sleeps 1 s before asking is at least 1 s old, and younger than the parent's wall time around it."""
    import subprocess
    import sys
    import time

    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", "import time; time.sleep(1.0); "
                          "from swarm_appo.metrics import process_age_s; print(process_age_s())"],
                         capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    age = float(out.stdout.strip())
    assert 1.0 <= age <= wall + 0.02, (age, wall)  # /proc counts in clock ticks (10 ms)
