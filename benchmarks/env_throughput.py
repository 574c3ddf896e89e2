"""Simulator throughput on one CPU core: agent-steps/s of VecQuadEnv, and numba compile times.

    python -m benchmarks.env_throughput [--agents 1,8,32,128] [--drones 8192] [--dtypes float64,float32]
                                        [--scenarios static_same_goal,mix,o_random] [--repeats 10] [--steps 40]
                                        [--core N] [--no-compile] [--no-append]

For each scenario and swarm size N (K = 6 "full" neighbours, all noise on) the process is
pinned to one core (``os.sched_setaffinity``, what ``taskset -c`` does) and E = drones // N swarms are
stepped with uniform random actions in [-1, 1], after a JIT warm-up. A figure is the best of
``--repeats`` windows of ``--steps`` control steps (the machine may be shared; the median is shown too).
Scenario logic: for each dynamic scenario at N = 8, the goal update alone (``scenario.update`` on a copy of the
goals, timers and random streams) is timed the same way and reported as a share of the whole step (target
<= 20%); resets are inside the step figure.
Obstacles: the o_* scenarios (and any scenario given as NAME+obstacles) run with ``env.obstacles``. Their cost
is measured against a twin env (same config and seed) whose kernels have the obstacle switch off (no cylinder
contacts, bounce or obstacle field; the layouts are still drawn at resets): windows of the two alternate,
and 1 - (best rate with) / (best rate without) is reported as the obstacles' share of the step (target <= 20%
at N = 8, with the goal update).
Compile time: a fresh Python process imports quad_env, builds an env and takes one step, first with an
empty numba cache (``NUMBA_CACHE_DIR`` = a new temp dir: cold) and then again with the cache it filled
(warm). Figures are appended to benchmarks/RESULTS.md with the command, commit and machine.
"""
from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from benchmarks.common import ROOT, append_results, commit, load_average, machine

TARGETS = {8: 1_000_000, 128: 500_000}  # agent-steps/s on one core (the targets)

COMPILE_SNIPPET = """
import time
t0 = time.perf_counter()
import numpy as np
from quad_env import EnvConfig, VecQuadEnv
t1 = time.perf_counter()
env = VecQuadEnv(EnvConfig(num_agents=8, sim_dtype="{dtype}"), num_envs=2, seed=0)
env.step(np.zeros((16, 4), np.float32))
t2 = time.perf_counter()
print(t1 - t0, t2 - t1)
"""


def parse_scenario(name: str):
    """'o_random' -> ('o_random', True); 'mix+obstacles' -> ('mix', True); 'mix' -> ('mix', False)."""
    from quad_env.scenarios import SCENARIO_REGISTRY

    base, _, extra = name.partition("+")
    if base not in SCENARIO_REGISTRY or extra not in ("", "obstacles"):
        raise SystemExit(f"unknown scenario {name!r}; valid: {sorted(SCENARIO_REGISTRY)} (optionally +obstacles)")
    return base, extra == "obstacles" or SCENARIO_REGISTRY[base].needs_obstacles


def time_window(env, actions, steps: int) -> float:
    """Agent-steps/s of ``steps`` control steps."""
    start = time.perf_counter()
    for t in range(steps):
        env.step(actions[t % 16])
    return steps * env.num_drones / (time.perf_counter() - start)


def measure(num_agents: int, num_drones: int, dtype: str, steps: int, repeats: int,
            scenario: str = "static_same_goal") -> dict:
    from quad_env import EnvConfig, VecQuadEnv
    from quad_env.params import I_OBSTACLES

    base, obstacles = parse_scenario(scenario)
    num_envs = max(1, num_drones // num_agents)
    cfg = EnvConfig(num_agents=num_agents, num_neighbors=6, sim_dtype=dtype, scenario=base, obstacles=obstacles)
    env = VecQuadEnv(cfg, num_envs=num_envs, seed=0)
    twin = None
    if obstacles:  # the same env without the kernels' obstacle work
        twin = VecQuadEnv(cfg, num_envs=num_envs, seed=0)
        twin._ip[I_OBSTACLES] = 0
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (16, env.num_drones, 4)).astype(np.float32)
    for t in range(5):  # JIT warm-up (compiled or loaded from the cache)
        env.step(actions[t])
        if twin is not None:
            twin.step(actions[t])
    rates, twin_rates = [], []
    for _ in range(repeats):
        rates.append(time_window(env, actions, steps))
        if twin is not None:
            twin_rates.append(time_window(twin, actions, steps))
    airborne = float((env.get_state().pos[:, 2] > cfg.physics.floor_z + 1e-9).mean())
    row = dict(N=num_agents, E=num_envs, M=env.num_drones, dtype=dtype, best=max(rates),
               median=float(np.median(rates)), airborne=airborne, scenario=scenario, share=None,
               obstacle_share=1.0 - max(rates) / max(twin_rates) if twin is not None else None)
    if env.scenario.dynamic:  # the goal update alone, on copies (the env's own state is left as it is)
        sc, goal, count = env.scenario, env._goal.copy(), env._step_count.copy()
        rng = env._rng.copy()
        update_rates = []
        for _ in range(repeats):
            start = time.perf_counter()
            for t in range(steps):
                sc.update(goal, count, rng)
                count += 1
            update_rates.append(steps * env.num_drones / (time.perf_counter() - start))
        row["share"] = max(rates) / max(update_rates)  # best update time per step / best step time
    return row


