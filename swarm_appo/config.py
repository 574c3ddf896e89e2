"""The training configuration: one typed dataclass tree, loaded from YAML and ``key=value`` overrides.

    cfg = load_config("configs/paper.yaml", ["env.num_agents=16", "model.encoder=se3_kattention"])
    cfg = load_config(None)              # the embedded quickstart setting (2 cores, a few minutes)

A YAML file holds any subset of the tree; it is merged onto the dataclass defaults (the paper's
algorithm hyperparameters), then the overrides are applied, then every value is type-checked and
``validate`` checks ranges and cross-field consistency. Unknown keys, wrong types and inconsistent
sizes raise ``ConfigError`` naming the dotted key and what is allowed.
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import math
import os
import re
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import yaml

from quad_env.config import EnvConfig
from swarm_appo.atomic import atomic_write_bytes

DEVICES = ("auto", "cpu", "cuda")
WANDB_MODES = ("offline", "online", "disabled")
LR_SCHEDULES = ("constant", "linear")
PRECISIONS = ("auto", "fp32", "bf16")  # runner.precision (swarm_appo.precision resolves "auto")
COMPILE_MODES = ("off", "default", "reduce-overhead")  # runner.compile: torch.compile modes of the learner forward


class ConfigError(ValueError):
    """A configuration value is unknown, of the wrong type, out of range or inconsistent with another."""


# =============================================================================================== the tree
@dataclass
class ModelConfig:
    """The actor-critic (``encoders.ActorCritic``)."""

    encoder: str = "deepsets"
    """Neighbour encoder, a name in ``encoders.ENCODERS``: the architectures graphormer, kattention, deepsets, mlp,
    infomarl, and the paper's names se3_graphormer, se3_kattention (= graphormer / kattention with
    ``symmetry: se3``)."""
    symmetry: Optional[str] = None
    """Symmetry group the encoder is made equivariant to by canonicalization (paper, Lemma 1), for every
    architecture: "none" (world-frame inputs, the paper's baselines), "se3" (each input in drone i's frame
    (x_i, R_i), typed outputs mapped back to world axes by R_i: the paper's SE(3) encoders), "yaw" (the same in
    drone i's heading frame, the rotation about gravity by its yaw: the symmetry of the quadrotor dynamics).
    null = the encoder name's own (se3 for se3_*, none otherwise)."""
    size: str = "paper"
    """Size preset of the encoder and the heads: "paper" (the paper's widths, head 256) or "small" (~64-wide
    layers and heads, for a 2-core laptop). ``encoder_kwargs`` and ``head_hidden`` override single values."""
    encoder_kwargs: Dict[str, Any] = field(default_factory=dict)
    """Options of the chosen encoder over its size preset (constructor keywords, e.g. ``{multiplicity: 16}``;
    with a symmetry also ``out_vectors``, the number of 3-vector outputs); empty = the preset."""
    share_encoder: bool = False
    """Actor and critic share one encoder; False (the paper, Sample Factory's default) gives each its own."""
    head_hidden: Optional[int] = None
    """Hidden width of the actor and critic MLP heads on top of the encoder; null = the size preset's (256 / 64);
    0 = linear heads (one Linear each, like Sample Factory's: for like-for-like comparisons with it)."""
    head_activation: str = "tanh"
    """Nonlinearity of the heads (the paper uses tanh)."""
    init_log_std: float = 0.0
    """Initial log standard deviation of the Gaussian policy (learned, state-independent), in [-10, 2]."""
    normalize_obs: bool = False
    """Divide each observation field by the running RMS of its norm (one scalar per field; rotations and the
    mask untouched), which keeps the SE(3) encoders exactly equivariant. The learner updates the statistics
    from every training batch; rollout workers receive them with the weights."""
    init_action_mean: float = 0.0
    """Initial mean action (the actor's output bias). 2 / thrust_to_weight - 1 (0.053 for the Crazyflie)
    is the hover command: the untrained policy then commands hover thrust on average (0 gives 0.95 g)."""
    body_frame_obs: Optional[bool] = False
    """Give the network the observation in the drone's body frame (world vectors v -> R_i^T v, neighbour
    rotations -> R_i^T R_j, R_i kept): a rotor command depends on body-frame quantities, which a small
    world-frame MLP must otherwise learn as products of its inputs. Only with ``symmetry: none`` (a symmetry
    canonicalizes the inputs itself). null = auto: on with ``symmetry: none``, off with a symmetry (the quickstart:
    ``model.encoder=se3_graphormer`` on top of it just works). Not in the paper (False); it hands a "none"
    encoder part of what ``se3`` canonicalization gives, so the symmetry comparison keeps it off."""
    init_actor_out_scale: float = 1.0
    """Multiplies the Xavier-uniform init of the actor's last layer (1 = the paper). 0.01 (PPO practice)
    makes the untrained policy command ``init_action_mean`` in every state instead of a random state-dependent
    thrust pattern that flips a drone within a second."""
    critic: str = "local"
    """Value function input: "local" (the drone's own observation, as the actor; the paper) or "central" (MAPPO:
    also the swarm's global state, every drone's own-state block: position relative to its goal, velocity,
    rotation, body rates, through a DeepSets over the drones). The actor stays decentralised either way; the
    global state is read from the fragment's observations (no extra simulation or data)."""
    core: str = "none"
    """Recurrent core between encoder and heads (Sample Factory's ``use_rnn``): "none" (feed-forward, the paper),
    "gru" or "lstm". Actor and critic each get a cell (one shared with ``share_encoder``); rollout workers carry
    each drone's state across fragments and reset it at episode starts; the learner unrolls whole
    trajectories from the state stored with each fragment, recomputing the states with the current weights."""
    core_size: Optional[int] = None
    """Hidden size of each recurrent cell; null = the heads' width (the size preset's: 256 / 64)."""


@dataclass
class AlgoConfig:
    """APPO with V-trace. Defaults: the paper's Appendix III (Sample Factory's values where the paper is silent)."""

    lr: float = 1e-4
    """Adam learning rate."""
    gamma: float = 0.99
    """Discount factor."""
    adam_betas: Tuple[float, float] = (0.9, 0.995)
    """Adam (beta1, beta2)."""
    adam_eps: float = 2e-6
    """Adam epsilon."""
    max_grad_norm: float = 5.0
    """Global gradient-norm clipping threshold."""
    rollout: int = 128
    """T, time steps per fragment (the length of every trajectory the learner sees)."""
    batch_size: int = 4096
    """Samples (drone steps) per minibatch, i.e. ``batch_size / rollout`` whole trajectories; a multiple of rollout.
    The learner trains once it has collected at least this many samples."""
    num_epochs: int = 5
    """Passes over each collected batch (PPO epochs)."""
    ppo_clip_ratio: float = 0.2
    """PPO clipping range epsilon of the probability ratio: [1 - eps, 1 + eps]. 0.2 is PPO's usual value and the
    quickstart's; Sample Factory's default, which the paper's training commands keep, is 0.1 (configs/paper.yaml,
    configs/table1/quality.yaml)."""
    value_loss_coeff: float = 0.5
    """Weight of the value loss, mean squared error to the V-trace targets."""
    entropy_coeff: float = 0.0
    """Weight of the entropy bonus (0: Sample Factory's quadrotor setting)."""
    value_clip: Optional[float] = None
    """Absolute clip range of the value change against the behaviour-time value; None = no value clipping."""
    normalize_advantages: bool = True
    """Standardise the advantages of each minibatch (over its valid samples)."""
    max_policy_lag: int = 100
    """Steps whose policy lag (learner version - behaviour version) exceeds this are masked out of the loss."""
    vtrace_rho_clip: Optional[float] = 1.0
    """V-trace rho-bar: clips the importance weights of the TD errors; None = no clipping."""
    vtrace_c_clip: Optional[float] = 1.0
    """V-trace c-bar: clips the trace-cutting coefficients; None = no clipping."""
    vtrace_pg_rho_clip: Optional[float] = 1.0
    """Clip of the importance weight on the policy-gradient advantage; None = no clipping."""
    vtrace_lambda: float = 1.0
    """V-trace trace factor lambda (IMPALA, Remark 2): 1 = plain V-trace; e.g. 0.95 cuts variance like GAE."""
    max_consecutive_skips: int = 50
    """Stop the run with an error (exit 1, naming the checkpoint to resume) after this many consecutive skipped
    updates (non-finite loss or gradient: the run cannot learn); 0 = never stop. Skips are counted in the
    metrics (``losses/skipped_updates``) and the progress bar either way."""
    lr_schedule: str = "constant"
    """"constant" (the paper) or "linear": lr * (1 - agent_steps / runner.total_agent_steps), down to 0 at the
    budget (Sample Factory's linear decay). A run of the 2-core recipe at constant 3e-4 collapsed after ~30 M steps
    with approx-KL rising to 0.05-0.085 (benchmarks/RESULTS.md, "quality goal")."""
    weight_ema: Tuple[float, ...] = ()
    """Horizons H (agent steps) of exponential moving averages of the weights, e.g. [2000000, 5000000]: each
    weighs the weights after a batch by exp(-age / H) (``swarm_appo.weight_ema``). A read-out only (training is
    unchanged); saved in checkpoints, where ``swarm_appo.select_checkpoint`` flies them as candidates for the final
    policy. Empty (default): none."""


@dataclass
class RunnerConfig:
    """Processes, budgets, devices and the run directory."""

    ray_address: Optional[str] = None
    """Where the Ray actors run. None: start a local Ray on this machine (all its cores). "auto": join the Ray
    cluster this process runs in (a job submitted with ``launchers.ray_cluster`` does this); "<host>:<port>":
    join the cluster whose head (GCS) listens there. On a cluster, ``num_workers=0`` sizes the rollout workers
    from the CPUs of all nodes (minus one for the learner) and spreads them over the nodes; the learner runs
    in this (driver) process and uses its GPU if the node has one (``device=auto``). Where each worker ran is
    written to ``<run dir>/cluster.json``."""
    seed: int = 0
    """One seed drives everything (environments, sampling, initialisation); same seed, same results in serial mode."""
    serial: bool = False
    """Run the rollout workers in-process, one after another (no Ray): for debugging and reproducible tests."""
    num_workers: int = 0
    """Rollout workers (Ray actors, one core each); 0 = one per core, minus one for the learner (at least 1);
    on a cluster (``ray_address`` set) the cores are the CPUs of all its nodes."""
    envs_per_worker: int = 2
    """E, swarms simulated by each worker; a fragment holds E * env.num_agents trajectories."""
    max_fragments_in_flight: int = 0
    """Backpressure: at most this many fragments requested but not yet trained on; 0 = 2 per worker."""
    total_agent_steps: int = 50_000_000
    """Training budget in agent steps (one drone, one control step)."""
    time_limit_s: float = 0.0
    """Also stop after this many seconds of training (wall clock, this process); 0 = no limit."""
    device: str = "auto"
    """Learner device: "auto" (cuda when present, else cpu), "cpu", "cuda" or "cuda:<index>"."""
    precision: str = "auto"
    """The learner's matmul precision: "fp32", "bf16" (mixed precision: torch.autocast, fp32 weights, optimizer,
    log-probs, V-trace and losses) or "auto": bf16 on a CPU with native bf16 (AMX / AVX-512 BF16) for
    ``model.size: paper``; fp32 otherwise, and on CUDA, where the learner is launch-bound at these batch sizes
    (``swarm_appo.precision``). The choice and its reason are logged and written at the top of the run's
    config.yaml."""
    compile: str = "off"
    """``torch.compile`` the learner's forward (``evaluate_sequence``; its backward follows): "off", "default"
    (fuses the many small element-wise ops into fewer kernels) or "reduce-overhead" (also replays them as CUDA
    graphs). Meant for a CUDA learner, which is bound by kernel launches at these batch sizes (RESULTS.md,
    gpu_check); its gain there is not measured yet (``benchmarks/gpu_check.sh`` with ``LEARNER_COMPILE``). Costs
    compile time at start (20-60 s on a CPU; inductor needs a C++ compiler there). On a CPU it gained nothing for the
    paper's Graphormer (bound by its matmuls) and 1.13x end to end for K-Attention in bf16 at batch 1024, where the
    element-wise work between the matmuls is a third of the learner's time (RESULTS.md, "peer_throughput",
    2026-12-07). Checkpoints and exported policies are the same either way."""
    inference_precision: str = "auto"
    """The rollout workers' inference precision: "fp32", "bf16" or "auto", the same rule as ``precision``,
    resolved by each worker on its own CPU."""
    checkpoint_every_s: float = 600.0
    """Seconds between checkpoints (a final one is always written at the end or on Ctrl-C)."""
    checkpoint_every_updates: int = 0
    """Also checkpoint every this many learner iterations; 0 = only by time."""
    keep_checkpoints: int = 3
    """How many of the most recent checkpoints to keep, besides best.pt."""
    run_dir: str = "runs"
    """Root folder of the run directories. A job submitted with ``launchers.ray_cluster`` resolves a relative one
    against the home directory of the node that runs the learner (the job's own working directory is a
    temporary copy that Ray deletes)."""
    name: Optional[str] = None
    """Run directory name under run_dir (also the wandb run name); None = a timestamp."""
    learner_threads: int = 0
    """torch threads of the learner; 0 = the cores left after the rollout workers on this machine (at least 1; all
    cores in serial mode), so that learner threads + rollout workers never exceed the cores."""
    final_eval_episodes: int = 8
    """At the end of a run, evaluate the mean-action policy and a random policy on this many seeded
    episodes (``eval/*``, ``eval_random/*`` metrics); 0 = skip."""
    init_checkpoint: Optional[str] = None
    """Start this (new) run from the policy of a checkpoint: a file, or a run directory (its newest valid
    checkpoint). The network's weights, including its observation normaliser, are loaded; the optimizer, the
    counters (agent steps from 0), the lr and reward schedules and the history start afresh, in this run's own
    directory. For training stages (a new reward, scenario or budget on a trained policy) without touching the
    first run. The model must fit (the same ``model`` options and observation layout): checked before the run
    directory is made. A resumed run continues from its own checkpoints and ignores this. A job submitted with
    ``launchers.ray_cluster`` resolves a relative path like ``run_dir``: against the learner node's home."""


@dataclass
class WandbConfig:
    """Weights & Biases logging (metrics.jsonl is always written)."""

    mode: str = "offline"
    """"offline" (a local run, upload later with ``wandb sync``), "online" or "disabled"."""
    project: str = "swarm-appo"
    """wandb project."""
    entity: Optional[str] = None
    """wandb entity (user or team); None = your default."""
    group: Optional[str] = None
    """wandb group, e.g. to gather the seeds of one experiment; null = ``<architecture>/<symmetry>``."""
    tags: Tuple[str, ...] = ()
    """wandb tags; every run also gets its architecture, ``symmetry:<s>``, ``size:<s>`` and ``scenario:<s>``."""


@dataclass
class TrainConfig:
    """Everything a training run needs."""

    env: EnvConfig = field(default_factory=EnvConfig)
    """The environment (``quad_env.config.EnvConfig``)."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """The actor-critic."""
    algo: AlgoConfig = field(default_factory=AlgoConfig)
    """The learning algorithm."""
    runner: RunnerConfig = field(default_factory=RunnerConfig)
    """Processes, budgets and the run directory."""
    wandb: WandbConfig = field(default_factory=WandbConfig)
    """Weights & Biases."""


# The quickstart setting (load_config(None)): what differs from the defaults above.
# configs/quickstart.yaml states the same values; a test keeps the two equal.
QUICKSTART: Dict[str, Any] = {
    "env": {"num_agents": 8, "scenario": "static_same_goal", "respawn_on_floor": True,
            "reward": {"crash": 2.0, "tilt": 1.0}},
    "model": {"encoder": "deepsets", "size": "small",
              "normalize_obs": True, "body_frame_obs": None, "init_action_mean": 0.053,
              "init_actor_out_scale": 0.01, "init_log_std": -2.0},
    "algo": {"batch_size": 2048, "num_epochs": 2, "lr": 3e-4},
    "runner": {"num_workers": 0, "envs_per_worker": 16, "total_agent_steps": 10_000_000, "time_limit_s": 420.0,
               "checkpoint_every_s": 120.0, "name": "quickstart"},
}


# =============================================================================================== YAML
class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads ``1e-4`` as a float (YAML 1.1 insists on ``1.0e-4``), and takes only
    true/false as booleans (YAML 1.2): YAML 1.1's on/off/yes/no stay words, so ``runner.compile=off`` is the
    mode "off", and a boolean key given ``yes`` is an error naming the key."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                   |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                   |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                   |[-+]?\.(?:inf|Inf|INF)
                   |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


_Loader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag != "tag:yaml.org,2002:bool"]
    for first, resolvers in _Loader.yaml_implicit_resolvers.items()}
_Loader.add_implicit_resolver("tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
                              list("tTfF"))


def yaml_load(text: str) -> Any:
    return yaml.load(text, Loader=_Loader)


# =============================================================================================== dict <-> tree
def config_to_dict(cfg: Any) -> Dict[str, Any]:
    """A plain nested dict (tuples as lists) that ``config_from_dict`` turns back into the same tree."""
    def plain(x: Any) -> Any:
        if dataclasses.is_dataclass(x) and not isinstance(x, type):
            return {f.name: plain(getattr(x, f.name)) for f in dataclasses.fields(x)}
        if isinstance(x, (list, tuple)):
            return [plain(v) for v in x]
        if isinstance(x, dict):
            return {k: plain(v) for k, v in x.items()}
        return x
    return plain(cfg)


def config_from_dict(d: Mapping[str, Any], cls: type = None, prefix: str = "") -> Any:
    """Build a config tree (``TrainConfig`` by default) from a nested dict; missing keys keep their defaults.

    Strict: an unknown key raises ConfigError naming the full dotted key and the valid keys at its level;
    a value of the wrong type raises ConfigError naming the key, the expected type and the value.
    Lists are accepted for tuple fields; ints for float fields; integral floats (2e6) for int fields.
    """
    cls = cls or TrainConfig
    if not isinstance(d, Mapping):
        raise ConfigError(f"config section {prefix.rstrip('.') or '<root>'!r} must be a mapping of keys to values, "
                          f"got {_describe(d)}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    kwargs = {}
    for key, value in d.items():
        dotted = f"{prefix}{key}"
        if key not in fields:
            raise ConfigError(_unknown_key_message(dotted, str(key), list(fields), prefix))
        kwargs[key] = _coerce(value, hints[key], dotted)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:  # a dataclass's own __post_init__ checks
        raise ConfigError(f"config section {prefix.rstrip('.') or '<root>'!r}: {e}") from e


def _unknown_key_message(dotted: str, key: str, valid: List[str], prefix: str) -> str:
    level = f"in {prefix.rstrip('.')!r}" if prefix else "at the top level"
    close = difflib.get_close_matches(key, valid, n=1)
    hint = f" (did you mean {prefix + close[0]!r}?)" if close else ""
    return f"unknown config key {dotted!r}{hint}; valid keys {level}: {sorted(valid)}"


def _describe(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})"


def _type_name(tp: Any) -> str:
    if isinstance(tp, type):
        return tp.__name__
    return str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Check ``value`` against the annotation ``tp`` and convert it (lists -> tuples, int -> float, ...)."""
    wrong = ConfigError(f"config key {key!r} expects {_type_name(tp)}, got {_describe(value)}")
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)

    if tp is Any:
        return copy.deepcopy(value)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            if type(None) in args:
                return None
            raise wrong
        for option in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, option, key)
            except ConfigError:
                pass
        raise wrong
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return copy.deepcopy(value)
        return config_from_dict(value, tp, prefix=f"{key}.")
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise wrong
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise wrong
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):  # every float of the tree is a finite quantity; None where "off" is meant
                raise ConfigError(f"config key {key!r} must be a finite number, got {value}")
            return float(value)
        raise wrong
    if tp is str:
        if isinstance(value, str):
            return value
        raise wrong
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise wrong
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"config key {key!r} expects {len(args)} values ({_type_name(tp)}), "
                              f"got {len(value)}: {value!r}")
        return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if origin is list or tp is list:
        if not isinstance(value, (list, tuple)):
            raise wrong
        item = args[0] if args else Any
        return [_coerce(v, item, f"{key}[{i}]") for i, v in enumerate(value)]
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise wrong
        value_type = args[1] if args else Any
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise ConfigError(f"config key {key!r} expects string keys, got {_describe(k)}")
            out[k] = _coerce(v, value_type, f"{key}.{k}")
        return out
    raise ConfigError(f"config key {key!r} has an unsupported annotation {tp!r}")  # a bug in the tree


