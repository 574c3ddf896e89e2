"""Export the actor for deployment: flat observations in, deterministic actions out, as TorchScript and ONNX.

    python -m swarm_appo.export --checkpoint runs/quickstart --out export/ [--format torchscript,onnx]
                                [--clip-actions]

Writes into ``--out``:

    actor.pt      TorchScript (``torch.jit.load``), traced
    actor.onnx    ONNX, opset 17 (onnxruntime, TensorRT, ...)
    actor.json    the contract: observation fields and their slices, the action's meaning, provenance

Both models map ``obs`` float32 ``[B, D]`` to ``actions`` float32 ``[B, 4]``: the policy's mean action,
i.e. observation normalisation + encoder + projection head h_p (the critic and the Gaussian's log-std
are left out). B is free (one row per drone); D is fixed by the layout (K neighbour slots), and the
policies are size-independent, so one file flies any swarm size. Actions are the raw mean, as the
trained policy emits them: the simulator clips them to [-1, 1] (``--clip-actions`` puts that clip
into the model). Before writing ``actor.json`` the export runs each file on random observations of
another batch size (and on padded neighbour slots) and checks it against the PyTorch actor.

A recurrent policy (``model.core: gru | lstm``) is exported with its core state as an explicit input and
output: ``(obs [B, D], state [B, S]) -> (actions [B, 4], state_out [B, S])``; the caller feeds zeros at an
episode start and ``state_out`` at every later step (``actor.json``: ``state``). Only the actor's cell is
in it (the critic's is not needed to fly).

ONNX needs the ``onnx`` package, its check ``onnxruntime`` (``pip install -e ".[export]"``). It uses
torch's TorchScript-based exporter (``dynamo=False``): it needs no further package and is several times
faster than the ``torch.export`` one, which would need ``onnxscript`` plus decompositions of ``cdist``
and stable ``argsort``. Two of the encoders' operators get ONNX translations here, for the duration of
the export: a boolean ``eye`` (onnxruntime has no boolean EyeLike: built as float, then cast) and a
stable ``argsort`` (ONNX TopK, whose ties keep index order).
"""
from __future__ import annotations

import contextlib
import copy
import json
import os
import warnings
from pathlib import Path
from typing import Dict, Optional, Sequence

import numpy as np
import torch
from torch import nn

from quad_env import ObsLayout

FORMATS = ("torchscript", "onnx")
FILE_NAMES = {"torchscript": "actor.pt", "onnx": "actor.onnx"}
SIDECAR = "actor.json"
SIDECAR_FORMAT = "swarm_appo-actor"
SIDECAR_VERSION = 1
ONNX_OPSET = 17  # LayerNormalization is native from 17
VERIFY_TOLERANCE = 1e-4  # max |exported - PyTorch| action allowed by the export's own check

# What each observation field holds (units, frame); fields not listed here are described by name only.
FIELD_MEANINGS = {
    ("self", "rel_goal"): "own position minus own goal, x_i - x_i^d (m, world axes)",
    ("self", "vel"): "own velocity (m/s, world axes)",
    ("self", "rot"): "own attitude R_i, body -> world rotation matrix, row-major",
    ("self", "omega"): "own body rates (rad/s, body axes)",
    ("neighbor", "rel_pos"): "neighbour position minus own position, x_j - x_i (m, world axes)",
    ("neighbor", "rel_vel"): "neighbour velocity minus own velocity, v_j - v_i (m/s, world axes)",
    ("neighbor", "rot"): "neighbour attitude R_j, body -> world, row-major",
    ("neighbor", "omega"): "neighbour body rates (rad/s, its body axes)",
    ("neighbor", "goal_offset"): "neighbour goal minus neighbour position, x_j^d - x_j (m, world axes)",
    ("mask", "mask"): "1 = the slot holds a real neighbour, 0 = padding (its block is all zeros)",
}


