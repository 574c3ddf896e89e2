"""End-to-end behaviour of the trainer: learner updates, lag masking, reproducibility, Ray runs,
resume, rollout-worker faults. Sizes are tiny so the whole file runs in about a minute on 2 cores."""
from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import ray
import torch

from swarm_appo.checkpoint import load_checkpoint
from swarm_appo.config import load_config
from swarm_appo.learner import Learner, stack_fragments
from swarm_appo.metrics import wait_for_wandb_history
from swarm_appo.model import model_factory
from swarm_appo.rollout import RolloutWorker
from swarm_appo.ray_sampling import RaySampler, StallPolicy, WeightsStore, init_local_ray
from swarm_appo.trainer import train
from swarm_appo.vtrace import vtrace


def tiny_overrides(run_dir: Path, name: str, **extra) -> list:
    base = {
        "env.num_agents": 2, "env.num_neighbors": 1, "env.episode_duration": 0.3,
        "runner.envs_per_worker": 2, "runner.num_workers": 1, "runner.serial": "true",
        "runner.total_agent_steps": 320, "runner.run_dir": str(run_dir), "runner.name": name,
        "runner.checkpoint_every_s": 0, "algo.rollout": 16, "algo.batch_size": 64, "algo.num_epochs": 2,
        "model.encoder": "deepsets", "wandb.mode": "disabled", "runner.final_eval_episodes": 2,
    }
    base.update(extra)
    return [f"{k}={v}" for k, v in base.items()]


def tiny_config(run_dir: Path, name: str, **extra):
    return load_config(None, tiny_overrides(run_dir, name, **extra))


def read_metrics(run_dir: Path) -> list:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def fixed_fragments(cfg, seed=0, n=2):
    """Fragments from a worker whose weights are the ones ``make_learner(cfg, seed)`` starts with."""
    layout = cfg.env.obs_layout()
    torch.manual_seed(seed)
    worker = RolloutWorker(cfg.env, model_factory(layout, cfg.model), cfg.runner.envs_per_worker,
                           cfg.algo.rollout, seed)
    worker.set_weights(0, worker.model.state_dict())
    return [worker.collect() for _ in range(n)]


def make_learner(cfg, seed=0):
    layout = cfg.env.obs_layout()
    torch.manual_seed(seed)
    return Learner(model_factory(layout, cfg.model)(), cfg.algo, torch.device("cpu"), seed=seed)


# --------------------------------------------------------------------------- sampling
def test_acting_without_the_critic_gives_the_same_fragment(tmp_path):
    cfg = tiny_config(tmp_path, "v")
    layout = cfg.env.obs_layout()
    make = model_factory(layout, cfg.model)
    torch.manual_seed(0)
    weights = make().state_dict()
    frags = {}
    for store in (False, True):
        worker = RolloutWorker(cfg.env, make, 2, 16, seed=5, store_values=store)
        worker.set_weights(0, weights)
        frags[store] = worker.collect()
    for key in ("obs", "actions", "log_probs", "rewards", "truncated"):
        np.testing.assert_array_equal(frags[False][key], frags[True][key])
    assert not frags[False]["values"].any() and frags[True]["values"].any()


