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
overhead, not a network's bandwidth. Figures are appended to benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List

import numpy as np

from benchmarks.common import ROOT, append_results, commit, load_average, machine
from benchmarks.training_throughput import measure_run

FETCH_KEYS = ("perf/fetch_share", "perf/remote_fetch_share", "perf/remote_fragment_fraction",
              "perf/fetch_ms_local", "perf/fetch_ms_remote", "perf/fragment_mb", "perf/transfer_share")


def overrides(seconds: float, run_dir: Path, name: str, workers: int) -> List[str]:
    return [f"runner.num_workers={workers}", f"runner.time_limit_s={seconds}", "runner.total_agent_steps=10000000000",
            "runner.final_eval_episodes=0", "runner.checkpoint_every_s=100000", "wandb.mode=disabled",
            f"runner.run_dir={run_dir}", f"runner.name={name}"]


def transfer_figures(run_dir: Path) -> Dict[str, float]:
    """Means of the fetch metrics over the steady part of the run (same warm-up rule as measure_run)."""
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    records = [r for r in records if "perf/learner_share" in r]
    t0, t1 = records[0]["charts/elapsed_s"], records[-1]["charts/elapsed_s"]
    steady = [r for r in records if r["charts/elapsed_s"] >= t0 + 0.3 * (t1 - t0)] or records[-2:]
    out = {}
    for key in FETCH_KEYS:
        values = [r[key] for r in steady if r.get(key) is not None]
        out[key] = float(np.mean(values)) if values else float("nan")
    return out


def one_node_rows(worker_counts: List[int], seconds: float, tmp: Path) -> List[dict]:
    import ray

    from swarm_appo.config import load_config
    from swarm_appo.sampling import init_local_ray
    from swarm_appo.trainer import train

    init_local_ray(num_cpus=max(worker_counts) + 1)  # logical CPUs: every worker and the learner get one
    rows = []
    try:
        for k in worker_counts:
            name = f"local_w{k}"
            result = train(load_config(None, overrides(seconds, tmp, name, k)), progress=False)
            row = dict(setup="1 node", workers=k, **measure_run(result.run_dir), **transfer_figures(result.run_dir))
            rows.append(row)
            print(f"1 node, {k} workers: {row['sps']:,.0f} agent-steps/s, fetch "
                  f"{row['perf/fetch_ms_local']:.1f} ms per fragment", flush=True)
    finally:
        ray.shutdown()
    return rows


def two_node_row(workers: int, seconds: float, cpus_per_node: float, tmp: Path) -> dict:
    from launchers.local_cluster import LocalCluster

    name = f"cluster_w{workers}"
    with LocalCluster(nodes=2, cpus_per_node=cpus_per_node) as cluster:
        cmd = [sys.executable, "-m", "launchers.ray_cluster", "submit", "--address", cluster.dashboard_url, "--follow",
               *overrides(seconds, tmp, name, workers)]
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        start = time.perf_counter()
        done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        job_s = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"the cluster run failed:\n{(done.stdout + done.stderr)[-4000:]}")
    run_dir = tmp / name
    placement = json.loads((run_dir / "cluster.json").read_text())
    learner = placement["learner"]["node_id"]
    per_node = [sum(w["node_id"] == n for w in placement["rollout_workers"]) for n in placement["fragments_per_node"]]
    row = dict(setup="2 nodes", workers=workers, job_s=job_s, **measure_run(run_dir), **transfer_figures(run_dir))
    row["placement"] = (f"learner + {sum(w['node_id'] == learner for w in placement['rollout_workers'])} worker(s) "
                        f"on the head, {workers - sum(w['node_id'] == learner for w in placement['rollout_workers'])}"
                        f" on the second node (workers per node {per_node})")
    print(f"2 nodes, {workers} workers: {row['sps']:,.0f} agent-steps/s, fetch local "
          f"{row['perf/fetch_ms_local']:.1f} ms / remote {row['perf/fetch_ms_remote']:.1f} ms per fragment, "
          f"remote fetch share {100 * row['perf/remote_fetch_share']:.1f}%", flush=True)
    return row


def fmt(value: float, spec: str) -> str:
    return "-" if value is None or (isinstance(value, float) and np.isnan(value)) else format(value, spec)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--workers", default="1,2,3", help="rollout-actor counts on one node")
    p.add_argument("--cluster-workers", type=int, default=3, help="rollout actors on the two-node cluster")
    p.add_argument("--cpus-per-node", type=float, default=2, help="logical CPUs of each cluster node")
    p.add_argument("--seconds", type=float, default=60.0, help="training time per row")
    p.add_argument("--no-cluster", action="store_true", help="skip the two-node cluster row")
    p.add_argument("--no-append", action="store_true", help="do not append to benchmarks/RESULTS.md")
    p.add_argument("--note", default="", help="a line about the conditions (e.g. a shared machine)")
    args = p.parse_args(argv)
    os.environ.setdefault("WANDB_SILENT", "true")
    load_before = load_average()

    tmp = Path(tempfile.mkdtemp(prefix="cluster_bench_"))
    rows = one_node_rows([int(k) for k in args.workers.split(",")], args.seconds, tmp)
    if not args.no_cluster:
        rows.append(two_node_row(args.cluster_workers, args.seconds, args.cpus_per_node, tmp))

    header = ("| setup | rollout actors | agent-steps/s | fragment MiB | fetch ms, same node / other node | "
              "fragments from the other node | remote fetch share | all fetches share | wait+publish share | "
              "lag mean / max |\n|---|---|---|---|---|---|---|---|---|---|")
    lines = [f"| {r['setup']} | {r['workers']} | {r['sps']:,.0f} | {fmt(r['perf/fragment_mb'], '.1f')} | "
             f"{fmt(r['perf/fetch_ms_local'], '.1f')} / {fmt(r['perf/fetch_ms_remote'], '.1f')} | "
             f"{fmt(100 * r['perf/remote_fragment_fraction'], '.0f')}% | "
             f"{fmt(100 * r['perf/remote_fetch_share'], '.1f')}% | {fmt(100 * r['perf/fetch_share'], '.1f')}% | "
             f"{fmt(100 * r['perf/transfer_share'], '.0f')}% | {r['lag_mean']:.1f} / {r['lag_max']:.0f} |"
             for r in rows]
    notes = [f"- two-node run: {r['placement']}; job wall time {r['job_s']:.0f} s (cluster start-up excluded, "
             f"job start-up and numba compilation on each node included)" for r in rows if "placement" in r]
    section = "\n".join([
        f"## cluster_throughput — {datetime.datetime.now().isoformat(timespec='seconds')}",
        "",
        f"- command: `nice -n 15 python -m benchmarks.cluster_throughput "
        f"{' '.join(argv if argv is not None else sys.argv[1:])}`",
        f"- commit: {commit(['swarm_appo', 'launchers', 'benchmarks/cluster_throughput.py'])}",
        f"- machine: {machine()}; load average before: {load_before}, after: {load_average()}",
        *([f"- conditions: {args.note}"] if args.note else []),
        f"- config: quickstart (DeepSets 64, N = 8, 16 swarms x 8 drones per worker, T = 128, batch 2048, "
        f"2 epochs), {args.seconds:.0f} s of training per row, figures after a 30% warm-up; one node = a local "
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
