"""Training throughput vs the number of rollout actors, on one Ray node and on a two-node Ray cluster, with
the time spent moving fragments between nodes.

    python -m benchmarks.cluster_throughput                         # workers 1,2,3 locally + the two-node cluster
    python -m benchmarks.cluster_throughput --workers 1,2 --seconds 30 --no-cluster

Every row trains the quickstart setting (``load_config(None)``: DeepSets 64, N = 8, 16 swarms per worker,
fragments of 128 steps x 128 drones, about 10 MiB) for ``--seconds`` and reports its steady state (after a
30% warm-up) from the run's metrics.jsonl:

- one node: ``launchers``-free, in this process, a local Ray with ``max(workers) + 1`` logical CPUs (the
  learner's included), so that 3 workers fit on a 2-core machine (they then share its cores);
- two nodes: a ``launchers.local_cluster`` cluster (head + worker node, ``--cpus-per-node`` logical CPUs
  each, one object store each) and a real submission through ``launchers.ray_cluster`` (Jobs API); the
  learner sits on the head with one worker, the other workers on the second node, so their fragments are
  copied between object stores.

The transfer columns come from the trainer's perf/ metrics: ``fetch`` is the learner's ray.get of a fragment
that is ready (moving it to the learner's node when it was made elsewhere, and deserialising it), split by
where the fragment was made; "remote fetch share" is the share of the learner loop spent fetching fragments
from the other node. On one machine the "network" is loopback: the figures are Ray's object-transfer
overhead, not a network's bandwidth.

On a shared machine a run only gets the cores others leave: every row also reports the cores its own
processes used and the cores all other processes used meanwhile (from /proc), and ``--repeats`` runs the
rows interleaved several times. Figures are appended to benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Dict, List

import numpy as np

from benchmarks.common import ROOT, append_results, commit, load_average, machine, steady_window
from benchmarks.training_throughput import measure_run

FETCH_KEYS = ("perf/fetch_share", "perf/remote_fetch_share", "perf/remote_fragment_fraction",
              "perf/fetch_ms_local", "perf/fetch_ms_remote", "perf/fragment_mb", "perf/transfer_share")


class CpuMonitor:
    """Cores used by this process and its descendants vs by everything else on the machine, sampled each second
    from /proc while the ``with`` block runs (Linux only). ``figures(t0, t1)`` gives the means over a window
    of wall-clock time (``time.time()``, as in metrics.jsonl records), e.g. a run's steady state."""

    def __init__(self, interval_s: float = 1.0):
        self.interval_s = interval_s
        self.ticks = os.sysconf("SC_CLK_TCK")
        self.own = self.machine = 0.0  # CPU-seconds so far
        self.samples: List[tuple] = []  # (time.time(), own CPU-s, machine busy CPU-s), cumulative
        self._last: Dict[int, float] = {}
        self._stop = threading.Event()

    @staticmethod
    def _processes() -> Dict[int, tuple]:
        out = {}
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    fields = Path(f"/proc/{entry}/stat").read_text().rsplit(") ", 1)[1].split()
                    out[int(entry)] = (int(fields[1]), int(fields[11]) + int(fields[12]))  # ppid, utime + stime
                except (OSError, IndexError, ValueError):
                    pass
        return out

    def _own_times(self) -> Dict[int, float]:
        procs = self._processes()
        children: Dict[int, List[int]] = {}
        for pid, (ppid, _) in procs.items():
            children.setdefault(ppid, []).append(pid)
        todo, own = [os.getpid()], {}
        while todo:
            pid = todo.pop()
            if pid in procs:
                own[pid] = procs[pid][1] / self.ticks
            todo.extend(children.get(pid, []))
        return own

    @staticmethod
    def _busy() -> float:
        fields = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
        return (sum(fields) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")  # all but idle and iowait

    def _sample(self) -> None:
        own = self._own_times()
        self.own += sum(t - self._last.get(pid, t) for pid, t in own.items())  # new processes count from now
        self._last = own
        busy = self._busy()
        self.machine += busy - self._busy_last
        self._busy_last = busy
        self.samples.append((time.time(), self.own, self.machine))

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._sample()

    def __enter__(self) -> "CpuMonitor":
        self.t0 = time.perf_counter()
        try:
            self._last, self._busy_last = self._own_times(), self._busy()
        except OSError:
            return self
        self.samples.append((time.time(), 0.0, 0.0))
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.wall = time.perf_counter() - self.t0
        if hasattr(self, "_thread"):
            self._stop.set()
            self._thread.join()
            self._sample()

    def figures(self, t0: float, t1: float) -> Dict[str, float]:
        """``own_cores`` and ``other_cores``: mean cores busy with this run, and with everything else, between
        the samples nearest to wall-clock times ``t0`` and ``t1``."""
        if len(self.samples) < 2:
            return {"own_cores": float("nan"), "other_cores": float("nan")}
        a = min(self.samples, key=lambda x: abs(x[0] - t0))
        b = min(self.samples, key=lambda x: abs(x[0] - t1))
        wall = max(b[0] - a[0], 1e-9)
        own = (b[1] - a[1]) / wall
        return {"own_cores": own, "other_cores": max((b[2] - a[2]) / wall - own, 0.0)}


def overrides(seconds: float, run_dir: Path, name: str, workers: int) -> List[str]:
    return [f"runner.num_workers={workers}", f"runner.time_limit_s={seconds}", "runner.total_agent_steps=10000000000",
            "runner.final_eval_episodes=0", "runner.checkpoint_every_s=100000", "wandb.mode=disabled",
            f"runner.run_dir={run_dir}", f"runner.name={name}"]


def steady_figures(run_dir: Path, cpu: CpuMonitor) -> Dict[str, float]:
    """measure_run's figures, the fetch metrics and the cores used, all over the steady part of the run
    (the same warm-up rule as measure_run: records after 30% of the logged time)."""
    out = measure_run(run_dir)
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    records = [r for r in records if "perf/learner_share" in r]
    steady = steady_window(records, lambda r: r["charts/elapsed_s"])
    for key in FETCH_KEYS:
        values = [r[key] for r in steady if r.get(key) is not None]
        out[key] = float(np.mean(values)) if values else float("nan")
    out.update(cpu.figures(steady[0]["time"], steady[-1]["time"]))
    out["sps_per_core"] = out["sps"] / out["own_cores"] if out["own_cores"] > 0 else float("nan")
    return out


def one_node_row(workers: int, seconds: float, tmp: Path, max_workers: int, repeat: int) -> dict:
    import ray

    from swarm_appo.config import load_config
    from swarm_appo.ray_sampling import init_local_ray
    from swarm_appo.trainer import train

    init_local_ray(num_cpus=max_workers + 1)  # logical CPUs: every worker and the learner get one
    try:
        with CpuMonitor() as cpu:
            result = train(load_config(None, overrides(seconds, tmp, f"local_w{workers}_r{repeat}", workers)),
                           progress=False)
    finally:
        ray.shutdown()
    row = dict(setup="1 node", workers=workers, **steady_figures(result.run_dir, cpu))
    print(f"1 node, {workers} workers: {row['sps']:,.0f} agent-steps/s, fetch {row['perf/fetch_ms_local']:.1f} ms "
          f"per fragment; cores: this run {row['own_cores']:.2f}, others {row['other_cores']:.2f}", flush=True)
    return row


def two_node_row(workers: int, seconds: float, cpus_per_node: float, tmp: Path, repeat: int) -> dict:
    from launchers.local_cluster import LocalCluster

    name = f"cluster_w{workers}_r{repeat}"
    with LocalCluster(nodes=2, cpus_per_node=cpus_per_node) as cluster:
        cmd = [sys.executable, "-m", "launchers.ray_cluster", "submit", "--address", cluster.dashboard_url, "--follow",
               *overrides(seconds, tmp, name, workers)]
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        start = time.perf_counter()
        with CpuMonitor() as cpu:
            done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        job_s = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"the cluster run failed:\n{(done.stdout + done.stderr)[-4000:]}")
    run_dir = tmp / name
    placement = json.loads((run_dir / "cluster.json").read_text())
    learner = placement["learner"]["node_id"]
    on_head = sum(w["node_id"] == learner for w in placement["rollout_workers"])
    fragments = placement["fragments_per_node"]
    row = dict(setup="2 nodes", workers=workers, job_s=job_s, **steady_figures(run_dir, cpu))
    row["placement"] = (f"learner + {on_head} worker(s) on the head ({fragments.get(learner, 0)} fragments), "
                        f"{workers - on_head} on the second node "
                        f"({sum(v for k, v in fragments.items() if k != learner)} fragments)")
    print(f"2 nodes, {workers} workers: {row['sps']:,.0f} agent-steps/s, fetch local "
          f"{row['perf/fetch_ms_local']:.1f} ms / remote {row['perf/fetch_ms_remote']:.1f} ms per fragment, "
          f"remote fetch share {100 * row['perf/remote_fetch_share']:.1f}%; cores: this run "
          f"{row['own_cores']:.2f}, others {row['other_cores']:.2f}", flush=True)
    return row


