"""Reliability under abuse: kill -9 torture, rollout-actor kills, SIGTERM at random moments, and a memory soak.

    python -m benchmarks.reliability                       # 20 kills, 3 actor kills, 5 SIGTERMs, 60-min soak
    python -m benchmarks.reliability --kills 5 --sigterms 2 --actor-kills 1 --soak-minutes 0   # a short check

Each phase runs the real command line (``python -m launchers.local``, a local Ray on this machine, a small
quickstart-sized config that checkpoints every two learner iterations) as a subprocess in its own session, and
only ever signals that process tree:

- **kill -9** at a random moment (some timed onto a checkpoint write: the moment its temporary file appears),
  then ``--resume``: counted are intact run directories (every checkpoint verifies, metrics.jsonl parses but for a
  torn last line), correct resumes (the resumed run starts from the newest valid checkpoint), and at the end the
  duplicated or missing steps in metrics.jsonl and in the newest wandb run (read back from its .wandb file);
- **actor kills**: SIGKILL to one rollout actor of a running training; counted: replaced workers
  (``perf/worker_restarts``) and whether the run finished;
- **SIGTERM** at a random moment: the final checkpoint must be an iteration boundary (agent_steps = version x
  steps per iteration, num_updates = version x updates per iteration);
- **soak**: the learner's RSS every 30 s for ``--soak-minutes``, growth from minute 5 to the end.

The counts are appended to benchmarks/RESULTS.md with the command, commit and machine. Goal (issue 14): 0 lost
or duplicated steps anywhere, 0 mid-iteration checkpoints, RSS growth < 5 % over the hour.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Tuple

from benchmarks.common import ROOT, load_average, publish, section_header

# a quickstart-sized run: 4 swarms x 8 drones x 128 steps = 4096 agent steps per fragment, batch 4096 = one
# fragment per iteration, 1 minibatch x 2 epochs = 2 updates per iteration
STEPS_PER_ITERATION, UPDATES_PER_ITERATION = 4096, 2
TMP_PREFIX = ".tmp-"  # swarm_appo.checkpoint's temporary files (atomic writes)
RUN = ["runner.envs_per_worker=4", "algo.batch_size=4096", "algo.num_epochs=2", "runner.checkpoint_every_updates=2",
       "runner.checkpoint_every_s=1000000", "runner.final_eval_episodes=0", "runner.time_limit_s=0",
       "model.encoder_kwargs.hidden=32", "model.encoder_kwargs.out_dim=32", "runner.num_workers=1"]


def launch(run_root: Path, name: str, extra: List[str], resume: bool = False) -> subprocess.Popen:
    """``python -m launchers.local`` for run ``run_root/name`` (or ``--resume`` it), in its own session; its
    log (stderr) is appended to ``run_root/name.log``."""
    cmd = [sys.executable, "-m", "launchers.local", "--no-progress"]
    cmd += ["--resume", str(run_root / name)] if resume else [*RUN, f"runner.run_dir={run_root}", f"runner.name={name}"]
    env = dict(os.environ, WANDB_MODE="offline", WANDB_SILENT="true")
    log = open(run_root / f"{name}.log", "a")
    return subprocess.Popen([*cmd, *extra], cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=log,
                            start_new_session=True)


def descendants(pid: int) -> List[int]:
    """``pid`` and every process below it (from /proc: Ray's raylet, GCS and workers of this run only)."""
    children: Dict[int, List[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return out


def kill_tree(proc: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
    """``sig`` to the launcher and every process below it, at once (kill -9: the run dies mid-anything)."""
    for pid in descendants(proc.pid):
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            pass
    proc.wait()


def stop(proc: subprocess.Popen, timeout_s: float = 300.0) -> None:
    """SIGTERM to the launcher (it checkpoints and stops its own Ray), then SIGKILL to whatever of its tree is
    left (listed before: once the launcher exits its children are re-parented and cannot be found)."""
    tree = descendants(proc.pid)
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=timeout_s)
    finally:
        for pid in tree[1:]:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def wait_for(predicate, timeout_s: float, poll_s: float = 0.05) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(poll_s)
    return False


def checkpoints_intact(run_dir: Path) -> bool:
    from swarm_appo.checkpoint import CheckpointCorruptError, load_checkpoint

    try:
        for path in (run_dir / "checkpoints").glob("ckpt_*.pt"):
            load_checkpoint(path)
    except CheckpointCorruptError:
        return False
    lines = (run_dir / "metrics.jsonl").read_text().splitlines() if (run_dir / "metrics.jsonl").exists() else []
    for k, line in enumerate(lines):
        try:
            json.loads(line)
        except json.JSONDecodeError:
            if k != len(lines) - 1:  # only the last line may be torn
                return False
    return True


def newest_step(run_dir: Path) -> int:
    from swarm_appo.checkpoint import load_latest_checkpoint

    state, _ = load_latest_checkpoint(run_dir)
    return int(state["agent_steps"]) if state else 0


def history_faults(run_dir: Path) -> Dict[str, int]:
    """Duplicated and missing steps of metrics.jsonl and of the newest wandb run (learner iterations only)."""
    from swarm_appo.metrics import read_metrics, wait_for_wandb_history

    out = {}
    steps = [r["global_step"] for r in read_metrics(run_dir) if "losses/total_loss" in r]
    expected = list(range(STEPS_PER_ITERATION, (steps[-1] if steps else 0) + 1, STEPS_PER_ITERATION))
    out["jsonl_duplicated"] = len(steps) - len(set(steps))
    out["jsonl_missing"] = len(set(expected) - set(steps))
    run_id = (run_dir / "wandb_id.txt").read_text().strip()
    files = list((run_dir / "wandb").glob(f"offline-run-*-{run_id}/run-{run_id}.wandb"))
    history = wait_for_wandb_history(files[0], len(read_metrics(run_dir))) if files else []
    wsteps = [h["global_step"] for h in history if "losses/total_loss" in h]
    out["wandb_duplicated"] = len(wsteps) - len(set(wsteps))
    out["wandb_missing"] = len(set(expected) - set(wsteps))
    return out


# ----------------------------------------------------------------------------------------------- phases
def kill9_phase(root: Path, kills: int, rng: random.Random) -> Dict[str, int]:
    from swarm_appo.checkpoint import checkpoint_path

    run_dir, log = root / "kill9", root / "kill9.log"
    counts = {"kills": 0, "kills_on_checkpoint_write": 0, "intact": 0, "correct_resumes": 0}
    proc = launch(root, "kill9", [f"runner.total_agent_steps={10**9}"])
    for k in range(kills):
        on_write = k % 4 == 3  # every fourth kill lands on a checkpoint write (its temporary file exists)
        if on_write:
            wait_for(lambda: any((run_dir / "checkpoints").glob(f"{TMP_PREFIX}*")), 120.0, 0.001)
        else:
            time.sleep(rng.uniform(2.0, 15.0))
        kill_tree(proc)
        counts["kills"] += 1
        counts["kills_on_checkpoint_write"] += on_write
        counts["intact"] += checkpoints_intact(run_dir)
        expected = newest_step(run_dir)
        seen = log.read_text() if log.exists() else ""
        killed_id = wandb_id(run_dir)  # the killed run's wandb run (None if it was killed before making one)
        proc = launch(root, "kill9", [], resume=True)
        # what the resumed run says it continues from: the newest valid checkpoint, or a fresh start at 0
        want = f"from {checkpoint_path(run_dir, expected)}" if expected else "starting it afresh at step 0"
        counts["correct_resumes"] += wait_for(lambda: want in log.read_text()[len(seen):], 120.0, 0.2)
    # the last resume runs until it has trained an iteration past its checkpoint, then stops cleanly (a stop
    # earlier, before its wandb run exists, would leave the killed run's wandb file as the newest). Records past
    # the checkpoint that the killed run wrote do not count: only once the resumed run's own wandb run exists
    # (a new id in wandb_id.txt) has it trimmed metrics.jsonl to its checkpoint.
    resumed_from = newest_step(run_dir)
    wait_for(lambda: wandb_id(run_dir) not in (None, killed_id)
             and any(r.get("global_step", 0) > resumed_from for r in _records(run_dir)), 180.0, 0.5)
    stop(proc)
    counts.update(history_faults(run_dir))
    return counts


def wandb_id(run_dir: Path):
    """The id in the run's wandb_id.txt (the newest wandb run), or None."""
    try:
        return (run_dir / "wandb_id.txt").read_text().strip() or None
    except OSError:
        return None


def _records(run_dir: Path) -> List[dict]:
    from swarm_appo.metrics import read_metrics

    try:
        return read_metrics(run_dir)
    except (OSError, json.JSONDecodeError):  # a line being written
        return []


def actor_kill_phase(root: Path, kills: int, rng: random.Random) -> Dict[str, int]:
    from swarm_appo.metrics import read_metrics

    steps = STEPS_PER_ITERATION * (60 + 30 * kills)
    proc = launch(root, "actors", [f"runner.total_agent_steps={steps}"])
    killed = 0
    find = lambda: [p for p in descendants(proc.pid) if "RayRolloutWorker" in cmdline(p)]  # noqa: E731
    for _ in range(kills):
        if not wait_for(lambda: bool(find()), 120.0, 0.5):  # the actors exist once Ray has started them
            break
        time.sleep(rng.uniform(2.0, 6.0))
        actors = find()
        if actors:
            os.kill(rng.choice(actors), signal.SIGKILL)
            killed += 1
            wait_for(lambda: not set(actors) & set(find()) and bool(find()), 120.0, 0.5)  # replaced
    proc.wait()
    records = read_metrics(root / "actors")
    restarts = max((r.get("perf/worker_restarts", 0) for r in records), default=0)
    return {"actor_kills": killed, "workers_replaced": int(restarts), "run_finished": int(proc.returncode == 0)}


def sigterm_phase(root: Path, count: int, rng: random.Random) -> Dict[str, int]:
    from swarm_appo.checkpoint import load_latest_checkpoint

    out = {"sigterms": 0, "boundary_checkpoints": 0}
    for k in range(count):
        proc = launch(root, f"term{k}", [f"runner.total_agent_steps={10**9}"])
        time.sleep(rng.uniform(10.0, 25.0))
        stop(proc)
        state, _ = load_latest_checkpoint(root / f"term{k}")
        v = state["learner"]["version"]
        out["sigterms"] += 1
        out["boundary_checkpoints"] += (state["agent_steps"] == v * STEPS_PER_ITERATION
                                        and state["learner"]["num_updates"] == v * UPDATES_PER_ITERATION)
    return out


def soak_phase(root: Path, minutes: float) -> Dict[str, float]:
    proc = launch(root, "soak", [f"runner.total_agent_steps={10**10}"])
    samples = []  # (minute, MB)
    start = time.monotonic()
    while (time.monotonic() - start) < 60 * minutes:
        time.sleep(30)
        samples.append(((time.monotonic() - start) / 60, rss_mb(proc.pid)))
    stop(proc)
    return {"soak_minutes": minutes, **rss_growth(samples, minutes)}


def rss_growth(samples: List[Tuple[float, float]], minutes: float) -> Dict[str, float]:
    """RSS growth from minute 5 to the end of a soak, from (minute, MB) samples. A learner's RSS swings by
    10-30 % with the fragments it holds at a given moment, so besides the single samples at minute 5 and at the
    end the growth is measured between the medians of the first five minutes after minute 5 and of the last
    five minutes (``rss_growth_pct``)."""
    after5 = [(m, mb) for m, mb in samples if m >= 5] or list(samples)
    first = [mb for m, mb in after5 if m < after5[0][0] + 5]
    last = [mb for m, mb in after5 if m >= max(after5[-1][0] - 5, after5[0][0])]
    median = lambda xs: float(sorted(xs)[len(xs) // 2])  # noqa: E731
    return {"rss_mb_at_5min": after5[0][1], "rss_mb_end": after5[-1][1],
            "rss_growth_endpoints_pct": 100 * (after5[-1][1] / after5[0][1] - 1),
            "rss_mb_median_first_5min": median(first), "rss_mb_median_last_5min": median(last),
            "rss_growth_pct": 100 * (median(last) / median(first) - 1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kills", type=int, default=20)
    p.add_argument("--actor-kills", type=int, default=3)
    p.add_argument("--sigterms", type=int, default=5)
    p.add_argument("--soak-minutes", type=float, default=60.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-append", action="store_true")
    args = p.parse_args(argv)
    rng = random.Random(args.seed)
    root = Path(tempfile.mkdtemp(prefix="reliability_"))
    started, load_before = datetime.datetime.now().isoformat(timespec="seconds"), load_average()
    results: Dict[str, float] = {}
    if args.kills:
        results.update(kill9_phase(root, args.kills, rng))
    if args.actor_kills:
        results.update(actor_kill_phase(root, args.actor_kills, rng))
    if args.sigterms:
        results.update(sigterm_phase(root, args.sigterms, rng))
    if args.soak_minutes:
        results.update(soak_phase(root, args.soak_minutes))
    lines = [f"| {k} | {v:.1f} |" if isinstance(v, float) else f"| {k} | {v} |" for k, v in results.items()]
    section = "\n".join([
        *section_header("reliability", started, argv, ["swarm_appo", "launchers"], load_before),
        f"- runs in {root}", "", "| count | value |", "|---|---|", *lines])
    publish(section, not args.no_append)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
