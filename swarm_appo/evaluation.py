"""The evaluation library: whole seeded episodes with a trained policy (or random actions), the evaluation
environment, checkpoint loading, evaluation tasks in this process or on Ray actors.

The trainer calls ``compare_with_random`` at the end of every run; the command line (``swarm_appo.evaluate``)
builds the paper's tables from ``run_tasks``; ``swarm_appo.export`` loads checkpoints with
``load_checkpoint_policy``.

How episodes run: the episodes of one (policy, N, scenario) are cut into tasks of at most
``episodes_per_task``; a task is one ``VecQuadEnv`` with one swarm per episode, stepped for the whole
episode with one batched policy forward per step. Tasks run in this process (``workers=0``) or on Ray
actors (one core each). Task c of a (N, scenario) is seeded by ``task_seed(seed, c)`` whatever the policy
and the number of workers, so every policy flies the same episodes, and serial and Ray runs give the same
numbers. (Task 0 uses the seed itself: with up to ``episodes_per_task`` episodes, the training scenario and
the default seed, the command line repeats the end-of-run evaluation exactly.)

Each checkpoint acts in ``evaluation_env`` of the environment it was trained in: the training aids
(``TRAINING_AIDS``: respawn on the floor, collision replay) switched off, the scenario and N replaced, all
else (physics, noise, reward coefficients) kept; the end-of-run evaluation uses the same function. The
policies are size-independent (K neighbour slots, padded and masked when N - 1 < K), so N may change
freely; an observation layout that differs from the checkpoint's (K, neighbour fields) is an error.
"""
from __future__ import annotations

import dataclasses
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from quad_env import EnvConfig, ObsLayout, VecQuadEnv
from quad_env.render import Episode, SwarmRecorder
from quad_env.scenarios import SCENARIO_REGISTRY, SCENARIOS
from swarm_appo.eval_tables import METRICS

Policy = Callable[[np.ndarray], np.ndarray]  # obs [M, D] -> actions [M, 4]

EXCLUDED_FROM_ALL = ("mix",)  # a random mixture of the others: its episodes already appear under their names

# EnvConfig fields that exist only to help training, and their value in every evaluation. Reward
# coefficients (shaping included) stay: they change no observation, and the tables report the paper's
# terms apart from the shaping ones (swarm_appo.eval_tables).
TRAINING_AIDS = {
    "respawn_on_floor": False,  # a crashed drone would be put back in the air
    "replay_prob": 0.0,  # collision replay (auto-resets only: evaluation never auto-resets, set for clarity)
}


def evaluation_env(train_env: EnvConfig, num_agents: Optional[int] = None,
                   scenario: Optional[str] = None) -> EnvConfig:
    """The environment a policy is judged in, by the command line and at the end of a run: its training
    environment without the training aids (``TRAINING_AIDS``), with N and the scenario replaced when given.
    The training config is not modified."""
    changes: Dict[str, object] = dict(TRAINING_AIDS)
    if num_agents is not None:
        changes["num_agents"] = num_agents
    if scenario is not None:
        changes["scenario"] = scenario
    return dataclasses.replace(train_env, **changes)


# ----------------------------------------------------------------------------------------------- policies
def model_policy(model: torch.nn.Module, deterministic: bool = True,
                 generator: Optional[torch.Generator] = None) -> Policy:
    """The actor's mean action (or a sample drawn with ``generator``), on CPU; the critic is not run.

    A recurrent policy (``model.core``) carries its core state from call to call, from zeros: one policy flies
    one batch of episodes from their first step (``fly_episodes``); a batch of another size starts afresh."""
    model = model.to("cpu").eval()
    state = model.initial_state(0)

    @torch.no_grad()
    def act(obs: np.ndarray) -> np.ndarray:
        nonlocal state
        if state.shape[0] != obs.shape[0]:
            state = model.initial_state(obs.shape[0])
        actions, _, _, state = model.act(torch.from_numpy(obs), deterministic, generator, with_value=False,
                                         state=state)  # [M, 4]
        return actions.numpy()

    return act


def random_policy(seed: int) -> Policy:
    rng = np.random.default_rng(seed)
    return lambda obs: rng.uniform(-1.0, 1.0, size=(obs.shape[0], 4)).astype(np.float32)


