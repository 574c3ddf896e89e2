"""The evaluation command line: the paper's Table 1 (per scenario) and Table 2 (zero-shot scaling to larger
swarms) from one or more checkpoints, side by side::

    python -m swarm_appo.evaluate --checkpoint runs/a [runs/b ...] [--scenarios all|name,name]
        [--episodes 50] [--num-agents 8|16,32,64,128] [--workers N] [--seed S] [--out DIR] [--stochastic]
        [--address auto|<host>:<port>]    # the actors on a Ray cluster (launchers.ray_cluster evaluate)

The arguments are parsed before torch, numba or Ray load (``--help`` answers at once); the work is done by
the library ``swarm_appo.evaluation`` (how episodes run, the evaluation environment, seeding), whose names
this module also forwards (``from swarm_appo.evaluate import compare_with_random`` keeps working).
"""
from __future__ import annotations

import sys
from pathlib import Path

EPISODES_PER_TASK = 25  # default chunk: episodes flown together, seeded per chunk (also select_checkpoint's)


def __getattr__(name: str):
    """Library names (``swarm_appo.evaluation``) through this module, loaded on first use."""
    if name.startswith("__"):
        raise AttributeError(name)
    from swarm_appo import evaluation

    try:
        return getattr(evaluation, name)
    except AttributeError:
        raise AttributeError(f"module 'swarm_appo.evaluate' has no attribute {name!r}") from None


def build_parser():
    """The command line of ``main`` (``launchers.ray_cluster evaluate`` checks its arguments with it)."""
    import argparse

    p = argparse.ArgumentParser(prog="swarm-eval", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, nargs="+", metavar="PATH",
                   help="checkpoint files or run directories (their latest valid checkpoint); several side by side")
    p.add_argument("--scenarios", default="all", help="'all' (every scenario but mix) or names separated by commas")
    p.add_argument("--episodes", type=int, default=50, help="episodes per scenario and swarm size (paper: 50)")
    p.add_argument("--num-agents", default=None,
                   help="swarm size N (default: as trained); several, e.g. 16,32,64,128, add the scaling table")
    p.add_argument("--workers", type=int, default=None,
                   help="Ray actors, one core each (default: all cores, or all CPUs of the cluster with "
                        "--address); 0 = in this process, no Ray")
    p.add_argument("--address", default=None,
                   help="run the actors on this Ray cluster ('auto' or <host>:<port> of its GCS), spread over "
                        "its nodes, instead of a local Ray; `python -m launchers.ray_cluster evaluate` submits "
                        "an evaluation to a cluster as a job")
    p.add_argument("--seed", type=int, default=None,
                   help="episode seed (default: the end-of-run evaluation's seed of the first checkpoint)")
    p.add_argument("--out", default=None,
                   help="output folder (default: <run dir of the first checkpoint>/eval, or eval_2, eval_3... "
                        "if that exists: earlier evaluations are kept)")
    p.add_argument("--stochastic", action="store_true", help="sample actions instead of the mean action")
    p.add_argument("--random-baseline", action="store_true", help="add uniformly random actions as a policy")
    p.add_argument("--episodes-per-task", type=int, default=EPISODES_PER_TASK,
                   help="episodes flown together in one environment (one batched forward per step)")
    p.add_argument("--no-pictures", action="store_true", help="no trajectory pictures")
    p.add_argument("--wandb-mode", default="offline", choices=("offline", "online", "disabled"))
    p.add_argument("--wandb-project", default="swarm-appo")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv=None) -> int:
    """The paper's evaluation tables for one or more checkpoints (see the module docstring)."""
    p = build_parser()
    args = p.parse_args(argv)  # before the heavy imports: --help and argument errors answer at once
    import time
    import warnings

    import torch

    from swarm_appo import eval_report
    from swarm_appo import evaluation as ev
    from swarm_appo.checkpoint import CheckpointCorruptError

    if args.workers is not None and args.workers < 0:
        p.error(f"--workers must be >= 0, got {args.workers}")
    if args.workers == 0 and args.address is not None:
        p.error("--workers 0 evaluates in this process; it cannot be combined with --address")
    if args.episodes < 1 or args.episodes_per_task < 1:
        p.error("--episodes and --episodes-per-task must be >= 1")

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one core per task, in-process as on the Ray actors (same numbers)
    try:
        try:
            specs = ev.load_policy_specs(args.checkpoint)
            trained_n = sorted({s.env.num_agents for s in specs})
            if args.num_agents is None and len(trained_n) > 1:
                raise ValueError(f"the checkpoints were trained with different swarm sizes {trained_n}: "
                                 "choose one with --num-agents")
            num_agents = ev.parse_num_agents(args.num_agents) if args.num_agents else trained_n
            # a policy without the obstacle field cannot fly the obstacle scenarios: "all" leaves them out
            obstacles = all(s.env.obstacles for s in specs if s.layout is not None)
            scenarios = ev.resolve_scenarios(args.scenarios, num_agents, obstacles)
            for s in specs[1:]:
                keys = ev._differing_env_keys(specs[0].env, s.env)
                if keys:
                    warnings.warn(f"{s.label} was trained in another environment than {specs[0].label} "
                                  f"(env keys {keys}); each is evaluated in its own", RuntimeWarning)
            if args.random_baseline:
                specs.append(ev.random_spec(specs[0].env))
            ev.check_layouts(specs, num_agents, scenarios)
        except (ValueError, FileNotFoundError, CheckpointCorruptError) as exc:
            p.error(str(exc))
        seed = ev.default_eval_seed(specs[0].seed) if args.seed is None else args.seed
        out = Path(args.out) if args.out else ev.numbered_dir(ev.run_dir_of(args.checkpoint[0]) / "eval")
        tasks = ev.plan_tasks(specs, num_agents, scenarios, args.episodes, args.episodes_per_task, seed,
                              deterministic=not args.stochastic, pictures=not args.no_pictures)
        start = time.perf_counter()
        placement: dict = {}
        try:
            results = ev.run_tasks(tasks, specs, args.workers, progress=not args.no_progress,
                                   address=args.address, placement=placement)
        except ConnectionError as exc:  # --address: no cluster there
            print(f"swarm-eval: cannot join the Ray cluster at --address {args.address}: {exc}", file=sys.stderr)
            return 1
        elapsed = time.perf_counter() - start
    finally:
        torch.set_num_threads(threads)

    setup = eval_report.EvalSetup(
        policies=[(s.label, s.source, s.step) for s in specs], num_agents=num_agents, scenarios=scenarios,
        episodes=args.episodes, seed=seed, deterministic=not args.stochastic, workers=placement.get("workers", 0),
        wall_s=elapsed)
    report = eval_report.write_report(out, setup, results, [s.label for s in specs])
    if placement:
        report.files.append(eval_report.write_placement(out, results, address=args.address, **placement))
    print(report.text)
    eval_report.log_to_wandb(out, report, setup, mode=args.wandb_mode, project=args.wandb_project)
    print(f"written to {out}: {', '.join(sorted(str(p.relative_to(out)) for p in report.files))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
