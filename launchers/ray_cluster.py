"""Train on a Ray cluster: submit a run through the Ray Jobs API, follow it, stop it.

    python -m launchers.ray_cluster submit --address http://<head>:8265 --config configs/paper.yaml \\
        model.encoder=se3_graphormer --follow          # prints the job id, then streams the logs
    python -m launchers.ray_cluster status [JOB_ID]    # one job, or every job of the cluster
    python -m launchers.ray_cluster logs JOB_ID [--follow]
    python -m launchers.ray_cluster stop JOB_ID        # SIGTERM: a final checkpoint, then the job ends

``submit`` loads and validates the config here, with the same ``--config`` and ``key=value`` overrides as
``launchers.local`` (an error names the key and nothing is sent), then ships the project directory (without
runs/, .git, virtual environments, wandb/ and caches) and the resolved config in the job's runtime
environment. On the cluster the job runs ``python -m launchers.ray_cluster run``: it joins the cluster
(``runner.ray_address=auto``), starts one rollout worker per CPU of all nodes, minus one CPU for the
learner (``runner.num_workers=0``), spread over the nodes, and trains. The learner runs in that entrypoint
process; ``submit`` asks Ray to start it on a node with a free GPU when the cluster has one (``cuda``),
otherwise on the head node with one CPU reserved for it. A relative ``runner.run_dir`` is taken relative to
the home directory of the learner's node: the run directory (checkpoints, metrics.jsonl, cluster.json)
lives there. The config is the same as on a laptop; only the resources differ.

The address defaults to $RAY_API_SERVER_ADDRESS, then $RAY_ADDRESS if it is an http(s) address, then
http://127.0.0.1:8265. Clusters with token authentication: the token is read from $RAY_AUTH_TOKEN,
$RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token (RAY_AUTH_MODE=token is set when one exists and the mode is unset).
"""
from __future__ import annotations

import argparse
import asyncio
import logging
import os
import shlex
import socket
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

os.environ.setdefault("WANDB_SILENT", "true")

from launchers.common import (add_config_arguments, enable_token_auth_if_available, load_cli_config,  # noqa: E402
                              print_result, report_training_error, stop_on_sigterm)

PROJECT_ROOT = Path(__file__).resolve().parent.parent
CONFIG_ENV = "SWARM_APPO_CONFIG"  # the resolved config (YAML) travels to the cluster in this variable
DEFAULT_ADDRESS = "http://127.0.0.1:8265"
# Not shipped to the cluster (gitignore patterns; Ray also honours the project's .gitignore).
DEFAULT_EXCLUDES = ["runs/", "wandb/", ".git/", ".venv/", "venv/", "__pycache__/", ".pytest_cache/", "*.egg-info/",
                    "*.nbi", "*.nbc"]
HEAD_LABEL = "ray.io/node-id"  # every Ray node carries this label with its own id


# =============================================================================================== helpers
def default_address() -> str:
    for var in ("RAY_API_SERVER_ADDRESS", "RAY_ADDRESS"):
        value = os.environ.get(var, "")
        if value.startswith(("http://", "https://")):
            return value
    return DEFAULT_ADDRESS


def cluster_run_root(run_dir: str, home: Optional[Path] = None) -> Path:
    """Where a run directory goes on the cluster: absolute paths as given, ``~`` expanded, and relative ones
    under the home directory (the job's working directory is a temporary copy that Ray deletes)."""
    path = Path(os.path.expanduser(run_dir))
    return path if path.is_absolute() else (home or Path.home()) / path


def entrypoint_options(nodes: List[Dict[str, Any]], learner_gpus: str, device: str) -> Tuple[Dict[str, Any], str]:
    """Where Ray starts the entrypoint (the learner's process): ``submit_job`` keywords and a line saying why.

    ``nodes``: the alive nodes as ``{"node_id", "head", "cpus", "gpus"}``. ``learner_gpus``: "auto" (a GPU
    when the cluster has one, or when ``runner.device`` asks for cuda), "0" or "1".
    """
    if learner_gpus == "auto":
        want_gpu = device.startswith("cuda") or (device == "auto" and any(n["gpus"] >= 1 for n in nodes))
    else:
        want_gpu = int(learner_gpus) > 0
    if want_gpu:
        return ({"entrypoint_num_cpus": 1, "entrypoint_num_gpus": 1},
                "the learner runs on a node with a free GPU (cuda), one CPU and one GPU reserved for it")
    head = next((n for n in nodes if n["head"]), None)
    if head is not None and head["cpus"] >= 1:
        return ({"entrypoint_num_cpus": 1, "entrypoint_label_selector": {HEAD_LABEL: head["node_id"]}},
                "the learner runs on the head node's CPU, one CPU reserved for it")
    return {}, "the learner runs on the head node (no CPU of the head to reserve for it)"