# ----------------------------------------------------------------------------------------------- episodes
def fly_episodes(env_cfg: EnvConfig, policy: Policy, num_episodes: int, seed: int,
                 record_first: bool = False, on_step: Optional[Callable[[], None]] = None
                 ) -> Tuple[List[Dict], Optional[SwarmRecorder]]:
    """``num_episodes`` swarm episodes, all in parallel (one swarm each), seeded: the same seed gives the
    same initial states whatever the policy. Returns the episode stats (swarm order) and, with
    ``record_first``, a recorder holding the first episode's trajectory. ``on_step`` is called after each
    control step (a progress bar)."""
    env = VecQuadEnv(env_cfg, num_envs=num_episodes, seed=seed, auto_reset=False)
    obs = env.reset()
    recorder = SwarmRecorder(env, 0) if record_first else None
    for _ in range(env_cfg.episode_steps):
        obs, _, term, trunc = env.step(policy(obs))
        if recorder is not None:
            recorder.record()
        if on_step is not None:
            on_step()
        if (term | trunc).all():
            break
    return env.pop_episode_stats(), recorder


def run_episodes(env_cfg: EnvConfig, policy: Policy, num_episodes: int, seed: int,
                 on_step: Optional[Callable[[], None]] = None) -> List[Dict]:
    """The stats of ``fly_episodes``."""
    return fly_episodes(env_cfg, policy, num_episodes, seed, on_step=on_step)[0]


# <prefix>/<name> of the end-of-run evaluation <- the table metric (swarm_appo.eval_tables.METRICS) it is
# the episode mean of, unscaled (success and reached rates as shares)
SUMMARY_METRICS = {m.name: key for key, m in METRICS.items()}


def summarize(episodes: List[Dict], prefix: str) -> Dict[str, float]:
    """``{prefix}/{name}``: the episode means of the tables' columns (those the episodes have the stats of)."""
    return {f"{prefix}/{name}": float(np.mean([METRICS[key].value(e) for e in episodes]))
            for name, key in SUMMARY_METRICS.items() if episodes and all(METRICS[key].available(e) for e in episodes)}


def default_eval_seed(train_seed: int) -> int:
    """Evaluation episodes are seeded apart from training's, and the same for the end-of-run and CLI evaluation."""
    return train_seed + 1_000_003


def compare_with_random(train_env: EnvConfig, model: torch.nn.Module, num_episodes: int = 8,
                        seed: int = 12345, progress: bool = False) -> Dict[str, float]:
    """``eval/*`` (trained, mean actions) and ``eval_random/*`` metrics on the same episodes, flown in
    ``evaluation_env(train_env)`` (the training aids off), as the command line flies them. ``progress``: a bar
    over the control steps of both (the end of a training run would otherwise be minutes of silence)."""
    env_cfg = evaluation_env(train_env)
    bar = on_step = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=2 * env_cfg.episode_steps, unit="step", dynamic_ncols=True,
                   desc=f"final evaluation: {num_episodes} episodes, policy then random actions")
        on_step = lambda: bar.update(1)
    try:
        out = summarize(run_episodes(env_cfg, model_policy(model), num_episodes, seed, on_step), "eval")
        out.update(summarize(run_episodes(env_cfg, random_policy(seed), num_episodes, seed, on_step), "eval_random"))
    finally:
        if bar is not None:
            bar.close()
    if out.get("eval_random/dist"):
        out["eval/dist_ratio_to_random"] = out["eval/dist"] / out["eval_random/dist"]
    return out


# ----------------------------------------------------------------------------------------------- checkpoints
@dataclass
class LoadedPolicy:
    """A checkpoint's policy: its run config, the model with its weights, and how to build another."""

    cfg: object  # swarm_appo.config.TrainConfig
    model: torch.nn.Module  # encoders.ActorCritic, weights loaded
    factory: Callable[[], torch.nn.Module]  # picklable constructor of the same (untrained) model
    agent_steps: int  # training steps of the checkpoint
    run_name: str