# =============================================================================================== overrides
def parse_override(text: str) -> Tuple[str, Any]:
    """``"a.b=value"`` -> ``("a.b", value)`` with the value read as YAML (``16``, ``1e-4``, ``true``,
    ``null``, ``[0.9, 0.99]``, ``{multiplicity: 16}``; anything else is a string)."""
    if not isinstance(text, str) or "=" not in text:
        raise ConfigError(f"override {text!r} must look like key=value, e.g. env.num_agents=16")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise ConfigError(f"override {text!r} has an empty key part; expected e.g. algo.lr=1e-4")
    try:
        value = yaml_load(raw) if raw.strip() else None
    except yaml.YAMLError as e:
        raise ConfigError(f"override {text!r}: the value is not valid YAML ({e})") from e
    return key, value


def apply_override(d: Dict[str, Any], key: str, value: Any) -> None:
    """Set dotted ``key`` in the nested dict ``d`` in place; mappings are merged into mappings."""
    parts = key.split(".")
    node = d
    for i, part in enumerate(parts[:-1]):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"cannot set {key!r}: {'.'.join(parts[:i + 1])!r} is a value, not a section")
        node = child
    last = parts[-1]
    if isinstance(value, Mapping) and isinstance(node.get(last), dict):
        _deep_merge(node[last], value)
    else:
        node[last] = copy.deepcopy(value)