def list_cluster_nodes(address: str) -> List[Dict[str, Any]]:
    """The cluster's alive nodes, through the dashboard's state API."""
    from ray.util.state import list_nodes
    return [{"node_id": n.node_id, "head": bool(n.is_head_node), "ip": n.node_ip,
             "cpus": float(n.resources_total.get("CPU", 0)), "gpus": float(n.resources_total.get("GPU", 0))}
            for n in list_nodes(address=address, raise_on_missing_output=False) if n.state == "ALIVE"]


def _client(address: str):
    from ray.job_submission import JobSubmissionClient
    return JobSubmissionClient(address)


def _terminal(status) -> bool:
    return str(status) in ("SUCCEEDED", "FAILED", "STOPPED")


def _wait_for_end(client, job_id: str, poll_s: float = 1.0, timeout_s: Optional[float] = None) -> str:
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    while True:
        status = str(client.get_job_status(job_id))
        if _terminal(status) or (deadline is not None and time.monotonic() > deadline):
            return status
        time.sleep(poll_s)


def _follow(client, job_id: str) -> str:
    """Stream the job's logs until it ends; its final status."""
    async def stream():
        async for lines in client.tail_job_logs(job_id):
            print(lines, end="", flush=True)
    try:
        asyncio.run(stream())
    except KeyboardInterrupt:
        print(f"\nstopped following; the job goes on (stop it with: python -m launchers.ray_cluster stop {job_id})",
              file=sys.stderr)
        return str(client.get_job_status(job_id))
    return _wait_for_end(client, job_id)