# --------------------------------------------------------------------------- learner
def test_stack_fragments_offsets_truncation_columns(tmp_path):
    cfg = tiny_config(tmp_path, "s")
    frags = fixed_fragments(cfg, n=2)  # steps 0-15 and 16-31; the 30-step episode truncates at step 29
    B = frags[0]["rewards"].shape[1]
    assert frags[0]["final_idx"].shape[0] == 0 and frags[1]["final_idx"].shape[0] == B
    np.testing.assert_array_equal(frags[1]["final_idx"][:, 0], 13)  # step 29 = row 13 of fragment 2
    batch = stack_fragments(frags[::-1])  # fragment 2 first: its columns stay 0..B-1
    assert batch["obs"].shape == (16, 2 * B, frags[0]["obs"].shape[-1])
    t, b = batch["final_idx"].T
    assert batch["truncated"][t, b].all() and batch["truncated"].sum() == len(t) == B
    np.testing.assert_array_equal(np.sort(b), np.arange(B))
    batch = stack_fragments(frags)  # fragment 2 second: its columns shift by B
    np.testing.assert_array_equal(np.sort(batch["final_idx"][:, 1]), np.arange(B, 2 * B))
    np.testing.assert_array_equal(batch["final_obs"], frags[1]["final_obs"])
    # the true final observation is not the reset observation that follows it
    assert not np.allclose(frags[1]["final_obs"], frags[1]["obs"][14])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_learner_steps_improve_the_objective_on_a_fixed_batch(tmp_path, seed):
    """With targets frozen before the update: the clipped surrogate rises and the value error falls.

    gamma = 0 makes the value targets the rewards themselves: with a bootstrap they would move with the
    critic (TD), and "the error to the old targets" would not be what the learner minimises.
    """
    cfg = tiny_config(tmp_path, "l", **{"algo.lr": 1e-4, "algo.num_epochs": 1, "model.normalize_obs": "false",
                                         "algo.gamma": 0.0, "env.episode_duration": 5.0})
    frags = fixed_fragments(cfg, seed)
    learner = make_learner(cfg, seed)  # on-policy: the fragments' behaviour weights
    batch = {k: torch.as_tensor(v) for k, v in stack_fragments(frags).items()}
    T, B, D = batch["obs"].shape
    obs, actions = batch["obs"].reshape(T * B, D), batch["actions"].reshape(T * B, 4)
    with torch.no_grad():
        logp0, _, v0 = learner.model.evaluate(obs, actions)
        targets = vtrace(torch.zeros(T, B), torch.full((T, B), cfg.algo.gamma), batch["rewards"],
                         v0.reshape(T, B), learner.model.get_value(batch["last_obs"]))
        adv = targets.pg_advantages.reshape(-1)
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)

    def objective():
        with torch.no_grad():
            logp, _, v = learner.model.evaluate(obs, actions)
            ratio = torch.exp(logp - logp0)
            surrogate = torch.min(ratio * adv, torch.clamp(ratio, 0.8, 1.2) * adv).mean()
            return float(surrogate), float(((v - targets.vs.reshape(-1)) ** 2).mean())

    surrogate0, value_err0 = objective()
    for _ in range(3):
        learner.train(frags)
    surrogate1, value_err1 = objective()
    assert surrogate1 > surrogate0 and value_err1 < value_err0, (surrogate0, surrogate1, value_err0, value_err1)


def test_policy_lag_beyond_bound_is_masked_out(tmp_path):
    cfg = tiny_config(tmp_path, "m", **{"algo.max_policy_lag": 3})
    frags = fixed_fragments(cfg)
    learner = make_learner(cfg)
    learner.version = 10  # the fragments were produced by version 0: lag 10 > 3
    params = [p.detach().clone() for p in learner.model.parameters()]
    stats = learner.train(frags)
    assert stats["lag/min"] == 10 and stats["lag/max"] == 10 and stats["lag/mean"] == 10
    assert stats["lag/masked_fraction"] == 1.0
    for p, q in zip(params, learner.model.parameters()):
        torch.testing.assert_close(p, q, rtol=0, atol=0)  # nothing stale reached the weights
    # within the bound the same data does move the weights
    learner.version = 3
    learner.train(frags)
    assert any(not torch.equal(p, q) for p, q in zip(params, learner.model.parameters()))


def test_non_finite_loss_skips_the_update(tmp_path):
    cfg = tiny_config(tmp_path, "n")
    frags = fixed_fragments(cfg)
    frags[0]["rewards"][3, 0] = np.nan
    learner = make_learner(cfg)
    params = [p.detach().clone() for p in learner.model.parameters()]
    with pytest.warns(UserWarning, match="skipped"):
        learner.train(frags)
    assert learner.skipped_updates > 0
    for p, q in zip(params, learner.model.parameters()):
        assert torch.isfinite(q).all()
    # minibatches without the NaN column still update; the weights never become NaN


# --------------------------------------------------------------------------- serial runs
def test_serial_run_is_bit_reproducible_by_seed(tmp_path):
    results = []
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        res = train(tiny_config(tmp_path, name, **{"runner.seed": seed}), progress=False)
        state = load_checkpoint(res.checkpoint)
        records = read_metrics(res.run_dir)
        results.append((state["learner"]["model"], [r.get("losses/total_loss") for r in records],
                        [r.get("charts/episode_reward") for r in records]))
    (wa, la, ra), (wb, lb, rb), (wc, lc, rc) = results
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    assert la == lb and ra == rb
    assert any(not torch.equal(wa[k], wc[k]) for k in wa), "a different seed must give a different run"


