"""The training loop: sampler -> learner -> publish weights -> log -> checkpoint, until the step budget.

    cfg = load_config("configs/quickstart.yaml", ["env.num_agents=16"])
    result = train(cfg)                       # new run in runs/<name>
    result = train(None, resume_dir=result.run_dir)   # continue it

The loop lives in the driver process together with the learner; rollout workers are Ray actors
(or in-process objects in serial mode), on this machine or, with ``runner.ray_address``, spread over the
nodes of a Ray cluster (``swarm_appo.cluster``). Counters, weights, optimizer, RNG states and the wandb run id
are checkpointed atomically, so a run killed at any moment resumes from its last checkpoint.
"""
from __future__ import annotations

import errno
import logging
import os
import random
import shutil
import signal
import threading
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

import numpy as np
import torch

from quad_env import REWARD_TERMS, VecQuadEnv
from swarm_appo.checkpoint import TrainingState, capture_rng_states, restore_rng_states
from swarm_appo.config import (ConfigError, TrainConfig, config_from_dict, config_to_dict, save_config, validate,
                               yaml_load)
from swarm_appo.eval_tables import METRICS as TABLE_METRICS
from swarm_appo.evaluation import compare_with_random, default_eval_seed
from swarm_appo.learner import Learner
from swarm_appo.metrics import MetricsLogger, process_age_s, system_metrics
from swarm_appo.model import model_factory
from swarm_appo.precision import resolve_precision
from swarm_appo.sampling import SerialSampler, fragment_nbytes

log = logging.getLogger(__name__)


class TrainingError(RuntimeError):
    """Training stopped by an error (the run directory is intact; the message names the checkpoint to resume)."""


class GracefulStop:
    """While active, SIGINT (Ctrl-C) and SIGTERM only set ``requested``: the loop stops at the next iteration
    boundary, so the final checkpoint is a state the run really passed through (whole learner iterations,
    published weights, no untrained fragment counted). A second Ctrl-C raises KeyboardInterrupt at once.
    Outside the main thread (signals cannot be caught there) it does nothing."""

    def __init__(self):
        self.requested: Optional[str] = None
        self._previous: Dict[int, Any] = {}

    def __enter__(self) -> "GracefulStop":
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name
        log.warning("%s: stopping after this learner iteration, with a final checkpoint (Ctrl-C again to stop at "
                    "once, keeping the last checkpoint)", self.requested)

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()


def stopped_by_error(exc: BaseException, run_dir: Path, last_ckpt: Optional[Path]) -> TrainingError:
    """What to tell the user when ``exc`` ends training: what happened, what to do first, how to resume."""
    if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
        return TrainingError(f"the disk holding {run_dir} is full ({exc.strerror}). Free space there first, then "
                             f"resume from the last checkpoint ({last_ckpt}) with --resume {run_dir}")
    return TrainingError(f"training stopped by an error in the learner loop ({type(exc).__name__}: {exc}). "
                         f"The run directory {run_dir} is intact; resume it from its last checkpoint "
                         f"({last_ckpt}) with --resume {run_dir}")


_STARTUP_LOGGED = False  # perf/startup_s is logged by the first run of a process only


@dataclass
class RunResult:
    run_dir: Path
    agent_steps: int
    policy_version: int
    checkpoint: Optional[Path]
    worker_restarts: int
    interrupted: bool = False
    final_eval: Optional[Dict[str, float]] = None
    stopped_by: str = "steps"  # "steps" (the budget), "time" (runner.time_limit_s) or "interrupted"
    planned_agent_steps: int = 0


PROGRESS_UNITS = 1000  # the progress bar counts in thousandths of the run


def progress_units(cfg: TrainConfig, agent_steps: int, elapsed_s: float) -> int:
    """How far the run is toward whichever limit it reaches first, in PROGRESS_UNITS."""
    done = agent_steps / cfg.runner.total_agent_steps
    if cfg.runner.time_limit_s > 0:
        done = max(done, elapsed_s / cfg.runner.time_limit_s)
    return min(PROGRESS_UNITS, int(PROGRESS_UNITS * done))