def _submit_with_retry(client, timeout_s: float = 60.0, **kwargs) -> str:
    """A freshly started head may not have its job agent yet; Ray answers "try again later"."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return client.submit_job(**kwargs)
        except RuntimeError as exc:
            if "No available agent" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(2.0)


# =============================================================================================== subcommands
def cmd_submit(args) -> int:
    from swarm_appo.config import ConfigError, config_to_dict, validate
    try:
        cfg = load_cli_config(args.config, args.overrides)
        if cfg.runner.ray_address not in (None, "auto"):
            print(f"note: runner.ray_address={cfg.runner.ray_address!r} is replaced by 'auto' (the job joins "
                  f"the cluster it runs in)", file=sys.stderr)
        cfg.runner.ray_address = "auto"
        validate(cfg)
    except (ConfigError, FileNotFoundError) as exc:
        print(f"config error: {exc}", file=sys.stderr)
        return 2
    if args.learner_gpus not in ("auto", "0", "1"):
        print(f"--learner-gpus must be auto, 0 or 1, got {args.learner_gpus!r}", file=sys.stderr)
        return 2
    extra_env = _shipping_options(args)
    if extra_env is None:
        return 2

    import yaml
    client = _connect(args)
    if client is None:
        return 1
    try:
        nodes = list_cluster_nodes(args.address)
    except Exception as exc:  # an older cluster without the state API: Ray's default places the driver on the head
        print(f"note: could not list the cluster's nodes ({exc}); the learner runs on the head node",
              file=sys.stderr)
        nodes = []
    options, where = entrypoint_options(nodes, args.learner_gpus, cfg.runner.device)
    cpus = sum(n["cpus"] for n in nodes)
    if nodes and cfg.runner.num_workers > max(1, cpus - 1):
        print(f"warning: runner.num_workers={cfg.runner.num_workers} but the cluster has {cpus:g} CPUs, one of them "
              f"for the learner: the extra workers wait for CPUs (the run fails if they cannot start within 10 "
              f"minutes); runner.num_workers=0 fits the cluster", file=sys.stderr)

    name = cfg.runner.name or "run"
    entrypoint = f"{args.python} -m launchers.ray_cluster run --log-every-s {args.log_every_s:g}"
    env_vars = {CONFIG_ENV: yaml.safe_dump(config_to_dict(cfg), sort_keys=False),
                "RAY_JOB_STOP_WAIT_TIME_S": str(int(args.stop_timeout_s)),  # time for the final checkpoint
                **extra_env}
    summary = f"{len(nodes)} node(s), {cpus:g} CPUs" if nodes else "nodes unknown"
    return _ship_and_submit(args, client, entrypoint, env_vars, options, f"swarm_{name}",
                            {"swarm_appo.run_name": name}, f"{summary}; {where}")


def _shipping_options(args) -> Optional[Dict[str, str]]:
    """``--env NAME=VALUE`` as a dict, after checking ``--working-dir``; None (and a message) on a bad one."""
    extra_env = {}
    for item in args.env:
        name, sep, value = item.partition("=")
        if not sep or not name:
            print(f"--env expects NAME=VALUE, got {item!r}", file=sys.stderr)
            return None
        extra_env[name] = value
    working_dir = Path(args.working_dir).resolve()
    if not (working_dir / "launchers" / "ray_cluster.py").exists():
        print(f"--working-dir {working_dir} does not hold this project (launchers/ray_cluster.py)", file=sys.stderr)
        return None
    return extra_env


def _ship_and_submit(args, client, entrypoint: str, env_vars: Dict[str, str], options: Dict[str, Any],
                     id_prefix: str, metadata: Dict[str, str], where: str) -> int:
    """Submit ``entrypoint`` with the project directory as its working directory; print the job id and how
    to follow it; with ``--follow`` stream its logs and return 0 only if it succeeded."""
    job_id = args.job_id or f"{id_prefix}_{time.strftime('%Y%m%d_%H%M%S')}_{uuid.uuid4().hex[:4]}"
    runtime_env = {
        "working_dir": str(Path(args.working_dir).resolve()),
        "excludes": DEFAULT_EXCLUDES + list(args.exclude),
        "env_vars": {"PYTHONUNBUFFERED": "1", "WANDB_SILENT": "true", **env_vars},
    }
    try:
        job_id = _submit_with_retry(client, entrypoint=entrypoint, submission_id=job_id, runtime_env=runtime_env,
                                    metadata=metadata, **options)
    except Exception as exc:
        print(f"submission to {args.address} failed: {exc}", file=sys.stderr)
        return 1
    print(job_id, flush=True)
    print(f"submitted to {args.address} ({where}).\n"
          f"  logs:   python -m launchers.ray_cluster logs {job_id} --follow --address {args.address}\n"
          f"  status: python -m launchers.ray_cluster status {job_id} --address {args.address}\n"
          f"  stop:   python -m launchers.ray_cluster stop {job_id} --address {args.address}", file=sys.stderr)
    if not args.follow:
        return 0
    status = _follow(client, job_id)
    print(f"job {job_id}: {status}", file=sys.stderr)
    return 0 if status == "SUCCEEDED" else 1


def cmd_evaluate(args) -> int:
    """Submit ``swarm_appo.evaluate`` as a job: its driver on the node that holds the checkpoints (the head,
    or ``--node``), its actors on every CPU of the cluster. The evaluation's own arguments are checked here."""
    from swarm_appo.evaluate import build_parser
    eval_parser = build_parser()
    eval_parser.prog = "launchers.ray_cluster evaluate"
    eval_args = eval_parser.parse_args(args.eval_args)  # a bad argument exits here (2), before any contact
    if eval_args.workers == 0:  # (--address is this launcher's: the job sets the evaluation's to "auto")
        eval_parser.error("--workers 0 cannot be used: where the episodes run is set by the job itself "
                          "(it spreads them over the cluster)")
    extra_env = _shipping_options(args)
    if extra_env is None:
        return 2
    client = _connect(args)
    if client is None:
        return 1
    options: Dict[str, Any] = {}
    where = "the evaluation's driver runs on the head node, its actors on every CPU of the cluster"
    if args.node:
        try:
            node_ids = [n["node_id"] for n in list_cluster_nodes(args.address)]
        except Exception:  # no state API: Ray reports an unknown node by leaving the job pending
            node_ids = [args.node]
        if args.node not in node_ids:
            print(f"--node {args.node} is not an alive node of the cluster; its nodes: {node_ids}", file=sys.stderr)
            return 2
        options["entrypoint_label_selector"] = {HEAD_LABEL: args.node}
        where = f"the evaluation's driver runs on node {args.node}, its actors on every CPU of the cluster"
    entrypoint = " ".join([args.python, "-m", "launchers.ray_cluster", "run-eval",
                           *(shlex.quote(a) for a in args.eval_args)])
    return _ship_and_submit(args, client, entrypoint, extra_env, options, "swarm_eval", {"swarm_appo.job": "eval"},
                            where)


def _connect(args):
    enable_token_auth_if_available(os.environ)
    try:
        return _client(args.address)
    except Exception as exc:
        print(f"cannot reach the Ray Jobs API at {args.address}: {exc}", file=sys.stderr)
        return None


