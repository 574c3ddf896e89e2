"""Rollout workers as Ray actors (``RaySampler``), with the same three calls as ``sampling.SerialSampler``,
and starting or joining Ray (``init_local_ray``, ``init_ray``).

On a cluster the rollout actors are spread over the nodes (``scheduling_strategy="SPREAD"``), every
fragment carries the id of the node that produced it, and the sampler times how long fetching each ready
fragment takes (``fetch_time_s``: moving it to the learner's node, when it was made elsewhere, plus
deserialising it), so the trainer can report the cost of moving fragments between nodes.

The Ray sampler bounds the fragments in flight (backpressure): at most ``max_in_flight`` rollout
calls are outstanding, so workers idle rather than run ahead of a slow learner, which bounds policy lag.
Weights go through a small ``WeightsStore`` actor that holds the newest version itself: a worker asks
it at the *start* of every fragment, so a call that waited in an actor's queue still acts with the
newest weights (passing the weights with the call would freeze the version at submission). The store
holds values, not object references: an ObjectRef handed to an actor inside a container is a borrowed
reference, and Ray's owner-side bookkeeping of borrowed references grew the learner by ~1 KB per
published version (benchmarks/RESULTS.md, "reliability": a 1-hour soak grew 13 % that way).

A watchdog replaces a rollout actor whose call never comes back while the others keep delivering
(``StallPolicy``). On a two-node test cluster about one submission in four had a worker whose two calls
had FINISHED in Ray's task table but never became ready at the driver: without the watchdog that worker
stays silent for the rest of the run. A stalled call is first tried once more with ``ray.get``; if that
times out too, the actor is killed and restarted like a dead one (counted in ``restarts``).
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, NamedTuple, Optional

import numpy as np
import ray
import torch

from quad_env import EnvConfig, VecQuadEnv
from swarm_appo.rollout import RolloutWorker, worker_seed
from swarm_appo.sampling import Weights

log = logging.getLogger(__name__)

# A store that takes longer than this to accept one version is stuck (it takes milliseconds): fail with a clear
# error rather than hang the learner for good (seen once in ~12 test-suite runs, never understood).
PUBLISH_TIMEOUT_S = 300.0
# A worker that dies this often in a row without delivering a fragment ends the run with its error (a crash now and
# then is restarted; a worker that cannot even start would otherwise be restarted for ever).
MAX_DEATHS_IN_A_ROW = 5


@dataclass(frozen=True)
class StallPolicy:
    """When a rollout worker's oldest outstanding call counts as stalled. Counting the fragments the other
    workers delivered meanwhile (``overtaken``) makes the rule independent of load and fragment size: a busy
    machine slows every worker alike. The ages only keep a brief hiccup (or a worker still compiling its
    first fragment) from costing a restart; ``hard_s`` covers a lone worker, which nobody can overtake."""
    min_age_s: float = 10.0
    """A call younger than this is never stalled."""
    first_call_min_age_s: float = 120.0
    """The same for a fresh actor's first call when nobody waited for it to compile (``ready_timeout_s=None``)."""
    overtakes_per_worker: int = 25
    """Stalled once every other worker has, on average, delivered this many fragments since the call was made."""
    hard_s: float = 900.0
    """Stalled after this long whatever the others did."""
    check_every_s: float = 1.0
    """How long the sampler waits for a fragment before it looks for stalled calls."""

    def is_stalled(self, age_s: float, overtaken: int, num_workers: int, first_call: bool) -> bool:
        if age_s >= self.hard_s:
            return True
        if age_s < (self.first_call_min_age_s if first_call else self.min_age_s):
            return False
        return num_workers > 1 and overtaken >= self.overtakes_per_worker * (num_workers - 1)


class _Call(NamedTuple):
    """One outstanding rollout call: its worker, when it was sent, and how many fragments had been delivered
    by then (what ``StallPolicy`` counts as overtaking)."""
    worker: int
    sent_at: float
    delivered_before: int


@ray.remote(num_cpus=0)
class WeightsStore:
    """Holds the newest published ``(version, state_dict, env_schedule)`` and hands it to workers that lack it."""

    def __init__(self):
        self._latest: Optional[Weights] = None

    def set(self, version: int, state_dict: Dict[str, torch.Tensor],
            env_schedule: Optional[Dict[str, float]]) -> None:
        self._latest = (version, state_dict, env_schedule)

    def newer_than(self, version: int) -> Optional[Weights]:
        """The newest weights if their version differs from ``version`` (the caller's), else None: a worker
        that is up to date receives a few bytes, not the weights."""
        if self._latest is None or self._latest[0] == version:
            return None
        return self._latest


