"""algo.weight_ema: running averages of the weights over agent steps. Checked against a float64 numpy reference of
the exponential kernel, shown to leave training unchanged, saved and restored with the learner, and offered to
select_checkpoint as candidates for the final policy."""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch

from swarm_appo import evaluate
from swarm_appo import select_checkpoint as sel
from swarm_appo.checkpoint import load_checkpoint
from swarm_appo.config import ConfigError, load_config
from swarm_appo.eval_tables import METRICS
from swarm_appo.learner import Learner
from swarm_appo.model import model_factory
from swarm_appo.trainer import train
from swarm_appo.weight_ema import STATE_KEY, WeightEMA, averaged_model_state

from .test_training import fixed_fragments, tiny_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py
CPU = torch.device("cpu")


def kernel_mean(snapshots, steps, horizon):
    """Reference, float64: the weights as a function of agent steps (snapshot k held over the k-th batch's steps)
    averaged with the kernel exp(-age / H) over the steps so far."""
    ends = np.cumsum(steps, dtype=np.float64)
    starts = ends - np.asarray(steps, np.float64)
    now = ends[-1]
    w = np.exp(-(now - ends) / horizon) - np.exp(-(now - starts) / horizon)  # integral of the kernel per batch
    out = {}
    for name in snapshots[0]:
        stack = np.stack([s[name] for s in snapshots]).astype(np.float64)
        out[name] = np.tensordot(w, stack, axes=1) / w.sum()
    return out


def test_the_average_is_the_exponential_kernel_mean_of_the_weights_over_agent_steps():
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Tanh(), torch.nn.Linear(4, 2))
    model.register_buffer("stats", torch.ones(3))  # a buffer: not averaged
    horizons = [150.0, 1000.0, 1e9]
    ema = WeightEMA(model, horizons)
    steps = [64, 320, 64, 128, 64, 640]  # batches of different sizes weigh by the steps they cover
    snapshots = []
    rng = np.random.default_rng(1)
    for n in steps:
        with torch.no_grad():
            for p in model.parameters():
                p.copy_(torch.from_numpy(rng.normal(size=tuple(p.shape))))
        snapshots.append({k: v.detach().numpy().copy() for k, v in model.named_parameters()})
        ema.update(model, n)
        for i, h in enumerate(horizons):
            ref = kernel_mean(snapshots, steps[:len(snapshots)], h)
            for name, value in ema.averages[i].items():
                np.testing.assert_allclose(value.numpy(), ref[name], rtol=1e-5, atol=1e-6, err_msg=f"{h} {name}")
    # limits: a short horizon follows the last weights, a very long one is the step-weighted mean of all of them
    last = snapshots[-1]["0.weight"]
    assert np.abs(ema.averages[0]["0.weight"].numpy() - last).max() < 0.05
    uniform = np.tensordot(np.asarray(steps, np.float64) / sum(steps),
                           np.stack([s["0.weight"] for s in snapshots]), axes=1)
    np.testing.assert_allclose(ema.averages[2]["0.weight"].numpy(), uniform, rtol=1e-4, atol=1e-5)
    assert np.abs(uniform - last).max() > 0.5  # the two limits differ: each check above can fail
    # a policy's state with an average as its parameters keeps the live buffers
    state = averaged_model_state(model.state_dict(), ema.state_dict(), 1)
    assert torch.equal(state["stats"], model.stats) and torch.equal(state["2.bias"], ema.averages[1]["2.bias"])
    with pytest.raises(IndexError, match="out of range"):
        averaged_model_state(model.state_dict(), ema.state_dict(), 3)


def ema_config(tmp_path, name, horizons="[100,1000]", **extra):
    return tiny_config(tmp_path, name, **{"algo.weight_ema": horizons, **extra})