def test_run_dir_contents_and_resume_continues_counters(tmp_path):
    cfg = tiny_config(tmp_path, "r", **{"wandb.mode": "offline"})
    first = train(cfg, progress=False)
    run_dir = first.run_dir
    assert (run_dir / "config.yaml").exists()
    assert list((run_dir / "checkpoints").glob("ckpt_*.pt"))
    assert list((run_dir / "wandb").glob("offline-run-*")), "an offline wandb run must be in the run dir"
    records = read_metrics(run_dir)
    assert records[-1]["global_step"] == first.agent_steps
    wandb_id = (run_dir / "wandb_id.txt").read_text().strip()

    resumed_cfg = tiny_config(tmp_path, "r", **{"wandb.mode": "offline", "runner.total_agent_steps": 640})
    second = train(resumed_cfg, resume_dir=str(run_dir), progress=False)
    assert second.agent_steps >= 640 and second.policy_version > first.policy_version
    new_records = read_metrics(run_dir)[len(records):]
    assert new_records and new_records[0]["global_step"] > first.agent_steps
    # one history: a new wandb run that replays metrics.jsonl, then continues (swarm_appo.metrics)
    new_id = (run_dir / "wandb_id.txt").read_text().strip()
    assert new_id != wandb_id
    newest, = (run_dir / "wandb").glob(f"offline-run-*-{new_id}")
    expected = [r["global_step"] for r in read_metrics(run_dir)]
    steps = [h["global_step"] for h in wait_for_wandb_history(newest / f"run-{new_id}.wandb", len(expected))]
    assert steps == expected  # each step once, none missing


def test_new_run_never_overwrites_an_old_run(tmp_path):
    first = train(tiny_config(tmp_path, "o"), progress=False)
    before = {p.name: p.read_bytes() for p in (first.run_dir / "checkpoints").iterdir()}
    second = train(tiny_config(tmp_path, "o"), progress=False)
    assert first.run_dir == tmp_path / "o" and second.run_dir == tmp_path / "o_2"
    assert {p.name: p.read_bytes() for p in (first.run_dir / "checkpoints").iterdir()} == before


# --------------------------------------------------------------------------- Ray
@pytest.fixture(scope="module")
def local_ray():
    init_local_ray(num_cpus=2)
    yield
    ray.shutdown()


def test_cluster_addresses_are_checked_before_ray_is_asked():
    import socket

    from swarm_appo.ray_sampling import check_reachable
    with socket.socket() as server:  # something listening: accepted
        server.bind(("127.0.0.1", 0))
        server.listen()
        check_reachable(f"127.0.0.1:{server.getsockname()[1]}")
    with pytest.raises(ConnectionError, match="no Ray cluster answers at 127.0.0.1:9"):
        check_reachable("127.0.0.1:9")
    with pytest.raises(ConnectionError, match="'auto' or '<host>:<port>'"):
        check_reachable("head-node")
    check_reachable("auto")  # left to Ray


def test_local_ray_is_on_loopback_only(local_ray):
    """The node's address, the GCS the driver talks to, and every worker's node are 127.0.0.1 (Ray would
    put the machine's network address there for a node_ip_address of 127.0.0.1)."""
    context = ray.get_runtime_context()
    assert context.gcs_address.startswith("127.0.0.1:")
    assert {n["NodeManagerAddress"] for n in ray.nodes()} == {"127.0.0.1"}
    assert ray.get(ray.remote(lambda: ray.util.get_node_ip_address()).remote()) == "127.0.0.1"


def test_ray_run_with_two_actors_writes_run_dir(tmp_path, local_ray):
    cfg = tiny_config(tmp_path, "ray", **{"runner.serial": "false", "runner.num_workers": 2,
                                           "runner.total_agent_steps": 640, "wandb.mode": "offline",
                                           "algo.max_policy_lag": 2})
    res = train(cfg, progress=False)
    assert res.agent_steps >= 640
    assert list((res.run_dir / "checkpoints").glob("ckpt_*.pt"))
    assert list((res.run_dir / "wandb").glob("offline-run-*"))
    records = read_metrics(res.run_dir)
    *records, final = records
    assert all({"lag/min", "lag/mean", "lag/max", "losses/policy_loss", "perf/worker_restarts",
                "perf/worker_stalls"} <= set(r)
               for r in records)
    assert {"eval/dist", "eval_random/dist", "eval/dist_ratio_to_random"} <= set(final)
    # one node: every fragment is fetched from the learner's own object store
    assert all(r["perf/remote_fragment_fraction"] == 0 and r["perf/fragment_mb"] > 0 for r in records)
    assert not (res.run_dir / "cluster.json").exists(), "cluster.json is written on a cluster only"
    # lag is measured per step and never negative; steps beyond algo.max_policy_lag (2 here) are masked
    assert all(0 <= r["lag/min"] <= r["lag/mean"] <= r["lag/max"] for r in records)
    for r in records:
        assert (r["lag/max"] > 2) == (r["lag/masked_fraction"] > 0), r
        assert "losses/valid_fraction" not in r  # the complement of lag/masked_fraction is not logged twice