class RayRolloutWorker(RolloutWorker):
    """A RolloutWorker that fetches the newest weights from the store before each fragment."""

    def __init__(self, store, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.store = store
        self.node_id = ray.get_runtime_context().get_node_id()

    def location(self) -> Dict[str, Any]:
        """Where this actor runs: Ray node id, node IP, host name and process id."""
        return {"node_id": self.node_id, "ip": ray.util.get_node_ip_address(), "hostname": socket.gethostname(),
                "pid": os.getpid()}

    def ready(self) -> Dict[str, Any]:
        """Compile the simulator kernels (on a throwaway swarm: this worker's own streams stay untouched), then
        say where this actor runs. A fresh node has no numba cache yet; compiling here keeps the first
        fragments of all workers equally fast."""
        cfg = self.env.cfg
        VecQuadEnv(cfg, num_envs=1, seed=0).step(np.zeros((cfg.num_agents, 4), np.float32))
        return self.location()

    def collect_latest(self) -> Dict[str, Any]:
        weights = ray.get(self.store.newer_than.remote(self.policy_version))
        if weights is not None:
            self.set_weights(*weights)
        fragment = self.collect()
        fragment["node_id"] = self.node_id
        return fragment


class RaySampler:
    """Rollout workers as Ray actors streaming fragments through the object store."""

    def __init__(self, env_cfg: EnvConfig, model_factory: Callable, num_workers: int, envs_per_worker: int,
                 rollout: int, seed: int, max_in_flight: int, cpus_per_worker: float = 1.0,
                 store_values: bool = False, precision: str = "fp32", scheduling_strategy: str = "DEFAULT",
                 ready_timeout_s: Optional[float] = None, publish_timeout_s: float = PUBLISH_TIMEOUT_S,
                 stall_policy: StallPolicy = StallPolicy(), max_deaths_in_a_row: int = MAX_DEATHS_IN_A_ROW):
        """``scheduling_strategy="SPREAD"`` places the actors over all nodes of a cluster; with
        ``ready_timeout_s`` the constructor waits until every actor is placed and has compiled its kernels,
        and raises a clear error if the cluster cannot host them all in that time. A worker that dies
        ``max_deaths_in_a_row`` times without delivering a fragment ends the run with its error."""
        if max_deaths_in_a_row < 1:
            raise ValueError(f"max_deaths_in_a_row must be >= 1 (deaths of one worker before the run ends), got "
                             f"{max_deaths_in_a_row}")
        if max_in_flight < num_workers:
            raise ValueError(f"runner.max_fragments_in_flight ({max_in_flight}) must be >= the number of "
                             f"rollout workers ({num_workers}), or some workers would never run")
        self._args = (env_cfg, model_factory, envs_per_worker, rollout)
        self._seed = seed
        self._store_values = store_values
        self._precision = precision
        self.publish_timeout_s = publish_timeout_s
        self.stall_policy = stall_policy
        self.max_deaths_in_a_row = max_deaths_in_a_row
        self._remote_cls = ray.remote(num_cpus=cpus_per_worker, max_restarts=0,
                                      scheduling_strategy=scheduling_strategy)(RayRolloutWorker)
        self._store = WeightsStore.remote()
        self.workers: List[Any] = []
        self._incarnation: List[int] = []
        for i in range(num_workers):
            self.workers.append(self._spawn(i, 0))
            self._incarnation.append(0)
        self.max_in_flight = max_in_flight
        self._pending: Dict[Any, _Call] = {}  # object ref -> its call, oldest first
        self.restarts = 0
        # watchdog state: fragments delivered so far; per worker, whether its current incarnation has delivered
        # (a fresh actor's first call may still be compiling)
        self._delivered = 0
        self._last_stall_check = time.monotonic()
        self._has_delivered = [False] * num_workers
        # per worker: deaths since it last delivered; a worker that keeps dying before its first fragment has a
        # fault no restart fixes (e.g. its class no longer imports: code edited under a running job, seen once)
        self._deaths_in_a_row = [0] * num_workers
        self.stalls = 0  # calls the watchdog gave up on (each one restarted its worker)
        self.stalls_recovered = 0  # stalled calls that ray.get still returned (wait had missed them)
        if ready_timeout_s is not None:
            self._wait_until_ready(ready_timeout_s, cpus_per_worker)
            self._has_delivered = [True] * num_workers  # compiled: the first call is an ordinary one

    def _wait_until_ready(self, timeout_s: float, cpus_per_worker: float) -> None:
        refs = [w.ready.remote() for w in self.workers]
        ready, _ = ray.wait(refs, num_returns=len(refs), timeout=timeout_s)
        if len(ready) < len(refs):
            self.close()
            cpus = ray.cluster_resources().get("CPU", 0)
            raise RuntimeError(
                f"only {len(ready)} of {len(refs)} rollout workers started within {timeout_s:.0f} s; the cluster "
                f"has {cpus:g} CPUs and each worker needs {cpus_per_worker:g}. Lower runner.num_workers "
                f"(0 = fit the cluster) or add nodes")
        ray.get(ready)  # raises if an actor failed to start

    def _spawn(self, index: int, incarnation: int):
        env_cfg, model_factory, envs_per_worker, rollout = self._args
        return self._remote_cls.remote(self._store, env_cfg, model_factory, envs_per_worker, rollout,
                                       worker_seed(self._seed, index, incarnation), index,
                                       store_values=self._store_values, precision=self._precision)

    def publish(self, version: int, state_dict: Dict[str, torch.Tensor],
                env_schedule: Optional[Dict[str, float]] = None) -> None:
        """The weights of ``version``, with the environment values of the training schedule at this point
        (``RolloutWorker.set_weights``); workers pick them up before their next fragment."""
        # Waiting for the store keeps the order: a fragment started after publish() returns acts with this version.
        try:
            ray.get(self._store.set.remote(version, state_dict, env_schedule), timeout=self.publish_timeout_s)
        except ray.exceptions.GetTimeoutError:
            raise RuntimeError(f"the weights store did not take policy version {version} within "
                               f"{self.publish_timeout_s:g} s (it takes milliseconds when healthy): Ray is stuck; "
                               f"the run stops here and resumes from its last checkpoint") from None

    def _fill(self) -> None:
        """Keep every worker busy, round-robin, up to the in-flight bound."""
        in_flight = [0] * len(self.workers)
        for call in self._pending.values():
            in_flight[call.worker] += 1
        while len(self._pending) < self.max_in_flight:
            w = min(range(len(self.workers)), key=lambda i: (in_flight[i], i))
            ref = self.workers[w].collect_latest.remote()
            self._pending[ref] = _Call(w, time.monotonic(), self._delivered)
            in_flight[w] += 1

    def get(self) -> Dict[str, Any]:
        while True:
            self._fill()
            # fetch_local=False: return as soon as a fragment exists on any node, so that the ray.get below
            # times the move to this node (and the deserialisation) apart from the wait for a worker.
            ready, _ = ray.wait(list(self._pending), num_returns=1, fetch_local=False,
                                timeout=self.stall_policy.check_every_s)
            # look for stalled calls on a clock, not only when nothing arrives: in the failure seen, the other
            # workers kept delivering while one worker's calls never came back
            if time.monotonic() - self._last_stall_check >= self.stall_policy.check_every_s:
                self._last_stall_check = time.monotonic()
                fragment = self._check_stalls()
                if fragment is not None:
                    return fragment
            if ready and ready[0] in self._pending:  # (its worker may just have been restarted)
                fragment = self._take(self._oldest_ready())
                if fragment is not None:
                    return fragment

    def _oldest_ready(self):
        """Of the calls that are ready now, the one sent first: fragments come in the order they were asked
        for (bounding their policy lag), and a dead worker's failed calls are handled (and it is replaced)
        before the live workers' newer fragments, not whenever Ray happens to list them first."""
        pending = list(self._pending)
        ready, _ = ray.wait(pending, num_returns=len(pending), timeout=0, fetch_local=False)
        return min(ready, key=lambda ref: self._pending[ref].sent_at)

    def _take(self, ref, timeout: Optional[float] = None) -> Optional[Dict[str, Any]]:
        """The fragment behind ``ref``, or None when its worker died (it is replaced) or ``timeout`` ran out."""
        w = self._pending[ref].worker
        try:
            t0 = time.perf_counter()
            fragment = ray.get(ref, timeout=timeout)
            fragment["fetch_time_s"] = time.perf_counter() - t0
        except ray.exceptions.GetTimeoutError:
            return None
        except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError) as exc:
            self._deaths_in_a_row[w] += 1
            if self._deaths_in_a_row[w] >= self.max_deaths_in_a_row:
                raise RuntimeError(f"rollout worker {w} died {self._deaths_in_a_row[w]} times in a row without "
                                   f"delivering a fragment: restarting it cannot help ({type(exc).__name__}: "
                                   f"{str(exc).strip()[-2000:]})") from exc
            log.warning("rollout worker %d died (%s); restarting it", w, type(exc).__name__)
            self._replace(w)
            return None
        del self._pending[ref]
        self._delivered += 1
        self._has_delivered[w] = True
        self._deaths_in_a_row[w] = 0
        return fragment

    def _check_stalls(self) -> Optional[Dict[str, Any]]:
        """Restart every worker whose oldest call is stalled (``StallPolicy``); a stalled call that ray.get
        still returns within a few seconds is delivered instead."""
        now = time.monotonic()
        oldest: Dict[int, Any] = {}  # worker -> its oldest pending ref (a worker runs its calls in order)
        for ref, call in self._pending.items():  # (insertion order: the first seen per worker is its oldest)
            oldest.setdefault(call.worker, ref)
        for w, ref in oldest.items():
            call = self._pending[ref]
            age, overtaken = now - call.sent_at, self._delivered - call.delivered_before
            if not self.stall_policy.is_stalled(age, overtaken, len(self.workers), not self._has_delivered[w]):
                continue
            fragment = self._take(ref, timeout=2.0)
            if fragment is not None:
                self.stalls_recovered += 1
                log.warning("rollout worker %d: a fragment finished %.0f s ago was never reported ready; "
                            "fetched it directly", w, age)
                return fragment
            if ref not in self._pending:  # the worker died meanwhile and was replaced
                continue
            self.stalls += 1
            log.warning("rollout worker %d delivered nothing for %.0f s while the other workers delivered %d "
                        "fragments; restarting it", w, age, overtaken)
            self._replace(w)
        return None

    def _replace(self, w: int) -> None:
        """A dead (or stalled) worker: discard its in-flight fragments, start a fresh one with a new seed."""
        for ref in [r for r, call in self._pending.items() if call.worker == w]:
            del self._pending[ref]
        self._has_delivered[w] = False
        try:
            ray.kill(self.workers[w])
        except Exception:  # already gone
            pass
        self._incarnation[w] += 1
        self.workers[w] = self._spawn(w, self._incarnation[w])
        self.restarts += 1

    def worker_pids(self) -> List[int]:
        return ray.get([w.pid.remote() for w in self.workers])

    def worker_locations(self) -> List[Dict[str, Any]]:
        """Node id, IP, host name and pid of every current rollout actor, in worker order."""
        return ray.get([w.location.remote() for w in self.workers])

    def close(self) -> None:
        for w in self.workers:
            try:
                ray.kill(w)
            except Exception:
                pass
        self.workers.clear()
        self._pending.clear()
        try:
            ray.kill(self._store)
        except Exception:
            pass


