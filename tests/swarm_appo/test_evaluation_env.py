"""One evaluation environment: the training one minus the training aids, for the end-of-run evaluation and
the command line alike, which then print the same numbers for the same checkpoint and episodes."""
import csv
import json

import pytest

from encoders.testing import TINY_OPTIONS
from quad_env import EnvConfig, VecQuadEnv
from swarm_appo import evaluate
from swarm_appo.eval_tables import METRICS, TABLE1_METRICS
from swarm_appo.evaluate import TRAINING_AIDS, evaluation_env
from swarm_appo.testing import untrained_checkpoint

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


def test_evaluation_env_switches_the_training_aids_off_and_keeps_the_rest():
    train = EnvConfig(num_agents=3, scenario="swap_goals", respawn_on_floor=True, replay_prob=0.5,
                      reward=dict(crash=5.0, tilt=1.0))
    ev = evaluation_env(train)
    assert (ev.respawn_on_floor, ev.replay_prob) == (False, 0.0)
    assert {k: getattr(ev, k) for k in TRAINING_AIDS} == TRAINING_AIDS
    assert (train.respawn_on_floor, train.replay_prob) == (True, 0.5)  # the training config is not modified
    assert (ev.num_agents, ev.scenario, ev.reward.crash, ev.reward.tilt) == (3, "swap_goals", 5.0, 1.0)
    other = evaluation_env(train, num_agents=16, scenario="static_same_goal")
    assert (other.num_agents, other.scenario, other.respawn_on_floor) == (16, "static_same_goal", False)
    # and the evaluation env really lets a crashed drone lie on the floor
    env = VecQuadEnv(ev, num_envs=1, seed=0)
    for _ in range(400):
        env.step([[-1.0] * 4] * 3)
    assert (env.get_state().pos[:, 2] <= ev.physics.floor_z).all()
    assert env.episode_stats(0)["respawns"] == 0


def test_end_of_run_and_command_line_evaluations_agree_and_fly_without_respawns(tmp_path, capsys):
    # trained with respawns and shaping (the quickstart config), 1 s episodes: random actions crash in them
    run = untrained_checkpoint(tmp_path, "q", ["env.num_agents=3", "env.num_neighbors=2", "env.episode_duration=1.0",
                                               "env.respawn_on_floor=true", "model.encoder=deepsets",
                                               "model.head_hidden=16"], TINY_OPTIONS["deepsets"])
    cfg, model = evaluate.load_policy_from_checkpoint(str(run))
    assert cfg.env.respawn_on_floor
    seed = evaluate.default_eval_seed(cfg.runner.seed)

    # the end-of-run evaluation, called as the trainer calls it (with its progress bar: 2 x 100 control steps)
    final = evaluate.compare_with_random(cfg.env, model, 3, seed=seed, progress=True)
    bar = capsys.readouterr().err
    assert "final evaluation: 3 episodes" in bar and "200/200" in bar
    # the command line, its default seed is the same
    out = tmp_path / "eval"
    assert evaluate.main(["--checkpoint", str(run), "--episodes", "3", "--scenarios", cfg.env.scenario,
                          "--random-baseline", "--workers", "0", "--out", str(out), "--no-pictures",
                          "--wandb-mode", "disabled", "--no-progress"]) == 0
    with open(out / "table1_scenarios.csv", newline="") as f:
        rows = {"eval": None, "eval_random": None}
        rows["eval"], rows["eval_random"] = csv.DictReader(f)
    compared = 0
    for prefix, row in rows.items():
        for name, key in evaluate.SUMMARY_METRICS.items():
            m = METRICS[key]
            column = f"{m.csv_name}_mean"
            assert (f"{prefix}/{name}" in final) == (column in row or key not in TABLE1_METRICS), (prefix, name)
            if column in row:
                assert float(row[column]) == pytest.approx(final[f"{prefix}/{name}"] * m.scale, rel=1e-9, abs=1e-12)
                compared += 1
    assert compared >= 2 * 7  # Rew, Shaping, Dist, Col, ColD, Suc, IColR (and Reached when the stats have it)

    # no episode of either policy respawned a drone ...
    records = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    assert len(records) == 6 and all(r["respawns"] == 0 for r in records)
    # ... although the same random episodes in the training environment do
    trained_env = evaluate.run_episodes(cfg.env, evaluate.random_policy(seed), 3, seed)
    assert sum(e["respawns"] for e in trained_env) > 0


def test_all_scenarios_leave_out_obstacle_scenarios_for_a_policy_without_obstacles():
    from quad_env.scenarios import SCENARIO_REGISTRY
    from swarm_appo.evaluate import resolve_scenarios

    with_obstacles = resolve_scenarios("all", [8], obstacles=True)
    without = resolve_scenarios("all", [8], obstacles=False)
    obstacle_scenarios = {s for s in with_obstacles if SCENARIO_REGISTRY[s].needs_obstacles}
    assert obstacle_scenarios == {"o_random", "o_static_same_goal"}
    assert set(without) == set(with_obstacles) - obstacle_scenarios and "mix" not in with_obstacles


def test_the_command_line_parses_before_loading_torch_and_forwards_the_library():
    import subprocess
    import sys

    code = ("import sys, swarm_appo.evaluate as e; e.build_parser().parse_args(['--checkpoint', 'x']); "
            "print('torch' in sys.modules, 'numba' in sys.modules, 'ray' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False", "False"]
    from swarm_appo import evaluation

    assert evaluate.compare_with_random is evaluation.compare_with_random  # old imports keep working
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        evaluate.nope
