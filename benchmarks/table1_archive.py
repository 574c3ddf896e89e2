"""Slim copies of finished Table 1 runs, small enough to commit, so that a table can be rebuilt and filled in on
another machine (``python -m benchmarks.table1 ... --archive DIR``).

A run directory holds checkpoints and a metrics.jsonl of every logged key (megabytes per run). The table needs
three things of it: ``done.json`` (budget, agent-steps/s), the evaluation's ``episodes.jsonl`` and the training
curve's few ``swarm/*`` keys. The archive keeps those (gzipped JSON lines) and the run's ``config.yaml``, in the
layout of the experiment folder, so ``--out DIR --report-only`` reads an archive directly.

Restoring copies an archived run into an experiment folder where that run is missing, only if its recipe is the
one the command asks for (``recipe_differences``): same env, model and algo, same seed, budget and the runner keys
that change learning. A restored run has no checkpoint: raising the budget trains it again from the start.
"""
from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path
from typing import Any, Iterable, List, Mapping, Optional, Sequence, Tuple

# metrics.jsonl keys the table and its curves read (benchmarks.table1.CURVES, benchmarks.learning_speed)
CURVE_KEYS = ("global_step", "swarm/success_rate", "swarm/collisions_drone", "swarm/collisions", "swarm/dist")
# runner keys that change what a run learns (the rest are paths, devices, threads, checkpoint cadence)
RECIPE_RUNNER_KEYS = ("seed", "serial", "num_workers", "envs_per_worker", "max_fragments_in_flight",
                      "total_agent_steps", "precision", "inference_precision", "init_checkpoint")
RECIPE_SECTIONS = ("env", "model", "algo")
# recipe keys added after runs were archived, with the value every run before them had in effect: an archived
# config without one of them counts as having this value (the goal bonus and the height and centre terms did not
# exist: they paid 0, and the bonus' radius then changed nothing). Add a key here only if its value reproduces the
# runs written before it existed.
KEYS_ADDED_LATER = {"env.reward.goal": 0.0, "env.reward.goal_radius": 0.5, "env.reward.height": 0.0,
                    "env.reward.centre": 0.0}
# keys of the recipe sections that change what a run saves, not how it trains (the weight EMA is a read-out: the
# trained weights are bit-identical with or without it, RESULTS.md "weight EMA ..."): never a recipe difference
READOUT_KEYS = ("algo.weight_ema",)
EVAL_FILE = "episodes.jsonl"


def read_jsonl(path: Path) -> List[dict]:
    """Records of a JSON-lines file, plain or ``.gz``; a torn last line (a killed writer) is skipped."""
    opener = gzip.open if path.suffix == ".gz" else open
    records = []
    with opener(path, "rt") as f:
        for line in f:
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return records


def existing(path: Path) -> Optional[Path]:
    """``path`` or its gzipped twin, whichever exists (a run folder has the first, an archive the second)."""
    for p in (path, path.with_name(path.name + ".gz")):
        if p.exists():
            return p
    return None


def _slim(record: Mapping[str, Any]) -> Optional[dict]:
    kept = {k: record[k] for k in CURVE_KEYS if k in record}
    return kept if len(kept) > 1 and "global_step" in kept else None  # a record with episode statistics