def test_killed_rollout_actor_is_replaced_and_sampling_goes_on(tmp_path, local_ray):
    cfg = tiny_config(tmp_path, "k")
    layout = cfg.env.obs_layout()
    make_model = model_factory(layout, cfg.model)
    sampler = RaySampler(cfg.env, make_model, num_workers=2, envs_per_worker=2, rollout=16, seed=0,
                         max_in_flight=4)
    try:
        sampler.publish(0, make_model().state_dict())
        sampler.get()
        victim = sampler.worker_pids()[0]
        os.kill(victim, signal.SIGKILL)
        # how many fragments the survivor delivers before Ray reports the death depends on the machine's load: wait
        # for the restart, then for a fragment of the replacement (bounded by a count, not a clock)
        before, after = [], []
        while sampler.restarts == 0 and len(before) < 500:
            before.append(sampler.get())
        while not any(f["worker_id"] == 0 for f in after) and len(after) < 500:
            after.append(sampler.get())
        assert sampler.restarts == 1, f"{len(before)} fragments after the kill and no restart"
        assert any(f["worker_id"] == 0 for f in after), "the replacement worker must produce fragments"
        assert {f["worker_id"] for f in after} <= {0, 1}
        assert victim not in sampler.worker_pids()
    finally:
        sampler.close()


@pytest.mark.parametrize("age_s, overtaken, num_workers, first_call, stalled", [
    (11.0, 50, 3, False, True),     # both workers delivered 25 fragments each meanwhile
    (11.0, 49, 3, False, False),    # ... one short of it
    (9.0, 500, 3, False, False),    # too young, however many overtook it
    (60.0, 500, 3, True, False),    # a fresh actor's first call may still be compiling
    (121.0, 500, 3, True, True),
    (800.0, 10_000, 1, False, False),  # nobody can overtake a lone worker ...
    (900.0, 0, 1, False, True),     # ... so only the hard limit applies
])
def test_stall_policy(age_s, overtaken, num_workers, first_call, stalled):
    assert StallPolicy().is_stalled(age_s, overtaken, num_workers, first_call) == stalled


class _BrokenFactory:
    """A model factory that fails inside every rollout actor, as an actor whose code cannot load does."""

    def __call__(self):
        raise RuntimeError("this policy cannot be built")


def test_a_death_limit_below_one_is_refused_before_any_actor_starts(tmp_path):
    cfg = tiny_config(tmp_path, "d0")
    with pytest.raises(ValueError, match="max_deaths_in_a_row must be >= 1.*got 0"):
        RaySampler(cfg.env, _BrokenFactory(), num_workers=1, envs_per_worker=1, rollout=8, seed=0,
                   max_in_flight=1, max_deaths_in_a_row=0)


def test_a_worker_that_dies_before_every_fragment_ends_the_run_with_its_error(tmp_path, local_ray):
    cfg = tiny_config(tmp_path, "d")
    sampler = RaySampler(cfg.env, _BrokenFactory(), num_workers=1, envs_per_worker=1, rollout=8, seed=0,
                         max_in_flight=1, max_deaths_in_a_row=3)  # 5 by default: each death is an actor start
    try:
        with pytest.raises(RuntimeError, match="died 3 times in a row") as e:
            for _ in range(50):
                sampler.get()
        assert "this policy cannot be built" in str(e.value)
        assert sampler.restarts == 2  # restarted after each of the first two deaths, then given up
    finally:
        sampler.close()


