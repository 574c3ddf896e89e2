"""Training throughput against the peer: this trainer vs Sample Factory 2 + QuadSwarm at matched settings.

    python -m benchmarks.peer_throughput --peer-python /path/sf-venv/bin/python --peer-src /path/quad-swarm-rl
    python -m benchmarks.peer_throughput ... --encoders attention --epochs 1 --seconds 120 --peer-envs 2,8

The peer (sample-factory 2.x and the quad-swarm-rl sources) lives in its own virtual environment: neither is a
dependency of this project. Each configuration runs the peer, then this trainer in each of ``--precisions``,
back to back, alone on the machine; agent-steps/s is the learner's consumed agent steps over the time after a
warm-up (30% of the span from the first trained batch to the end), read from the peer's ``sf_log.txt``
("Total num frames": env steps consumed by its learner, one per agent) and from our ``metrics.jsonl``.

Matched settings: 8 drones on ``mix``, 6 nearest neighbours observed as position + velocity, the same encoder
layers (QuadSwarm's "attention" = our ``kattention``, its "mean_embed" = our ``deepsets``: 256-wide tanh MLPs
joined by a 512-wide tanh layer), separate actor and critic, linear heads (``model.head_hidden=0``), no
recurrent core, no observation normalisation, rollout 128, batch 1024, lr 1e-4, the given epochs; advantages by
V-trace here, by GAE (lambda 1, its quadrotor baseline's) in the peer, whose V-trace fails in sample-factory 2.1.1.
The peer runs ``--peer-workers`` rollout processes with ``--peer-envs`` swarms each (its own inference and
learner processes beside them); ours, per ``--layouts``, one rollout worker and the learner on a core each
(``async``, the default) or serial mode (``serial``: collect a batch, then learn on it, both on both cores), the
best of them counting as the peer's best layout does. With ``serial`` the peer also runs its own serial mode
(``--serial_mode=True --async_rl=False``, one process with all the cores' threads) beside its asynchronous layouts.
"""
from __future__ import annotations

import argparse
import datetime
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Sequence

import torch

from benchmarks.common import ROOT, load_average, publish, section_header, steady_window
from swarm_appo.config import COMPILE_MODES

PEER_ENCODERS = {"attention": "kattention", "mean_embed": "deepsets"}  # peer name -> ours
AGENTS, ROLLOUT, BATCH = 8, 128, 1024  # matched on both sides
_STAMP = re.compile(r"^\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(\d{3})\]\[\s*\d+\] ")
_FRAMES = re.compile(r"Fps is .*?Total num frames: (\d+)")


def peer_command(python: str, encoder: str, epochs: int, seconds: float, train_dir: str, workers: int,
                 envs_per_worker: int, seed: int = 0, serial: bool = False) -> List[str]:
    """The peer's command line at the matched settings (see the module docstring); ``serial``: its serial mode
    (one process: collect, then learn), the counterpart of our ``runner.serial``."""
    # synchronous: one training iteration per rollout of all swarms (2 x 8 swarms x 8 drones x 128 steps = 16
    # batches of 1024), 5 epochs over it, as our serial mode; sample-factory refuses any other ratio
    per_rollout = workers * envs_per_worker * AGENTS * ROLLOUT // BATCH
    layout = ["--serial_mode=True", "--async_rl=False", f"--num_batches_per_epoch={per_rollout}"] if serial else []
    return [python, "-m", "swarm_rl.train", "--env=quadrotor_multi", "--algo=APPO", f"--experiment=peer_{encoder}",
            f"--train_dir={train_dir}", "--device=cpu", f"--seed={seed}",
            f"--train_for_seconds={int(seconds)}",  # ignored by 2.1.1: run_peer stops it
            "--train_for_env_steps=10000000000", f"--num_workers={workers}",
            f"--num_envs_per_worker={envs_per_worker}", "--use_rnn=False", "--rnn_size=256",
            "--nonlinearity=tanh", "--actor_critic_share_weights=False", "--policy_initialization=xavier_uniform",
            "--adaptive_stddev=False", "--learning_rate=0.0001", f"--rollout={ROLLOUT}", "--recurrence=1",
            # its quadrotor baseline's advantages (GAE, lambda 1): sample-factory 2.1.1's V-trace path fails in
            # its summaries ('advantages' missing); our V-trace costs a few vector ops per batch either way
            "--with_vtrace=False", "--gae_lambda=1.0",
            f"--batch_size={BATCH}", f"--num_epochs={epochs}", "--max_grad_norm=5.0", "--exploration_loss_coeff=0.0",
            "--normalize_input=False", "--normalize_returns=False", "--gamma=0.99", "--quads_use_numba=True",
            f"--quads_num_agents={AGENTS}", "--quads_mode=mix", "--quads_episode_duration=15.0",
            f"--quads_neighbor_encoder_type={encoder}", "--quads_neighbor_hidden_size=256",
            "--quads_neighbor_obs_type=pos_vel", "--quads_neighbor_visible_num=6", "--quads_collision_reward=5.0",
            "--with_wandb=False", "--save_every_sec=100000", "--save_best_every_sec=100000", *layout]