class DeterministicActor(nn.Module):
    """``obs [B, D] -> mean action [B, 4]`` of an ``encoders.ActorCritic`` (its actor part only)."""

    def __init__(self, model: nn.Module, clip_actions: bool = False):
        super().__init__()
        self.body_frame = getattr(model, "body_frame", None)  # None unless trained with model.body_frame_obs
        self.obs_norm = model.obs_norm  # None when the policy was trained without it
        self.encoder = model.actor_encoder
        self.head = model.actor_head
        self.clip_actions = clip_actions

    def prepare(self, obs: torch.Tensor) -> torch.Tensor:
        # The same input preparation as ActorCritic: body frame (optional), then per-field scaling.
        if self.body_frame is not None:
            obs = self.body_frame(obs)
        return obs if self.obs_norm is None else self.obs_norm(obs)

    def finish(self, actions: torch.Tensor) -> torch.Tensor:
        return actions.clamp(-1.0, 1.0) if self.clip_actions else actions

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.finish(self.head(self.encoder(self.prepare(obs))))  # [B, 4]


class RecurrentDeterministicActor(DeterministicActor):
    """``(obs [B, D], state [B, S]) -> (mean action [B, 4], state' [B, S])``: the actor of a recurrent policy,
    S = its cell's state (``model.state_sizes[0]``)."""

    def __init__(self, model: nn.Module, clip_actions: bool = False):
        super().__init__(model, clip_actions)
        self.core = model.actor_core

    def forward(self, obs: torch.Tensor, state: torch.Tensor):
        features, state = self.core(self.encoder(self.prepare(obs)), state)
        return self.finish(self.head(features)), state  # [B, 4], [B, S]


