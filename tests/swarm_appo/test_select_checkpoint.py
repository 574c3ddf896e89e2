"""Final-policy selection by evaluation: every kept checkpoint flies the same validation episodes (seeded apart
from the reported evaluation's), the best by Suc, then Col, then Dist, is copied to checkpoints/selected.pt."""
import json

import numpy as np
import pytest

from encoders.testing import TINY_OPTIONS
from swarm_appo import evaluate
from swarm_appo import select_checkpoint as sel
from swarm_appo.checkpoint import list_checkpoints, load_latest_checkpoint
from swarm_appo.eval_tables import METRICS
from swarm_appo.testing import untrained_checkpoint

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py

OVERRIDES = ["env.num_agents=3", "env.num_neighbors=2", "env.episode_duration=1.0", "model.encoder=deepsets",
             "model.head_hidden=16", "runner.keep_checkpoints=5"]


def test_ranking_puts_success_first_then_collisions_then_distance():
    c = [sel.Candidate("a", 1, {"suc": 0.5, "col": 3.0, "dist": 0.2}),
         sel.Candidate("b", 2, {"suc": 0.6, "col": 9.0, "dist": 2.0}),   # most successes wins whatever else
         sel.Candidate("c", 3, {"suc": 0.6, "col": 9.0, "dist": 1.0}),   # ... and on a tie, the smaller distance
         sel.Candidate("d", 4, {"suc": 0.6, "col": 10.0, "dist": 0.1})]  # more collisions lose before distance
    assert sel.best_of(c).path == "c"
    assert sel.best_of(c[:2]).path == "b"
    tie = [sel.Candidate("old", 1, {"suc": 0.5, "col": 1.0, "dist": 1.0}),
           sel.Candidate("new", 2, {"suc": 0.5, "col": 1.0, "dist": 1.0})]
    assert sel.best_of(tie).path == "new"  # the later checkpoint on an exact tie
    with pytest.raises(ValueError, match="no candidates"):
        sel.best_of([])


def test_selection_scores_each_checkpoint_on_validation_episodes_and_copies_the_best(tmp_path, capsys):
    # three checkpoints of one run: different weights (initialised from different seeds), steps 1000..3000
    for k in range(3):
        run = untrained_checkpoint(tmp_path, "r", OVERRIDES + ["env.respawn_on_floor=true"], TINY_OPTIONS["deepsets"],
                                   seed=k, agent_steps=1000 * (k + 1))
    paths = list_checkpoints(run)
    assert len(paths) == 3
    latest_before = load_latest_checkpoint(run)[1]

    assert sel.main(["--run", str(run), "--episodes", "4", "--workers", "0", "--no-progress", "--no-averages"]) == 0
    printed = capsys.readouterr().out
    record = json.loads((run / sel.SELECTION_FILE).read_text())

    # independent reference: each checkpoint flown by the evaluation library on the validation seed,
    # in the evaluation environment (respawns off although the run trained with them)
    cfg, _ = evaluate.load_policy_from_checkpoint(str(paths[-1]))
    seed = sel.validation_seed(cfg.runner.seed)
    assert seed == record["seed"] != evaluate.default_eval_seed(cfg.runner.seed)
    env = evaluate.evaluation_env(cfg.env)
    assert not env.respawn_on_floor
    ref = {}
    for p in paths:
        _, model = evaluate.load_policy_from_checkpoint(str(p))
        episodes = evaluate.run_episodes(env, evaluate.model_policy(model), 4, seed)
        assert all(e["respawns"] == 0 for e in episodes)
        ref[p.name] = {m: float(np.mean([METRICS[m].value(e) for e in episodes])) for m in ("suc", "col", "dist")}
    got = {c["checkpoint"]: c for c in record["candidates"]}
    assert set(got) == set(ref)
    for name, scores in ref.items():
        for m, v in scores.items():
            assert got[name][m] == pytest.approx(v, rel=1e-9, abs=1e-12), (name, m)
    # the untrained policies differ, so the choice is not a default
    assert len({round(s["dist"], 9) for s in ref.values()}) == 3
    expected = min(ref, key=lambda n: (-ref[n]["suc"], ref[n]["col"], ref[n]["dist"], -int(n[5:17])))
    assert record["selected"] == expected
    selected = run / "checkpoints" / sel.SELECTED_NAME
    assert selected.read_bytes() == (run / "checkpoints" / expected).read_bytes()
    assert f"{expected} (selected)" in printed
    # selected.pt is no ckpt_* file: a resume still starts from the latest checkpoint
    assert [p.name for p in list_checkpoints(run)] == [p.name for p in paths]
    assert load_latest_checkpoint(run)[1] == latest_before

    # --last 1: only the latest one is a candidate (no average of one)
    record = sel.select(str(run), last=1, episodes=2, workers=0)
    assert [c["checkpoint"] for c in record["candidates"]] == [paths[-1].name] == [record["selected"]]


def test_bad_input_is_a_usage_error_naming_the_problem(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit):
        sel.main(["--run", str(tmp_path / "empty"), "--workers", "0"])
    assert "no checkpoints" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sel.main(["--run", str(tmp_path / "missing")])
    assert "is not a directory" in capsys.readouterr().err
    run = untrained_checkpoint(tmp_path, "r", OVERRIDES, TINY_OPTIONS["deepsets"])
    with pytest.raises(SystemExit):
        sel.main(["--run", str(run), "--last", "0", "--workers", "0"])
    assert "--last must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        sel.main(["--run", str(run), "--scenarios", "nope", "--workers", "0"])
    assert "unknown scenario" in capsys.readouterr().err