def fresh_run_dir(root: Path, name: str) -> Path:
    """``root/name``, or ``root/name_2``, ``_3``... if that already holds a run: a new run never
    overwrites an old one (resume one explicitly with ``--resume``)."""
    candidate, n = root / name, 1
    while (candidate / "config.yaml").exists():
        n += 1
        candidate = root / f"{name}_{n}"
    if n > 1:
        log.warning("%s already holds a run; this run goes to %s (resume the old one with --resume)",
                    root / name, candidate)
    return candidate


def remove_failed_start(run_dir: Path, existed_before: Optional[set]) -> None:
    """Delete what a fresh run that failed to start wrote into ``run_dir`` (all of it if the folder is new;
    else only the entries not in ``existed_before``)."""
    if existed_before is None:
        shutil.rmtree(run_dir, ignore_errors=True)
    else:
        for entry in set(run_dir.iterdir()) - existed_before:
            if entry.is_dir():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
    log.warning("the run failed to start; removed what it had written to %s", run_dir)


def init_policy(cfg: TrainConfig) -> TrainingState:
    """The checkpoint ``runner.init_checkpoint`` names, checked to fit ``cfg``: the same ``model`` options (but for
    the ``init_*`` ones, which only set a fresh network's initial values) and weights that load into this run's
    network. Every problem is a ConfigError naming the key."""
    from swarm_appo.checkpoint import CheckpointCorruptError

    path = Path(cfg.runner.init_checkpoint)
    key = "runner.init_checkpoint"
    try:
        if path.is_dir():
            state, _ = TrainingState.load_latest(path)
            if state is None:
                raise ConfigError(f"{key}: no valid checkpoint in {path / 'checkpoints'}")
        elif path.is_file():
            state = TrainingState.load(path)
        else:
            raise ConfigError(f"{key}: {path} does not exist (give a checkpoint file or a run directory)")
    except CheckpointCorruptError as exc:
        raise ConfigError(f"{key}: {exc}") from exc
    try:  # (through the config loader: keys an older checkpoint lacks take their defaults)
        theirs = config_to_dict(config_from_dict(state.config))["model"]
    except ConfigError as exc:
        raise ConfigError(f"{key}: the config saved in {path} does not load: {exc}") from exc
    ours = config_to_dict(cfg)["model"]
    differ = [f"model.{k}: {theirs.get(k)!r} there, {ours[k]!r} here" for k in ours
              if not k.startswith("init_") and theirs.get(k) != ours[k]]
    if differ:
        raise ConfigError(f"{key}: the policy of {path} was trained with other model options: {'; '.join(differ)}")
    try:
        model_factory(cfg.env.obs_layout(), cfg.model)().load_state_dict(state.learner["model"])
    except (RuntimeError, KeyError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConfigError(f"{key}: the weights of {path} do not fit this run's network (its observation layout: "
                          f"env.num_neighbors, env.neighbor_obs, env.obstacles?): {first}") from exc
    return state


def pick_device(name: str) -> torch.device:
    """The learner's device for ``runner.device``; ConfigError (before any run directory exists) if it is absent."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ConfigError(f"runner.device={name} but this machine has no CUDA device; use 'auto' or 'cpu'")
        if device.index is not None and device.index >= count:
            raise ConfigError(f"runner.device={name} but this machine has {count} CUDA device(s) (0..{count - 1})")
    return device


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def on_cluster(cfg: TrainConfig) -> bool:
    return cfg.runner.ray_address is not None and not cfg.runner.serial


def num_rollout_workers(cfg: TrainConfig) -> int:
    """runner.num_workers, or 0 = fit the cores (of this machine, or of the whole cluster; Ray must be up)."""
    if cfg.runner.num_workers > 0:
        return cfg.runner.num_workers
    if on_cluster(cfg):
        from swarm_appo.cluster import cluster_rollout_workers
        return cluster_rollout_workers()
    return max(1, (os.cpu_count() or 2) - 1)  # one core stays with the learner


def learner_threads(cfg: TrainConfig, num_workers: int) -> int:
    """runner.learner_threads, or 0 = the cores this machine has left after its rollout workers (at least 1):
    learner threads + rollout workers never exceed the cores (oversubscribed, both slow down several-fold).
    In serial mode the workers take turns with the learner, so it gets every core; on a cluster the workers are
    spread over the nodes and this node keeps one core per worker it may host."""
    if cfg.runner.learner_threads > 0:
        return cfg.runner.learner_threads
    cores = os.cpu_count() or 1
    if cfg.runner.serial:
        return cores
    local_workers = num_workers if not on_cluster(cfg) else min(num_workers, cores - 1)
    return max(1, cores - local_workers)


def scheduled_lr(cfg: TrainConfig, agent_steps: int) -> float:
    """The learning rate for a batch trained at ``agent_steps`` (``algo.lr_schedule``); a function of the step
    count only, so a resumed run continues the same schedule."""
    if cfg.algo.lr_schedule == "linear":
        return cfg.algo.lr * max(0.0, 1.0 - agent_steps / cfg.runner.total_agent_steps)
    return cfg.algo.lr


def env_schedule(cfg: TrainConfig, agent_steps: int) -> Dict[str, float]:
    """The environment values of the training schedule at ``agent_steps``, published with the weights: the
    collision penalties' scale ``min(1, agent_steps / env.reward.collision_anneal_steps)`` (1 when off). A
    function of the step count only, so a resumed run continues the same schedule."""
    anneal = cfg.env.reward.collision_anneal_steps
    return {"collision_scale": min(1.0, agent_steps / anneal) if anneal > 0 else 1.0}


def model_group(cfg: TrainConfig) -> str:
    """Default wandb group: runs of one architecture and symmetry side by side (``deepsets/se3``)."""
    import encoders
    arch, symmetry = encoders.resolve(cfg.model.encoder, cfg.model.symmetry)
    return f"{arch}/{symmetry}"


def model_tags(cfg: TrainConfig) -> tuple:
    """Tags every run gets, to filter a dashboard: architecture, symmetry, size and scenario."""
    import encoders
    arch, symmetry = encoders.resolve(cfg.model.encoder, cfg.model.symmetry)
    return (arch, f"symmetry:{symmetry}", f"size:{cfg.model.size}", f"scenario:{cfg.env.scenario}")


def max_fragments_in_flight(cfg: TrainConfig, num_workers: int) -> int:
    return cfg.runner.max_fragments_in_flight or 2 * num_workers  # 0 = auto: one queued behind each running


# swarm/<name> <- episode-stats key (the paper's Table 1 columns; definitions in the README)
def summarize_episodes(episodes: List[Dict[str, Any]]) -> Dict[str, float]:
    """charts/ and swarm/ records from the swarm episodes that ended since the last log."""
    if not episodes:
        return {}
    out = {"charts/episode_reward": float(np.mean([e["return"] for e in episodes])),
           "charts/episode_length": float(np.mean([e["length"] for e in episodes])),
           "charts/episodes": float(len(episodes))}
    by_scenario: Dict[str, List[Dict[str, Any]]] = defaultdict(list)
    for e in episodes:
        by_scenario[e.get("scenario", "unknown")].append(e)
    for term in REWARD_TERMS:
        vals = [e[f"rew_{term}"] for e in episodes if f"rew_{term}" in e]
        if vals:
            out[f"reward/{term}"] = float(np.mean(vals))
    # swarm/<name>: the evaluation tables' metrics (eval_tables.METRICS) on the training episodes, with the
    # training aids on; also per scenario as swarm/<scenario>/<name>
    groups = [("", episodes), *((f"{scen}/", eps) for scen, eps in by_scenario.items())]
    for metric in TABLE_METRICS.values():
        for scope, eps in groups:
            vals = [metric.value(e) for e in eps if metric.available(e)]
            if vals:
                out[f"swarm/{scope}{metric.name}"] = float(np.mean(vals))
    return out


def fetch_metrics(timers: Dict[str, float], driver_time: float) -> Dict[str, float]:
    """perf/ records of fragment fetching (Ray samplers): share of the learner loop, ms per fragment, size."""
    n_local, n_remote = timers["fragments_local"], timers["fragments_remote"]
    if n_local + n_remote == 0:
        return {}
    out = {"perf/fetch_share": (timers["fetch_local"] + timers["fetch_remote"]) / driver_time,
           "perf/remote_fetch_share": timers["fetch_remote"] / driver_time,
           "perf/remote_fragment_fraction": n_remote / (n_local + n_remote),
           "perf/fragment_mb": timers["fragment_bytes"] / (n_local + n_remote) / 2**20}
    if n_local:
        out["perf/fetch_ms_local"] = 1e3 * timers["fetch_local"] / n_local
    if n_remote:
        out["perf/fetch_ms_remote"] = 1e3 * timers["fetch_remote"] / n_remote
    return out


def _start_sampling(cfg: TrainConfig, make_model, learner: Learner, device: torch.device, run_dir: Path):
    """The sampler (serial, or Ray rollout actors on this machine or a cluster), the number of rollout workers,
    and on a cluster the placement of the learner and the workers (written to cluster.json)."""
    sampler_seed = cfg.runner.seed + 7919 * learner.version  # a resumed run does not replay old episodes
    store_values = cfg.algo.value_clip is not None  # behaviour values are only needed for value clipping
    placement = None  # on a cluster: where the learner and each rollout worker run (cluster.json)
    if cfg.runner.serial:
        num_workers = num_rollout_workers(cfg)
        sampler = SerialSampler(cfg.env, make_model, num_workers, cfg.runner.envs_per_worker, cfg.algo.rollout,
                                sampler_seed, store_values=store_values,
                                precision=cfg.runner.inference_precision)
    else:
        from swarm_appo.ray_sampling import RaySampler, init_ray  # only here: a serial run needs no Ray

        init_ray(cfg.runner.ray_address)
        num_workers = num_rollout_workers(cfg)
        cluster_options = {}
        if on_cluster(cfg):
            from swarm_appo.cluster import READY_TIMEOUT_S, Placement
            placement = Placement(cfg.runner.ray_address, device)
            cluster_options = dict(scheduling_strategy="SPREAD", ready_timeout_s=READY_TIMEOUT_S)
        sampler = RaySampler(cfg.env, make_model, num_workers, cfg.runner.envs_per_worker, cfg.algo.rollout,
                             sampler_seed, max_in_flight=max_fragments_in_flight(cfg, num_workers),
                             store_values=store_values, precision=cfg.runner.inference_precision,
                             **cluster_options)
        if placement is not None:
            placement.set_workers(sampler.worker_locations())
            placement.write(run_dir)
            log.info("learner on %s (%s); %d rollout workers on %d node(s), details in %s",
                     placement.learner["ip"], device, num_workers,
                     len({w["node_id"] for w in placement.workers}), run_dir / "cluster.json")
    return sampler, num_workers, placement


def train(cfg: Optional[TrainConfig], resume_dir: Optional[str] = None, progress: bool = True,
          on_iteration: Optional[Callable[[int, Any], None]] = None) -> RunResult:
    """Run (or resume) one training run; returns where it ended.

    ``on_iteration(policy_version, sampler)``, if given, is called after every learner iteration
    (monitoring, fault-injection in tests).
    """
    with Trainer(cfg, resume_dir, progress, on_iteration) as trainer:
        return trainer.run()


class Trainer:
    """One training run, read top to bottom: ``__init__`` (run directory, config, learner, resumed state),
    ``start()`` (metrics, wandb, samplers), ``run()`` (the loop of ``iteration()`` + ``record()`` +
    ``checkpoint()``, then the final checkpoint and ``final_eval()``), and an idempotent ``close()`` that
    ``__exit__`` calls whatever happened, so metrics.jsonl and the wandb run are always closed."""

    def __init__(self, cfg: Optional[TrainConfig], resume_dir: Optional[str] = None, progress: bool = True,
                 on_iteration: Optional[Callable[[int, Any], None]] = None):
        self.progress, self.on_iteration, self.resume_dir = progress, on_iteration, resume_dir
        # ------------------------------------------------------------ run directory and config
        state: Optional[TrainingState] = None
        if resume_dir is not None:
            run_dir = Path(resume_dir)
            state, ckpt_path = TrainingState.load_latest(run_dir)
            if cfg is None:
                cfg = config_from_dict(yaml_load((run_dir / "config.yaml").read_text()))
            if state is None:  # killed before its first checkpoint: nothing to continue, one history to keep
                log.warning("%s has no checkpoint yet: starting it afresh at step 0 (its metrics so far are "
                            "dropped, a new wandb run is made)", run_dir)
                (run_dir / "wandb_id.txt").unlink(missing_ok=True)
            else:
                log.info("resuming %s from %s", run_dir, ckpt_path)
        assert cfg is not None, "train() needs a config or a run directory to resume"
        validate(cfg)
        # A fresh run may start from another run's policy; whether it fits is checked before a run dir exists.
        init_state = init_policy(cfg) if resume_dir is None and cfg.runner.init_checkpoint else None
        if cfg.runner.ray_address is not None and not cfg.runner.serial:
            from swarm_appo.ray_sampling import check_reachable

            check_reachable(cfg.runner.ray_address)  # before a run dir exists: a typo leaves nothing behind
        self.device = pick_device(cfg.runner.device)
        precision, why = resolve_precision(cfg.runner.precision, self.device, cfg.model.size)
        if resume_dir is None:
            run_dir = fresh_run_dir(Path(cfg.runner.run_dir), cfg.runner.name or time.strftime("run_%Y%m%d_%H%M%S"))
        inference, inference_why = resolve_precision(cfg.runner.inference_precision, torch.device("cpu"),
                                                     cfg.model.size)
        precisions = (f"learner precision {precision} ({why}); rollout inference on this machine's CPU "
                      f"{inference} ({inference_why})")
        # A fresh run that fails to start (Ray's raylet timing out under load, ...) removes what it made, so no
        # half-made run dir is left to confuse --resume; entries that were there before are kept.
        self._existed_before = set(run_dir.iterdir()) if resume_dir is None and run_dir.is_dir() else None
        try:
            run_dir.mkdir(parents=True, exist_ok=True)
            save_config(cfg, run_dir / "config.yaml", notes=[f"on this machine: {precisions}"])
        except OSError as exc:  # read-only, not a folder, disk full: one line naming the key, not a traceback
            raise ConfigError(f"runner.run_dir: cannot write the run directory {run_dir}: "
                              f"{exc.strerror or exc}") from exc
        log.info(precisions)
        self.cfg, self.run_dir, self.resumed_state = cfg, run_dir, state

        seed_everything(cfg.runner.seed)
        self.make_model = model_factory(cfg.env.obs_layout(), cfg.model)
        self.learner = Learner(self.make_model(), cfg.algo, self.device, seed=cfg.runner.seed, precision=precision,
                               compile=cfg.runner.compile)
        self.agent_steps = 0
        if state is not None:
            self.learner.load_state_dict(state.learner)
            self.agent_steps = state.agent_steps
            restore_rng_states(state.rng)
        elif init_state is not None:
            self.learner.model.load_state_dict(init_state.learner["model"])
            log.info("initialised from %s (%s agent steps of run %s); optimizer, counters and schedules start afresh",
                     cfg.runner.init_checkpoint, f"{init_state.agent_steps:,}",
                     init_state.config.get("runner", {}).get("name"))

        # Compile the numba kernels once here, so workers load them from the on-disk cache.
        VecQuadEnv(cfg.env, num_envs=1, seed=0).step(np.zeros((cfg.env.num_agents, 4), np.float32))

        self.stop = GracefulStop()
        self.logger: Optional[MetricsLogger] = None
        self.sampler = self.placement = self.bar = None
        self.num_workers = 0
        self.last_ckpt: Optional[Path] = None
        self.last_reward: Optional[float] = None
        self._closed = False

    # ---------------------------------------------------------------- start-up
    def start(self) -> None:
        """Metrics logger (and wandb run), samplers, the first published weights, the progress bar."""
        cfg = self.cfg
        # From here on SIGINT / SIGTERM only ask to stop (GracefulStop): a signal during start-up (wandb, Ray, the
        # workers) ends the run before its first iteration, with a final checkpoint and everything closed.
        self.stop.__enter__()
        try:
            state = self.resumed_state
            self.logger = MetricsLogger(
                self.run_dir, config_to_dict(cfg), wandb_mode=cfg.wandb.mode, project=cfg.wandb.project,
                run_name=self.run_dir.name, resume_id=state.wandb_id if state else None, entity=cfg.wandb.entity,
                group=cfg.wandb.group or model_group(cfg), tags=tuple(dict.fromkeys((*cfg.wandb.tags,
                                                                                     *model_tags(cfg)))),
                resume_step=self.agent_steps if self.resume_dir is not None else None)
            self.sampler, self.num_workers, self.placement = _start_sampling(cfg, self.make_model, self.learner,
                                                                             self.device, self.run_dir)
        except BaseException:
            self.close()
            if self.resume_dir is None:
                remove_failed_start(self.run_dir, self._existed_before)
            raise
        threads = learner_threads(cfg, self.num_workers)
        torch.set_num_threads(threads)  # after the samplers: an in-process RolloutWorker sets 1 thread
        log.info("learner: %d torch thread(s) on %s; %d rollout worker(s)", threads, self.device, self.num_workers)
        self.publish()
        if self.progress:  # progress toward whichever limit applies: the step budget or, if set, the time limit
            from tqdm.auto import tqdm
            self.bar = tqdm(total=PROGRESS_UNITS, unit="‰", dynamic_ncols=True, desc=self.run_dir.name,
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}{postfix}")

    def publish(self) -> None:
        """The learner's weights, with the training schedule's environment values, to the rollout workers."""
        self.schedule = env_schedule(self.cfg, self.agent_steps)  # also logged by record()
        self.sampler.publish(*self.learner.cpu_weights(), self.schedule)

    # ---------------------------------------------------------------- one iteration
    def iteration(self, batch: List[Dict[str, Any]], batch_steps: int) -> Dict[str, float]:
        """Train on one batch of fragments and publish the new weights; returns the learner's stats. Between
        ``learner.train`` and the publish the learner's weights match no published version (``mid_iteration``)."""
        self.agent_steps += batch_steps
        lr = scheduled_lr(self.cfg, self.agent_steps)
        for group in self.learner.optimizer.param_groups:
            group["lr"] = lr
        self.mid_iteration = True
        t1 = time.perf_counter()
        stats = self.learner.train(batch)
        self.timers["learner"] += time.perf_counter() - t1
        self.timers["learner_samples"] += batch_steps
        t2 = time.perf_counter()
        self.publish()
        self.mid_iteration = False
        self.timers["publish"] += time.perf_counter() - t2
        return stats

    def record(self, stats: Dict[str, float], episodes: List[Dict[str, Any]], now: float) -> Dict[str, float]:
        """One metrics record: learner stats, episodes since the last record, speeds and time shares."""
        timers = self.timers
        record = dict(stats)
        record.update(summarize_episodes(episodes))
        if "charts/episode_reward" in record:
            self.last_reward = record["charts/episode_reward"]
        wall = max(now - self.t_log, 1e-9)
        driver = max(timers["wait"] + timers["learner"] + timers["publish"], 1e-9)
        worker = max(timers["env"] + timers["inference"], 1e-9)
        record.update({
            "charts/sps": (self.agent_steps - self.steps_at_log) / wall,
            "perf/agent_steps_per_s": (self.agent_steps - self.steps_at_log) / wall,
            "perf/learner_samples_per_s": timers["learner_samples"] / max(timers["learner"], 1e-9),
            "perf/transfer_share": (timers["wait"] + timers["publish"]) / driver,
            "perf/learner_share": timers["learner"] / driver,
            "perf/env_share": timers["env"] / worker,
            "perf/inference_share": timers["inference"] / worker,
            "perf/worker_restarts": float(self.sampler.restarts),
            "perf/worker_stalls": float(self.sampler.stalls),
            "charts/elapsed_s": now - self.t_start,
            "charts/learning_rate": self.learner.optimizer.param_groups[0]["lr"],
            "charts/collision_scale": self.schedule["collision_scale"],
        })
        global _STARTUP_LOGGED
        if self.startup_s is not None and self.startup_s >= 0 and not _STARTUP_LOGGED:
            record["perf/startup_s"] = self.startup_s  # only the process's first run measures a start-up
            _STARTUP_LOGGED = True
        record.update(fetch_metrics(timers, driver))
        record.update(system_metrics(self.device))
        return record

    def checkpoint(self) -> Path:
        """Write the training state (atomically) at ``agent_steps``, scored by the last training return."""
        state = TrainingState(learner=self.learner.state_dict(), agent_steps=self.agent_steps,
                              config=config_to_dict(self.cfg), rng=capture_rng_states(), wandb_id=self.logger.run_id)
        self.last_ckpt = state.save(self.run_dir, metric=self.last_reward, keep_last=self.cfg.runner.keep_checkpoints)
        return self.last_ckpt

    def _count_fragment(self, frag: Dict[str, Any]) -> None:
        timers, placement = self.timers, self.placement
        timers["env"] += frag["env_time_s"]
        timers["inference"] += frag["inference_time_s"]
        if "fetch_time_s" in frag:  # Ray: moving the fragment to this node + deserialising (part of wait)
            remote = "remote" if placement is not None and frag["node_id"] != placement.learner_node else "local"
            timers[f"fetch_{remote}"] += frag["fetch_time_s"]
            timers[f"fragments_{remote}"] += 1
            timers["fragment_bytes"] += fragment_nbytes(frag)
        if placement is not None:
            placement.count(frag)

    def _after_iteration(self, record: Dict[str, float]) -> None:
        """Progress bar, the skipped-updates guard and the periodic checkpoint."""
        cfg, learner = self.cfg, self.learner
        if self.bar is not None:
            self.bar.update(progress_units(cfg, self.agent_steps, time.perf_counter() - self.t_start) - self.bar.n)
            skipped = {"skipped": learner.skipped_updates} if learner.skipped_updates else {}
            self.bar.set_postfix(steps=f"{self.agent_steps:,}", sps=f"{record['charts/sps']:.0f}",
                                 reward=f"{self.last_reward:.2f}" if self.last_reward is not None else "-",
                                 lag=f"{record['lag/mean']:.1f}", **skipped, refresh=False)
        limit = cfg.algo.max_consecutive_skips
        if limit and learner.consecutive_skips >= limit:
            raise TrainingError(
                f"{learner.consecutive_skips} consecutive updates skipped (non-finite loss or gradient; "
                f"algo.max_consecutive_skips={limit}): this run cannot learn. Check the reward and the "
                f"learning rate; the run directory {self.run_dir} is intact and its last checkpoint "
                f"({self.last_ckpt}) precedes the failure; resume it with --resume {self.run_dir}")
        every_updates = cfg.runner.checkpoint_every_updates
        by_updates = every_updates and learner.version % every_updates == 0
        if time.perf_counter() - self.t_ckpt >= cfg.runner.checkpoint_every_s or by_updates:
            self.checkpoint()
            self.t_ckpt = time.perf_counter()

    # ---------------------------------------------------------------- the run
    def run(self) -> RunResult:
        cfg = self.cfg
        self.start()
        # agent_steps counts trained fragments only: a batch is counted when the learner has trained on it, and a
        # batch still being collected when the run stops is dropped, so a checkpoint never counts untrained steps.
        batch: List[Dict[str, Any]] = []
        episodes: List[Dict[str, Any]] = []
        self.timers = defaultdict(float)  # driver wall time per phase, and worker time per phase
        self.t_start = self.t_log = self.t_ckpt = time.perf_counter()
        self.steps_at_log = self.agent_steps
        interrupted = False
        self.startup_s: Optional[float] = None  # process start -> first fragment (perf/startup_s)
        self.mid_iteration = False  # the learner is between its first update and publishing the new version
        try:
            time_limit = cfg.runner.time_limit_s or float("inf")
            while (self.agent_steps < cfg.runner.total_agent_steps and time.perf_counter() - self.t_start < time_limit
                   and self.stop.requested is None):
                t0 = time.perf_counter()
                frag = self.sampler.get()  # [T, B] fragment
                self.timers["wait"] += time.perf_counter() - t0
                if self.startup_s is None:
                    self.startup_s = process_age_s() or -1.0  # logged once, with the first record
                self._count_fragment(frag)
                episodes.extend(frag["episode_stats"])
                batch.append(frag)
                batch_steps = sum(f["num_agent_steps"] for f in batch)
                if batch_steps < cfg.algo.batch_size:
                    continue
                stats = self.iteration(batch, batch_steps)
                batch = []
                now = time.perf_counter()
                record = self.record(stats, episodes, now)
                episodes = []
                self.logger.log(self.agent_steps, record)
                if self.on_iteration is not None:
                    self.on_iteration(self.learner.version, self.sampler)
                self.timers.clear()
                self.t_log, self.steps_at_log = now, self.agent_steps
                self._after_iteration(record)
        except KeyboardInterrupt:  # a second Ctrl-C: stop now
            interrupted = True
            if self.mid_iteration:
                log.warning("interrupted inside a learner iteration: no final checkpoint (its weights match no "
                            "published version); the last one is %s", self.last_ckpt)
            else:
                log.warning("interrupted: writing a final checkpoint to %s", self.run_dir)
        except TrainingError:
            raise
        except Exception as exc:
            raise stopped_by_error(exc, self.run_dir, self.last_ckpt) from exc
        finally:
            self.stop.__exit__()
        if self.stop.requested is not None:
            interrupted = True
            log.warning("%s: stopped at an iteration boundary, writing a final checkpoint to %s", self.stop.requested,
                        self.run_dir)
        if not (interrupted and self.mid_iteration):
            try:
                self.checkpoint()
            except OSError as exc:  # e.g. the disk filled up: the earlier checkpoints are intact
                raise stopped_by_error(exc, self.run_dir, self.last_ckpt) from exc
        if self.placement is not None:
            try:
                self.placement.set_workers(self.sampler.worker_locations())  # replacements may sit elsewhere
            except Exception:  # a worker died just now: keep the last known placement
                pass
            self.placement.write(self.run_dir, worker_restarts=self.sampler.restarts)
        restarts = self.sampler.restarts
        self._close_sampling()
        stopped_by = ("interrupted" if interrupted else "steps" if self.agent_steps >= cfg.runner.total_agent_steps
                      else "time")
        if stopped_by == "time":
            log.warning("time limit reached (runner.time_limit_s=%g): %s of the planned %s agent steps (%.0f%%)",
                        cfg.runner.time_limit_s, f"{self.agent_steps:,}", f"{cfg.runner.total_agent_steps:,}",
                        100.0 * self.agent_steps / cfg.runner.total_agent_steps)
        final_eval = self.final_eval() if cfg.runner.final_eval_episodes > 0 and not interrupted else {}
        return RunResult(self.run_dir, self.agent_steps, self.learner.version, self.last_ckpt, restarts, interrupted,
                         final_eval, stopped_by, cfg.runner.total_agent_steps)

    def final_eval(self) -> Dict[str, float]:
        """The end-of-run evaluation (trained policy and random actions on the same seeded episodes), logged."""
        cfg = self.cfg
        log.info("end-of-run evaluation: %d seeded episodes of %g s, trained policy and random actions, "
                 "training aids off", cfg.runner.final_eval_episodes, cfg.env.episode_duration)
        # in swarm_appo.evaluation.evaluation_env(cfg.env): the training aids off, as the command line evaluates
        result = compare_with_random(cfg.env, self.learner.model, cfg.runner.final_eval_episodes,
                                     seed=default_eval_seed(cfg.runner.seed), progress=self.progress)
        self.logger.log(self.agent_steps, result)
        return result

    # ---------------------------------------------------------------- clean-up
    def _close_sampling(self) -> None:
        if self.sampler is not None:
            self.sampler.close()
            self.sampler = None
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def close(self) -> None:
        """Samplers, progress bar, signal handlers, metrics.jsonl and the wandb run; safe to call again."""
        if self._closed:
            return
        self._closed = True
        self._close_sampling()
        self.stop.__exit__()
        if self.logger is not None:
            self.logger.close()

    def __enter__(self) -> "Trainer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
