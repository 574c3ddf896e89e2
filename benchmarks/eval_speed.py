"""Evaluation speed on one CPU core: full 15 s episodes per second for N = 8 and N = 128.

    nice -n 15 python -m benchmarks.eval_speed [--agents 8,128] [--episodes-per-task 25] [--seconds 60]
                                               [--models quickstart,paper] [--core C] [--no-append]

What one evaluation task does (``swarm_appo.evaluate``, what each Ray actor runs): E episodes of one
swarm size flown together in one VecQuadEnv, one batched forward of the policy's mean action for all
E x N drones per control step, one torch thread. Models: the quickstart config (K-DeepSets, 64 wide)
and the paper's (SE(3)-Graphormer, multiplicity 60, heads of 256), untrained (the cost per step does
not depend on the weights). A row flies whole 15 s episodes when that fits in ``--seconds``, else the
first steps of them (timed after a few warm-up steps); episodes/s per core is then agent-steps per
CPU-second divided by N x 1500. Rates per CPU-second (this process's CPU time) stay meaningful on a shared
machine; the wall-clock rate and the share of the core the run got are reported too. An evaluation on W
workers runs W tasks at once: W times the figure, cores permitting.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import sys
import time

import numpy as np
import torch

from benchmarks.common import ROOT, append_results, commit, load_average, machine
from quad_env import VecQuadEnv
from swarm_appo.config import load_config
from swarm_appo.evaluate import fly_episodes, model_policy
from swarm_appo.model import model_factory

MODELS = {"quickstart": None, "paper": str(ROOT / "configs" / "paper.yaml")}  # config file (None: embedded)
WARMUP_STEPS = 3


def build(model_name: str):
    cfg = load_config(MODELS[model_name])
    torch.manual_seed(0)
    model = model_factory(cfg.env.obs_layout(), cfg.model)()
    return cfg, model


def measure(model_name: str, num_agents: int, episodes: int, budget_s: float) -> dict:
    cfg, model = build(model_name)
    env_cfg = dataclasses.replace(cfg.env, num_agents=num_agents)
    full_steps = env_cfg.episode_steps
    act = model_policy(model, deterministic=True)
    inference = [0.0]

    def timed_policy(obs):
        start = time.perf_counter()
        out = act(obs)
        inference[0] += time.perf_counter() - start
        return out

    # Warm-up (numba cache, torch's first calls) and a first estimate of the time per step.
    probe = dataclasses.replace(env_cfg, episode_duration=WARMUP_STEPS * env_cfg.control_dt)
    fly_episodes(probe, timed_policy, episodes, seed=0)
    start = time.perf_counter()
    fly_episodes(probe, timed_policy, episodes, seed=1)
    per_step = (time.perf_counter() - start) / WARMUP_STEPS
    steps = int(min(full_steps, max(10, budget_s / per_step)))

    window = dataclasses.replace(env_cfg, episode_duration=steps * env_cfg.control_dt)
    inference[0] = 0.0
    start, cpu_start = time.perf_counter(), time.process_time()
    stats, _ = fly_episodes(window, timed_policy, episodes, seed=2)
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    assert len(stats) == episodes and stats[0]["length"] == steps
    agent_steps = episodes * num_agents * steps
    per_cpu_s = agent_steps / cpu  # per second of this core's time: what the core does when it is not shared
    return {"model": model_name, "encoder": cfg.model.encoder, "N": num_agents, "E": episodes, "steps": steps,
            "full": steps == full_steps, "sps": agent_steps / elapsed, "cpu_share": cpu / elapsed,
            "per_cpu_s": per_cpu_s, "inference_share": inference[0] / elapsed,
            "episodes_per_core_s": per_cpu_s / (num_agents * full_steps), "full_steps": full_steps}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", default="8,128", help="comma-separated swarm sizes N")
    parser.add_argument("--episodes-per-task", type=int, default=25, help="E (the evaluation CLI's default)")
    parser.add_argument("--models", default="quickstart,paper", help=f"comma-separated, of {list(MODELS)}")
    parser.add_argument("--seconds", type=float, default=60.0, help="time budget per row")
    parser.add_argument("--core", type=int, default=None, help="CPU core to pin to (default: the last one)")
    parser.add_argument("--no-append", action="store_true", help="do not append to benchmarks/RESULTS.md")
    args = parser.parse_args(argv)
    models = [m for m in args.models.split(",") if m]
    for m in models:
        if m not in MODELS:
            parser.error(f"unknown model {m!r}; valid: {list(MODELS)}")
    agents = [int(n) for n in args.agents.split(",") if n]

    torch.set_num_threads(1)
    core = args.core if args.core is not None else max(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})  # one core, like `taskset -c core`
    VecQuadEnv(load_config(None).env, num_envs=1).step(np.zeros((8, 4), np.float32))  # compile / load the kernels
    load_before = load_average()
    rows = []
    for m in models:
        for n in agents:
            r = measure(m, n, args.episodes_per_task, args.seconds)
            rows.append(r)
            print(f"{m} N={n}: {r['per_cpu_s']:,.0f} agent-steps per CPU-s over {r['steps']} steps, "
                  f"{r['episodes_per_core_s']:.3f} episodes/s per core", flush=True)
    load_after = load_average()

    lines = ["| model (encoder) | N | E | drones per forward | steps timed | agent-steps/s (wall) | CPU share | "
             "agent-steps per CPU-s | µs CPU / agent-step | inference share | episodes/s per core | "
             "core-s per episode |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        timed = f"{r['steps']} (full)" if r["full"] else f"{r['steps']} of {r['full_steps']}"
        lines.append(f"| {r['model']} ({r['encoder']}) | {r['N']} | {r['E']} | {r['N'] * r['E']:,} | {timed} | "
                     f"{r['sps']:,.0f} | {r['cpu_share']:.0%} | {r['per_cpu_s']:,.0f} | {1e6 / r['per_cpu_s']:.1f} | "
                     f"{r['inference_share']:.0%} | {r['episodes_per_core_s']:.3g} | "
                     f"{1 / r['episodes_per_core_s']:.3g} |")
    section = "\n".join([
        f"## eval_speed — {datetime.datetime.now().isoformat(timespec='seconds')}",
        "",
        f"- command: `python -m benchmarks.eval_speed {' '.join(argv if argv is not None else sys.argv[1:])}`"
        f" (run under `nice -n {os.nice(0)}`)",
        f"- commit: {commit(['swarm_appo', 'encoders', 'quad_env', 'benchmarks/eval_speed.py'])}",
        f"- machine: {machine(f'torch {torch.__version__}')}; 1 thread pinned to core {core}; "
        f"load average before: {load_before}, after: {load_after}",
        "- evaluation task of swarm_appo.evaluate: E episodes in one VecQuadEnv, one batched forward of the mean "
        "action for E x N drones per step; static_same_goal, thrust and sensor noise on, untrained weights; "
        "episodes of 15 s (1500 steps); 'steps timed' < 1500: the first steps of the episodes; "
        "CPU share = this process's CPU time / wall time (below 100%: the core was shared); per core = per second "
        "of CPU time; episodes/s per core = agent-steps per CPU-s / (N x 1500)",
        "",
        *lines,
    ])
    print(section)
    if not args.no_append:
        append_results(section)


if __name__ == "__main__":
    main()
