"""Policy evaluation: run whole episodes with a policy (or random actions) and average the swarm metrics.

Used at the end of every training run to show whether it learned: the trained policy's mean distance
to goal against a uniformly random policy's, on the same seeds.
"""
from __future__ import annotations

from typing import Callable, Dict, List

import numpy as np
import torch

from quad_env import EnvConfig, VecQuadEnv

Policy = Callable[[np.ndarray], np.ndarray]  # obs [M, D] -> actions [M, 4]


def model_policy(model: torch.nn.Module, deterministic: bool = True) -> Policy:
    """The actor's mean action (or a sample), on CPU."""
    model = model.to("cpu").eval()

    @torch.no_grad()
    def act(obs: np.ndarray) -> np.ndarray:
        actions, _, _ = model.act(torch.from_numpy(obs), deterministic=deterministic)
        return actions.numpy()

    return act


def random_policy(seed: int) -> Policy:
    rng = np.random.default_rng(seed)
    return lambda obs: rng.uniform(-1.0, 1.0, size=(obs.shape[0], 4)).astype(np.float32)


def run_episodes(env_cfg: EnvConfig, policy: Policy, num_episodes: int, seed: int) -> List[Dict]:
    """``num_episodes`` swarm episodes, all in parallel (one swarm each), seeded: the same seed gives the
    same initial states whatever the policy, so two policies are compared on the same episodes."""
    env = VecQuadEnv(env_cfg, num_envs=num_episodes, seed=seed, auto_reset=False)
    obs = env.reset()
    for _ in range(env_cfg.episode_steps):
        obs, _, term, trunc = env.step(policy(obs))
        if (term | trunc).all():
            break
    return env.pop_episode_stats()


def summarize(episodes: List[Dict], prefix: str) -> Dict[str, float]:
    keys = {"return": "reward", "dist_last_5s": "dist", "dist_final": "dist_final",
            "collisions_after_grace": "collisions", "success_rate": "success_rate",
            "inter_collision_rate": "inter_collision_rate"}
    return {f"{prefix}/{name}": float(np.mean([e[k] for e in episodes])) for k, name in keys.items()
            if episodes and k in episodes[0]}


def default_eval_seed(train_seed: int) -> int:
    """Evaluation episodes are seeded apart from training's, and the same for the end-of-run and CLI evaluation."""
    return train_seed + 1_000_003


def compare_with_random(env_cfg: EnvConfig, model: torch.nn.Module, num_episodes: int = 8,
                        seed: int = 12345) -> Dict[str, float]:
    """``eval/*`` (trained, mean actions) and ``eval_random/*`` metrics on the same episodes."""
    out = summarize(run_episodes(env_cfg, model_policy(model), num_episodes, seed), "eval")
    out.update(summarize(run_episodes(env_cfg, random_policy(seed), num_episodes, seed), "eval_random"))
    if out.get("eval_random/dist"):
        out["eval/dist_ratio_to_random"] = out["eval/dist"] / out["eval_random/dist"]
    return out


def load_policy_from_checkpoint(path: str):
    """(TrainConfig, model) from a checkpoint file or a run directory (its latest valid checkpoint)."""
    import os

    from quad_env import ObsLayout
    from swarm_appo.checkpoint import load_checkpoint, load_latest_checkpoint
    from swarm_appo.config import config_from_dict
    from swarm_appo.model import model_factory

    if os.path.isdir(path):
        state, found = load_latest_checkpoint(path)
        if state is None:
            raise FileNotFoundError(f"no valid checkpoint in {path}/checkpoints")
    else:
        state = load_checkpoint(path)
    cfg = config_from_dict(state["config"])
    model = model_factory(ObsLayout(cfg.env.num_neighbors, cfg.env.neighbor_obs), cfg.model)()
    model.load_state_dict(state["learner"]["model"])
    return cfg, model


def main(argv=None) -> int:
    """``python -m swarm_appo.evaluate --checkpoint runs/quickstart``: trained vs random policy."""
    import argparse
    import dataclasses

    p = argparse.ArgumentParser(prog="swarm-eval", description=main.__doc__)
    p.add_argument("--checkpoint", required=True, help="checkpoint file or run directory")
    p.add_argument("--episodes", type=int, default=8, help="seeded swarm episodes per policy")
    p.add_argument("--num-agents", type=int, default=None, help="swarm size (default: as trained)")
    p.add_argument("--scenario", default=None, help="scenario (default: as trained)")
    p.add_argument("--seed", type=int, default=None,
                   help="episode seed (default: the one the end-of-run evaluation used)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    cfg, model = load_policy_from_checkpoint(args.checkpoint)
    env_cfg = dataclasses.replace(cfg.env, **{k: v for k, v in (("num_agents", args.num_agents),
                                                                ("scenario", args.scenario)) if v is not None})
    seed = default_eval_seed(cfg.runner.seed) if args.seed is None else args.seed
    result = compare_with_random(env_cfg, model, args.episodes, seed)
    for k in sorted(result):
        print(f"{k:32s} {result[k]:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
