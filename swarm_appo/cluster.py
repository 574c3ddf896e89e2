"""Running on a Ray cluster: how many rollout workers fit, where the learner sits, and ``cluster.json``.

    init_ray("auto")                                   # swarm_appo.ray_sampling: join the cluster
    num_workers = cluster_rollout_workers()            # CPUs of all nodes, minus one for the learner
    placement = Placement("auto", device)              # the nodes and the learner's node
    placement.set_workers(sampler.worker_locations())  # where each rollout actor was placed
    placement.count(fragment)                          # where each fragment was made
    placement.write(run_dir)                           # run_dir/cluster.json

The learner runs in the driver process (the job's entrypoint), next to the training loop. It gets a GPU
when the driver runs on a GPU node: ``launchers.ray_cluster`` asks Ray to start the entrypoint on a node
with a free GPU whenever the cluster has one, and ``runner.device=auto`` then picks ``cuda``. A driver
started elsewhere on a cluster with GPUs trains on the CPU and says so in a warning.
"""
from __future__ import annotations

import json
import logging
import os
import socket
from collections import Counter
from pathlib import Path
from typing import Any, Dict, List, Optional

import ray
import torch

from swarm_appo.atomic import atomic_write_bytes

log = logging.getLogger(__name__)

CLUSTER_FILE = "cluster.json"
HEAD_RESOURCE = "node:__internal_head__"  # a resource only the head node holds
READY_TIMEOUT_S = 600.0  # rollout actors must be up by then (an autoscaler may need minutes to add nodes)


def cluster_rollout_workers(cpus_per_worker: float = 1.0, learner_cpus: float = 1.0) -> int:
    """Rollout workers that fill the CPUs of all nodes, leaving ``learner_cpus`` for the learner (at least 1)."""
    cpus = ray.cluster_resources().get("CPU", 0.0)
    return max(1, int((cpus - learner_cpus) // cpus_per_worker))


def cluster_nodes() -> List[Dict[str, Any]]:
    """The alive nodes: id, IP, host name, head or not, CPUs and GPUs."""
    nodes = []
    for n in ray.nodes():
        if not n.get("Alive"):
            continue
        res = n.get("Resources", {})
        nodes.append({"node_id": n["NodeID"], "ip": n.get("NodeManagerAddress"), "hostname": n.get("NodeName"),
                      "head": HEAD_RESOURCE in res, "cpus": res.get("CPU", 0.0), "gpus": res.get("GPU", 0.0)})
    return nodes


def learner_location(device: torch.device) -> Dict[str, Any]:
    """The driver process that runs the learner: its node and device."""
    return {"node_id": ray.get_runtime_context().get_node_id(), "ip": ray.util.get_node_ip_address(),
            "hostname": socket.gethostname(), "pid": os.getpid(), "device": str(device)}


class Placement:
    """Where a run's processes sit on the cluster, and how many fragments each node produced."""

    def __init__(self, ray_address: str, device: torch.device):
        self.nodes = cluster_nodes()
        self.learner = learner_location(device)
        self.ray_address = ray_address
        self.workers: List[Dict[str, Any]] = []
        self.fragments = Counter()  # node id -> fragments
        self.agent_steps = Counter()  # node id -> agent steps
        self.worker_fragments = Counter()  # worker index -> fragments (tells a stuck actor from a slow node)
        gpus = sum(n["gpus"] for n in self.nodes)
        if device.type != "cuda" and gpus > 0:
            log.warning("the cluster has %g GPU(s) but the learner runs on the CPU of node %s (%s): the driver "
                        "process is not on a GPU node. Submit with launchers.ray_cluster (which starts the "
                        "driver on a GPU node) or check runner.device", gpus, self.learner["ip"],
                        self.learner["node_id"][:8])

    @property
    def learner_node(self) -> str:
        return self.learner["node_id"]

    def set_workers(self, locations: List[Dict[str, Any]]) -> None:
        self.workers = [dict(worker_id=i, **loc) for i, loc in enumerate(locations)]

    def count(self, fragment: Dict[str, Any]) -> None:
        node = fragment.get("node_id")
        if node is not None:
            self.fragments[node] += 1
            self.agent_steps[node] += fragment["num_agent_steps"]
        self.worker_fragments[int(fragment["worker_id"])] += 1  # every fragment names its worker (rollout.py)

    def as_dict(self, worker_restarts: int = 0) -> Dict[str, Any]:
        return {"ray_address": self.ray_address, "nodes": self.nodes, "learner": self.learner,
                "rollout_workers": [dict(w, fragments=self.worker_fragments[w["worker_id"]]) for w in self.workers],
                "fragments_per_node": dict(self.fragments),
                "agent_steps_per_node": dict(self.agent_steps), "worker_restarts": worker_restarts}

    def write(self, run_dir: Path, worker_restarts: int = 0) -> Path:
        path = Path(run_dir) / CLUSTER_FILE
        atomic_write_bytes(path, (json.dumps(self.as_dict(worker_restarts), indent=1) + "\n").encode())
        return path


def read_placement(run_dir: str | os.PathLike) -> Optional[Dict[str, Any]]:
    """``run_dir/cluster.json`` as a dict, or None for a run that did not use a cluster."""
    path = Path(run_dir) / CLUSTER_FILE
    return json.loads(path.read_text()) if path.exists() else None
