"""End-to-end training throughput: agent-steps/s of the whole trainer (Ray workers + learner) per encoder.

    python -m benchmarks.training_throughput                       # paper sizes, N = 8, 5 and 1 epochs
    python -m benchmarks.training_throughput --encoders deepsets --epochs 1 --seconds 60
    python -m benchmarks.training_throughput --precisions fp32,bf16/fp32,bf16   # learner[/inference]

For each encoder, epoch count and precision it trains with ``configs/paper.yaml`` (the paper's model sizes and
hyperparameters) for ``--seconds`` and reports, after a warm-up, agent-steps/s, mean/max policy lag and
the share of time per phase. A precision is ``learner/inference`` (``runner.precision`` /
``runner.inference_precision``); one name sets both. The roofline is the matmul bound: FLOPs per agent step
(one inference forward of the actor + ``epochs`` x forward-and-backward of the training loss, counted by
torch's FlopCounterMode), each part at the one-thread GEMM rate of its precision, spread over all cores
(rates measured in the same run). Figures are appended to benchmarks/RESULTS.md.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from benchmarks.common import ROOT, append_results, commit, gemm_rate, load_average, machine, steady_window
from encoders import swarm_observations
from encoders.testing import random_obs
from swarm_appo.config import load_config
from swarm_appo.model import model_factory

DEFAULT_ENCODERS = ("deepsets", "kattention", "se3_kattention", "se3_graphormer")


def flops_per_agent_step(cfg, batch: int = 512) -> dict:
    """Counted matmul FLOPs per agent step: inference (actor forward) and training per epoch."""
    layout = cfg.env.obs_layout()
    model = model_factory(layout, cfg.model)()
    obs = torch.as_tensor(random_obs(layout, batch, np.random.default_rng(0)), dtype=torch.float32)
    # a central critic reads each drone's swarm; a recurrent core steps from a state (zeros here)
    swarm = swarm_observations(obs, cfg.env.num_agents) if model.central else None
    state = model.initial_state(batch)
    with FlopCounterMode(display=False) as fc:
        with torch.no_grad():  # what a rollout worker runs per step: the actor, plus the critic for value clipping
            model.act(obs, with_value=cfg.algo.value_clip is not None, swarm_obs=swarm, state=state)
    inference = fc.get_total_flops() / batch
    actions = torch.randn(batch, 4)
    with FlopCounterMode(display=False) as fc:
        log_prob, entropy, value, _ = model.evaluate_sequence(obs[None], actions[None], state, None,
                                                              None if swarm is None else swarm[None])
        (log_prob.mean() + entropy.mean() + value.pow(2).mean()).backward()
    train_epoch = fc.get_total_flops() / batch
    return {"inference": inference, "train_epoch": train_epoch,
            "total": inference + cfg.algo.num_epochs * train_epoch}


def measure_run(run_dir: Path, warmup_fraction: float = 0.3) -> dict:
    """Steady-state figures from a run's metrics.jsonl (records after the warm-up fraction of its time)."""
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    records = [r for r in records if "perf/learner_share" in r]
    if len(records) < 2:
        raise RuntimeError(f"only {len(records)} learner iterations in {run_dir}: raise --seconds")
    steady = steady_window(records, lambda r: r["charts/elapsed_s"], warmup_fraction)
    first, last = steady[0], steady[-1]
    sps = (last["global_step"] - first["global_step"]) / max(last["charts/elapsed_s"] - first["charts/elapsed_s"], 1e-9)
    mean = lambda key: float(np.mean([r[key] for r in steady]))  # noqa: E731
    return {"sps": sps, "lag_mean": mean("lag/mean"), "lag_max": max(r["lag/max"] for r in steady),
            "learner_share": mean("perf/learner_share"), "transfer_share": mean("perf/transfer_share"),
            "env_share": mean("perf/env_share"), "inference_share": mean("perf/inference_share"),
            "agent_steps": last["global_step"]}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--encoders", default=",".join(DEFAULT_ENCODERS))
    p.add_argument("--epochs", default="5,1", help="comma-separated epoch counts (paper: 5)")
    p.add_argument("--precisions", default="fp32,bf16", help="comma-separated learner[/inference] precisions")
    p.add_argument("--seconds", type=float, default=90.0, help="training time per configuration")
    p.add_argument("--num-agents", type=int, default=8)
    p.add_argument("--config", default=str(ROOT / "configs" / "paper.yaml"))
    p.add_argument("--no-append", action="store_true", help="do not append to benchmarks/RESULTS.md")
    p.add_argument("overrides", nargs="*", help="extra config overrides (key=value)")
    args = p.parse_args(argv)
    os.environ.setdefault("WANDB_SILENT", "true")

    precisions = []
    for spec in (s for s in args.precisions.split(",") if s):
        learner, _, inference = spec.partition("/")
        pair = (learner, inference or learner)
        if not set(pair) <= {"fp32", "bf16"}:
            p.error(f"bad precision {spec!r}: learner[/inference], each fp32 or bf16")
        precisions.append(pair)
    cores = os.cpu_count() or 1
    torch.set_num_threads(1)
    per_core = {name: gemm_rate(name) for name in ("fp32", "bf16")}
    for name, rate in per_core.items():
        print(f"GEMM {name}: {rate / 1e9:.1f} GFLOP/s per core x {cores} cores")

    from swarm_appo.trainer import train  # after the thread setting above, which train() overrides anyway

    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="train_bench_"))
    for encoder in args.encoders.split(","):
        for epochs, (learner, inference) in ((int(e), pr) for e in args.epochs.split(",") for pr in precisions):
            label = learner if learner == inference else f"{learner}/{inference}"
            name = f"{encoder}_e{epochs}_{label.replace('/', '-')}"
            cfg = load_config(args.config, [
                f"model.encoder={encoder}", f"algo.num_epochs={epochs}", f"env.num_agents={args.num_agents}",
                f"runner.precision={learner}", f"runner.inference_precision={inference}",
                f"runner.time_limit_s={args.seconds}", "runner.total_agent_steps=10000000000",
                "runner.final_eval_episodes=0", "runner.checkpoint_every_s=100000", "wandb.mode=disabled",
                f"runner.run_dir={tmp}", f"runner.name={name}", *args.overrides])
            flops = flops_per_agent_step(cfg)
            result = train(cfg, progress=False)
            try:
                m = measure_run(result.run_dir)
            except RuntimeError as exc:  # too slow for this time budget: say so, keep the other rows
                print(f"{name}: {exc}", flush=True)
                continue
            # matmul-bound seconds per agent step, every core busy: each part at its precision's GEMM rate
            bound_s = (flops["inference"] / per_core[inference]
                       + epochs * flops["train_epoch"] / per_core[learner]) / cores
            roofline_sps = 1.0 / bound_s
            row = dict(encoder=encoder, epochs=epochs, precision=label, **m, mflop_per_step=flops["total"] / 1e6,
                       roofline_sps=roofline_sps, fraction=m["sps"] / roofline_sps)
            rows.append(row)
            print(f"{name}: {m['sps']:,.0f} agent-steps/s, {flops['total'] / 1e6:.2f} MFLOP/step, roofline "
                  f"{roofline_sps:,.0f} -> {100 * row['fraction']:.0f}%, lag mean {m['lag_mean']:.1f} max "
                  f"{m['lag_max']:.0f}", flush=True)

    header = ("| encoder | epochs | precision | agent-steps/s | vs fp32 | MFLOP/agent-step | roofline steps/s | "
              "% of roofline | lag mean / max | learner / transfer share | worker env / inference share |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|")
    fp32 = {(r["encoder"], r["epochs"]): r["sps"] for r in rows if r["precision"] == "fp32"}
    for r in rows:
        base = fp32.get((r["encoder"], r["epochs"]))
        r["vs_fp32"] = f"{r['sps'] / base:.2f}x" if base else "-"
    lines = [f"| {r['encoder']} | {r['epochs']} | {r['precision']} | {r['sps']:,.0f} | {r['vs_fp32']} | "
             f"{r['mflop_per_step']:.2f} | "
             f"{r['roofline_sps']:,.0f} | {100 * r['fraction']:.0f}% | {r['lag_mean']:.1f} / {r['lag_max']:.0f} | "
             f"{r['learner_share']:.2f} / {r['transfer_share']:.2f} | {r['env_share']:.2f} / "
             f"{r['inference_share']:.2f} |" for r in rows]
    section = "\n".join([
        f"## training_throughput — {datetime.datetime.now().isoformat(timespec='seconds')}",
        "",
        f"- command: `python -m benchmarks.training_throughput {' '.join(argv if argv is not None else sys.argv[1:])}`",
        f"- commit: {commit(['swarm_appo', 'encoders', 'quad_env'])}",
        f"- machine: {machine(f'torch {torch.__version__}')}; load average before: {load_average()}",
        f"- config: {Path(args.config).name} (paper sizes), N = {args.num_agents}, {args.seconds:.0f} s per row, "
        f"figures after a 30% warm-up",
        "- precision: learner[/inference] (runner.precision / runner.inference_precision; bf16 = autocast, fp32 "
        "weights and losses)",
        f"- roofline: one-thread GEMM 1024^3 fp32 {per_core['fp32'] / 1e9:.1f}, bf16 {per_core['bf16'] / 1e9:.1f} "
        f"GFLOP/s, x {cores} cores; FLOPs = inference forward (actor) at the inference precision's rate + epochs x "
        f"training forward+backward (actor + critic) at the learner's, counted by FlopCounterMode (matmuls only)",
        "",
        header, *lines,
    ])
    print(section)
    if not args.no_append:
        append_results(section)


if __name__ == "__main__":
    main()