def cmd_status(args) -> int:
    client = _connect(args)
    if client is None:
        return 1
    if args.job_id is None:
        jobs = sorted(client.list_jobs(), key=lambda j: j.start_time or 0)
        for job in jobs:
            print(f"{job.submission_id or job.job_id}  {job.status}  {job.entrypoint}")
        if not jobs:
            print("no jobs")
        return 0
    info = client.get_job_info(args.job_id)
    print(f"{args.job_id}: {info.status}")
    if info.message:
        print(info.message)
    return 0


def cmd_logs(args) -> int:
    client = _connect(args)
    if client is None:
        return 1
    if args.follow:
        status = _follow(client, args.job_id)
        print(f"job {args.job_id}: {status}", file=sys.stderr)
    else:
        print(client.get_job_logs(args.job_id), end="")
    return 0


def cmd_stop(args) -> int:
    client = _connect(args)
    if client is None:
        return 1
    was_running = client.stop_job(args.job_id)
    if not was_running:
        print(f"job {args.job_id} was not running: {client.get_job_status(args.job_id)}")
        return 0
    if args.no_wait:
        print(f"stop requested for {args.job_id}")
        return 0
    status = _wait_for_end(client, args.job_id, timeout_s=args.timeout_s)
    print(f"job {args.job_id}: {status}")
    return 0 if _terminal(status) else 1


# =============================================================================================== on the cluster
class ProgressLines:
    """A log line with the newest metrics every ``every_s`` seconds (a progress bar does not suit job logs)."""

    def __init__(self, run_dir: Path, every_s: float):
        self.path = run_dir / "metrics.jsonl"
        self.every_s = every_s
        self._last = time.monotonic()

    def __call__(self, version: int, sampler) -> None:
        if time.monotonic() - self._last < self.every_s:
            return
        self._last = time.monotonic()
        import json
        with open(self.path, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - 65536))
            lines = f.read().splitlines()
        if not lines:
            return
        r = json.loads(lines[-1])
        reward = r.get("charts/episode_reward")
        print(f"agent steps {r['global_step']:,}  steps/s {r.get('charts/sps', 0):,.0f}  "
              f"reward {reward if reward is None else round(reward, 3)}  lag {r.get('lag/mean', 0):.1f}  "
              f"policy version {version}  worker restarts {sampler.restarts}", flush=True)


