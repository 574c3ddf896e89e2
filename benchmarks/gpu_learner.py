"""The learner alone on a device, at the config's sizes: how many agent steps per second it can take in, fp32 vs
bf16, and its peak device memory (issue 16 items 1 and 5: the GPU path, bf16 on a GPU).

    python -m benchmarks.gpu_learner [--device cuda] [--encoders se3_graphormer,se3_kattention]
                                     [--precisions fp32,bf16] [--compile off,reduce-overhead] [--seconds 20]
                                     [--config configs/paper.yaml]

One batch of real fragments (the trainer's batch: fragments until ``algo.batch_size`` agent steps) is collected
once on the CPU by a RolloutWorker of the config's environment; then the learner trains on it again and again,
its current policy version stamped on the batch each time (so no sample is masked as stale). learner agent-steps/s
= agent steps of the batch / time of one ``Learner.train`` call (all epochs; CUDA synchronised), best of the timed
calls after one warm-up call (whose time, "first call", holds the compilation under ``--compile``). That is the
rate at which rollout workers must deliver to keep this learner busy.
Runs on a CPU too (``--device cpu``), which is how it is checked where there is no GPU.
"""
from __future__ import annotations

import argparse
import datetime
import sys
import time
from typing import Dict, List, Optional, Sequence

import torch

from benchmarks.common import ROOT, append_results, commit, load_average, machine


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return f"{torch.cuda.get_device_name(device)} (torch {torch.__version__}, CUDA {torch.version.cuda})"
    return f"cpu (torch {torch.__version__}, {torch.get_num_threads()} threads)"


def collect_batch(cfg) -> List[Dict]:
    """Fragments from one CPU rollout worker until the batch holds ``algo.batch_size`` agent steps."""
    from swarm_appo.model import model_factory
    from swarm_appo.rollout import RolloutWorker

    make = model_factory(cfg.env.obs_layout(), cfg.model)
    threads = torch.get_num_threads()  # a RolloutWorker takes one thread; the learner gets them back below
    worker = RolloutWorker(cfg.env, make, cfg.runner.envs_per_worker, cfg.algo.rollout, seed=cfg.runner.seed)
    worker.set_weights(0, make().state_dict())
    batch, steps = [], 0
    while steps < cfg.algo.batch_size:
        batch.append(worker.collect())
        steps += batch[-1]["num_agent_steps"]
    torch.set_num_threads(threads)
    return batch


def make_learner(cfg, device: torch.device, precision: str, compile: str = "off"):
    from swarm_appo.learner import Learner
    from swarm_appo.model import model_factory

    torch.manual_seed(cfg.runner.seed)
    return Learner(model_factory(cfg.env.obs_layout(), cfg.model)(), cfg.algo, device, seed=cfg.runner.seed,
                   precision=precision, compile=compile)


def timed_call(learner, batch: List[Dict], device: torch.device) -> float:
    """Seconds of one ``Learner.train`` call on ``batch`` (CUDA synchronised), the batch stamped fresh."""
    for f in batch:
        f["policy_version"][...] = learner.version  # fresh data every call: nothing masked as stale
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    learner.train(batch)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - t0