def test_a_hung_rollout_actor_is_restarted_by_the_watchdog(tmp_path, local_ray):
    """A worker whose calls never come back while the other delivers (its process frozen with SIGSTOP
    here; a lost reply on a two-node cluster in the failure seen) is killed and replaced."""
    cfg = tiny_config(tmp_path, "h")
    make_model = model_factory(cfg.env.obs_layout(), cfg.model)
    policy = StallPolicy(min_age_s=1.0, overtakes_per_worker=3, check_every_s=0.1)
    sampler = RaySampler(cfg.env, make_model, num_workers=2, envs_per_worker=1, rollout=8, seed=0,
                         max_in_flight=4, stall_policy=policy, ready_timeout_s=300)  # both started and compiled
    frozen = None
    try:
        sampler.publish(0, make_model().state_dict())
        first = {sampler.get()["worker_id"] for _ in range(8)}
        assert first == {0, 1}
        frozen = sampler.worker_pids()[0]
        os.kill(frozen, signal.SIGSTOP)
        after = []
        while sampler.restarts == 0 and len(after) < 1000:  # the frozen worker is given up on after 6 others
            after.append(sampler.get()["worker_id"])
        assert sampler.stalls == 1 and sampler.restarts == 1 and sampler.stalls_recovered == 0
        # not before: the worker's calls finished before the freeze (2 in flight at most) are all it delivered
        assert after.count(1) >= 6 and after.count(0) <= 2, after
        deadline = time.monotonic() + 180  # a hang guard, not a speed limit: the replacement starts from scratch
        replacement_delivered = False
        while not replacement_delivered and time.monotonic() < deadline:
            replacement_delivered = sampler.get()["worker_id"] == 0
        assert replacement_delivered
        assert sampler.restarts == 1, "a fresh actor's first call (still starting) is not taken for stalled"
        assert frozen not in sampler.worker_pids()
    finally:
        if frozen is not None:
            try:
                os.kill(frozen, signal.SIGKILL)
            except ProcessLookupError:
                pass  # ray.kill took it
        sampler.close()


def test_killing_a_rollout_actor_mid_run_does_not_stop_training(tmp_path, local_ray):
    cfg = tiny_config(tmp_path, "kill", **{"runner.serial": "false", "runner.num_workers": 2,
                                            "runner.total_agent_steps": 960})
    killed = []

    def kill_once(version, sampler):
        if version == 3 and not killed:
            killed.append(sampler.worker_pids()[1])
            os.kill(killed[0], signal.SIGKILL)
            # wait until Ray has declared the actor dead, so that its pending fragments fail before the run can
            # reach its last step on the other worker's fragments alone. A call can first fail with
            # ActorUnavailableError (the process is gone, Ray has not decided yet): pending calls then still wait.
            deadline = time.monotonic() + 60
            while True:
                try:
                    ray.get(sampler.workers[1].pid.remote(), timeout=60)
                except ray.exceptions.ActorUnavailableError:
                    assert time.monotonic() < deadline, "Ray never declared the killed actor dead"
                    time.sleep(0.05)
                    continue
                except ray.exceptions.RayActorError:
                    break
                raise AssertionError("the killed actor still answers")

    res = train(cfg, progress=False, on_iteration=kill_once)
    assert killed and res.worker_restarts == 1
    assert res.agent_steps >= 960
    records = [r for r in read_metrics(res.run_dir) if "perf/worker_restarts" in r]
    assert records[-1]["perf/worker_restarts"] == 1
    assert records[-1]["global_step"] > records[2]["global_step"], "training went on after the kill"


def test_learner_failure_ends_with_a_resumable_run_dir(tmp_path, monkeypatch):
    cfg = tiny_config(tmp_path, "fail", **{"runner.total_agent_steps": 640})
    real_train = Learner.train

    def failing_train(self, fragments):
        if self.version == 3:
            raise MemoryError("simulated learner death")
        return real_train(self, fragments)

    monkeypatch.setattr(Learner, "train", failing_train)
    with pytest.raises(RuntimeError, match="--resume") as info:
        train(cfg, progress=False)
    assert "simulated learner death" in str(info.value)
    monkeypatch.setattr(Learner, "train", real_train)
    resumed = train(None, resume_dir=str(tmp_path / "fail"), progress=False)
    assert resumed.agent_steps >= 640
    steps = [r["global_step"] for r in read_metrics(resumed.run_dir) if "losses/total_loss" in r]
    assert steps == sorted(steps) and len(set(steps)) == len(steps), "resumed records continue the counters"


def test_every_logged_key_is_documented_once(tmp_path):
    """Every key a run writes (training, end-of-run evaluation) is in swarm_appo.metrics.METRICS (a per-scenario
    swarm/<scenario>/<name> through its swarm/<name>), and no two logged keys always carry the same value."""
    from quad_env.scenarios import SCENARIOS
    from swarm_appo.metrics import METRICS

    result = train(tiny_config(tmp_path, "doc"), progress=False)
    records = read_metrics(result.run_dir)
    keys = {k for r in records for k in r} - {"global_step", "time"}
    undocumented = []
    for k in sorted(keys):
        parts = k.split("/")
        generic = f"swarm/{parts[2]}" if len(parts) == 3 and parts[0] == "swarm" and parts[1] in SCENARIOS else k
        if generic not in METRICS:
            undocumented.append(k)
    assert not undocumented, undocumented
    assert {"swarm/collisions", "swarm/collisions_drone", "eval/collisions_drone", "losses/total_loss"} <= keys
    assert not {"losses/loss", "losses/valid_fraction"} & keys  # the duplicates are gone


