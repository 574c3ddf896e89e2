"""Pick a run's final policy by evaluation, on episodes the reported evaluation never flies::

    python -m swarm_appo.select_checkpoint --run runs/NAME [--last K] [--episodes 25] [--scenarios NAME,...]
        [--workers N] [--seed S] [--no-averages] [--no-ema]
    python -m swarm_appo.evaluate --checkpoint runs/NAME/checkpoints/selected.pt      # the reported numbers

Why: the policy's success rate swings by 15-30 points between checkpoints late in a run (benchmarks/RESULTS.md,
"one hour in serial mode"), so the last checkpoint is as likely to sit in a trough as on a crest. Each of the
run's kept checkpoints (``runner.keep_checkpoints``; the last ``--last`` of them) flies the same validation
episodes in the evaluation environment (no training aids, mean actions), and so do the averages of the last j of
them (j = 2..K: the mean of their weights, the observation statistics of the newest; ``--no-averages`` leaves them
out): late in a run, with a small lr and a critic that explains little, Adam's steps wander about a good policy,
and their mean can be better than any one of them. A run trained with ``algo.weight_ema`` adds the running
averages saved in its newest checkpoint (one per horizon; ``swarm_appo.weight_ema``). The best candidate is
written, atomically, to ``checkpoints/selected.pt`` (a copy of the file, or the averaged policy as a policy-only
checkpoint) and the scores to ``selection.json``.

Ranking: the paper's Suc (higher), then Col (fewer), then Dist (smaller), each the mean over the validation
episodes. The validation episodes are seeded by ``validation_seed`` (the run's seed + 2,000,029), apart from
training's and from the evaluation's (``default_eval_seed``: + 1,000,003), so the reported numbers of the
selected checkpoint are not the numbers it was selected on. Episodes are chunked and seeded as
``swarm_appo.evaluate`` flies them: ``--seed`` with the evaluation's seed scores every candidate on the very
episodes the evaluation command reports (a diagnostic: then the choice has seen them). ``selected.pt`` is not a
``ckpt_*`` file: resuming the run still starts from its latest checkpoint.
"""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence

SELECTED_NAME = "selected.pt"
SELECTION_FILE = "selection.json"
RANKING = (("suc", True), ("col", False), ("dist", False))  # (table metric, higher is better), in order


def validation_seed(train_seed: int) -> int:
    """Episodes the selection flies: apart from training's and from the reported evaluation's."""
    return int(train_seed) + 2_000_029


@dataclass
class Candidate:
    path: str  # the checkpoint file, or "mean of the last j" for an average
    step: int  # agent steps (of the newest checkpoint in an average)
    scores: Dict[str, float]  # table metric -> mean over the validation episodes (unscaled: Suc as a share)
    averaged: int = 1  # how many checkpoints' weights it is the mean of
    kind: str = "checkpoint"  # "checkpoint" (a file as saved), "mean" (of the last j) or "ema" (algo.weight_ema)


def average_weights(states: Sequence[Dict], parameters: Sequence[str]) -> Dict:
    """The mean (in float64, cast back) of the named parameters over the state dicts; every other entry (the
    observation statistics, integer buffers) from the last state dict."""
    import torch

    out = dict(states[-1])
    for name in parameters:
        out[name] = (torch.stack([s[name].to(torch.float64) for s in states]).mean(0)
                     .to(states[-1][name].dtype))
    return out


def rank_key(scores: Dict[str, float]):
    """Sort key, best first: higher Suc, then fewer collisions, then a smaller distance."""
    return tuple(-scores[m] if higher else scores[m] for m, higher in RANKING)


def best_of(candidates: Sequence[Candidate]) -> Candidate:
    """The best candidate by ``rank_key``; a tie goes to the later checkpoint (more training), then to the
    plain checkpoint over an average (of checkpoints, or a running one)."""
    if not candidates:
        raise ValueError("no candidates to select from")
    return min(candidates, key=lambda c: (rank_key(c.scores), -c.step, c.averaged, c.kind != "checkpoint"))


