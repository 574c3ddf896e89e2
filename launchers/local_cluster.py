"""A multi-node Ray cluster on this machine, on loopback only: to try ``launchers.ray_cluster``, to test and
benchmark it without a second computer.

    python -m launchers.local_cluster --nodes 2 --cpus-per-node 2   # prints the dashboard address; Ctrl-C ends it

    with LocalCluster(nodes=2, cpus_per_node=2) as cluster:         # in Python (tests, benchmarks)
        submit to cluster.dashboard_url                             # http://127.0.0.1:<port>

Each node is a separate Ray node (its own raylet and object store, so fragments made on one node are
copied to the other like on a real cluster) at 127.0.0.1. A keeper process starts the nodes with
``ray.cluster_utils.Cluster`` in its own process session and Ray temp dir, and stops exactly those nodes
when it ends (``LocalCluster.stop``, Ctrl-C, or its parent closing the pipe): other Ray instances on the
machine are never touched (no ``ray stop``). Ports are picked free, so it runs next to other clusters.

Four settings make a loopback cluster work: each node unpacks a job's working directory into its own
folder, as separate machines would (sharing one, a node's agent replaces the copy another node's processes
run from); ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` stops Ray from replacing 127.0.0.1 by the machine's
network address when a process joins; the nodes' temp dir is ``$RAY_TMPDIR/ray``, where the job supervisor
finds the head's address for a job's driver (elsewhere it would pick any Ray instance running on the
machine); and token authentication is switched on like ``ray start`` does when a token exists
(``~/.ray/auth_token``), so clients authenticate as on a real cluster.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

from launchers.common import enable_token_auth_if_available

LOOPBACK = "127.0.0.1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


def ray_temp_dir(keeper_dir: str) -> str:
    """The nodes' Ray temp dir (sessions, logs, the current-cluster file) inside the keeper's folder."""
    return os.path.join(keeper_dir, "ray")


# ------------------------------------------------------------------------------------------- the keeper
def serve(nodes: int, cpus_per_node: float, object_store_mb: int, temp_dir: str, info_file: str) -> None:
    """Start the nodes, write their addresses to ``info_file``, block until stdin closes or a signal."""
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # see the module docstring
    # The "current cluster" file: the keeper writes it to $RAY_TMPDIR/ray, and a job supervisor looks for it in
    # its node's temp dir to find the GCS for the job's driver: the two must be the same folder. Without the
    # file the supervisor takes any GCS it sees in `ps`, another Ray instance's when one runs on the machine.
    os.environ["RAY_TMPDIR"] = temp_dir
    node_temp_dir = ray_temp_dir(temp_dir)
    os.makedirs(node_temp_dir, exist_ok=True)
    from ray.cluster_utils import Cluster  # after the environment is set: Ray reads it at import

    dashboard_port = free_port()
    common = dict(node_ip_address=LOOPBACK, num_cpus=cpus_per_node, object_store_memory=object_store_mb * 2**20,
                  temp_dir=node_temp_dir, metrics_export_port=free_port(), runtime_env_agent_port=free_port())
    # The nodes share one session directory; each gets its own runtime-env folder (where the job's working
    # directory is unpacked), as on separate machines: otherwise one node's agent replaces the copy that the
    # other node's processes are running from.
    cluster = Cluster(initialize_head=True, head_node_args=dict(
        common, include_dashboard=True, dashboard_host=LOOPBACK, dashboard_port=dashboard_port,
        dashboard_agent_listen_port=free_port(), runtime_env_dir_name="runtime_resources_node0"))
    for i in range(1, nodes):
        cluster.add_node(**dict(common, metrics_export_port=free_port(), runtime_env_agent_port=free_port(),
                                runtime_env_dir_name=f"runtime_resources_node{i}"))
    cluster.wait_for_nodes()

    def stop(*_):
        cluster.shutdown()
        os._exit(0)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    all_nodes = [cluster.head_node, *cluster.worker_nodes]
    info = {"dashboard_url": f"http://{LOOPBACK}:{dashboard_port}", "gcs_address": cluster.address,
            "node_ids": [n.node_id for n in all_nodes], "keeper_pid": os.getpid(),
            "node_pids": sorted({p.process.pid for n in all_nodes for procs in n.all_processes.values()
                                 for p in procs})}
    tmp = info_file + ".tmp"
    Path(tmp).write_text(json.dumps(info))
    os.replace(tmp, info_file)
    sys.stdin.read()  # returns when the parent closes the pipe (or dies)
    stop()


# ------------------------------------------------------------------------------------------- the handle
class LocalCluster:
    """Start a keeper process with ``nodes`` Ray nodes; ``stop()`` (or leaving the ``with``) ends them all.

    Attributes after start: ``dashboard_url`` (the Jobs API address), ``gcs_address``, ``node_ids``,
    ``node_pids`` (the nodes' own processes: GCS, raylets, dashboard, agents), ``temp_dir``.
    """

    def __init__(self, nodes: int = 2, cpus_per_node: float = 2, object_store_mb: int = 256,
                 start_timeout_s: float = 120.0, keep_temp_dir: bool = False):
        if nodes < 1:
            raise ValueError(f"nodes must be >= 1, got {nodes}")
        self.nodes, self.cpus_per_node, self.object_store_mb = nodes, cpus_per_node, object_store_mb
        self.start_timeout_s = start_timeout_s
        self.keep_temp_dir = keep_temp_dir
        self.proc: Optional[subprocess.Popen] = None
        self.temp_dir = ""
        self._group_killed = False
        self.info: Dict[str, Any] = {}

    @property
    def dashboard_url(self) -> str:
        return self.info["dashboard_url"]

    @property
    def gcs_address(self) -> str:
        return self.info["gcs_address"]

    @property
    def node_ids(self) -> List[str]:
        return self.info["node_ids"]

    @property
    def node_pids(self) -> List[int]:
        return self.info["node_pids"]

    def env(self) -> Dict[str, str]:
        """The keeper's environment (inherited by every Ray process of the cluster, job entrypoints included):
        this interpreter first on PATH, so a job's ``python`` is the one running here."""
        env = dict(os.environ)
        env["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
        env["PATH"] = os.path.dirname(sys.executable) + os.pathsep + env.get("PATH", "")
        env.pop("RAY_ADDRESS", None)
        env.setdefault("RAY_DASHBOARD_STARTUP_TIMEOUT_S", "300")  # Ray's 60 s is short on a busy machine
        enable_token_auth_if_available(env)
        return env

    def start(self, attempts: int = 2) -> "LocalCluster":
        """Start the nodes. Some of Ray's start-up waits are fixed (30 s for a raylet to register), which a
        busy machine can miss: a failed start is retried from scratch ``attempts - 1`` times."""
        for attempt in range(1, attempts + 1):
            try:
                return self._start_once()
            except RuntimeError as exc:
                if attempt == attempts:
                    raise
                print(f"local Ray cluster: start attempt {attempt} failed, retrying ({str(exc)[-300:]})",
                      file=sys.stderr)
        raise AssertionError("unreachable")

    def _start_once(self) -> "LocalCluster":
        # Short path: Ray's unix socket paths must stay under ~100 characters.
        self.temp_dir = tempfile.mkdtemp(prefix="swc_", dir="/tmp")
        info_file = os.path.join(self.temp_dir, "cluster.json")
        log = open(os.path.join(self.temp_dir, "keeper.log"), "wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "launchers.local_cluster", "--serve", "--nodes", str(self.nodes),
             "--cpus-per-node", str(self.cpus_per_node), "--object-store-mb", str(self.object_store_mb),
             "--temp-dir", self.temp_dir, "--info-file", info_file],
            stdin=subprocess.PIPE, stdout=log, stderr=subprocess.STDOUT, env=self.env(),
            cwd=str(Path(__file__).resolve().parent.parent), start_new_session=True)
        log.close()
        deadline = time.monotonic() + self.start_timeout_s
        while not os.path.exists(info_file):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                tail = self.log_tail()
                self.stop()
                raise RuntimeError(f"the local Ray cluster did not start (keeper log tail):\n{tail}")
            time.sleep(0.2)
        self.info = json.loads(Path(info_file).read_text())
        return self

    def log_tail(self, chars: int = 3000) -> str:
        try:
            return Path(self.temp_dir, "keeper.log").read_text(errors="replace")[-chars:]
        except OSError:
            return ""

    def stop(self, timeout_s: float = 60.0) -> None:
        """End the keeper and its nodes: close its stdin (it shuts the nodes down), then signal its own
        process group if it lingers. Only processes this handle started are touched."""
        if self.proc is not None and self.proc.poll() is None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                for sig in (signal.SIGTERM, signal.SIGKILL):
                    try:
                        os.killpg(self.proc.pid, sig)  # the keeper's own session (start_new_session)
                    except ProcessLookupError:
                        break
                    try:
                        self.proc.wait(10)
                        break
                    except subprocess.TimeoutExpired:
                        continue
        if self.proc is not None and self.proc.stdin and not self.proc.stdin.closed:
            self.proc.stdin.close()
        if self.proc is not None and not self._group_killed:
            self._group_killed = True  # once: later, the group id could belong to someone else
            try:  # stragglers of the keeper's session (its nodes' workers), which are ours alone
                os.killpg(self.proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        if self.temp_dir and not self.keep_temp_dir:
            self._remove_temp_dir()

    def _remove_temp_dir(self, timeout_s: float = 30.0) -> None:
        """Remove the temp dir; retried, since a Ray process that is still exiting can write a last log file
        into a folder being removed (seen once: the folder outlived ``stop``)."""
        deadline = time.monotonic() + timeout_s
        while True:
            shutil.rmtree(self.temp_dir, ignore_errors=True)
            if not os.path.exists(self.temp_dir):
                return
            if time.monotonic() > deadline:
                left = [str(p) for p in Path(self.temp_dir).rglob("*")][:10]
                raise RuntimeError(f"could not remove the cluster's temp dir {self.temp_dir}; left: {left}")
            time.sleep(0.2)

    def __enter__(self) -> "LocalCluster":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="swarm-local-cluster", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--nodes", type=int, default=2, help="Ray nodes, the head included")
    p.add_argument("--cpus-per-node", type=float, default=2, help="logical CPUs of each node")
    p.add_argument("--object-store-mb", type=int, default=256, help="object store of each node (MiB)")
    p.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)  # the keeper process itself
    p.add_argument("--temp-dir", help=argparse.SUPPRESS)
    p.add_argument("--info-file", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.serve:
        serve(args.nodes, args.cpus_per_node, args.object_store_mb, args.temp_dir, args.info_file)
        return 0
    with LocalCluster(args.nodes, args.cpus_per_node, args.object_store_mb) as cluster:
        print(f"{args.nodes} Ray nodes on {LOOPBACK}, {args.cpus_per_node:g} CPUs each")
        print(f"dashboard / Jobs API: {cluster.dashboard_url}")
        print(f"submit a run: python -m launchers.ray_cluster submit --address {cluster.dashboard_url} --follow")
        print("Ctrl-C stops the cluster", flush=True)
        try:
            while cluster.proc.poll() is None:
                time.sleep(1)
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