def test_published_weights_are_cpu_copies_that_later_updates_do_not_touch(tmp_path):
    """What a rollout worker receives is a CPU snapshot of one version (on a GPU learner: copied off the device);
    the learner's next in-place optimizer steps must not change it."""
    cfg = tiny_config(tmp_path, "w")
    learner = make_learner(cfg)
    version, weights = learner.cpu_weights()
    snapshot = {k: v.clone() for k, v in weights.items()}
    assert all(v.device.type == "cpu" for v in weights.values())
    learner.train(fixed_fragments(cfg))
    assert learner.version == version + 1
    assert all(torch.equal(weights[k], snapshot[k]) for k in weights)
    moved = [k for k, v in learner.model.state_dict().items() if not torch.equal(v, snapshot[k])]
    assert moved  # the learner did change its own weights


def test_ray_workers_collect_with_the_published_scale(tmp_path, local_ray):
    cfg = tiny_config(tmp_path, "r")
    make_model = model_factory(cfg.env.obs_layout(), cfg.model)
    sampler = RaySampler(cfg.env, make_model, num_workers=2, envs_per_worker=1, rollout=8, seed=0, max_in_flight=2)
    try:
        sampler.publish(0, make_model().state_dict(), {"collision_scale": 0.75})
        # the first fragments may have been requested before the publish reached the store: later ones use it
        scales = [sampler.get()["collision_scale"] for _ in range(6)]
        assert scales[-2:] == [0.75, 0.75]
    finally:
        sampler.close()


def test_weights_store_hands_out_only_newer_weights_as_values(local_ray):
    store = WeightsStore.remote()
    assert ray.get(store.newer_than.remote(-1)) is None, "nothing published yet"
    sd = {"w": torch.arange(6.0).reshape(2, 3)}
    ray.get(store.set.remote(3, sd, {"collision_scale": 0.5}))
    assert ray.get(store.newer_than.remote(3)) is None, "an up-to-date worker receives no weights"
    version, weights, schedule = ray.get(store.newer_than.remote(2))
    # values, not object references: nothing borrowed stays behind in the store or the worker
    assert version == 3 and schedule == {"collision_scale": 0.5} and torch.equal(weights["w"], sd["w"])
    ray.get(store.set.remote(4, {"w": torch.zeros(2, 3)}, None))
    assert ray.get(store.newer_than.remote(3))[0] == 4


@ray.remote(num_cpus=0)
class _StuckStore:
    def set(self, *args):
        time.sleep(30)


def test_a_stuck_weights_store_fails_publish_with_a_clear_error(tmp_path, local_ray):
    cfg = tiny_config(tmp_path, "s")
    make_model = model_factory(cfg.env.obs_layout(), cfg.model)
    sampler = RaySampler(cfg.env, make_model, num_workers=1, envs_per_worker=1, rollout=8, seed=0, max_in_flight=1)
    real_store = sampler._store
    try:
        sampler.publish(0, make_model().state_dict())  # the real store (its first call waits for it to start)
        sampler._store, sampler.publish_timeout_s = _StuckStore.remote(), 0.5
        with pytest.raises(RuntimeError, match="weights store did not take policy version 1 within 0.5 s"):
            sampler.publish(1, make_model().state_dict())
    finally:
        ray.kill(real_store)
        sampler.close()


def test_ray_workers_switch_to_each_newly_published_version(tmp_path, local_ray):
    cfg = tiny_config(tmp_path, "v")
    make_model = model_factory(cfg.env.obs_layout(), cfg.model)
    sampler = RaySampler(cfg.env, make_model, num_workers=2, envs_per_worker=1, rollout=8, seed=0, max_in_flight=2)
    try:
        for version in (0, 7):
            sampler.publish(version, make_model().state_dict())
            # fragments requested before the publish may still carry the older version; later ones do not
            versions = [int(sampler.get()["policy_version"][0]) for _ in range(6)]
            assert versions[-2:] == [version, version], versions
    finally:
        sampler.close()