OUR_LAYOUTS = {"async": "runner.serial=false", "serial": "runner.serial=true"}  # our process layouts on the cores
# runner.compile on a CPU: the config's modes without "reduce-overhead" (CUDA graphs)
OUR_COMPILE_MODES = tuple(m for m in COMPILE_MODES if m != "reduce-overhead")


def our_overrides(encoder: str, epochs: int, seconds: float, precision: str, layout: str = "async",
                  compile: str = "off") -> List[str]:
    """Our config overrides (on configs/paper.yaml) at the same matched settings, in one of OUR_LAYOUTS: ``async``
    (one rollout worker + the learner, one core each) or ``serial`` (collect, then learn, each on both cores);
    ``compile``: ``runner.compile``, torch.compile of the learner's forward (off by default, as in every config)."""
    return [OUR_LAYOUTS[layout], f"runner.compile={compile}", f"model.encoder={PEER_ENCODERS[encoder]}",
            "model.symmetry=none", "model.head_hidden=0", "model.share_encoder=false", "model.normalize_obs=false",
            f"env.num_agents={AGENTS}", "env.scenario=mix",
            "env.num_neighbors=6", "env.neighbor_obs=pos_vel", f"algo.rollout={ROLLOUT}", f"algo.batch_size={BATCH}",
            "algo.lr=0.0001", f"algo.num_epochs={epochs}", f"runner.precision={precision}",
            f"runner.inference_precision={precision}", f"runner.time_limit_s={seconds}",
            "runner.total_agent_steps=10000000000", "runner.final_eval_episodes=0",
            "runner.checkpoint_every_s=100000", "wandb.mode=disabled"]


def parse_peer_log(text: str, warmup_fraction: float = 0.3) -> Dict[str, float]:
    """Steady-state agent-steps/s from a Sample Factory log: the learner's frame count over time, after a warm-up
    (``warmup_fraction`` of the span from its first trained batch to the last report where the count moved)."""
    points, start = [], None  # (seconds since epoch, frames); the log's first stamped line
    for line in text.splitlines():
        stamp = _STAMP.match(line)
        if not stamp:
            continue
        t = datetime.datetime.strptime(stamp.group(1), "%Y-%m-%d %H:%M:%S").timestamp() + int(stamp.group(2)) / 1000
        start = t if start is None else start
        frames = _FRAMES.match(line, stamp.end())
        if frames:
            points.append((t, int(frames.group(1))))
    # the reports where the count moved (its serial mode trains in steps of a whole rollout, 16 x 1024 frames,
    # reported unchanged every few seconds between): a rate between two moves is not biased by where the window
    # cuts a flat stretch
    trained = [p for i, p in enumerate(points) if p[1] > 0 and (i == 0 or p[1] != points[i - 1][1])]
    if len(trained) < 2:
        raise RuntimeError(f"the peer's log has {len(trained)} reports with trained frames: raise --seconds")
    steady = steady_window(trained, lambda p: p[0], warmup_fraction)
    (ta, fa), (tb, fb) = steady[0], steady[-1]
    return {"sps": (fb - fa) / max(tb - ta, 1e-9), "agent_steps": fb, "first_trained_s": trained[0][0] - start}


