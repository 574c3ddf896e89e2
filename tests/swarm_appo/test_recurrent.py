"""Recurrent policies (``model.core: gru | lstm``): the worker carries each drone's core state across fragments
and resets it at episode starts, the learner unrolls whole trajectories from the state stored with each fragment,
and a memory task that a feed-forward policy cannot solve is learned by a GRU policy with the real learner."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from encoders import ActorCritic
from quad_env import EnvConfig
from swarm_appo.config import AlgoConfig, ConfigError, load_config
from swarm_appo.evaluation import (evaluation_env, load_checkpoint_policy, load_policy_specs, model_policy,
                                   run_episodes)
from swarm_appo.export import export_actor, run_exported
from swarm_appo.learner import Learner, stack_fragments
from swarm_appo.model import model_factory
from swarm_appo.rollout import RolloutWorker
from swarm_appo.trainer import train


def tiny(tmp_path, name, **extra):
    base = {"env.num_agents": 2, "env.num_neighbors": 1, "env.episode_duration": 0.1, "runner.envs_per_worker": 2,
            "runner.num_workers": 1, "runner.serial": "true", "runner.total_agent_steps": 256,
            "runner.run_dir": str(tmp_path), "runner.name": name, "runner.checkpoint_every_s": 0,
            "algo.rollout": 16, "algo.batch_size": 32, "algo.num_epochs": 2, "model.encoder": "deepsets",
            "model.size": "small", "model.core": "gru", "model.core_size": 16, "wandb.mode": "disabled",
            "runner.final_eval_episodes": 2}
    base.update(extra)
    return load_config(None, [f"{k}={v}" for k, v in base.items()])


def worker_and_learner(cfg, seed=0):
    layout = cfg.env.obs_layout()
    torch.manual_seed(seed)
    worker = RolloutWorker(cfg.env, model_factory(layout, cfg.model), cfg.runner.envs_per_worker, cfg.algo.rollout,
                           seed=seed + 1)
    learner = Learner(model_factory(layout, cfg.model)(), cfg.algo, torch.device("cpu"), seed=seed)
    worker.set_weights(*learner.cpu_weights())  # lag 0: the worker acts with the learner's weights
    return worker, learner


def unroll(learner, frag, reset=True):
    """The learner's log-probs of a fragment, unrolled from its stored state (``reset=False``: never reset)."""
    t = {k: torch.as_tensor(v) for k, v in stack_fragments([frag]).items() if k != "num_agents"}
    done = t["terminated"] | t["truncated"]
    starts = torch.cat([torch.zeros_like(done[:1]), done[:-1]]) if reset else None
    with torch.no_grad():
        logp, _, _, _ = learner.model.evaluate_sequence(t["obs"], t["actions"], t["rnn_state"], starts)
    return logp.numpy(), done.numpy()


@pytest.mark.parametrize("core", ["gru", "lstm"])
def test_learner_and_worker_agree_on_log_probs_and_the_reset_matters(tmp_path, core):
    """Episodes of 10 control steps in 16-step fragments: every trajectory resets inside the first fragment.
    Unrolled from the stored state with resets, the learner reproduces the worker's log-probs; without the reset
    the steps after it differ (so this test fails if either side skips it). The second fragment starts from a
    carried, non-zero state, which the learner must use too."""
    cfg = tiny(tmp_path, "a", **{"model.core": core})
    worker, learner = worker_and_learner(cfg)
    first, second = worker.collect(), worker.collect()
    assert first["rnn_state"].shape == (4, learner.model.state_size) and not first["rnn_state"].any()
    assert np.abs(second["rnn_state"]).max() > 1e-3  # carried across fragments, not reset between them
    for frag in (first, second):
        logp, done = unroll(learner, frag)
        np.testing.assert_allclose(logp, frag["log_probs"], rtol=0, atol=2e-5)
    logp_no_reset, done = unroll(learner, first, reset=False)
    t_reset = int(np.flatnonzero(done[:, 0])[0]) + 1  # first step of the second episode
    assert np.abs(logp_no_reset[t_reset:] - first["log_probs"][t_reset:]).max() > 1e-3
    np.testing.assert_allclose(logp_no_reset[:t_reset], first["log_probs"][:t_reset], rtol=0, atol=2e-5)