def cmd_run(args) -> int:
    """The job's entrypoint: train with the shipped config, joining the cluster."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from swarm_appo.cluster import read_placement
    from swarm_appo.config import ConfigError, config_from_dict, validate, yaml_load
    from swarm_appo.trainer import TrainingError, fresh_run_dir, train

    text = os.environ.get(CONFIG_ENV)
    if not text:
        print(f"`run` is the entrypoint of a job made by `submit` (no {CONFIG_ENV} in the environment)",
              file=sys.stderr)
        return 2
    try:
        cfg = validate(config_from_dict(yaml_load(text)))
    except ConfigError as exc:
        print(f"config error: {exc}", file=sys.stderr)
        return 2
    root = cluster_run_root(cfg.runner.run_dir)
    run_dir = fresh_run_dir(root, cfg.runner.name or time.strftime("run_%Y%m%d_%H%M%S"))
    cfg.runner.run_dir, cfg.runner.name = str(root), run_dir.name
    if cfg.runner.init_checkpoint:  # where the run directories are: relative to the home directory, as run_dir
        cfg.runner.init_checkpoint = str(cluster_run_root(cfg.runner.init_checkpoint))
    print(f"run directory: {run_dir} (on {socket.gethostname()})", flush=True)
    stop_on_sigterm()
    try:
        result = train(cfg, progress=False, on_iteration=ProgressLines(run_dir, args.log_every_s))
    except TrainingError as exc:
        return report_training_error(exc)
    except ConfigError as exc:  # what only the learner's node can tell: its device, its disk
        print(f"config error: {exc}", file=sys.stderr)
        return 2
    print_result(result)
    placement = read_placement(result.run_dir)
    if placement:
        for node, count in placement["fragments_per_node"].items():
            workers = sum(w["node_id"] == node for w in placement["rollout_workers"])
            print(f"node {node[:8]}: {workers} rollout worker(s), {count} fragments"
                  f"{' (learner)' if node == placement['learner']['node_id'] else ''}")
    return 130 if result.interrupted else 0


def cmd_run_eval(args) -> int:
    """The evaluation job's entrypoint: ``swarm_appo.evaluate`` with its actors on the whole cluster.
    Relative paths (and ``~``) are taken from the home directory, where training runs keep their run dirs."""
    from swarm_appo import evaluate
    # `python -m` put the job's copy of the project on sys.path as an absolute path: imports survive the chdir
    os.chdir(Path.home())
    argv = [os.path.expanduser(a) if a.startswith("~") else a for a in args.eval_args]
    return evaluate.main([*argv, "--address", "auto", "--no-progress"])


# =============================================================================================== CLI
def parse_args(argv: Optional[List[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="swarm-cluster", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)

    def with_address(sp):
        sp.add_argument("--address", default=default_address(),
                        help="the head's dashboard, http://<head>:8265 (default: %(default)s)")
        return sp

    s = with_address(sub.add_parser("submit", help="submit a training run; prints the job id"))
    s.add_argument("--follow", action="store_true", help="stream the logs until the job ends (exit 0 = succeeded)")
    s.add_argument("--job-id", default=None, help="submission id (default: swarm_<run name>_<time>_<random>)")
    s.add_argument("--learner-gpus", default="auto",
                   help="GPU for the learner: auto (one when the cluster has a GPU), 0 or 1 (default: auto)")
    _shipping_arguments(s)
    s.add_argument("--log-every-s", type=float, default=30.0, help="seconds between progress lines in the logs")
    s.add_argument("--stop-timeout-s", type=float, default=60.0,
                   help="on `stop`, seconds the run has for its final checkpoint before it is killed")
    add_config_arguments(s)

    st = with_address(sub.add_parser("status", help="status of one job, or list all jobs"))
    st.add_argument("job_id", nargs="?", default=None)

    lg = with_address(sub.add_parser("logs", help="print a job's logs"))
    lg.add_argument("job_id")
    lg.add_argument("--follow", action="store_true", help="stream until the job ends")

    sp = with_address(sub.add_parser("stop", help="stop a job (SIGTERM: it writes a final checkpoint)"))
    sp.add_argument("job_id")
    sp.add_argument("--no-wait", action="store_true", help="return without waiting for the job to end")
    sp.add_argument("--timeout-s", type=float, default=120.0, help="how long to wait for the job to end")

    ev = with_address(sub.add_parser(
        "evaluate", help="evaluate checkpoints on the cluster (the paper's tables); other arguments go to "
                         "swarm_appo.evaluate, paths relative to the home directory of the driver's node",
        usage="%(prog)s [--address URL] [--follow] [--node NODE_ID] ... --checkpoint PATH [PATH ...] "
              "[swarm_appo.evaluate arguments]", allow_abbrev=False))
    ev.add_argument("--follow", action="store_true", help="stream the logs until the job ends (exit 0 = succeeded)")
    ev.add_argument("--node", default=None, metavar="NODE_ID",
                    help="run the driver (which reads the checkpoints and writes the tables) on this node "
                         "(default: the head; a run's cluster.json names its learner's node)")
    ev.add_argument("--job-id", default=None, help="submission id (default: swarm_eval_<time>_<random>)")
    _shipping_arguments(ev)

    r = sub.add_parser("run", help="(runs on the cluster) the job's entrypoint")
    r.add_argument("--log-every-s", type=float, default=30.0)
    sub.add_parser("run-eval", help="(runs on the cluster) the evaluation job's entrypoint", add_help=False)
    args, rest = p.parse_known_args(argv)
    if args.command in ("evaluate", "run-eval"):  # the rest goes to swarm_appo.evaluate, in order
        args.eval_args = rest
    elif rest:
        p.error(f"unrecognized arguments: {' '.join(rest)}")
    return args


def _shipping_arguments(sp) -> None:
    sp.add_argument("--working-dir", default=str(PROJECT_ROOT), help="project directory to ship (default: this one)")
    sp.add_argument("--exclude", action="append", default=[], metavar="PATTERN",
                    help=f"also leave out these paths (gitignore syntax); always left out: {DEFAULT_EXCLUDES}")
    sp.add_argument("--env", action="append", default=[], metavar="NAME=VALUE",
                    help="an environment variable for the job on the cluster, e.g. WANDB_API_KEY=... for "
                         "wandb online (visible to whoever can read the cluster's job list)")
    sp.add_argument("--python", default="python", help="Python of the cluster's nodes (default: python)")


COMMANDS = {"submit": cmd_submit, "status": cmd_status, "logs": cmd_logs, "stop": cmd_stop, "run": cmd_run,
            "evaluate": cmd_evaluate, "run-eval": cmd_run_eval}


def main(argv: Optional[List[str]] = None) -> int:
    args = parse_args(argv)
    return COMMANDS[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
