"""Metrics: one JSON line per record in ``run_dir/metrics.jsonl`` and the same record in wandb.

Every record is keyed by ``global_step`` (agent steps: one drone, one control step) and holds metrics
named ``<group>/<name>``; the groups are fixed (``METRIC_GROUPS``) and the standard names are listed in
``METRICS`` with their meaning. ``metrics.jsonl`` is enough for tests and plots; wandb runs offline by
default (``wandb sync run_dir/wandb/offline-run-*`` uploads later). Non-finite numbers are written to
the JSON file as ``null`` (strict JSON).

One history: ``metrics.jsonl`` is the source of truth. On resume from a checkpoint, records past its step
are dropped from it, and a *new* wandb run (same name and group, tag ``resumed``) starts by replaying every
record kept there, then continues: the newest wandb run of a run directory holds each global_step exactly
once, none missing (also the records that the killed run logged too late to reach its own .wandb file).
The earlier wandb runs stay as they were (histories up to each crash); ``run_dir/wandb_id.txt`` names the
newest. ``read_wandb_history`` reads an offline run's history back from its .wandb file.
"""
from __future__ import annotations

import json
import math
import os
import resource
import sys
import time
import uuid
import warnings
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence

import numpy as np

from quad_env.params import REWARD_TERMS
from swarm_appo.atomic import atomic_write_bytes
from swarm_appo.eval_tables import METRICS as TABLE_METRICS

METRICS_FILE = "metrics.jsonl"
WANDB_ID_FILE = "wandb_id.txt"
STEP_KEY = "global_step"
WANDB_MODES = ("offline", "online", "disabled")

METRIC_GROUPS = ("charts", "swarm", "reward", "losses", "lag", "perf", "system", "eval", "eval_random")

METRICS: Dict[str, str] = {
    # reward/: what the policy is paid for (quad_env.REWARD_TERMS)
    **{f"reward/{term}": f"per-agent episode sum of the reward term {term!r} (env.reward.{term} sets its weight)"
       for term in REWARD_TERMS},
    # eval/, eval_random/: end-of-run evaluation (mean actions vs uniformly random actions, same episodes), in
    # the training environment without its training aids (swarm_appo.evaluation.evaluation_env); each is the
    # episode mean of a column of the evaluation tables, unscaled (swarm_appo.eval_tables.METRICS)
    **{f"eval/{m.name}": f"{m.description}, trained policy (mean actions)" for m in TABLE_METRICS.values()},
    **{f"eval_random/{m.name}": f"{m.description}, uniformly random actions" for m in TABLE_METRICS.values()},
    "eval/dist_ratio_to_random": "eval/dist divided by eval_random/dist (learning shows as < 1; quickstart target "
                                 "<= 0.5)",
    # charts/: training progress
    "charts/episode_reward": "mean return per drone of the episodes that ended since the last record",
    "charts/episode_length": "mean length (control steps) of those episodes",
    "charts/episodes": "number of those episodes",
    "charts/sps": "agent steps per second since the last record",
    "charts/elapsed_s": "wall time since the start of this process",
    "charts/learning_rate": "Adam learning rate of the last batch (algo.lr_schedule)",
    "charts/collision_scale": "factor on the collision penalties c2, c3 and obstacle contacts in the workers' "
                              "environments (env.reward.collision_anneal_steps; 1 = the paper's reward)",
    # swarm/: the evaluation tables' metrics on the training episodes (training aids on), also per scenario as
    # swarm/<scenario>/<name> (swarm_metric)
    **{f"swarm/{m.name}": m.description for m in TABLE_METRICS.values()},
    # losses/: the learner (means over the minibatches of one learner iteration)
    "losses/policy_loss": "clipped-surrogate loss",
    "losses/value_loss": "value loss (squared error to the V-trace targets)",
    "losses/entropy": "policy entropy",
    "losses/approx_kl": "approximate KL(behaviour || current), mean((r - 1) - log r)",
    "losses/clip_fraction": "share of samples whose probability ratio left the clip range",
    "losses/explained_variance": "explained variance of the V-trace targets by the critic",
    "losses/total_loss": "the optimised loss",
    "losses/grad_norm": "global gradient norm before clipping",
    "losses/skipped_updates": "updates skipped because of a non-finite loss or gradient (cumulative)",
    # lag/: policy lag = learner version - behaviour version, per trained step (LagStats)
    "lag/min": "smallest policy lag", "lag/mean": "mean policy lag", "lag/max": "largest policy lag",
    "lag/masked_fraction": "share of steps masked out for exceeding algo.max_policy_lag",
    # perf/: throughput and where the time goes
    "perf/agent_steps_per_s": "agent steps per second (same as charts/sps)",
    "perf/learner_samples_per_s": "samples per second of learner compute",
    "perf/env_share": "share of rollout-worker time spent stepping the simulator",
    "perf/inference_share": "share of rollout-worker time spent in policy inference",
    "perf/transfer_share": "share of learner-loop time spent waiting for fragments and publishing weights",
    "perf/learner_share": "share of learner-loop time spent training",
    "perf/fetch_share": "share of learner-loop time spent fetching ready fragments (moving them to the learner's "
                        "node and deserialising them; part of perf/transfer_share; Ray only)",
    "perf/remote_fetch_share": "the same for fragments made on another node than the learner's: the cost of "
                               "moving fragments between nodes",
    "perf/remote_fragment_fraction": "share of fragments made on another node than the learner's",
    "perf/fetch_ms_local": "mean time to fetch a fragment made on the learner's node (ms)",
    "perf/fetch_ms_remote": "mean time to fetch a fragment made on another node (ms)",
    "perf/fragment_mb": "mean size of a fragment's arrays (MiB)",
    "perf/policy_version": "learner policy version (bumped once per learner iteration)",
    "perf/num_updates": "optimizer steps taken",
    "perf/worker_restarts": "rollout workers replaced after dying or stalling (cumulative)",
    "perf/worker_stalls": "rollout calls that never came back while other workers delivered; each restarted "
                          "its worker (cumulative)",
    "perf/startup_s": "first record of a process only: seconds from the process start to the first fragment in the "
                      "learner (imports, config, kernel compilation, Ray and worker start-up, one rollout)",
    # system/: resources of the learner process (system_metrics)
    "system/rss_mb": "resident memory of the learner process (MiB)",
    "system/max_rss_mb": "peak resident memory of the learner process (MiB)",
    "system/gpu_mem_mb": "GPU memory held by the learner's tensors (MiB; learner on a CUDA device only)",
    "system/gpu_max_mem_mb": "peak GPU memory of the learner's tensors since the start (MiB; CUDA only)",
    "system/gpu_util": "GPU utilisation over the last sample period, % (CUDA only, where NVML is installed)",
}