def test_truncation_bootstraps_with_the_state_that_reached_the_final_observation(tmp_path):
    """The learner's value of a truncated step's final observation uses the core state after that step (before
    the reset): the same value a one-step critic call gives from the unrolled state; a zero state differs."""
    cfg = tiny(tmp_path, "b")
    worker, learner = worker_and_learner(cfg)
    frag = worker.collect()
    t = {k: torch.as_tensor(v) for k, v in stack_fragments([frag]).items() if k != "num_agents"}
    done = t["terminated"] | t["truncated"]
    starts = torch.cat([torch.zeros_like(done[:1]), done[:-1]])
    model = learner.model
    with torch.no_grad():
        _, _, _, states = model.evaluate_sequence(t["obs"], t["actions"], t["rnn_state"], starts)
        step, col = t["final_idx"][0].tolist()
        final = t["final_obs"][:1]
        with_state = model.get_value(final, None, states[step, col][None])
        zero_state = model.get_value(final, None, model.initial_state(1))
        # replay the column step by step with act(): the state after `step` is what the unroll holds
        state = t["rnn_state"][col][None]
        for s in range(step + 1):
            state = torch.where(starts[s, col], torch.zeros_like(state), state)
            state = model.act(t["obs"][s, col][None], True, with_value=False, state=state)[3]
    torch.testing.assert_close(states[step, col][None], state, rtol=0, atol=1e-5)
    assert abs(float(with_state - zero_state)) > 1e-5