# ----------------------------------------------------------------------------------------------- formats
@contextlib.contextmanager
def _quiet_torch():
    """Silence what these exporters always say: TorchScript and its ONNX exporter are deprecated in favour
    of torch.export (both still load everywhere: libtorch, onnxruntime), and the layout's "D entries?"
    checks compare shapes, which a trace evaluates once (harmless: D is fixed)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=torch.jit.TracerWarning)
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\.(jit|onnx)")
        warnings.filterwarnings("ignore", message=".*legacy TorchScript-based ONNX export.*")
        yield


def export_torchscript(actor: nn.Module, example: tuple, check: tuple, path: Path) -> Path:
    """Trace (the encoders are plain tensor code once the layout is fixed) and check the trace on
    another batch size, so a shape frozen into the graph would fail here rather than on the robot.
    ``example`` and ``check`` are the inputs: ``(obs,)`` or, recurrent, ``(obs, state)``."""
    with _quiet_torch():
        traced = torch.jit.trace(actor, example, check_inputs=[check])
    traced.save(str(path))
    return path


def _eye_symbolic(g, n, *args):
    """aten::eye(n, [m,] dtype, layout, device, pin_memory) as a float EyeLike cast to the dtype."""
    from torch.onnx import JitScalarType, symbolic_helper

    m = args[0] if len(args) == 5 else n
    dtype = symbolic_helper._maybe_get_const(args[-4], "i")
    zero = g.op("Constant", value_t=torch.tensor([0]))
    shape = g.op("Concat", g.op("Unsqueeze", n, zero), g.op("Unsqueeze", m, zero), axis_i=0)
    eye = g.op("EyeLike", g.op("ConstantOfShape", shape, value_t=torch.tensor([0.0])))
    if dtype is None or not isinstance(dtype, int):
        return eye
    return g.op("Cast", eye, to_i=JitScalarType(dtype).onnx_type())


def _argsort_symbolic(g, self, *args):
    """aten::argsort(self, [stable,] dim, descending) as ONNX TopK over the whole axis (ties: lower index
    first, as a stable sort)."""
    from torch.onnx import symbolic_helper

    dim = symbolic_helper._get_const(args[-2], "i", "dim")
    descending = symbolic_helper._get_const(args[-1], "b", "descending")
    length = g.op("Shape", self, start_i=dim, end_i=dim + 1) if dim != -1 else g.op("Shape", self, start_i=-1)
    _, indices = g.op("TopK", self, length, axis_i=dim, largest_i=int(descending), sorted_i=1, outputs=2)
    return indices


@contextlib.contextmanager
def _onnx_translations():
    custom = {"aten::eye": _eye_symbolic, "aten::argsort": _argsort_symbolic}
    for name, fn in custom.items():
        torch.onnx.register_custom_op_symbolic(name, fn, ONNX_OPSET)
    try:
        yield
    finally:
        for name in custom:
            torch.onnx.unregister_custom_op_symbolic(name, ONNX_OPSET)


def export_onnx(actor: nn.Module, example: tuple, path: Path) -> Path:
    """ONNX with a dynamic batch axis, checked by ``onnx.checker``; inputs ``obs`` (and ``state``), outputs
    ``actions`` (and ``state_out``)."""
    try:
        import onnx
    except ImportError as e:
        raise ImportError("ONNX export needs the onnx package: pip install -e '.[export]' "
                          "(or pip install onnx onnxruntime)") from e
    with _quiet_torch(), _onnx_translations():
        inputs, outputs = (["obs", "state"], ["actions", "state_out"]) if len(example) == 2 else (["obs"], ["actions"])
        torch.onnx.export(actor, example, str(path), dynamo=False, input_names=inputs, output_names=outputs,
                          dynamic_axes={name: {0: "batch"} for name in inputs + outputs}, opset_version=ONNX_OPSET)
    onnx.checker.check_model(onnx.load(str(path)))
    return path


def run_exported(fmt: str, path: Path, obs: np.ndarray, state: Optional[np.ndarray] = None):
    """Actions [B, 4] of an exported file (TorchScript through torch.jit, ONNX through onnxruntime); with a
    recurrent actor's ``state`` [B, S], ``(actions, state_out)``."""
    if fmt == "torchscript":
        with torch.no_grad(), _quiet_torch():
            model = torch.jit.load(str(path))
            if state is None:
                return model(torch.from_numpy(obs)).numpy()
            actions, state_out = model(torch.from_numpy(obs), torch.from_numpy(state))
            return actions.numpy(), state_out.numpy()
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    if state is None:
        return session.run(["actions"], {"obs": obs})[0]
    return tuple(session.run(["actions", "state_out"], {"obs": obs, "state": state}))


# ----------------------------------------------------------------------------------------------- contract
def observation_contract(layout: ObsLayout) -> Dict:
    """Every observation field: group, kind, meaning, and its slice(s) [start, stop) in the flat vector."""
    fields = []
    for f in layout.fields:
        entry = {"name": f.name, "group": f.group, "kind": f.kind, "size": f.size,
                 "meaning": FIELD_MEANINGS.get((f.group, f.name), f.name)}
        if f.group == "neighbor":  # one block per slot, nearest neighbour first
            entry["slices"] = [[f.start + k * layout.neighbor_dim, f.stop + k * layout.neighbor_dim]
                               for k in range(layout.num_neighbors)]
        else:
            entry["slice"] = [f.start, f.stop]
        fields.append(entry)
    return {
        "dim": layout.dim, "num_neighbors": layout.num_neighbors, "neighbor_obs": layout.neighbor_obs,
        "neighbor_dim": layout.neighbor_dim, "obstacle_obs": layout.obstacle_obs,
        "order": "self block | K neighbour blocks, nearest first | K mask entries | obstacle field (if any)",
        "padding": "with fewer than K neighbours (N - 1 < K or out of sensing range) the last slots are "
                   "zeros with mask 0",
        "frames": "world frame z up (gravity along -z); vectors in world axes unless marked body",
        "normalization": "inside the model: feed raw observations",
        "fields": fields,
    }