def run_peer(args, encoder: str, epochs: int, envs_per_worker: int, tmp: Path, serial: bool = False
             ) -> Dict[str, float]:
    train_dir = tmp / f"peer_{encoder}_e{epochs}_x{envs_per_worker}{'_serial' if serial else ''}"
    # one thread per process when its processes share the cores; its one serial process gets them all
    threads = str(os.cpu_count() or 1) if serial else "1"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [args.peer_src, os.environ.get("PYTHONPATH")])),
               OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", threads))
    cmd = peer_command(args.peer_python, encoder, epochs, args.seconds, str(train_dir), args.peer_workers,
                       envs_per_worker, serial=serial)
    log = train_dir / f"peer_{encoder}" / "sf_log.txt"
    start = time.time()
    train_dir.mkdir(parents=True)
    with open(train_dir / "console.txt", "w") as console:  # a file, not a pipe: the peer logs a lot
        proc = subprocess.Popen(cmd, env=env, cwd=args.peer_src, stdout=console, stderr=subprocess.STDOUT,
                                start_new_session=True)
    try:  # stopped from here: sample-factory 2.1.1 ignores --train_for_seconds, and hangs when its learner dies
        while proc.poll() is None and time.time() - start < args.seconds:
            time.sleep(2.0)
            text = log.read_text() if log.exists() else ""
            if "Unhandled exception" in text:
                raise RuntimeError(f"the peer's learner failed; its log ends:\n{text[-3000:]}")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    if not log.exists():
        raise RuntimeError(f"the peer wrote no log (exit {proc.returncode}):\n"
                           f"{(train_dir / 'console.txt').read_text()[-2000:]}")
    return parse_peer_log(log.read_text())


def our_label(layout: str, compile: str) -> str:
    """How a run of ours is named in the table: its layout, and its torch.compile mode when on."""
    return layout if compile == "off" else f"{layout} compiled ({compile})"


def run_ours(args, encoder: str, epochs: int, precision: str, layout: str, tmp: Path,
             compile: str = "off") -> Dict[str, float]:
    from benchmarks.training_throughput import measure_run
    from swarm_appo.config import load_config
    from swarm_appo.trainer import train

    cfg = load_config(str(ROOT / "configs" / "paper.yaml"), [
        *our_overrides(encoder, epochs, args.seconds, precision, layout, compile), f"runner.run_dir={tmp}",
        f"runner.name=ours_{encoder}_e{epochs}_{precision}_{layout}_{compile}"])
    result = train(cfg, progress=False)
    return measure_run(result.run_dir)


def our_cell(by_layout: Dict[str, Dict[str, float]], peer_sps: float) -> str:
    """One table cell: each layout's agent-steps/s (named when there are several), the best against the peer."""
    best = max(r["sps"] for r in by_layout.values())
    if len(by_layout) == 1:
        return f"{best:,.0f} (**{best / peer_sps:.2f}x**)"
    rates = ", ".join(f"{name}: {r['sps']:,.0f}" for name, r in by_layout.items())
    return f"{rates} (best **{best / peer_sps:.2f}x**)"