def memory_fragment(model, cues, T, L, generator, version):
    """A memory task: a cue c = +-1 is shown at the first step of each L-step episode only (in ``rel_goal[0]``),
    every other observation is zeros; the reward at every step is -mean((a - c)^2) over the 4 action entries.
    A feed-forward policy sees nothing after the first step, so its best later action is 0 (reward -1)."""
    B = cues.shape[1]
    D = model.layout.dim
    state = model.initial_state(B)
    obs = np.zeros((T, B, D), np.float32)
    actions = np.zeros((T, B, 4), np.float32)
    logp = np.zeros((T, B), np.float32)
    rewards = np.zeros((T, B), np.float32)
    done = np.zeros((T, B), bool)
    rnn_state = state.numpy().copy()
    for t in range(T):
        cue = cues[t // L]  # [B]
        if t % L == 0:
            obs[t, :, 0] = cue
        with torch.no_grad():
            a, lp, _, state = model.act(torch.from_numpy(obs[t]), generator=generator, with_value=False, state=state)
        actions[t], logp[t] = a.numpy(), lp.numpy()
        rewards[t] = -((a.numpy() - cue[:, None]) ** 2).mean(1)
        if t % L == L - 1:
            done[t] = True
            state = model.initial_state(B)
    return dict(obs=obs, actions=actions, log_probs=logp, values=np.zeros((T, B), np.float32), rewards=rewards,
                terminated=done, truncated=np.zeros((T, B), bool), final_obs=np.zeros((0, D), np.float32),
                final_idx=np.zeros((0, 2), np.int64), last_obs=np.zeros((B, D), np.float32),
                policy_version=np.full(T, version, np.int64), rnn_state=rnn_state, num_agents=1)


def train_memory(core: str, iterations: int = 120, seed: int = 0) -> float:
    """Mean |a - c| of the mean action over the steps after the cue, after ``iterations`` learner steps."""
    layout = EnvConfig(num_agents=1, num_neighbors=1, neighbor_obs="pos_vel").obs_layout()
    torch.manual_seed(seed)
    model = ActorCritic(layout, encoder="mlp", size="small", core=core, core_size=32, init_log_std=-0.5,
                        init_actor_out_scale=0.1)
    algo = AlgoConfig(lr=3e-3, rollout=16, batch_size=16 * 16, num_epochs=2, gamma=0.9)
    learner = Learner(model, algo, torch.device("cpu"), seed=seed)
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(seed)
    T, L, B = 16, 8, 32
    for _ in range(iterations):
        cues = rng.choice([-1.0, 1.0], size=(T // L, B)).astype(np.float32)
        learner.train([memory_fragment(model, cues, T, L, gen, learner.version)])
    cues = rng.choice([-1.0, 1.0], size=(1, 64)).astype(np.float32)
    state, errors = model.initial_state(64), []
    with torch.no_grad():
        for t in range(L):
            obs = torch.zeros(64, layout.dim)
            if t == 0:
                obs[:, 0] = torch.from_numpy(cues[0])
            a, _, _, state = model.act(obs, deterministic=True, with_value=False, state=state)
            if t > 0:
                errors.append((a - torch.from_numpy(cues[0])[:, None]).abs().mean().item())
    return float(np.mean(errors))


def test_a_gru_policy_learns_a_memory_task_that_a_feed_forward_policy_cannot(one_torch_thread):
    gru = train_memory("gru")
    feed_forward = train_memory("none")
    assert gru < 0.35 and feed_forward > 0.8, (gru, feed_forward)


def test_recurrent_run_resumes_evaluates_at_another_n_and_exports_with_its_state(tmp_path):
    cfg = tiny(tmp_path, "r", **{"model.critic": "central", "algo.value_clip": 0.5})  # rMAPPO-like: GRU + central
    first = train(cfg, progress=False)
    assert "core: gru" in (first.run_dir / "config.yaml").read_text()
    resumed = train(tiny(tmp_path, "r", **{"model.critic": "central", "algo.value_clip": 0.5,
                                           "runner.total_agent_steps": 512}),
                    resume_dir=str(first.run_dir), progress=False)
    assert resumed.policy_version > first.policy_version
    loaded = load_checkpoint_policy(str(first.run_dir))
    spec, = load_policy_specs([str(first.run_dir)])
    assert spec.label == "r (deepsets+gru+central)"  # the evaluation tables name the core and the critic
    stats = run_episodes(evaluation_env(loaded.cfg.env, num_agents=3), model_policy(loaded.model), 2, seed=0)
    assert len(stats) == 2 and all(np.isfinite(s["return"]) for s in stats)

    paths = export_actor(loaded.model, tmp_path / "export", loaded.cfg.env, formats=("torchscript",))
    sidecar = json.loads(paths["sidecar"].read_text())
    S = loaded.model.state_sizes[0]
    assert sidecar["state"]["shape"] == ["batch", S] and sidecar["state"]["core"] == "gru"
    # two steps through the exported file, feeding state_out back, match the model's own recurrence
    obs = np.random.default_rng(0).normal(size=(2, 5, loaded.model.layout.dim)).astype(np.float32)
    obs[..., -loaded.model.layout.num_neighbors:] = 1.0
    state, ref_state = np.zeros((5, S), np.float32), loaded.model.initial_state(5)
    for k in range(2):
        actions, state = run_exported("torchscript", paths["torchscript"], obs[k], state)
        with torch.no_grad():
            ref, _, _, ref_state = loaded.model.act(torch.from_numpy(obs[k]), True, with_value=False,
                                                    state=ref_state)
        np.testing.assert_allclose(actions, ref.numpy(), rtol=0, atol=1e-4)
    assert np.abs(state).max() > 0


def test_core_options_are_checked_with_the_config(tmp_path):
    with pytest.raises(ConfigError, match=r"model\.core must be one of \['none', 'gru', 'lstm'\], got 'rnn'"):
        tiny(tmp_path, "x", **{"model.core": "rnn"})
    with pytest.raises(ConfigError, match=r"model\.core_size must be >= 1"):
        tiny(tmp_path, "x", **{"model.core_size": 0})
    model = ActorCritic(EnvConfig(num_agents=2, num_neighbors=1).obs_layout(), size="small", core="gru")
    with pytest.raises(ValueError, match="needs the core state"):
        model.act(torch.zeros(2, model.layout.dim))