def load_checkpoint_policy(path: str) -> LoadedPolicy:
    """The policy of a checkpoint file, or of a run directory's latest valid checkpoint."""
    from swarm_appo.checkpoint import TrainingState
    from swarm_appo.config import config_from_dict
    from swarm_appo.model import model_factory

    if os.path.isdir(path):
        state, _ = TrainingState.load_latest(path)
        if state is None:
            raise FileNotFoundError(f"no valid checkpoint in {path}/checkpoints")
    elif os.path.exists(path):
        state = TrainingState.load(path)
    else:
        raise FileNotFoundError(f"checkpoint {path} does not exist (give a checkpoint file or a run directory)")
    cfg = config_from_dict(state.config)
    factory = model_factory(cfg.env.obs_layout(), cfg.model)
    model = factory()
    model.load_state_dict(state.learner["model"])
    return LoadedPolicy(cfg, model, factory, state.agent_steps, cfg.runner.name or run_dir_of(path).name)


def load_policy_from_checkpoint(path: str):
    """(TrainConfig, model) from a checkpoint file or a run directory (its latest valid checkpoint)."""
    loaded = load_checkpoint_policy(path)
    return loaded.cfg, loaded.model


def run_dir_of(path: str) -> Path:
    """The run directory a checkpoint belongs to (the path itself if it is a directory)."""
    p = Path(path)
    if p.is_dir():
        return p
    return p.parent.parent if p.parent.name == "checkpoints" else p.parent


@dataclass
class PolicySpec:
    """A policy to evaluate: a checkpoint's actor, or uniformly random actions (``factory`` None)."""

    label: str  # table label: run name and encoder, e.g. "quickstart (deepsets)"
    env: EnvConfig  # the environment it was trained in
    factory: Optional[Callable[[], torch.nn.Module]] = None  # picklable model constructor
    weights: Optional[Dict[str, torch.Tensor]] = None  # its state dict
    layout: Optional[ObsLayout] = None  # the observations it was trained on
    source: str = ""  # checkpoint path
    step: int = 0  # agent steps of the checkpoint
    seed: int = 0  # runner.seed of the run


def load_policy_specs(paths: Sequence[str]) -> List[PolicySpec]:
    """One spec per checkpoint, labelled ``run (encoder)`` (``run (encoder/symmetry)`` when the symmetry is not
    the encoder name's own); labels that clash (two checkpoints of one run) get the checkpoint's step,
    ``run@step (encoder)``, and then a counter."""
    loaded = [load_checkpoint_policy(str(p)) for p in paths]
    models = [_model_label(x.cfg.model) for x in loaded]
    labels = [f"{x.run_name} ({m})" for x, m in zip(loaded, models)]
    labels = [f"{x.run_name}@{x.agent_steps} ({m})" if labels.count(label) > 1 else label
              for x, m, label in zip(loaded, models, labels)]
    for label in set(labels):
        same = [i for i, other in enumerate(labels) if other == label]
        for n, i in enumerate(same if len(same) > 1 else []):
            labels[i] = f"{label} #{n + 1}"
    return [PolicySpec(label, x.cfg.env, x.factory, x.model.state_dict(), x.model.layout, str(p), x.agent_steps,
                       x.cfg.runner.seed) for label, x, p in zip(labels, loaded, paths)]


def _model_label(model) -> str:
    """``encoder``, or ``encoder/symmetry`` when a symmetry was set explicitly (deepsets/se3), followed by a
    recurrent core and a central critic when there are (mlp/none+gru+central: the rMAPPO row)."""
    label = model.encoder if model.symmetry is None else f"{model.encoder}/{model.symmetry}"
    extras = [getattr(model, "core", "none"), "central" if getattr(model, "critic", "local") == "central" else "none"]
    return label + "".join(f"+{x}" for x in extras if x != "none")


def random_spec(env: EnvConfig) -> PolicySpec:
    return PolicySpec("random actions", env, source="uniform in [-1, 1]")


# ----------------------------------------------------------------------------------------------- tasks
@dataclass(frozen=True)
class EvalTask:
    """``num_episodes`` episodes of one policy at one N in one scenario, all in one VecQuadEnv."""

    index: int  # position in the plan
    policy: int  # index into the policy list
    num_agents: int
    scenario: str
    chunk: int  # this task's index among the tasks of its (policy, N, scenario)
    num_episodes: int
    seed: int
    env: EnvConfig
    deterministic: bool
    record_first: bool  # keep the trajectory of the first episode (for a picture)


