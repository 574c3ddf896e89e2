"""The centralised critic (``model.critic: central``, MAPPO): what it sees, what it leaves alone, how the learner
feeds it, and that it can learn what a local critic cannot."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from encoders import ActorCritic, swarm_observations
from quad_env import EnvConfig
from swarm_appo.config import ConfigError, load_config
from swarm_appo.evaluation import evaluation_env, load_checkpoint_policy, model_policy, run_episodes
from swarm_appo.learner import Learner, stack_fragments, swarm_members
from swarm_appo.model import model_factory
from swarm_appo.rollout import RolloutWorker
from swarm_appo.trainer import train

LAYOUT = EnvConfig(num_agents=4, num_neighbors=1).obs_layout()  # each drone sees 1 of its 3 swarm mates


def random_swarms(E: int, N: int, seed: int = 0) -> torch.Tensor:
    """Observations of E swarms of N drones, rows swarm by swarm: ``[E*N, D]`` (float64, valid rotations)."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(E * N, LAYOUT.dim, generator=g, dtype=torch.float64)
    q, _ = torch.linalg.qr(torch.randn(E * N, 3, 3, generator=g, dtype=torch.float64))
    obs[:, 6:15] = q.reshape(E * N, 9)
    obs[:, LAYOUT.dim - LAYOUT.num_neighbors:] = 1.0  # mask: every neighbour slot real
    return obs


def central_model(**kw) -> ActorCritic:
    torch.manual_seed(0)
    return ActorCritic(LAYOUT, encoder="deepsets", size="small", critic="central", **kw).double()


def test_swarm_observations_give_each_drone_its_own_swarm():
    obs = torch.arange(6 * 2, dtype=torch.float64).reshape(6, 2)  # 2 swarms of 3 drones
    swarm = swarm_observations(obs, 3)  # [6, 3, 2]
    for b in range(6):
        e = b // 3
        assert torch.equal(swarm[b], obs[3 * e:3 * e + 3])
    with pytest.raises(ValueError, match="whole swarms of 4"):
        swarm_observations(obs, 4)
    cols = torch.tensor([4, 0, 5])
    assert swarm_members(cols, 3).tolist() == [[3, 4, 5], [0, 1, 2], [3, 4, 5]]


def test_central_value_is_invariant_to_the_drones_order_and_reads_every_swarm_mate():
    model = central_model()
    obs = random_swarms(2, 4)
    swarm = swarm_observations(obs, 4)
    with torch.no_grad():
        v = model.get_value(obs, swarm)
        shuffled = model.get_value(obs, swarm[:, torch.tensor([2, 0, 3, 1])])
        moved = swarm.clone()
        moved[:, 3, :3] += 1.0  # drone 3 of each swarm moves (relative to its goal): every swarm mate's value changes
        v_moved = model.get_value(obs, moved)
    np.testing.assert_allclose(shuffled.numpy(), v.numpy(), rtol=0, atol=1e-12)
    assert (v_moved - v).abs().min() > 1e-6, (v_moved - v)
    with pytest.raises(ValueError, match="needs swarm_obs"):
        model.get_value(obs)


def test_the_actor_is_the_same_with_a_central_critic():
    """Same seed, same actor weights and actions: the central critic adds parameters on the critic side only."""
    torch.manual_seed(0)
    local = ActorCritic(LAYOUT, encoder="deepsets", size="small").double()
    central = central_model()
    extra = set(central.state_dict()) - set(local.state_dict())
    assert extra and all(k.startswith("swarm_state.") for k in extra), extra
    central.load_state_dict({**central.state_dict(), **{k: v for k, v in local.state_dict().items()
                                                        if not k.startswith("critic_head")}})
    obs = random_swarms(2, 4, seed=1)
    with torch.no_grad():
        a_local, lp_local, _ = local.act(obs, deterministic=True, with_value=False)
        a_central, lp_central, _ = central.act(obs, deterministic=True, with_value=False)  # no swarm needed to act
    assert torch.equal(a_local, a_central) and torch.equal(lp_local, lp_central)