def main(argv: Sequence[str] = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--peer-python", required=True, help="python of a virtual environment with sample-factory 2")
    p.add_argument("--peer-src", required=True, help="a checkout of quad-swarm-rl (put on the peer's PYTHONPATH)")
    p.add_argument("--encoders", default="attention,mean_embed", help=f"peer names: {', '.join(PEER_ENCODERS)}")
    p.add_argument("--epochs", default="1,5")
    p.add_argument("--precisions", default="fp32,bf16", help="ours, runner.precision (learner and inference)")
    p.add_argument("--seconds", type=float, default=120.0, help="training time per run")
    p.add_argument("--peer-workers", type=int, default=2, help="the peer's rollout processes (its default: cores)")
    p.add_argument("--peer-envs", default="8", help="comma-separated swarms per peer rollout process; the best "
                   "counts (8 x 2 workers = our 16 swarms in flight)")
    p.add_argument("--layouts", default="async", help="comma-separated: async (ours: a rollout worker and the "
                   "learner, one core each) and/or serial (collecting, then learning, on all cores; the peer's serial "
                   "mode runs too); on each side the best counts")
    p.add_argument("--compile", default="off", help="comma-separated runner.compile modes of ours (off, default): "
                   "each layout runs once per mode; the compilation (its first learner call) falls in the warm-up")
    p.add_argument("--no-append", action="store_true", help="do not append to benchmarks/RESULTS.md")
    args = p.parse_args(argv)
    encoders, precisions = args.encoders.split(","), args.precisions.split(",")
    layouts, compiles = args.layouts.split(","), args.compile.split(",")
    for name in layouts:
        if name not in OUR_LAYOUTS:
            p.error(f"--layouts: unknown {name!r}; valid: {', '.join(OUR_LAYOUTS)}")
    for name in compiles:
        if name not in OUR_COMPILE_MODES:
            p.error(f"--compile: unknown {name!r}; valid: {', '.join(OUR_COMPILE_MODES)}")
    for name in encoders:
        if name not in PEER_ENCODERS:
            p.error(f"unknown encoder {name!r}; valid: {', '.join(PEER_ENCODERS)}")
    for name in precisions:
        if name not in ("fp32", "bf16"):
            p.error(f"--precisions: unknown {name!r}; valid: fp32, bf16")
    try:
        epoch_counts, peer_envs = ([int(x) for x in s.split(",")] for s in (args.epochs, args.peer_envs))
    except ValueError:
        p.error("--epochs and --peer-envs take comma-separated integers")
    if min(epoch_counts + peer_envs) < 1:
        p.error("--epochs and --peer-envs must be >= 1")
    if not Path(args.peer_python).exists() or not (Path(args.peer_src) / "swarm_rl").is_dir():
        p.error("--peer-python must exist and --peer-src must hold swarm_rl/")
    os.environ.setdefault("WANDB_SILENT", "true")
    started = datetime.datetime.now().isoformat(timespec="seconds")
    load_before = load_average()

    tmp = Path(tempfile.mkdtemp(prefix="peer_bench_"))
    lines = []
    try:
        for encoder in encoders:
            for epochs in epoch_counts:
                peers = {}  # layout label -> result; with our serial layout, the peer's serial mode runs too
                runs = [(f"{args.peer_workers}x{e}", e, False) for e in peer_envs]
                if "serial" in layouts:
                    runs.append((f"serial {args.peer_workers}x{max(peer_envs)}", max(peer_envs), True))
                for label, envs, serial in runs:
                    r = peers[label] = run_peer(args, encoder, epochs, envs, tmp, serial=serial)
                    print(f"peer {encoder} e{epochs} {label}: {r['sps']:,.0f} agent-steps/s (first trained batch "
                          f"after {r['first_trained_s']:.0f} s)", flush=True)
                peer = max(peers.values(), key=lambda r: r["sps"])
                ours = {}  # precision -> layout -> result
                for precision in precisions:
                    for layout in layouts:
                        for mode in compiles:
                            label = our_label(layout, mode)
                            r = ours.setdefault(precision, {})[label] = run_ours(args, encoder, epochs, precision,
                                                                                  layout, tmp, mode)
                            print(f"ours {PEER_ENCODERS[encoder]} e{epochs} {precision} {label}: {r['sps']:,.0f} "
                                  f"agent-steps/s, {r['sps'] / peer['sps']:.2f}x the peer", flush=True)
                peer_cells = ", ".join(f"{label}: {r['sps']:,.0f}" for label, r in peers.items())
                ours_cells = " | ".join(our_cell(by_layout, peer["sps"]) for by_layout in ours.values())
                shares = ", ".join(f"{r['learner_share']:.2f}" for by_layout in ours.values()
                                   for r in by_layout.values())
                lines.append(f"| {encoder} / {PEER_ENCODERS[encoder]} | {epochs} | {peer_cells} | {ours_cells} | "
                             f"{shares} |")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    labels = [f"{pr} {our_label(lo, m)}" for pr in precisions for lo in layouts for m in compiles]
    header = ("| encoder (peer / ours) | epochs | peer agent-steps/s (workers x swarms) | "
              + " | ".join(f"ours {pr} (vs best peer)" for pr in precisions)
              + f" | our learner share ({', '.join(labels)}) |\n"
              + "|---|---|---|" + "---|" * len(precisions) + "---|")
    peer_version = subprocess.run(
        [args.peer_python, "-c", "import importlib.metadata as m; print(m.version('sample-factory'))"],
        capture_output=True, text=True).stdout.strip() or "unknown"
    section = "\n".join([
        *section_header("peer_throughput", started, argv, ["swarm_appo", "encoders", "quad_env"], load_before),
        f"- peer: sample-factory {peer_version} + quad-swarm-rl ({args.peer_src}); torch {torch.__version__} (ours)",
        f"- {args.seconds:.0f} s per run, figures after a 30% warm-up; matched settings in the module docstring",
        "",
        header, *lines,
    ])
    publish(section, append=not args.no_append)


if __name__ == "__main__":
    main()