def swarm_metric(scenario: str, name: str) -> str:
    """Per-scenario name of a swarm metric, e.g. ``swarm_metric("swap_goals", "dist")`` -> ``swarm/swap_goals/dist``."""
    return f"swarm/{scenario}/{name}"


# ----------------------------------------------------------------------------------------------- lag
class LagStats:
    """Accumulates per-step policy lags (learner version - behaviour version) -> min / mean / max.

    ``update`` takes any array-like of lags (numpy, torch, list); NaN statistics mean "no step seen".
    With ``max_policy_lag`` it also counts the steps that exceed it (``masked_fraction``).
    """

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.count = 0
        self.total = 0.0
        self._min = math.inf
        self._max = -math.inf
        self.over_limit = 0

    def update(self, lags: Any, max_policy_lag: Optional[int] = None) -> None:
        if hasattr(lags, "detach"):  # torch tensor
            lags = lags.detach().cpu().numpy()
        lags = np.asarray(lags, dtype=np.float64).ravel()
        if lags.size == 0:
            return
        self.count += lags.size
        self.total += float(lags.sum())
        self._min = min(self._min, float(lags.min()))
        self._max = max(self._max, float(lags.max()))
        if max_policy_lag is not None:
            self.over_limit += int((lags > max_policy_lag).sum())

    @property
    def min(self) -> float:
        return self._min if self.count else math.nan

    @property
    def max(self) -> float:
        return self._max if self.count else math.nan

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else math.nan

    @property
    def masked_fraction(self) -> float:
        return self.over_limit / self.count if self.count else math.nan

    def summary(self) -> Dict[str, float]:
        """``{"lag/min", "lag/mean", "lag/max", "lag/masked_fraction"}``."""
        return {"lag/min": self.min, "lag/mean": self.mean, "lag/max": self.max,
                "lag/masked_fraction": self.masked_fraction}