def _write_jsonl_gz(path: Path, records: Iterable[Mapping[str, Any]]) -> None:
    # mtime=0: the same records give the same bytes (a re-archived run does not show as changed in git)
    with open(path, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as f:
        for r in records:
            f.write((json.dumps(r, separators=(",", ":")) + "\n").encode())


def archive_run(rd: Path, dest: Path, eval_dir: str) -> bool:
    """Write the slim copy of the finished, evaluated run ``rd`` to ``dest`` (complete or absent: written next to
    it, then renamed). Returns False, writing nothing, if the run is not finished and evaluated or ``dest`` holds
    it already at the same budget."""
    episodes = rd / eval_dir / EVAL_FILE
    if not (rd / "done.json").exists() or not episodes.exists():
        return False
    done = json.loads((rd / "done.json").read_text())
    if (dest / "done.json").exists() and json.loads((dest / "done.json").read_text()) == done:
        return False
    tmp = dest.with_name(dest.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / eval_dir).mkdir(parents=True)
    shutil.copyfile(rd / "config.yaml", tmp / "config.yaml")
    metrics = rd / "metrics.jsonl"
    curve = [s for s in (_slim(r) for r in (read_jsonl(metrics) if metrics.exists() else [])) if s is not None]
    _write_jsonl_gz(tmp / "metrics.jsonl.gz", curve)
    _write_jsonl_gz(tmp / eval_dir / (EVAL_FILE + ".gz"), read_jsonl(episodes))
    (tmp / "done.json").write_text(json.dumps(done, indent=1))
    shutil.rmtree(dest, ignore_errors=True)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp.rename(dest)
    return True


def recipe_differences(planned: Mapping[str, Any], archived: Mapping[str, Any]) -> List[str]:
    """Dotted keys whose values differ between two resolved configs (``config_to_dict`` form), recipe keys only;
    a config (either) lacking a key of ``KEYS_ADDED_LATER`` counts as holding its value there; ``READOUT_KEYS``
    are left out."""
    planned, archived = _with_keys_added_later(planned), _with_keys_added_later(archived)

    def walk(a: Any, b: Any, prefix: str) -> List[str]:
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            return [d for k in sorted(set(a) | set(b)) for d in walk(a.get(k), b.get(k), f"{prefix}.{k}")]
        if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
            a, b = list(a), list(b)
        return [] if a == b else [prefix]

    diffs = [d for s in RECIPE_SECTIONS for d in walk(planned.get(s, {}), archived.get(s, {}), s)
             if d not in READOUT_KEYS]
    pr, ar = planned.get("runner", {}), archived.get("runner", {})
    return diffs + [f"runner.{k}" for k in RECIPE_RUNNER_KEYS if pr.get(k) != ar.get(k)]


def _with_keys_added_later(config: Mapping[str, Any]) -> Mapping[str, Any]:
    """``config`` with every key of ``KEYS_ADDED_LATER`` it lacks set to that value (a copy where one is added)."""
    out = config
    for dotted, value in KEYS_ADDED_LATER.items():
        *parents, leaf = dotted.split(".")
        node = out
        for k in parents:
            node = node.get(k) if isinstance(node, Mapping) else None
        if not isinstance(node, Mapping) or leaf in node:
            continue  # the key is there (compared as it is), or its section is missing altogether
        if out is config:
            out = json.loads(json.dumps(config))
        node = out
        for k in parents:
            node = node[k]
        node[leaf] = value
    return out


def _recipe_error(src: Path, rd: Path, planned: Mapping[str, Any]) -> Optional[str]:
    """None if ``src`` is not to be restored into ``rd`` or matches ``planned``; else the message naming the keys."""
    from swarm_appo.config import yaml_load

    if rd.exists() or not (src / "done.json").exists():
        return None
    diffs = recipe_differences(planned, yaml_load((src / "config.yaml").read_text()))
    if not diffs:
        return None
    return (f"the archived run {src} was trained with another recipe than this command's ({', '.join(diffs)} "
            f"differ): archive into another folder, or use that run's recipe")


def restore_runs(items: Sequence[Tuple[Path, Path, Mapping[str, Any]]], eval_dir: str) -> List[int]:
    """``restore_run`` for each (archived run, run folder, planned config), after checking every one of them: a recipe
    mismatch anywhere raises ValueError before any run is restored. Returns the indices of the restored items."""
    for src, rd, planned in items:
        error = _recipe_error(src, rd, planned) or _evaluation_error(src, rd, eval_dir)
        if error:
            raise ValueError(error)
    return [i for i, (src, rd, planned) in enumerate(items) if restore_run(src, rd, planned, eval_dir)]


def _evaluation_error(src: Path, rd: Path, eval_dir: str) -> Optional[str]:
    """Why a finished archived run cannot stand in for ``rd``: it was evaluated under the other final-policy rule
    (``table1 --select`` or not), and an archived run has no checkpoints to evaluate again."""
    if rd.exists() or not (src / "done.json").exists() or existing(src / eval_dir / EVAL_FILE) is not None:
        return None
    return (f"archived run {src} has no {eval_dir}/{EVAL_FILE}: it was evaluated with the other final policy (with "
            f"or without table1 --select), and an archived run keeps no checkpoints to evaluate again; use the "
            f"archive's rule, or another --archive")


def restore_run(src: Path, rd: Path, planned: Mapping[str, Any], eval_dir: str) -> bool:
    """Copy the archived run ``src`` into the missing run folder ``rd`` (plain files, as the trainer writes them).
    Returns False if ``src`` holds no finished run or ``rd`` exists already (a local run, even a partial one,
    wins); raises ValueError naming the keys if the archived run was trained with another recipe."""
    error = _recipe_error(src, rd, planned) or _evaluation_error(src, rd, eval_dir)
    if error:
        raise ValueError(error)
    if rd.exists() or not (src / "done.json").exists():
        return False
    tmp = rd.with_name(rd.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / eval_dir).mkdir(parents=True)
    shutil.copyfile(src / "config.yaml", tmp / "config.yaml")
    shutil.copyfile(src / "done.json", tmp / "done.json")
    for rel in ("metrics.jsonl", f"{eval_dir}/{EVAL_FILE}"):
        found = existing(src / rel)
        records = read_jsonl(found) if found else []
        (tmp / rel).write_text("".join(json.dumps(r) + "\n" for r in records))
    tmp.rename(rd)
    return True