def action_contract(env_cfg, clip_actions: bool) -> Dict:
    p = env_cfg.physics
    return {
        "size": 4,
        "clipped": clip_actions,
        "meaning": "one command u_k per motor; the simulator clips u_k to [-1, 1] and commands the thrust "
                   "fraction c_k = (u_k + 1) / 2 of the motor's maximum thrust (the rotor speed tracks "
                   "sqrt(c_k) with a first-order lag)",
        "motors_body_xy": [[1, -1], [-1, -1], [-1, 1], [1, 1]],  # signs of (x, y) of motors 0..3, x-configuration
        "motor_spin": [-1, 1, -1, 1],
        "arm_xy_m": p.arm_xy,
        "max_thrust_per_motor_N": p.thrust_to_weight * p.mass * p.gravity / 4.0,
        "motor_time_constant_s": p.motor_time_constant,
        "control_rate_hz": 1.0 / env_cfg.control_dt,
        "hover_action": 2.0 / p.thrust_to_weight - 1.0,
    }


# ----------------------------------------------------------------------------------------------- API
def export_actor(model: nn.Module, out_dir, env_cfg, formats: Sequence[str] = FORMATS, clip_actions: bool = False,
                 provenance: Optional[Dict] = None, seed: int = 0) -> Dict[str, Path]:
    """Export ``model``'s deterministic actor in ``formats`` into ``out_dir`` with its ``actor.json``.

    Returns ``{format: path}`` plus ``"sidecar"``. Each file is checked against the PyTorch actor on
    random observations (another batch size than the traced one, padded neighbour slots included);
    a difference above ``VERIFY_TOLERANCE`` raises. ``env_cfg`` gives the action's physical meaning.
    """
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise ValueError(f"unknown export format(s) {unknown or list(formats)}; valid: {list(FORMATS)}")
    from encoders.testing import random_obs

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    layout = model.layout
    S = model.state_sizes[0] if getattr(model, "state_size", 0) else 0  # the actor cell's state; 0 feed-forward
    wrapper = RecurrentDeterministicActor if S else DeterministicActor
    actor = copy.deepcopy(wrapper(model, clip_actions)).cpu().eval()  # the caller's model untouched
    rng = np.random.default_rng(seed)
    K = layout.num_neighbors
    example = torch.as_tensor(random_obs(layout, 8, rng, num_real=[K] * 8), dtype=torch.float32)  # [8, D]
    check = random_obs(layout, 13, rng).astype(np.float32)  # [13, D], 0..K real neighbours
    check_state = rng.normal(size=(13, S)).astype(np.float32) if S else None  # a mid-episode state
    with torch.no_grad():  # checked against the policy itself, not the wrapper: catches a wrapper that drifts
        reference = copy.deepcopy(model).cpu().eval()
        if S:
            full = torch.zeros(13, reference.state_size)
            full[:, :S] = torch.from_numpy(check_state)
            actions, _, _, state_out = reference.act(torch.from_numpy(check), True, with_value=False, state=full)
            expected = actions
            expected_state = state_out[:, :S].numpy()
        else:
            expected = reference.policy(torch.from_numpy(check))[0]  # [13, 4]
        expected = (expected.clamp(-1.0, 1.0) if clip_actions else expected).numpy()
    example_in = (example, torch.zeros(8, S)) if S else (example,)
    check_in = (torch.from_numpy(check), torch.from_numpy(check_state)) if S else (torch.from_numpy(check),)

    paths, errors = {}, {}
    for fmt in dict.fromkeys(formats):
        path = out / FILE_NAMES[fmt]
        if fmt == "torchscript":
            export_torchscript(actor, example_in, check_in, path)
        else:
            export_onnx(actor, example_in, path)
        try:
            if S:
                got, got_state = run_exported(fmt, path, check, check_state)
                errors[fmt] = float(max(np.abs(got - expected).max(), np.abs(got_state - expected_state).max()))
            else:
                errors[fmt] = float(np.abs(run_exported(fmt, path, check) - expected).max())
        except ImportError:
            errors[fmt] = None  # onnxruntime missing: not verified
            warnings.warn(f"{path} was not checked: onnxruntime is not installed", RuntimeWarning)
        if errors[fmt] is not None and not errors[fmt] <= VERIFY_TOLERANCE:
            raise RuntimeError(f"exported {fmt} actor differs from the PyTorch actor by {errors[fmt]:.3g} "
                               f"(> {VERIFY_TOLERANCE}) on random observations")
        paths[fmt] = path

    sidecar = {
        "format": SIDECAR_FORMAT, "version": SIDECAR_VERSION,
        "files": {fmt: p.name for fmt, p in paths.items()},
        "input": {"name": "obs", "dtype": "float32", "shape": ["batch", layout.dim]},
        "output": {"name": "actions", "dtype": "float32", "shape": ["batch", 4]},
        "state": ({"input": "state", "output": "state_out", "dtype": "float32", "shape": ["batch", S],
                   "core": model.config["core"],
                   "usage": "recurrent policy: feed zeros at an episode start, then the previous call's state_out "
                            "(one row per drone, in the same order as obs)"} if S else None),
        "observation": observation_contract(layout),
        "action": action_contract(env_cfg, clip_actions),
        "policy": {**(provenance or {}), "encoder": model.config["encoder"],
                   "encoder_kwargs": model.config["encoder_kwargs"], "normalize_obs": model.obs_norm is not None,
                   "body_frame_obs": getattr(model, "body_frame", None) is not None},
        "check": {"max_abs_error": errors, "batch": len(check), "tolerance": VERIFY_TOLERANCE},
        "exported_with": {"torch": torch.__version__, "onnx_opset": ONNX_OPSET},
    }
    paths["sidecar"] = out / SIDECAR
    paths["sidecar"].write_text(json.dumps(sidecar, indent=2) + "\n")
    return paths