# ----------------------------------------------------------------------------------------------- system
def process_age_s() -> Optional[float]:
    """Seconds since this process started (Linux: /proc), None where that is unknown."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22, starttime, in clock ticks
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def system_metrics(device: Any = None) -> Dict[str, float]:
    """Memory of this process: ``system/rss_mb`` (current, Linux only) and ``system/max_rss_mb`` (peak); with a
    CUDA ``device`` (the learner's) also its GPU memory and utilisation (``system/gpu_*``)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    out = {"system/max_rss_mb": peak / (2**20 if sys.platform == "darwin" else 2**10)}
    try:
        with open("/proc/self/statm") as f:
            out["system/rss_mb"] = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        pass
    if device is not None and getattr(device, "type", None) == "cuda":
        out.update(gpu_metrics(device))
    return out


def gpu_metrics(device: Any) -> Dict[str, float]:
    """``system/gpu_mem_mb``, ``system/gpu_max_mem_mb`` and, where NVML answers, ``system/gpu_util``."""
    import torch

    out = {"system/gpu_mem_mb": torch.cuda.memory_allocated(device) / 2**20,
           "system/gpu_max_mem_mb": torch.cuda.max_memory_allocated(device) / 2**20}
    try:
        out["system/gpu_util"] = float(torch.cuda.utilization(device))
    except Exception:  # no NVML (pynvml / nvidia-ml-py) in this environment: leave the utilisation out
        pass
    return out


# ----------------------------------------------------------------------------------------------- logger
def _step_of_line(line: bytes) -> float:
    try:
        return json.loads(line).get(STEP_KEY, 0)
    except ValueError:
        return math.inf  # unreadable: dropped when trimming to a resume step
def _plain(value: Any, key: str) -> Any:
    """A JSON-able scalar from numbers, numpy/torch scalars, bools and strings."""
    if hasattr(value, "detach"):  # torch tensor
        value = value.detach().cpu()
        if value.numel() != 1:
            raise ValueError(f"metric {key!r} must be a scalar, got a tensor of shape {tuple(value.shape)}")
        value = value.item()
    if isinstance(value, np.ndarray):
        if value.size != 1:
            raise ValueError(f"metric {key!r} must be a scalar, got an array of shape {value.shape}")
        value = value.item()
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, str, int, float)):
        return value
    raise TypeError(f"metric {key!r} must be a number, bool or string, got {type(value).__name__}")


class MetricsLogger:
    """Writes metric records to ``run_dir/metrics.jsonl`` and to a wandb run.

    Args:
        run_dir: the run directory (created if needed).
        cfg_dict: the resolved config as a plain dict (stored as the wandb run config).
        wandb_mode: "offline" (default), "online" or "disabled" (no wandb at all, no wandb files).
        project: wandb project.
        run_name: wandb run name (default: the run directory's name).
        resume_id: wandb run id to continue; default: the id in ``run_dir/wandb_id.txt`` if present, else new.
        entity, group, tags: wandb entity, group and tags.
        resume_step: when resuming from a checkpoint at this global step, records logged after it (by the
            run that died) are dropped from ``metrics.jsonl`` so the file has one record per step, and the wandb
            run is a new one that replays the kept records first (``resume_id`` is then ignored).
    """

    def __init__(self, run_dir: str | os.PathLike, cfg_dict: Mapping[str, Any], wandb_mode: str = "offline",
                 project: str = "swarm-appo", run_name: Optional[str] = None, resume_id: Optional[str] = None,
                 entity: Optional[str] = None, group: Optional[str] = None, tags: Sequence[str] = (),
                 resume_step: Optional[int] = None):
        if wandb_mode not in WANDB_MODES:
            raise ValueError(f"wandb_mode must be one of {list(WANDB_MODES)}, got {wandb_mode!r}")
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.run_dir / METRICS_FILE
        self._repair_jsonl(resume_step)
        self._file = open(self.path, "a", encoding="utf-8")
        self._warned_keys: set = set()
        self._wandb_run = None
        self.run_id: Optional[str] = None
        if wandb_mode != "disabled":
            replay = resume_step is not None
            if replay:  # a new wandb run with the whole history, not a continuation holding some steps twice
                resume_id, tags = uuid.uuid4().hex[:12], (*tags, "resumed")
            self._start_wandb(cfg_dict, wandb_mode, project, run_name or self.run_dir.name, resume_id, entity,
                              group, tags, write_id=not replay)
            if replay and self._wandb_run is not None:
                for record in read_metrics(self.run_dir):
                    self._wandb_run.log({k: v for k, v in record.items() if k != "time" and v is not None})
            if replay:  # named the newest only once it holds the whole history so far
                atomic_write_bytes(self.run_dir / WANDB_ID_FILE, (self.run_id + "\n").encode())

    # ------------------------------------------------------------------ wandb
    def _start_wandb(self, cfg_dict, mode, project, run_name, resume_id, entity, group, tags,
                     write_id: bool = True) -> None:
        import wandb  # imported only when used: it is slow to import

        id_file = self.run_dir / WANDB_ID_FILE
        if resume_id is None and id_file.exists():
            resume_id = id_file.read_text().strip() or None
        self.run_id = resume_id or uuid.uuid4().hex[:12]  # not from `random`: seeded runs stay reproducible
        if write_id:
            atomic_write_bytes(id_file, (self.run_id + "\n").encode())
        try:
            self._wandb_run = wandb.init(
                dir=str(self.run_dir), id=self.run_id, resume="allow", mode=mode, project=project, entity=entity,
                group=group, tags=list(tags) or None, name=run_name, config=dict(cfg_dict),
                settings=wandb.Settings(console="off"))  # leave stdout/stderr (progress bar) alone
        except Exception as e:  # e.g. "online" without a network: keep training, keep metrics.jsonl
            warnings.warn(f"wandb ({mode}) failed to start: {e}; metrics go to {self.path} only", RuntimeWarning)
            return
        # Plot everything against agent steps; wandb's own step counter would reject a resumed run's steps.
        self._wandb_run.define_metric(STEP_KEY)
        self._wandb_run.define_metric("*", step_metric=STEP_KEY)

    # ------------------------------------------------------------------ jsonl
    def _repair_jsonl(self, resume_step: Optional[int]) -> None:
        """Drop a half-written last line (the process died mid-write) and records past ``resume_step``."""
        if not self.path.exists():
            return
        raw = self.path.read_bytes()
        lines = raw.split(b"\n")
        complete = lines[:-1]  # the part after the last newline is empty or a torn record
        if resume_step is not None:
            complete = [ln for ln in complete if ln.strip() and _step_of_line(ln) <= resume_step]
        repaired = b"".join(ln + b"\n" for ln in complete)
        if repaired != raw:
            atomic_write_bytes(self.path, repaired)

    def log(self, step: int, metrics: Mapping[str, Any]) -> Dict[str, Any]:
        """Write one record at ``global_step = step``; returns the record as written to the JSON file."""
        record: Dict[str, Any] = {STEP_KEY: int(step), "time": time.time()}
        for key, value in metrics.items():
            if key in (STEP_KEY, "time"):
                raise ValueError(f"metric name {key!r} is reserved")
            self._check_name(key)
            record[key] = _plain(value, key)
        json_record = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in record.items()}
        self._file.write(json.dumps(json_record) + "\n")
        self._file.flush()
        if self._wandb_run is not None:
            self._wandb_run.log({k: v for k, v in record.items() if k != "time" and v is not None})
        return json_record

    def _check_name(self, key: str) -> None:
        group = key.split("/", 1)[0]
        if ("/" not in key or group not in METRIC_GROUPS) and key not in self._warned_keys:
            self._warned_keys.add(key)
            warnings.warn(f"metric {key!r} is outside the standard groups {list(METRIC_GROUPS)} "
                          f"(name it '<group>/<name>')", RuntimeWarning, stacklevel=3)

    def close(self) -> None:
        """Flush and close the JSON file and finish the wandb run (safe to call twice)."""
        if not self._file.closed:
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
        if self._wandb_run is not None:
            self._wandb_run.finish()
            self._wandb_run = None

    def __enter__(self) -> "MetricsLogger":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_metrics(run_dir: str | os.PathLike) -> list:
    """All records of ``run_dir/metrics.jsonl`` as dicts (for tests, plots and benchmarks)."""
    path = Path(run_dir) / METRICS_FILE
    if not path.exists():
        return []
    with open(path, encoding="utf-8") as f:
        return [json.loads(line) for line in f if line.strip()]