def test_a_central_critic_fits_what_a_local_critic_cannot_see():
    """Target: how far the drone's swarm mates are from their goals, on average. Each drone observes one of its
    three mates, so the local critic can explain only part of it; the central critic reads all of them."""
    obs = random_swarms(64, 4, seed=2).float()
    swarm = swarm_observations(obs, 4)
    target = swarm[:, :, :3].norm(dim=-1).mean(1)  # [B]
    target = (target - target.mean()) / target.std()

    def fit(model, swarm_obs):
        opt = torch.optim.Adam(model.parameters(), lr=3e-3)
        for _ in range(300):
            loss = ((model.get_value(obs, swarm_obs) - target) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        return float(loss.detach())

    torch.manual_seed(0)
    local = fit(ActorCritic(LAYOUT, encoder="deepsets", size="small"), None)
    torch.manual_seed(0)
    central = fit(ActorCritic(LAYOUT, encoder="deepsets", size="small", critic="central"), swarm)
    assert central < 0.1 and local > 3 * central, (local, central)


def tiny(tmp_path, name, **extra):
    base = {"env.num_agents": 3, "env.num_neighbors": 1, "env.episode_duration": 0.12, "runner.envs_per_worker": 2,
            "runner.num_workers": 1, "runner.serial": "true", "runner.total_agent_steps": 384,
            "runner.run_dir": str(tmp_path), "runner.name": name, "runner.checkpoint_every_s": 0,
            "algo.rollout": 16, "algo.batch_size": 32, "algo.num_epochs": 2, "model.encoder": "deepsets",
            "model.size": "small", "model.critic": "central", "wandb.mode": "disabled",
            "runner.final_eval_episodes": 2}
    base.update(extra)
    return load_config(None, [f"{k}={v}" for k, v in base.items()])


def test_learner_bootstraps_truncations_from_the_whole_swarms_final_observations(tmp_path):
    """Episodes of 12 control steps in 16-step fragments: every column truncates inside the fragment, and the
    critic's bootstrap input is the true final observation of each swarm mate, as the env reported it."""
    cfg = tiny(tmp_path, "t")
    torch.manual_seed(0)
    worker = RolloutWorker(cfg.env, model_factory(cfg.env.obs_layout(), cfg.model), 2, 16, seed=3)
    frag = worker.collect()
    assert frag["num_agents"] == 3 and frag["final_idx"].shape[0] == 6  # 2 swarms x 3 drones truncated once
    learner = Learner(model_factory(cfg.env.obs_layout(), cfg.model)(), cfg.algo, torch.device("cpu"), seed=0)
    t, _, _ = learner._to_tensors([frag])
    fi = t["final_idx"][[1, 4]]  # one truncated step of each swarm
    got = learner._final_swarm(t, fi)  # [2, 3, D]
    for k, (step, col) in enumerate(fi.tolist()):
        e = col // 3
        for j in range(3):
            row = [m for m, (s, c) in enumerate(frag["final_idx"].tolist()) if s == step and c == 3 * e + j]
            np.testing.assert_array_equal(got[k, j].numpy(), frag["final_obs"][row[0]])
    with pytest.raises(ValueError, match="different swarm sizes"):
        stack_fragments([frag, dict(frag, num_agents=4)])


def test_serial_training_with_a_central_critic_resumes_and_flies_zero_shot_at_another_n(tmp_path):
    cfg = tiny(tmp_path, "c", **{"algo.value_clip": 0.5})  # value clipping: workers store central values too
    first = train(cfg, progress=False)
    assert "critic: central" in (first.run_dir / "config.yaml").read_text()
    resumed = train(tiny(tmp_path, "c", **{"runner.total_agent_steps": 768}), resume_dir=str(first.run_dir),
                    progress=False)
    assert resumed.agent_steps >= 768 and resumed.policy_version > first.policy_version
    loaded = load_checkpoint_policy(str(first.run_dir))
    assert loaded.model.central and any(k.startswith("swarm_state.") for k in loaded.model.state_dict())
    env = evaluation_env(loaded.cfg.env, num_agents=5)  # only the actor flies: any swarm size
    stats = run_episodes(env, model_policy(loaded.model), num_episodes=2, seed=0)
    assert len(stats) == 2 and all(np.isfinite(s["return"]) and not s["diverged"] for s in stats)


def test_unknown_critic_is_a_config_error_naming_the_key(tmp_path):
    with pytest.raises(ConfigError, match=r"model\.critic .*'local', 'central'.*'centre'"):
        tiny(tmp_path, "x", **{"model.critic": "centre"})