def fmt(value: float, spec: str) -> str:
    return "-" if value is None or (isinstance(value, float) and np.isnan(value)) else format(value, spec)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--workers", default="1,2,3", help="rollout-actor counts on one node")
    p.add_argument("--cluster-workers", type=int, default=3, help="rollout actors on the two-node cluster")
    p.add_argument("--cpus-per-node", type=float, default=2, help="logical CPUs of each cluster node")
    p.add_argument("--seconds", type=float, default=60.0, help="training time per row")
    p.add_argument("--repeats", type=int, default=2, help="run all rows this many times, interleaved")
    p.add_argument("--no-cluster", action="store_true", help="skip the two-node cluster row")
    p.add_argument("--no-append", action="store_true", help="do not append to benchmarks/RESULTS.md")
    p.add_argument("--note", default="", help="a line about the conditions (e.g. a shared machine)")
    args = p.parse_args(argv)
    os.environ.setdefault("WANDB_SILENT", "true")
    load_before = load_average()

    tmp = Path(tempfile.mkdtemp(prefix="cluster_bench_"))
    counts = [int(k) for k in args.workers.split(",")]
    rows = []
    try:
        for repeat in range(args.repeats):
            rows += [one_node_row(k, args.seconds, tmp, max(counts), repeat) for k in counts]
            if not args.no_cluster:
                rows.append(two_node_row(args.cluster_workers, args.seconds, args.cpus_per_node, tmp, repeat))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    rows.sort(key=lambda r: (r["setup"], r["workers"]))

    header = ("| setup | rollout actors | agent-steps/s | cores used: this run / others | agent-steps per "
              "CPU-second of this run | learner share | "
              "fragment MiB | fetch ms, same node / other node | fragments from the other node | remote fetch share | "
              "all fetches share | wait+publish share | lag mean / max |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [f"| {r['setup']} | {r['workers']} | {r['sps']:,.0f} | {r['own_cores']:.2f} / {r['other_cores']:.2f} | "
             f"{fmt(r['sps_per_core'], ',.0f')} | "
             f"{r['learner_share']:.2f} | {fmt(r['perf/fragment_mb'], '.1f')} | "
             f"{fmt(r['perf/fetch_ms_local'], '.1f')} / {fmt(r['perf/fetch_ms_remote'], '.1f')} | "
             f"{fmt(100 * r['perf/remote_fragment_fraction'], '.0f')}% | "
             f"{fmt(100 * r['perf/remote_fetch_share'], '.1f')}% | {fmt(100 * r['perf/fetch_share'], '.1f')}% | "
             f"{fmt(100 * r['perf/transfer_share'], '.0f')}% | {r['lag_mean']:.1f} / {r['lag_max']:.0f} |"
             for r in rows]
    notes = [f"- two-node run {i + 1}: {r['placement']}; job wall time {r['job_s']:.0f} s (cluster start-up excluded, "
             f"job start-up and numba compilation on each node included)"
             for i, r in enumerate(r for r in rows if "placement" in r)]
    section = "\n".join([
        f"## cluster_throughput — {datetime.datetime.now().isoformat(timespec='seconds')}",
        "",
        f"- command: `{f'nice -n {os.nice(0)} ' if os.nice(0) else ''}python -m benchmarks.cluster_throughput "
        f"{' '.join(argv if argv is not None else sys.argv[1:])}`",
        f"- commit: {commit(['swarm_appo', 'launchers', 'benchmarks/cluster_throughput.py'])}",
        f"- machine: {machine()}; load average before: {load_before}, after: {load_average()}",
        *([f"- conditions: {args.note}"] if args.note else []),
        f"- config: quickstart (DeepSets 64, N = 8, 16 swarms x 8 drones per worker, T = 128, batch 2048, "
        f"2 epochs), {args.seconds:.0f} s of training per row, {args.repeats} repeat(s) interleaved, figures after "
        f"a 30% warm-up; cores used = mean busy cores of this run's processes / of all other processes over the "
        f"same steady window (/proc); one node = a local "
        f"Ray with max(actors) + 1 logical CPUs; two nodes = launchers.local_cluster (2 Ray nodes x "
        f"{args.cpus_per_node:g} logical CPUs, own object stores, loopback) + launchers.ray_cluster submit",
        "- fetch = the learner's ray.get of a ready fragment (copy between object stores when made on the other "
        "node + deserialisation); shares are of the learner loop's wall time",
        *notes,
        "",
        header, *lines,
    ])
    print(section)
    if not args.no_append:
        append_results(section)


if __name__ == "__main__":
    main()