def _numpy_mean_state(paths, parameters):
    """Reference: the float64 numpy mean of the named parameters, the rest from the newest file."""
    import torch

    states = [evaluate.load_checkpoint_policy(str(p)).model.state_dict() for p in paths]
    out = {k: v.clone() for k, v in states[-1].items()}
    for name in parameters:
        mean = np.mean([s[name].numpy().astype(np.float64) for s in states], axis=0)
        out[name] = torch.from_numpy(mean).to(states[-1][name].dtype)
    return out


def test_averages_of_the_last_checkpoints_are_candidates_and_can_be_selected(tmp_path, monkeypatch):
    for k in range(3):
        run = untrained_checkpoint(tmp_path, "r", OVERRIDES, TINY_OPTIONS["deepsets"], seed=k,
                                   agent_steps=1000 * (k + 1))
    paths = list_checkpoints(run)
    loaded = evaluate.load_checkpoint_policy(str(paths[-1]))
    parameters = [n for n, _ in loaded.model.named_parameters()]
    buffers = [n for n in loaded.model.state_dict() if n not in parameters]
    assert "log_std" in parameters and any(n.startswith("obs_norm.") for n in buffers)

    # average_weights against the numpy reference; buffers (observation statistics) from the newest
    specs = evaluate.load_policy_specs([str(p) for p in paths])
    got = sel.average_weights([s.weights for s in specs], parameters)
    ref = _numpy_mean_state(paths, parameters)
    for name in parameters:
        assert torch_allclose(got[name], ref[name]), name
    for name in buffers:
        assert got[name].equal(specs[-1].weights[name]), name

    # the candidates: 3 files + the means of the last 2 and 3, each scored like the reference flies it
    chosen = {}

    def pick_the_mean_of_three(candidates):
        chosen["list"] = list(candidates)
        return next(c for c in candidates if c.averaged == 3)

    monkeypatch.setattr(sel, "best_of", pick_the_mean_of_three)
    record = sel.select(str(run), episodes=3, workers=0)
    assert [c["averaged"] for c in record["candidates"]] == [1, 1, 1, 2, 3]
    assert record["selected"] == "mean of the last 3" and record["averaged"] == 3
    seed = record["seed"]
    env = evaluate.evaluation_env(loaded.cfg.env)
    for c, j in zip(record["candidates"][3:], (2, 3)):
        model = loaded.factory()
        model.load_state_dict(_numpy_mean_state(paths[-j:], parameters))
        episodes = evaluate.run_episodes(env, evaluate.model_policy(model), 3, seed)
        assert c["dist"] == pytest.approx(float(np.mean([METRICS["dist"].value(e) for e in episodes])), rel=1e-6)
    # selected.pt: a valid policy-only checkpoint of the mean, with the newest checkpoint's config and steps,
    # that the evaluation command loads; resume still ignores it
    selected = evaluate.load_checkpoint_policy(str(run / "checkpoints" / sel.SELECTED_NAME))
    assert selected.agent_steps == 3000 and selected.cfg == loaded.cfg
    for name, value in selected.model.state_dict().items():
        assert torch_allclose(value, ref[name]), name
    assert load_latest_checkpoint(run)[1] == paths[-1]


def torch_allclose(a, b):
    import torch

    return torch.allclose(a.double(), b.double(), rtol=1e-6, atol=1e-7)


def test_on_the_evaluations_seed_the_scores_are_the_evaluation_commands_numbers(tmp_path, monkeypatch):
    # several chunks of episodes (seeded per chunk as swarm_appo.evaluate seeds them): chunk size 2, 5 episodes
    monkeypatch.setattr(evaluate, "EPISODES_PER_TASK", 2)
    run = untrained_checkpoint(tmp_path, "r", OVERRIDES, TINY_OPTIONS["deepsets"], seed=1)
    seed = 77
    record = sel.select(str(run), episodes=5, seed=seed, workers=0)
    out = tmp_path / "eval"
    scenario, = record["scenarios"]  # the training scenario
    assert evaluate.main(["--checkpoint", str(run), "--episodes", "5", "--episodes-per-task", "2", "--seed",
                          str(seed), "--scenarios", scenario, "--workers", "0", "--out", str(out), "--no-pictures",
                          "--wandb-mode", "disabled", "--no-progress"]) == 0
    episodes = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert len(episodes) == 5 and len({e["task_seed"] for e in episodes}) == 3
    candidate, = record["candidates"]
    for m in ("suc", "col", "dist"):
        assert candidate[m] == pytest.approx(float(np.mean([METRICS[m].value(e) for e in episodes])), rel=1e-9,
                                             abs=1e-12), m
    # one chunk of 5 (the chunking before) flies other episodes: the comparison above can fail
    monkeypatch.setattr(evaluate, "EPISODES_PER_TASK", 5)
    other = sel.select(str(run), episodes=5, seed=seed, workers=0)["candidates"][0]
    assert other["dist"] != pytest.approx(candidate["dist"], rel=1e-9)