def export_checkpoint(checkpoint: str, out_dir, formats: Sequence[str] = FORMATS,
                      clip_actions: bool = False) -> Dict[str, Path]:
    """``export_actor`` of a checkpoint file or run directory (its latest valid checkpoint)."""
    from swarm_appo.evaluation import load_checkpoint_policy

    loaded = load_checkpoint_policy(checkpoint)
    env = loaded.cfg.env
    provenance = {"checkpoint": os.path.abspath(checkpoint), "agent_steps": loaded.agent_steps,
                  "run": loaded.run_name, "trained_num_agents": env.num_agents, "trained_scenario": env.scenario,
                  "sensing_radius": env.sensing_radius}
    return export_actor(loaded.model, out_dir, env, formats, clip_actions, provenance)


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="swarm-export", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", required=True, help="checkpoint file or run directory")
    p.add_argument("--out", required=True, help="output folder (created)")
    p.add_argument("--format", default=",".join(FORMATS), help=f"comma-separated, of {list(FORMATS)}")
    p.add_argument("--clip-actions", action="store_true", help="clip the actions to [-1, 1] inside the model")
    args = p.parse_args(argv)
    formats = [f.strip() for f in args.format.split(",") if f.strip()]
    torch.set_num_threads(1)
    from swarm_appo.checkpoint import CheckpointCorruptError

    try:
        paths = export_checkpoint(args.checkpoint, args.out, formats, args.clip_actions)
    except (ValueError, FileNotFoundError, ImportError, CheckpointCorruptError) as exc:
        p.error(str(exc))
    check = json.loads(paths["sidecar"].read_text())["check"]["max_abs_error"]
    for fmt, path in paths.items():
        err = check.get(fmt)
        note = "" if fmt == "sidecar" else (" (not checked)" if err is None else f"  max |error| {err:.1e}")
        print(f"{fmt:12s} {path}{note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