def wait_for_wandb_history(wandb_file: str | os.PathLike, num_records: int, timeout_s: float = 60.0) -> list:
    """``read_wandb_history`` once the file holds ``num_records`` history records (wandb's service may still be
    writing just after ``finish()`` on a loaded machine), or what it holds after ``timeout_s``."""
    end = time.monotonic() + timeout_s
    while True:
        history = read_wandb_history(wandb_file) if Path(wandb_file).exists() else []
        if len(history) >= num_records or time.monotonic() > end:
            return history
        time.sleep(0.2)


def read_wandb_history(wandb_file: str | os.PathLike) -> list:
    """The history records (dicts, in logged order) of an offline run's ``run-<id>.wandb`` file, read with
    wandb's own record schema (``wandb.proto.wandb_internal_pb2.Record``) from its block format: a 7-byte
    header, then 32 KiB blocks of chunks (crc32 (4), length (2), type (1: full, 2: first, 3: middle, 4: last))."""
    import struct

    from wandb.proto import wandb_internal_pb2 as pb

    data = Path(wandb_file).read_bytes()
    if data[:4] != b":W&B":
        raise ValueError(f"{wandb_file} is not a wandb run file")
    block, pos, pending, history = 32768, 7, b"", []
    while pos + 7 <= len(data):
        left = block - pos % block
        if left < 7:  # the block's tail is padding
            pos += left
            continue
        _crc, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        if length == 0 and kind == 0:
            pos += left
            continue
        pending += data[pos + 7:pos + 7 + length]
        pos += 7 + length
        if kind in (1, 4):  # a full record, or the last chunk of one
            record = pb.Record()
            record.ParseFromString(pending)
            pending = b""
            if record.WhichOneof("record_type") == "history":
                history.append({item.key or "/".join(item.nested_key): json.loads(item.value_json)
                                for item in record.history.item})
    return history