def time_learner(cfg, batch: List[Dict], device: torch.device, precision: str, seconds: float,
                 compile: str = "off") -> Dict[str, float]:
    learner = make_learner(cfg, device, precision, compile)
    steps = sum(f["num_agent_steps"] for f in batch)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)

    first = timed_call(learner, batch, device)  # warm-up: allocations, kernel selection, compilation
    times, t_end = [], time.perf_counter() + seconds
    while time.perf_counter() < t_end or len(times) < 2:
        times.append(timed_call(learner, batch, device))
    best = min(times)
    out = {"steps_per_s": steps / best, "call_s": best, "first_call_s": first, "calls": len(times),
           "batch_steps": steps, "updates_per_call": cfg.algo.num_epochs * -(-steps // cfg.algo.batch_size)}
    if device.type == "cuda":
        out["peak_mem_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
    return out


def profile_call(cfg, batch: List[Dict], device: torch.device, precision: str, rows: int = 15,
                 compile: str = "off") -> str:
    """One ``Learner.train`` call under torch.profiler (after a warm-up call): its top operators by self CPU
    time, the kernel count and the device's busy time against the wall time, i.e. where a learner that is
    slower than its device's arithmetic spends the call."""
    from torch.profiler import ProfilerActivity, profile

    learner = make_learner(cfg, device, precision, compile)
    timed_call(learner, batch, device)  # warm-up: allocations, kernel selection, compilation
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        wall = timed_call(learner, batch, device)
    events = prof.key_averages()
    dev_us = sum(getattr(e, "self_device_time_total", 0.0) for e in events)
    kernels = sum(e.count for e in events if getattr(e, "self_device_time_total", 0.0) > 0)
    head = (f"profile {cfg.model.encoder}/{precision}/compile {compile}: wall {wall * 1e3:,.0f} ms (under the "
            f"profiler); device busy {dev_us / 1e3:,.0f} ms ({dev_us / 1e4 / wall:.0f} %); {kernels:,} device "
            f"kernels/copies; {torch.get_num_threads()} CPU thread(s)")
    return head + "\n" + events.table(sort_by="self_cpu_time_total", row_limit=rows, max_name_column_width=48)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--encoders", default="se3_graphormer,se3_kattention", help="comma-separated encoder names")
    p.add_argument("--precisions", default="fp32,bf16", help="comma-separated: fp32, bf16")
    p.add_argument("--compile", default="off",
                   help="comma-separated runner.compile modes to time (off, default, reduce-overhead)")
    p.add_argument("--seconds", type=float, default=20.0, help="timed training per (encoder, precision)")
    p.add_argument("--config", default=str(ROOT / "configs" / "paper.yaml"))
    p.add_argument("--threads", type=int, default=0,
                   help="torch threads of the learner while timed (0: torch's default); in training it has the "
                        "cores the rollout workers leave, often 1")
    p.add_argument("--profile", action="store_true",
                   help="after timing, profile one call per (encoder, precision) and print its top operators")
    p.add_argument("--no-append", action="store_true", help="do not append to benchmarks/RESULTS.md")
    p.add_argument("overrides", nargs="*", help="config overrides (key=value) for every encoder")
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    from swarm_appo.config import COMPILE_MODES, ConfigError, load_config

    device = torch.device(args.device)
    encoders = [e.strip() for e in args.encoders.split(",") if e.strip()]
    precisions = [p.strip() for p in args.precisions.split(",") if p.strip()]
    compiles = [c.strip() for c in args.compile.split(",") if c.strip()]
    bad = [c for c in compiles if c not in COMPILE_MODES]
    if bad:
        raise SystemExit(f"--compile: {bad} not in {list(COMPILE_MODES)}")
    if args.threads < 0:
        raise SystemExit(f"--threads must be >= 0 (0: torch's default), got {args.threads}")
    bad = [p for p in precisions if p not in ("fp32", "bf16")]
    if bad:
        raise SystemExit(f"--precisions: {bad} not in ['fp32', 'bf16']")
    load_before = load_average()
    lines = ["| encoder | precision | compile | batch (agent steps) | updates/call | first call (s) | call (s) | "
             "learner agent-steps/s | vs fp32, off | peak device MiB |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name in encoders:
        try:
            cfg = load_config(args.config, [f"model.encoder={name}", "model.symmetry=null", *args.overrides])
        except ConfigError as exc:
            raise SystemExit(f"config error: {exc}")
        batch = collect_batch(cfg)
        if args.threads:
            torch.set_num_threads(args.threads)
        base = None  # the fp32, uncompiled rate: every row is compared with it
        for precision in precisions:
            for mode in compiles:
                r = time_learner(cfg, batch, device, precision, args.seconds, mode)
                base = r["steps_per_s"] if (precision, mode) == ("fp32", "off") else base
                ratio = f"{r['steps_per_s'] / base:.2f}x" if base and (precision, mode) != ("fp32", "off") else "-"
                mem = f"{r['peak_mem_mb']:,.0f}" if "peak_mem_mb" in r else "-"
                lines.append(f"| {name} | {precision} | {mode} | {r['batch_steps']:,} | {r['updates_per_call']} | "
                             f"{r['first_call_s']:.1f} | {r['call_s']:.3f} | {r['steps_per_s']:,.0f} | {ratio} | "
                             f"{mem} |")
                print(lines[-1], flush=True)
                if args.profile:
                    print(profile_call(cfg, batch, device, precision, compile=mode), flush=True)
    text = "\n".join([
        f"## gpu_learner — {datetime.datetime.now().isoformat(timespec='seconds')}",
        "",
        f"- command: `python -m benchmarks.gpu_learner {' '.join(argv if argv is not None else sys.argv[1:])}`",
        f"- commit: {commit(['encoders', 'swarm_appo', 'configs'])}",
        f"- device: {device_name(device)}",
        f"- machine: {machine()}; load average before: {load_before}, after: {load_average()}",
        f"- config: `{args.config}`{' with ' + ' '.join(args.overrides) if args.overrides else ''}; learner "
        "agent-steps/s = agent steps of one batch / best time of one Learner.train call (all epochs)",
        "",
        *lines,
    ])
    print(text)
    if not args.no_append:
        append_results(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