def test_training_is_unchanged_and_the_learner_averages_after_every_batch(tmp_path):
    cfg = ema_config(tmp_path, "e")
    plain_algo = dataclasses.replace(cfg.algo, weight_ema=())
    make = model_factory(cfg.env.obs_layout(), cfg.model)
    fragments = [fixed_fragments(cfg, seed=s) for s in (0, 1, 2)]
    steps = [sum(f["num_agent_steps"] for f in batch) for batch in fragments]
    learners = {}
    for key, algo in (("ema", cfg.algo), ("plain", plain_algo)):
        torch.manual_seed(0)
        learners[key] = Learner(make(), algo, CPU, seed=0)
    snapshots = []
    for batch in fragments:
        for learner in learners.values():
            learner.train(batch)
        snapshots.append({k: v.detach().numpy().copy() for k, v in learners["plain"].model.named_parameters()})
    ema, plain = learners["ema"], learners["plain"]
    assert plain.weight_ema is None and STATE_KEY not in plain.state_dict()
    for k, v in plain.model.state_dict().items():  # a read-out: the trained weights are bit-identical
        assert torch.equal(ema.model.state_dict()[k], v), k
    for i, h in enumerate((100.0, 1000.0)):
        ref = kernel_mean(snapshots, steps, h)
        for name, value in ema.weight_ema.averages[i].items():
            np.testing.assert_allclose(value.numpy(), ref[name], rtol=1e-5, atol=1e-6, err_msg=f"{h} {name}")
    moved = max(float(np.abs(ref[n] - snapshots[-1][n]).max()) for n in ref)
    assert moved > 1e-4  # the long average is not just the last weights

    # saved with the learner and restored on resume: the next batch continues the same averages
    resumed = Learner(make(), cfg.algo, CPU, seed=0)
    resumed.load_state_dict(copy.deepcopy(ema.state_dict()))  # as read from a file: no tensor shared
    extra = fixed_fragments(cfg, seed=3)
    for learner in (ema, resumed):
        learner.train(extra)
    for a, b in zip(ema.weight_ema.averages, resumed.weight_ema.averages):
        for name in a:
            assert torch.equal(a[name], b[name]), name

    # a checkpoint without averages (a run trained without them): a warning, and they start at the weights
    fresh = Learner(make(), cfg.algo, CPU, seed=0)
    with pytest.warns(UserWarning, match="holds no weight EMA"):
        fresh.load_state_dict(plain.state_dict())
    fresh.train(extra)
    for name, p in fresh.model.named_parameters():
        assert torch.equal(fresh.weight_ema.averages[0][name], p.detach()), name
    # other horizons than the checkpoint's: refused by name, not mixed
    other = Learner(make(), dataclasses.replace(cfg.algo, weight_ema=(100.0, 2000.0)), CPU, seed=0)
    with pytest.raises(ValueError, match="horizons differ"):
        other.load_state_dict(ema.state_dict())


def test_bad_horizons_are_config_errors_naming_the_key(tmp_path):
    for value, match in (("[0]", "horizons > 0"), ("[-5]", "horizons > 0"), ("[100,100]", "repeat")):
        with pytest.raises(ConfigError, match=rf"algo\.weight_ema.*{match}"):
            load_config(None, [f"algo.weight_ema={value}"])


def test_a_run_with_weight_ema_offers_its_averages_to_select_checkpoint(tmp_path, monkeypatch):
    res = train(ema_config(tmp_path, "s", **{"runner.final_eval_episodes": 0}), progress=False)
    state = load_checkpoint(res.checkpoint)["learner"]
    assert state[STATE_KEY]["horizons"] == [100.0, 1000.0]

    def pick_the_long_ema(candidates):
        return next(c for c in candidates if c.path == sel.ema_label(1000.0))

    monkeypatch.setattr(sel, "best_of", pick_the_long_ema)
    record = sel.select(str(res.run_dir), last=1, episodes=2, workers=0)
    assert [c["kind"] for c in record["candidates"]] == ["checkpoint", "ema", "ema"]
    assert record["selected"] == sel.ema_label(1000.0) and record["kind"] == "ema"
    # selected.pt: a policy-only checkpoint with the average as weights, loaded by the evaluation command
    loaded = evaluate.load_checkpoint_policy(str(res.run_dir / "checkpoints" / sel.SELECTED_NAME))
    expected = averaged_model_state(state["model"], state[STATE_KEY], 1)
    got = loaded.model.state_dict()
    assert set(got) == set(expected)
    for name, value in expected.items():
        assert torch.equal(got[name], value), name
    assert any(not torch.equal(expected[n], state["model"][n]) for n in expected)  # not the last weights
    # its validation score is what the evaluation library measures for that policy on the validation seed
    env = evaluate.evaluation_env(loaded.cfg.env)
    episodes = evaluate.run_episodes(env, evaluate.model_policy(loaded.model), 2, record["seed"])
    chosen = next(c for c in record["candidates"] if c["checkpoint"] == record["selected"])
    assert chosen["dist"] == pytest.approx(float(np.mean([METRICS["dist"].value(e) for e in episodes])), rel=1e-6)

    # --no-ema leaves them out
    monkeypatch.undo()
    record = sel.select(str(res.run_dir), last=1, episodes=2, workers=0, emas=False)
    assert [c["kind"] for c in record["candidates"]] == ["checkpoint"]