def ema_label(horizon: float) -> str:
    return f"EMA over {horizon:,.0f} agent steps"


def score_checkpoints(paths: Sequence[str], scenarios: Optional[Sequence[str]], episodes: int, seed: Optional[int],
                      workers: Optional[int], progress: bool = False, averages: bool = True,
                      ema_state: Optional[Dict] = None):
    """(candidates, their specs, scenarios, seed): every checkpoint, with ``averages`` the mean of the last j
    of them for j = 2..len(paths), and the running averages of ``ema_state`` (the newest checkpoint's
    ``algo.weight_ema`` state), flown on the same validation episodes."""
    import dataclasses

    import numpy as np

    from swarm_appo import evaluation as ev
    from swarm_appo.eval_tables import METRICS
    from swarm_appo.evaluate import EPISODES_PER_TASK
    from swarm_appo.weight_ema import averaged_model_state

    specs = ev.load_policy_specs(list(paths))
    n = specs[-1].env.num_agents
    names = list(scenarios) if scenarios else [specs[-1].env.scenario]
    names = ev.resolve_scenarios(",".join(names), [n])
    ev.check_layouts(specs, [n], names)  # the files only: a weight mean has the newest file's layout
    kinds = [(1, "checkpoint")] * len(specs)  # (checkpoints averaged, kind) per spec
    newest = specs[-1]  # the newest file: observation statistics and layout of every average
    if averages and len(specs) > 1:
        files = list(specs)
        parameters = [name for name, _ in newest.factory().named_parameters()]
        for j in range(2, len(files) + 1):
            weights = average_weights([s.weights for s in files[-j:]], parameters)
            specs.append(dataclasses.replace(newest, label=f"mean of the last {j}", weights=weights,
                                             source=f"mean of the last {j}"))
            kinds.append((j, "mean"))
    for i, horizon in enumerate(ema_state["horizons"] if ema_state else []):
        specs.append(dataclasses.replace(newest, label=ema_label(horizon), source=ema_label(horizon),
                                         weights=averaged_model_state(newest.weights, ema_state, i)))
        kinds.append((1, "ema"))
    seed = validation_seed(specs[-1].seed) if seed is None else int(seed)
    # chunked as swarm_appo.evaluate chunks (episodes seeded per chunk): on the same seed, the same episodes
    tasks = ev.plan_tasks(specs, [n], names, episodes, EPISODES_PER_TASK, seed, deterministic=True, pictures=False)
    results = ev.run_tasks(tasks, specs, workers, progress=progress)
    candidates = []
    for p, spec in enumerate(specs):
        flown = [e for r in results if r.task.policy == p for e in r.episodes]
        scores = {m: float(np.mean([METRICS[m].value(e) for e in flown])) for m, _ in RANKING}
        candidates.append(Candidate(spec.source, spec.step, scores, *kinds[p]))
    return candidates, specs, names, seed