def _deep_merge(base: Dict[str, Any], update: Mapping[str, Any]) -> Dict[str, Any]:
    for k, v in update.items():
        if isinstance(v, Mapping) and isinstance(base.get(k), dict):
            _deep_merge(base[k], v)
        else:
            base[k] = copy.deepcopy(v)
    return base


# =============================================================================================== load / save
def default_config() -> TrainConfig:
    """The embedded quickstart setting (what ``load_config(None)`` returns)."""
    return config_from_dict(_deep_merge(config_to_dict(TrainConfig()), QUICKSTART))


def load_config(path: Optional[str], overrides: Sequence[str] = ()) -> TrainConfig:
    """Load a config: the YAML file ``path`` merged onto the defaults (None: the embedded quickstart
    setting), then the ``key=value`` overrides; type-checked and validated."""
    if path is None:
        d = config_to_dict(default_config())
    else:
        d = _deep_merge(config_to_dict(TrainConfig()), _read_yaml_config(path))
    for text in overrides:
        key, value = parse_override(text)
        try:
            apply_override(d, key, value)
            config_from_dict(d)
        except ConfigError as e:
            raise ConfigError(f"override {text!r}: {e}") from e
    return validate(config_from_dict(d))


def _read_yaml_config(path: str, _seen: Tuple[str, ...] = ()) -> Dict[str, Any]:
    """The sections of a YAML config file; a top-level ``base: <file>`` (relative to this file) is read first
    and this file's keys are merged over it (one Table 1 row = the paper's config + two keys)."""
    if not os.path.isfile(path):
        raise ConfigError(f"config file not found: {path}")
    real = os.path.realpath(path)
    if real in _seen:
        raise ConfigError(f"{path}: 'base' files form a cycle: {' -> '.join(_seen + (real,))}")
    try:
        with open(path) as f:
            loaded = yaml_load(f.read())
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from e
    loaded = {} if loaded is None else loaded
    if not isinstance(loaded, Mapping):
        raise ConfigError(f"{path}: the top level must be a mapping of sections, got {_describe(loaded)}")
    loaded = dict(loaded)
    base = loaded.pop("base", None)
    try:
        config_from_dict(loaded)  # report errors of the file itself, naming it
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from e
    if base is None:
        return loaded
    if not isinstance(base, str):
        raise ConfigError(f"{path}: 'base' must be the path of another config file, got {_describe(base)}")
    return _deep_merge(_read_yaml_config(os.path.join(os.path.dirname(path), base), _seen + (real,)), loaded)