@dataclass
class TaskResult:
    task: EvalTask
    episodes: List[Dict]  # stats, in episode order
    trajectory: Optional[Episode]
    node_id: str = ""  # the Ray node that flew it ("" in this process)


def task_seed(seed: int, chunk: int) -> int:
    """Seed of the chunk-th task of every (policy, N, scenario): the seed itself for the first."""
    if chunk == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), int(chunk)]).generate_state(1)[0])


def resolve_scenarios(text: str, num_agents: Sequence[int], obstacles: bool = True) -> List[str]:
    """``"all"`` (every registered scenario but ``mix`` that fits every N and, for policies trained without
    ``env.obstacles``, does not need obstacles) or a comma-separated list (each one checked)."""
    if text.strip() == "all":
        names = [s for s in SCENARIOS if s not in EXCLUDED_FROM_ALL]
        return [s for s in names if SCENARIO_REGISTRY[s].min_agents <= min(num_agents)
                and (obstacles or not SCENARIO_REGISTRY[s].needs_obstacles)]
    names = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [s for s in names if s not in SCENARIO_REGISTRY]
    if unknown or not names:
        raise ValueError(f"unknown scenario(s) {unknown or [text]}; valid: {['all', *SCENARIOS]}")
    for s in names:
        need = SCENARIO_REGISTRY[s].min_agents
        if need > min(num_agents):
            raise ValueError(f"scenario {s!r} needs at least {need} drones, --num-agents has {min(num_agents)}")
    return list(dict.fromkeys(names))


def eval_env(spec: PolicySpec, num_agents: int, scenario: str) -> EnvConfig:
    return evaluation_env(spec.env, num_agents, scenario)


def check_layouts(specs: Sequence[PolicySpec], num_agents: Sequence[int], scenarios: Sequence[str]) -> None:
    """Every checkpoint must see the observation layout it was trained on. Building the environments here
    also compiles the numba kernels once, so the workers load them from the on-disk cache."""
    for spec in specs:
        if spec.layout is None:  # random actions: no observations read
            continue
        for n in num_agents:
            for s in scenarios:
                layout = VecQuadEnv(eval_env(spec, n, s), num_envs=1, seed=0).layout
                if layout != spec.layout:
                    raise ValueError(
                        f"checkpoint {spec.source} was trained on observations {spec.layout!r}, but scenario "
                        f"{s!r} with {n} drones gives {layout!r}; a policy carries over to any swarm size, "
                        "not to another observation layout (K, neighbour fields, obstacle field)")


def plan_tasks(specs: Sequence[PolicySpec], num_agents: Sequence[int], scenarios: Sequence[str], episodes: int,
               episodes_per_task: int, seed: int, deterministic: bool = True, pictures: bool = True
               ) -> List[EvalTask]:
    """Tasks in table order: policy, then N, then scenario, then chunk."""
    if episodes < 1 or episodes_per_task < 1:
        raise ValueError(f"episodes ({episodes}) and episodes per task ({episodes_per_task}) must be >= 1")
    tasks = []
    for p, spec in enumerate(specs):
        for n in num_agents:
            for s in scenarios:
                for chunk, first in enumerate(range(0, episodes, episodes_per_task)):
                    tasks.append(EvalTask(len(tasks), p, n, s, chunk, min(episodes_per_task, episodes - first),
                                          task_seed(seed, chunk), eval_env(spec, n, s), deterministic,
                                          pictures and chunk == 0))
    return tasks


def run_task(task: EvalTask, factory: Optional[Callable], weights: Optional[Dict], label: str = "") -> TaskResult:
    """Fly one task's episodes (the same code in this process and in a Ray actor)."""
    if factory is None:
        policy = random_policy(task.seed)
    else:
        model = factory()
        model.load_state_dict(weights)
        policy = model_policy(model, task.deterministic, torch.Generator().manual_seed(task.seed))
    stats, recorder = fly_episodes(task.env, policy, task.num_episodes, task.seed, task.record_first)
    trajectory = None
    if recorder is not None:
        title = f"{label}: {task.scenario}, {task.num_agents} drones, seed {task.seed}"
        trajectory = recorder.episode(stats[0], title)
    return TaskResult(task, stats, trajectory)