def compile_times(dtype: str, core: int) -> dict:
    """(import s, build + first step s) in a fresh process: cold cache, then warm cache."""
    out = {}
    with tempfile.TemporaryDirectory(prefix="numba_cache_") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=str(ROOT))
        for label in ("cold", "warm"):
            res = subprocess.run(["taskset", "-c", str(core), sys.executable, "-c",
                                  COMPILE_SNIPPET.format(dtype=dtype)],
                                 env=env, cwd=ROOT, capture_output=True, text=True, check=True)
            imp, first = map(float, res.stdout.split())
            out[label] = (imp, first)
    return out


def numba_versions() -> str:
    import numba
    return f"numba {numba.__version__}, numpy {np.__version__}"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", default="1,8,32,128", help="comma-separated swarm sizes N")
    parser.add_argument("--drones", type=int, default=8192, help="drones per step call (E = drones // N)")
    parser.add_argument("--dtypes", default="float64,float32", help="simulator state dtypes to measure")
    parser.add_argument("--scenarios", default="static_same_goal,mix,o_random",
                        help="comma-separated scenario names (NAME+obstacles switches cylinders on)")
    parser.add_argument("--steps", type=int, default=40, help="control steps per timed window")
    parser.add_argument("--repeats", type=int, default=10, help="timed windows per figure (best is kept)")
    parser.add_argument("--core", type=int, default=None, help="CPU core to pin to (default: the first one)")
    parser.add_argument("--no-compile", action="store_true", help="skip the compile-time measurement")
    parser.add_argument("--no-append", action="store_true", help="do not append to benchmarks/RESULTS.md")
    args = parser.parse_args(argv)
    agents = [int(n) for n in args.agents.split(",") if n]
    dtypes = [d for d in args.dtypes.split(",") if d]
    core = args.core if args.core is not None else min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})  # one core, like `taskset -c core`
    load_before = load_average()

    compile_rows = {d: compile_times(d, core) for d in dtypes} if not args.no_compile else {}
    scenarios = [s for s in args.scenarios.split(",") if s]
    rows = [measure(n, args.drones, d, args.steps, args.repeats, sc) for sc in scenarios for d in dtypes
            for n in agents]

    lines = ["| scenario | N | E | dtype | agent-steps/s (best) | median | ns / agent-step | airborne at end | "
             "goal update / step | obstacles / step | target |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    verdicts = []
    for r in rows:
        target = TARGETS.get(r["N"])
        tgt = "" if target is None else f">= {target:,}: {'met' if r['best'] >= target else 'NOT met'}"
        share = "" if r["share"] is None else f"{r['share']:.1%}"
        obst = "" if r["obstacle_share"] is None else f"{r['obstacle_share']:.1%}"
        if (r["share"] is not None or r["obstacle_share"] is not None) and r["N"] == 8:
            total = (r["share"] or 0.0) + (r["obstacle_share"] or 0.0)
            verdicts.append(f"{r['scenario']} goal update + obstacles at N = 8 ({r['dtype']}): {total:.1%} of the step "
                            f"vs <= 20% -> {'met' if total <= 0.2 else 'NOT met'}")
        lines.append(f"| {r['scenario']} | {r['N']} | {r['E']} | {r['dtype']} | {r['best']:,.0f} | {r['median']:,.0f} "
                     f"| {1e9 / r['best']:.0f} | {r['airborne']:.0%} | {share} | {obst} | {tgt} |")
        if target is not None and r["dtype"] == dtypes[0]:
            verdicts.append(f"{r['scenario']} N = {r['N']}: {r['best']:,.0f} vs {target:,} -> "
                            f"{'met' if r['best'] >= target else 'NOT met'}")
    compile_lines = []
    for d, c in compile_rows.items():
        compile_lines.append(f"- compile ({d} state): cold cache {c['cold'][1]:.1f} s (build env + first step; "
                             f"import {c['cold'][0]:.1f} s), warm cache {c['warm'][1]:.2f} s "
                             f"(import {c['warm'][0]:.1f} s)")
    command = "python -m benchmarks.env_throughput " + " ".join(sys.argv[1:] if argv is None else argv)
    section = "\n".join([
        f"## env_throughput — {datetime.datetime.now().isoformat(timespec='seconds')}",
        "",
        f"- command: `{command.strip()}`",
        f"- commit: {commit(['quad_env', 'benchmarks/env_throughput.py'])}",
        f"- machine: {machine(numba_versions())}; pinned to core {core}; load average before: {load_before}, "
        f"after: {load_average()}",
        f"- K = 6 full neighbours, scenarios {', '.join(scenarios)} (o_*: 8 x 8 cylinders of 1 m cells, density 0.2, "
        f"obstacle field on), thrust + sensor noise on, downwash on, uniform random actions, "
        f"{args.drones} drones per step call; best (and median) of {args.repeats} windows of {args.steps} steps "
        f"after a 5-step warm-up; 'airborne' = share of drones off the floor at the end (random actions mostly "
        f"crash them)",
        *compile_lines,
        "",
        *lines,
        "",
        "Targets (first dtype): " + "; ".join(verdicts) + ".",
        "",
    ])
    print(section)
    if not args.no_append:
        append_results(section)


if __name__ == "__main__":
    main()