def save_config(cfg: TrainConfig, path: str | os.PathLike, notes: Sequence[str] = ()) -> None:
    """Write the resolved config as YAML, atomically (readable by ``load_config`` and ``yaml.safe_load``);
    ``notes`` become comment lines at the top (e.g. what ``auto`` values resolved to on this machine)."""
    text = "# Resolved swarm_appo config (every key). Load with swarm_appo.config.load_config.\n"
    text += "".join(f"# {line}\n" for line in notes)
    text += yaml.safe_dump(config_to_dict(cfg), sort_keys=False, default_flow_style=None)
    atomic_write_bytes(path, text.encode())


# =============================================================================================== validation
def validate(cfg: TrainConfig) -> TrainConfig:
    """Check ranges and cross-field consistency; returns ``cfg``, raises ConfigError naming the key.

    Everything a run needs is checked here, before anything is written: the scenario name, the encoder name,
    its symmetry and options (the actor-critic is built on torch's meta device, which allocates nothing).
    """
    config_from_dict(config_to_dict(cfg))  # type-check trees built in code, not only loaded ones
    try:
        cfg.env.validate()
    except ValueError as e:
        raise ConfigError(str(e)) from e

    _check_scenario(cfg.env)
    m, a, r, w = cfg.model, cfg.algo, cfg.runner, cfg.wandb
    _check_model(cfg)
    _check(m.head_hidden is None or m.head_hidden >= 0, "model.head_hidden", "must be >= 0 (0 = linear heads) or null",
           m.head_hidden)
    _check(-10.0 <= m.init_log_std <= 2.0, "model.init_log_std", "must be in [-10, 2] (std 4.5e-5 .. 7.4 for actions "
           "in [-1, 1])", m.init_log_std)
    _check(m.init_actor_out_scale >= 0, "model.init_actor_out_scale", "must be >= 0", m.init_actor_out_scale)
    _check(-1.0 <= m.init_action_mean <= 1.0, "model.init_action_mean", "must be in [-1, 1] (the action range)",
           m.init_action_mean)
    _check(bool(m.head_activation), "model.head_activation", "must name an activation", m.head_activation)

    _check(a.lr > 0, "algo.lr", "must be > 0", a.lr)
    _check(a.max_consecutive_skips >= 0, "algo.max_consecutive_skips", "must be >= 0 (0 = never stop)",
           a.max_consecutive_skips)
    _check(a.lr_schedule in LR_SCHEDULES, "algo.lr_schedule", f"must be one of {list(LR_SCHEDULES)}", a.lr_schedule)
    _check(all(h > 0 for h in a.weight_ema), "algo.weight_ema", "must be horizons > 0 (agent steps)", a.weight_ema)
    _check(len(set(a.weight_ema)) == len(a.weight_ema), "algo.weight_ema", "must not repeat a horizon", a.weight_ema)
    _check(0 <= a.gamma <= 1, "algo.gamma", "must be in [0, 1]", a.gamma)
    _check(0 <= a.vtrace_lambda <= 1, "algo.vtrace_lambda", "must be in [0, 1]", a.vtrace_lambda)
    _check(all(0 <= b < 1 for b in a.adam_betas), "algo.adam_betas", "must be two numbers in [0, 1)", a.adam_betas)
    _check(a.adam_eps > 0, "algo.adam_eps", "must be > 0", a.adam_eps)
    _check(a.max_grad_norm > 0, "algo.max_grad_norm", "must be > 0", a.max_grad_norm)
    _check(a.rollout >= 1, "algo.rollout", "must be >= 1", a.rollout)
    _check(a.batch_size >= 1, "algo.batch_size", "must be >= 1", a.batch_size)
    if a.batch_size % a.rollout:
        lower = max(a.rollout, a.batch_size // a.rollout * a.rollout)
        raise ConfigError(f"algo.batch_size ({a.batch_size}) must be a multiple of algo.rollout ({a.rollout}): "
                          f"minibatches are made of whole trajectories; e.g. {lower} or {lower + a.rollout}")
    _check(a.num_epochs >= 1, "algo.num_epochs", "must be >= 1", a.num_epochs)
    _check(a.ppo_clip_ratio > 0, "algo.ppo_clip_ratio", "must be > 0", a.ppo_clip_ratio)
    _check(a.value_loss_coeff >= 0, "algo.value_loss_coeff", "must be >= 0", a.value_loss_coeff)
    _check(a.entropy_coeff >= 0, "algo.entropy_coeff", "must be >= 0", a.entropy_coeff)
    _check(a.value_clip is None or a.value_clip > 0, "algo.value_clip", "must be > 0 or null", a.value_clip)
    _check(a.max_policy_lag >= 0, "algo.max_policy_lag", "must be >= 0", a.max_policy_lag)
    for name in ("vtrace_rho_clip", "vtrace_c_clip", "vtrace_pg_rho_clip"):
        value = getattr(a, name)
        _check(value is None or value > 0, f"algo.{name}", "must be > 0 or null", value)

    if r.ray_address is not None:
        _check(bool(r.ray_address.strip()), "runner.ray_address",
               "must be null (a local Ray), 'auto' (join this cluster) or '<host>:<port>'", r.ray_address)
        if r.serial:
            raise ConfigError(f"runner.serial=true runs without Ray, but runner.ray_address is {r.ray_address!r}: "
                              f"set runner.serial=false to run on the cluster, or runner.ray_address=null")
    _check(0 <= r.seed < 2**63, "runner.seed", "must be in [0, 2^63)", r.seed)
    _check(r.num_workers >= 0, "runner.num_workers", "must be >= 0 (0 = one per core)", r.num_workers)
    _check(r.envs_per_worker >= 1, "runner.envs_per_worker", "must be >= 1", r.envs_per_worker)
    _check(r.max_fragments_in_flight >= 0, "runner.max_fragments_in_flight", "must be >= 0 (0 = 2 per worker)",
           r.max_fragments_in_flight)
    if r.num_workers and r.max_fragments_in_flight and r.max_fragments_in_flight < r.num_workers:
        raise ConfigError(f"runner.max_fragments_in_flight ({r.max_fragments_in_flight}) is below runner.num_workers "
                          f"({r.num_workers}): some workers could never run; use >= {r.num_workers} or 0 (auto)")
    _check(r.total_agent_steps >= 1, "runner.total_agent_steps", "must be >= 1", r.total_agent_steps)
    _check(r.time_limit_s >= 0, "runner.time_limit_s", "must be >= 0 (0 = no limit)", r.time_limit_s)
    _check(r.device in DEVICES or re.fullmatch(r"cuda:\d+", r.device) is not None, "runner.device",
           f"must be one of {list(DEVICES)} or 'cuda:<index>'", r.device)
    _check(r.checkpoint_every_s >= 0, "runner.checkpoint_every_s", "must be >= 0", r.checkpoint_every_s)
    _check(r.checkpoint_every_updates >= 0, "runner.checkpoint_every_updates", "must be >= 0 (0 = off)",
           r.checkpoint_every_updates)
    _check(r.keep_checkpoints >= 1, "runner.keep_checkpoints", "must be >= 1", r.keep_checkpoints)
    _check(bool(r.run_dir), "runner.run_dir", "must be a folder", r.run_dir)
    if r.name is not None:
        _check(bool(r.name) and "/" not in r.name and "\\" not in r.name and r.name not in (".", ".."),
               "runner.name", "must be a plain folder name (no path separators) or null", r.name)

    _check(r.precision in PRECISIONS, "runner.precision", f"must be one of {list(PRECISIONS)}", r.precision)
    _check(r.compile in COMPILE_MODES, "runner.compile", f"must be one of {list(COMPILE_MODES)}", r.compile)
    _check(r.inference_precision in PRECISIONS, "runner.inference_precision", f"must be one of {list(PRECISIONS)}",
           r.inference_precision)
    if r.init_checkpoint is not None:  # (whether it exists and fits is the trainer's check: a run's saved config
        # is also read where the file is gone, by evaluation and export)
        _check(bool(str(r.init_checkpoint).strip()), "runner.init_checkpoint",
               "must be a checkpoint file or run directory, or null", r.init_checkpoint)
    _check(w.mode in WANDB_MODES, "wandb.mode", f"must be one of {list(WANDB_MODES)}", w.mode)
    _check(bool(w.project), "wandb.project", "must not be empty", w.project)
    return cfg


def _check_scenario(env: EnvConfig) -> None:
    from quad_env.scenarios import SCENARIO_REGISTRY, SCENARIOS
    if env.scenario not in SCENARIO_REGISTRY:
        close = difflib.get_close_matches(env.scenario, list(SCENARIOS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(f"env.scenario: unknown scenario {env.scenario!r}{hint}; valid: {list(SCENARIOS)}")
    scenario = SCENARIO_REGISTRY[env.scenario]
    if scenario.needs_obstacles and not env.obstacles:
        raise ConfigError(f"env.scenario={env.scenario!r} flies through obstacles: set env.obstacles=true")
    if env.num_agents < scenario.min_agents:
        raise ConfigError(f"env.scenario={env.scenario!r} needs env.num_agents >= {scenario.min_agents}, "
                          f"got {env.num_agents}")


def _check_model(cfg: TrainConfig) -> None:
    """Encoder name, symmetry, size and options, by building the actor-critic on the meta device."""
    import encoders  # late: the config tree itself needs neither torch nor the encoders
    import torch

    m = cfg.model
    if m.encoder not in encoders.ENCODERS:
        close = difflib.get_close_matches(m.encoder, list(encoders.ENCODERS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ConfigError(f"model.encoder: unknown encoder {m.encoder!r}{hint}; valid: {list(encoders.ENCODERS)}")
    _check(m.size in encoders.SIZES, "model.size", f"must be one of {list(encoders.SIZES)}", m.size)
    _check(m.symmetry is None or m.symmetry in encoders.SYMMETRIES, "model.symmetry",
           f"must be one of {list(encoders.SYMMETRIES)} or null (the encoder's own)", m.symmetry)
    _check(m.critic in encoders.CRITICS, "model.critic", f"must be one of {list(encoders.CRITICS)}", m.critic)
    _check(m.core in encoders.CORES, "model.core", f"must be one of {list(encoders.CORES)}", m.core)
    _check(m.core_size is None or m.core_size >= 1, "model.core_size", "must be >= 1 or null", m.core_size)
    try:
        _, symmetry = encoders.resolve(m.encoder, m.symmetry)
    except ValueError as e:
        raise ConfigError(f"model.encoder={m.encoder!r} and model.symmetry={m.symmetry!r} contradict: {e}") from e
    if m.body_frame_obs is True and symmetry != "none":
        raise ConfigError(f"model.body_frame_obs=true and model.symmetry={symmetry!r} (encoder {m.encoder!r}) both "
                          f"rotate the inputs into the drone's frame: set model.body_frame_obs=false (the symmetry "
                          f"canonicalizes the inputs itself) or model.symmetry=none")
    try:
        with torch.device("meta"):
            encoders.ActorCritic(cfg.env.obs_layout(), **dataclasses.asdict(m))
    except (TypeError, ValueError, ZeroDivisionError, RuntimeError) as e:
        raise ConfigError(f"model.encoder_kwargs / model options do not build encoder {m.encoder!r}: {e}") from e


def _check(ok: bool, key: str, requirement: str, value: Any) -> None:
    if not ok:
        raise ConfigError(f"{key} {requirement}, got {value!r}")