class EvalWorker:
    """A Ray actor (one core) that runs tasks."""

    def __init__(self):
        import ray
        torch.set_num_threads(1)
        self.node_id = ray.get_runtime_context().get_node_id()

    def run(self, task: EvalTask, factory, weights, label: str) -> TaskResult:
        return dataclasses.replace(run_task(task, factory, weights, label), node_id=self.node_id)


def run_tasks(tasks: Sequence[EvalTask], specs: Sequence[PolicySpec], workers: Optional[int],
              progress: bool = False, address: Optional[str] = None,
              placement: Optional[Dict] = None) -> List[TaskResult]:
    """Results in task order. ``workers`` 0: in this process, one task after another; else Ray actors, one
    core each: on a local Ray bound to 127.0.0.1 (started if none is running, shut down at the end), or, with
    ``address`` ("auto" or "<host>:<port>"), on the Ray cluster there, spread over its nodes. ``workers``
    None: one actor per CPU (of this machine, or of the whole cluster). ``placement``, when given, receives
    the number of actors started ("workers") and the Ray CPUs there were ("ray_cpus")."""
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=sum(t.num_episodes for t in tasks), unit="episode", dynamic_ncols=True, desc="evaluate")
    results: List[Optional[TaskResult]] = [None] * len(tasks)
    try:
        if workers == 0:
            if address is not None:
                raise ValueError("workers=0 runs in this process: it cannot use a Ray cluster (address)")
            for t in tasks:
                spec = specs[t.policy]
                results[t.index] = run_task(t, spec.factory, spec.weights, spec.label)
                if bar is not None:
                    bar.update(t.num_episodes)
        else:
            for r in _run_on_ray(tasks, specs, workers, address, placement if placement is not None else {}):
                results[r.task.index] = r
                if bar is not None:
                    bar.update(r.task.num_episodes)
    finally:
        if bar is not None:
            bar.close()
    return results


def _run_on_ray(tasks, specs, workers, address, placement):
    import ray
    from ray.util import ActorPool

    from swarm_appo.ray_sampling import init_local_ray, init_ray

    started = not ray.is_initialized()
    if address is None:
        init_local_ray(num_cpus=max(workers or 0, os.cpu_count() or 1))
    else:
        init_ray(address)
    actors = []
    try:
        cpus = int(ray.cluster_resources().get("CPU", 0))
        if workers is None:
            workers = max(cpus, 1)
        elif workers > cpus:
            warnings.warn(f"{workers} workers asked, Ray has {cpus} CPUs: using {max(cpus, 1)}", RuntimeWarning)
            workers = max(cpus, 1)
        placement.update(workers=workers, ray_cpus=cpus)
        weights = [ray.put(s.weights) if s.weights is not None else None for s in specs]
        # SPREAD: on a cluster the actors go to all nodes, not first fill the driver's
        actors = [ray.remote(num_cpus=1, max_restarts=0, scheduling_strategy="SPREAD")(EvalWorker).remote()
                  for _ in range(workers)]
        pool = ActorPool(actors)
        biggest_first = sorted(tasks, key=lambda t: (-t.num_agents * t.num_episodes, t.index))
        submit = lambda a, t: a.run.remote(t, specs[t.policy].factory, weights[t.policy], specs[t.policy].label)  # noqa: E731
        yield from pool.map_unordered(submit, biggest_first)
    finally:
        for a in actors:
            ray.kill(a)
        if started:
            ray.shutdown()


# ----------------------------------------------------------------------------------------------- command line
def parse_num_agents(text: str) -> List[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--num-agents must be integers separated by commas, e.g. 16,32,64,128; got {text!r}")
    if not values or min(values) < 1:
        raise ValueError(f"--num-agents must be integers >= 1, got {text!r}")
    return list(dict.fromkeys(values))


def _differing_env_keys(a: EnvConfig, b: EnvConfig) -> List[str]:
    ignored = ("num_agents", "scenario", "num_neighbors", "neighbor_obs")
    da, db = a.to_dict(), b.to_dict()
    return sorted(k for k in da if k not in ignored and da[k] != db.get(k))


def numbered_dir(base: Path) -> Path:
    """``base``, or ``base_2``, ``base_3``... if it exists: an evaluation never overwrites an earlier one."""
    candidate, n = base, 1
    while candidate.exists():
        n += 1
        candidate = base.with_name(f"{base.name}_{n}")
    return candidate
