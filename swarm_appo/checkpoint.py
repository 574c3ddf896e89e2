"""Checkpoints that survive being killed at any moment.

Layout under a run directory::

    checkpoints/ckpt_000000123456.pt   one per save, named by global step (agent steps), the last N kept
    checkpoints/best.pt                a copy of the checkpoint with the best metric so far

Each file is one JSON header line followed by the ``torch.save`` payload::

    {"format": "swarm_appo-checkpoint", "version": 1, "step": 123456, "metric": 1.5,
     "payload_bytes": 81234, "sha256": "<hex digest of the payload>", "time": 1700000000.0}\\n<payload>

Files are written to a temporary name in the same directory, fsync'ed and renamed over the final name
(``os.replace`` is atomic on POSIX), so a crash leaves either the old file or the new one, never half of
one. The checksum catches what renaming cannot: truncation or corruption after the fact (a bad disk,
a copy cut short). ``load_latest_checkpoint`` skips such files with a warning and uses the previous one.

The state is loaded with ``torch.load(weights_only=True)`` by default, so it must hold only tensors,
Python numbers/strings/None and lists/tuples/dicts of them (``capture_rng_states`` returns that).
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import os
import random
import re
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Tuple, Union

import numpy as np
import torch

from swarm_appo.atomic import TMP_PREFIX, atomic_write_bytes  # noqa: F401  (atomic_write_bytes: re-exported)

FORMAT_NAME = "swarm_appo-checkpoint"
FORMAT_VERSION = 1
CHECKPOINT_DIR = "checkpoints"
BEST_NAME = "best.pt"
_CKPT_RE = re.compile(r"^ckpt_(\d{12})\.pt$")
_MAX_HEADER_BYTES = 4096

PathLike = Union[str, os.PathLike]


class CheckpointCorruptError(RuntimeError):
    """A checkpoint file is truncated, corrupted or not a checkpoint at all."""




# ----------------------------------------------------------------------------------------------- payload
@dataclass
class TrainingState:
    """What a checkpoint holds: the one definition of its payload and of its format version (``FORMAT_VERSION``,
    also in every file's header). The trainer and ``swarm_appo.testing`` write it; resume, evaluation, export
    and the benchmarks read it.

    Payload keys: ``format``, ``learner`` (``Learner.state_dict()``: model, optimizer, version, num_updates,
    learner RNG, with ``algo.weight_ema`` the running weight averages ``weight_ema``; a policy-only checkpoint has
    just ``model``), ``agent_steps``, ``config`` (the resolved config
    tree), ``rng`` (python, numpy, torch; None in a policy-only checkpoint), ``wandb_id``."""

    learner: Dict[str, Any]
    agent_steps: int
    config: Dict[str, Any]
    rng: Optional[Dict[str, Any]] = None
    wandb_id: Optional[str] = None

    def payload(self) -> Dict[str, Any]:
        return {"format": FORMAT_VERSION, "learner": self.learner, "agent_steps": int(self.agent_steps),
                "config": self.config, "rng": self.rng, "wandb_id": self.wandb_id}

    @classmethod
    def from_payload(cls, payload: Mapping[str, Any], source: Any = "checkpoint") -> "TrainingState":
        version = payload.get("format", FORMAT_VERSION)
        if version != FORMAT_VERSION:
            raise CheckpointCorruptError(f"{source}: payload format {version!r}, this code reads {FORMAT_VERSION}")
        missing = [k for k in ("learner", "config") if k not in payload]
        if missing:
            raise CheckpointCorruptError(f"{source}: not a training checkpoint (no {', '.join(missing)})")
        return cls(learner=payload["learner"], agent_steps=int(payload.get("agent_steps", 0)),
                   config=payload["config"], rng=payload.get("rng"), wandb_id=payload.get("wandb_id"))

    def save(self, run_dir: PathLike, metric: Optional[float] = None, keep_last: int = 3) -> Path:
        """``save_checkpoint`` of this state at step ``agent_steps``."""
        return save_checkpoint(run_dir, self.payload(), step=self.agent_steps, metric=metric, keep_last=keep_last)

    @classmethod
    def load(cls, path: PathLike) -> "TrainingState":
        """The state of one checkpoint file (``CheckpointCorruptError`` if it is damaged)."""
        return cls.from_payload(load_checkpoint(path), source=path)

    @classmethod
    def load_latest(cls, run_dir: PathLike) -> Tuple[Optional["TrainingState"], Optional[Path]]:
        """The newest valid checkpoint of a run (``load_latest_checkpoint``), or ``(None, None)``."""
        payload, path = load_latest_checkpoint(run_dir)
        return (None, None) if payload is None else (cls.from_payload(payload, source=path), path)


# ----------------------------------------------------------------------------------------------- format
def _encode(state: Mapping[str, Any], step: int, metric: Optional[float]) -> bytes:
    buffer = io.BytesIO()
    torch.save(dict(state), buffer)
    payload = buffer.getvalue()
    header = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "step": int(step),
        "metric": float(metric) if metric is not None and math.isfinite(metric) else None,
        "payload_bytes": len(payload),
        "sha256": hashlib.sha256(payload).hexdigest(),
        "time": time.time(),
    }
    return json.dumps(header).encode() + b"\n" + payload


def write_checkpoint_file(path: PathLike, state: Mapping[str, Any], step: int) -> Path:
    """Atomically write ``state`` as one checkpoint file at ``path`` (a file outside the ``ckpt_*`` series, e.g.
    ``checkpoints/selected.pt``: no rotation, no ``best.pt``)."""
    return atomic_write_bytes(path, _encode(state, step, None))


def _read_verified(path: Path) -> Tuple[Dict[str, Any], bytes]:
    """Header and payload of a checkpoint file; CheckpointCorruptError if anything does not add up."""
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise CheckpointCorruptError(f"{path}: cannot read ({e})") from e
    newline = raw.find(b"\n", 0, _MAX_HEADER_BYTES)
    if newline < 0:
        raise CheckpointCorruptError(f"{path}: no checkpoint header (empty, truncated or not a checkpoint)")
    try:
        header = json.loads(raw[:newline])
    except ValueError as e:
        raise CheckpointCorruptError(f"{path}: unreadable header ({e})") from e
    if not isinstance(header, dict) or header.get("format") != FORMAT_NAME:
        raise CheckpointCorruptError(f"{path}: not a {FORMAT_NAME} file")
    if header.get("version") != FORMAT_VERSION:
        raise CheckpointCorruptError(f"{path}: format version {header.get('version')!r}, "
                                     f"this code reads version {FORMAT_VERSION}")
    payload = raw[newline + 1:]
    if len(payload) != header.get("payload_bytes"):
        raise CheckpointCorruptError(f"{path}: truncated or padded: payload has {len(payload)} bytes, "
                                     f"header says {header.get('payload_bytes')}")
    if hashlib.sha256(payload).hexdigest() != header.get("sha256"):
        raise CheckpointCorruptError(f"{path}: checksum mismatch (corrupted payload)")
    return header, payload


def read_checkpoint_header(path: PathLike) -> Dict[str, Any]:
    """The verified header of a checkpoint (step, metric, time, ...); CheckpointCorruptError if invalid."""
    return _read_verified(Path(path))[0]


def load_checkpoint(path: PathLike, map_location: Any = "cpu", weights_only: bool = True) -> Dict[str, Any]:
    """Load one checkpoint after verifying its checksum.

    Raises CheckpointCorruptError for truncated/corrupted files. An error from ``torch.load`` on a file
    whose checksum is correct is a programming error (e.g. a type ``weights_only`` refuses) and propagates.
    """
    _, payload = _read_verified(Path(path))
    return torch.load(io.BytesIO(payload), map_location=map_location, weights_only=weights_only)


# ----------------------------------------------------------------------------------------------- run directory
def checkpoint_dir(run_dir: PathLike) -> Path:
    return Path(run_dir) / CHECKPOINT_DIR


def checkpoint_path(run_dir: PathLike, step: int) -> Path:
    return checkpoint_dir(run_dir) / f"ckpt_{int(step):012d}.pt"


def list_checkpoints(run_dir: PathLike) -> List[Path]:
    """The ``ckpt_*.pt`` files of a run, oldest step first (``best.pt`` and temp files excluded)."""
    directory = checkpoint_dir(run_dir)
    if not directory.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in directory.iterdir() if (m := _CKPT_RE.match(p.name))]
    return [p for _, p in sorted(found)]


def _step_of(path: Path) -> int:
    return int(_CKPT_RE.match(path.name).group(1))


def _is_better(metric: float, best: Optional[float], higher_is_better: bool) -> bool:
    if best is None:
        return True
    return metric > best if higher_is_better else metric < best


def save_checkpoint(
    run_dir: PathLike,
    state: Mapping[str, Any],
    step: int,
    metric: Optional[float] = None,
    keep_last: int = 3,
    higher_is_better: bool = True,
) -> Path:
    """Atomically write ``checkpoints/ckpt_<step:012d>.pt``; keep the last ``keep_last`` plus ``best.pt``.

    Args:
        run_dir: the run directory.
        state: what to save (model/optimizer state dicts, counters, config dict, RNG states, ...).
        step: global step (agent steps); names the file. Saving the same step again replaces the file, and
            files of later steps (left by a run that was resumed from an earlier checkpoint) are deleted.
        metric: score of this checkpoint (e.g. mean episode reward); when it beats the best so far (NaN and
            None never do), the same bytes are also written to ``best.pt``.
        keep_last: how many ``ckpt_*.pt`` files to keep (>= 1); older ones are deleted.
        higher_is_better: direction of ``metric``.

    Returns:
        Path of the new ``ckpt_*.pt`` file.
    """
    if keep_last < 1:
        raise ValueError(f"keep_last must be >= 1, got {keep_last}")
    if step < 0:
        raise ValueError(f"step must be >= 0, got {step}")
    directory = checkpoint_dir(run_dir)
    directory.mkdir(parents=True, exist_ok=True)
    _remove_stale_temp_files(directory)

    blob = _encode(state, step, metric)
    path = atomic_write_bytes(checkpoint_path(run_dir, step), blob)

    if metric is not None and math.isfinite(metric):
        best_path = directory / BEST_NAME
        try:
            best_metric = read_checkpoint_header(best_path).get("metric") if best_path.exists() else None
        except CheckpointCorruptError:
            best_metric = None  # a damaged best.pt is replaced
        if _is_better(float(metric), best_metric, higher_is_better):
            atomic_write_bytes(best_path, blob)

    # Checkpoints past this step belong to a timeline abandoned by resuming from an earlier one.
    kept = []
    for p in list_checkpoints(run_dir):
        if _step_of(p) > step:
            p.unlink(missing_ok=True)
        else:
            kept.append(p)
    for old in kept[:-keep_last]:
        old.unlink(missing_ok=True)
    return path


def _remove_stale_temp_files(directory: Path) -> None:
    """Temp files left by a writer that was killed mid-write (one writer per run directory)."""
    for p in directory.glob(f"{TMP_PREFIX}*"):
        p.unlink(missing_ok=True)


def load_latest_checkpoint(
    run_dir: PathLike, map_location: Any = "cpu", weights_only: bool = True
) -> Tuple[Optional[Dict[str, Any]], Optional[Path]]:
    """The newest valid checkpoint of a run as ``(state, path)``, or ``(None, None)`` if there is none.

    Corrupt or truncated files are skipped with a ``warnings.warn`` naming the file; the previous one is
    tried next. ``best.pt`` is a candidate too, ranked by the step in its header (ties go to ``ckpt_*``).
    """
    candidates = [(_step_of(p), 1, p) for p in list_checkpoints(run_dir)]
    best_path = checkpoint_dir(run_dir) / BEST_NAME
    if best_path.exists():
        try:
            best_step = int(read_checkpoint_header(best_path)["step"])
        except (CheckpointCorruptError, KeyError, TypeError, ValueError):
            best_step = -1  # still tried, last
        candidates.append((best_step, 0, best_path))

    for _, _, path in sorted(candidates, key=lambda c: (c[0], c[1]), reverse=True):
        try:
            return load_checkpoint(path, map_location=map_location, weights_only=weights_only), path
        except CheckpointCorruptError as e:
            warnings.warn(f"skipping corrupt checkpoint {path}: {e}; trying the previous one", RuntimeWarning,
                          stacklevel=2)
    return None, None


# ----------------------------------------------------------------------------------------------- RNG states
def capture_rng_states(generators: Optional[Mapping[str, np.random.Generator]] = None) -> Dict[str, Any]:
    """States of Python's ``random``, NumPy's global RNG, torch's CPU (and CUDA) RNGs, and of the given
    NumPy ``Generator`` objects, as plain Python values and tensors (safe for ``weights_only`` loading)."""
    np_state = np.random.get_state(legacy=False)
    states: Dict[str, Any] = {
        "python": random.getstate(),
        "numpy": {
            "bit_generator": np_state["bit_generator"],
            "key": np_state["state"]["key"].tolist(),
            "pos": int(np_state["state"]["pos"]),
            "has_gauss": int(np_state["has_gauss"]),
            "gauss": float(np_state["gauss"]),
        },
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        states["torch_cuda"] = torch.cuda.get_rng_state_all()
    if generators:
        states["generators"] = {name: g.bit_generator.state for name, g in generators.items()}
    return states


def restore_rng_states(states: Mapping[str, Any], generators: Optional[Mapping[str, np.random.Generator]] = None
                       ) -> None:
    """Inverse of ``capture_rng_states``; ``generators`` are restored in place by name."""
    random.setstate(_as_tuples(states["python"]))
    n = states["numpy"]
    np.random.set_state({"bit_generator": n["bit_generator"],
                         "state": {"key": np.asarray(n["key"], dtype=np.uint32), "pos": n["pos"]},
                         "has_gauss": n["has_gauss"], "gauss": n["gauss"]})
    torch.set_rng_state(states["torch"])
    if "torch_cuda" in states and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(states["torch_cuda"])
    if generators:
        saved = states.get("generators", {})
        missing = sorted(set(generators) - set(saved))
        if missing:
            raise KeyError(f"no saved state for generators {missing}; saved: {sorted(saved)}")
        for name, g in generators.items():
            g.bit_generator.state = saved[name]


def _as_tuples(x: Any) -> Any:
    """random.setstate needs tuples; serialisation may hand lists back."""
    return tuple(_as_tuples(v) for v in x) if isinstance(x, (list, tuple)) else x