def select(run_dir: str, last: Optional[int] = None, episodes: int = 25, scenarios: Optional[Sequence[str]] = None,
           seed: Optional[int] = None, workers: Optional[int] = 0, progress: bool = False,
           averages: bool = True, emas: bool = True) -> dict:
    """Score the run's kept checkpoints, copy the best to ``checkpoints/selected.pt`` and write
    ``selection.json`` (both atomically). Returns the selection record."""
    from swarm_appo.atomic import atomic_write_bytes
    from swarm_appo.checkpoint import TrainingState, checkpoint_dir, list_checkpoints, write_checkpoint_file
    from swarm_appo.weight_ema import STATE_KEY as EMA_STATE_KEY

    paths = list_checkpoints(run_dir)
    if not paths:
        raise FileNotFoundError(f"no checkpoints (checkpoints/ckpt_*.pt) in run directory {run_dir}")
    if last is not None:
        if last < 1:
            raise ValueError(f"--last must be >= 1, got {last}")
        paths = paths[-last:]
    if episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {episodes}")
    newest = TrainingState.load(paths[-1])  # read once: its running averages, and the config of an averaged policy
    candidates, specs, names, seed = score_checkpoints([str(p) for p in paths], scenarios, episodes, seed, workers,
                                                       progress, averages,
                                                       newest.learner.get(EMA_STATE_KEY) if emas else None)
    best = best_of(candidates)
    target = checkpoint_dir(run_dir) / SELECTED_NAME
    if best.kind == "checkpoint":
        atomic_write_bytes(target, Path(best.path).read_bytes())
    else:  # a policy-only checkpoint of the averaged weights (a checkpoint mean or a running average), with the
        # newest checkpoint's config and steps
        state = TrainingState(learner={"model": specs[candidates.index(best)].weights},
                              agent_steps=newest.agent_steps, config=newest.config)
        write_checkpoint_file(target, state.payload(), newest.agent_steps)
    record = {
        "selected": Path(best.path).name, "selected_step": best.step, "averaged": best.averaged, "kind": best.kind,
        "copied_to": str(target),
        "ranking": [f"{m} ({'higher' if h else 'lower'} is better)" for m, h in RANKING],
        "scenarios": names, "episodes": episodes, "seed": seed, "deterministic": True,
        "candidates": [{"checkpoint": Path(c.path).name, "step": c.step, "averaged": c.averaged, "kind": c.kind,
                        **c.scores}
                       for c in candidates],
    }
    atomic_write_bytes(Path(run_dir) / SELECTION_FILE, (json.dumps(record, indent=2) + "\n").encode())
    return record


def format_record(record: dict) -> str:
    lines = [f"validation: {record['episodes']} episodes per checkpoint on {', '.join(record['scenarios'])}, "
             f"seed {record['seed']}, mean actions, no training aids",
             "| checkpoint | agent steps | Suc % | Col | Dist (m) |", "|---|---:|---:|---:|---:|"]
    for c in record["candidates"]:
        mark = " (selected)" if c["checkpoint"] == record["selected"] else ""
        lines.append(f"| {c['checkpoint']}{mark} | {c['step']:,} | {100 * c['suc']:.1f} | {c['col']:.2f} | "
                     f"{c['dist']:.2f} |")
    lines.append(f"selected {record['selected']} -> {record['copied_to']}")
    return "\n".join(lines)


def build_parser():
    import argparse

    p = argparse.ArgumentParser(prog="swarm-select", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", required=True, help="run directory")
    p.add_argument("--last", type=int, default=None, help="only the last K kept checkpoints (default: all kept)")
    p.add_argument("--episodes", type=int, default=25, help="validation episodes per checkpoint")
    p.add_argument("--scenarios", default=None, help="names separated by commas (default: the training scenario)")
    p.add_argument("--seed", type=int, default=None, help="validation seed (default: the run's seed + 2,000,029)")
    p.add_argument("--workers", type=int, default=None,
                   help="Ray actors, one core each (default: all cores); 0 = in this process")
    p.add_argument("--no-averages", action="store_true", help="only the checkpoints, not the means of the last j")
    p.add_argument("--no-ema", action="store_true", help="leave out the weight EMAs (algo.weight_ema) of the newest "
                   "checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: Optional[List[str]] = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    import torch

    from swarm_appo.checkpoint import CheckpointCorruptError

    if not Path(args.run).is_dir():
        p.error(f"--run {args.run} is not a directory")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one core per task, as in swarm_appo.evaluate
    try:
        record = select(args.run, args.last, args.episodes, args.scenarios.split(",") if args.scenarios else None,
                        args.seed, args.workers, progress=not args.no_progress, averages=not args.no_averages,
                        emas=not args.no_ema)
    except (ValueError, FileNotFoundError, CheckpointCorruptError) as exc:
        p.error(str(exc))
    finally:
        torch.set_num_threads(threads)
    print(format_record(record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