def _init_keeping_sigterm(**init_kwargs) -> None:
    """ray.init replaces the driver's SIGTERM handler with one that exits at once; keep the caller's
    (the launchers turn SIGTERM into a final checkpoint and a clean exit; ``ray job stop`` sends SIGTERM)."""
    in_main_thread = threading.current_thread() is threading.main_thread()
    sigterm = signal.getsignal(signal.SIGTERM) if in_main_thread else None
    ray.init(**init_kwargs)
    if callable(sigterm):
        signal.signal(signal.SIGTERM, sigterm)


LOOPBACK = "127.0.0.1"
_CLUSTER_SWITCH = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


def init_local_ray(num_cpus: Optional[int] = None) -> None:
    """Start (or reuse) a one-machine Ray whose nodes' address is 127.0.0.1.

    ``ray.init(_node_ip_address="127.0.0.1")`` alone is not enough on Linux: Ray replaces a loopback address
    by the machine's network address (meant for clusters, where other machines must reach the node) unless
    multi-node support is switched off with RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0. That switch is set for the
    processes this Ray starts and, for the time of ``ray.init``, in this one (Ray reads it at import)."""
    if ray.is_initialized():
        return
    # Ray starts its workers at niceness 15, below the learner (the driver): on a busy laptop the rollout
    # actors would then starve while the learner waits for them. Sampling is half of the job: same priority.
    os.environ.setdefault("RAY_worker_niceness", "0")
    from ray._private import ray_constants
    saved_env, saved_flag = os.environ.get(_CLUSTER_SWITCH), ray_constants.ENABLE_RAY_CLUSTER
    os.environ[_CLUSTER_SWITCH] = "0"
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        _init_keeping_sigterm(num_cpus=num_cpus or os.cpu_count(), _node_ip_address=LOOPBACK,
                              include_dashboard=False, log_to_driver=True, configure_logging=False)
    finally:  # a later join of a real cluster in this process sees Ray's defaults again
        ray_constants.ENABLE_RAY_CLUSTER = saved_flag
        if saved_env is None:
            os.environ.pop(_CLUSTER_SWITCH, None)
        else:
            os.environ[_CLUSTER_SWITCH] = saved_env


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Raise ConnectionError at once when nothing listens at a "<host>:<port>" Ray address (Ray itself
    retries for minutes before it gives up). "auto" and client ("ray://") addresses are left to Ray."""
    if address == "auto" or "://" in address:
        return
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        raise ConnectionError(f"a Ray address is 'auto' or '<host>:<port>' (the head's GCS), got {address!r}")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ConnectionError(f"no Ray cluster answers at {address} ({exc})") from None


def init_ray(address: Optional[str]) -> None:
    """``runner.ray_address``: None starts (or reuses) a local Ray; "auto" or "<host>:<port>" joins a cluster."""
    if address is None:
        init_local_ray()
    elif not ray.is_initialized():
        check_reachable(address)
        _init_keeping_sigterm(address=address, log_to_driver=True, configure_logging=False)
