"""The evaluation tables: exact numbers from hand-made episode stats, and the command line end to end on
tiny untrained checkpoints (serial and Ray give the same numbers, checkpoints side by side, zero-shot
scaling, pictures, wandb). Episodes last 0.3 s, so the file runs in well under a minute."""
from __future__ import annotations

import csv
import json
import math
import statistics
from pathlib import Path

import pytest

from encoders.testing import TINY_OPTIONS
from quad_env import ObsLayout
from quad_env.params import REWARD_TERMS
from swarm_appo import evaluate
from swarm_appo.eval_tables import (
    METRICS, PAPER_REWARD_TERMS, SHAPING_REWARD_TERMS, TABLE1_METRICS, TABLE2_METRICS, EpisodeGroup,
    episode_columns, table1_rows, table2_rows, to_csv, to_markdown,
)
from swarm_appo.testing import untrained_checkpoint


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # conftest.py


# --------------------------------------------------------------------------- the table writer
def episode(rew, dist, col, suc, icolr, shaping=0.0, room=0, obstacle=0):
    """Episode stats with the paper's reward terms summing to ``rew``, the shaping terms to ``shaping``,
    ``col`` contacts after the grace (drone-drone pairs plus the ``obstacle`` ones) and ``room`` contacts."""
    return {"return": rew + shaping, "rew_pos": rew + 0.5, "rew_collision": -0.25, "rew_proximity": -0.25,
            "rew_omega": 0.0, "rew_action": 0.0, "rew_floor": shaping, "rew_tilt": 0.0, "rew_crash": 0.0,
            "dist_last_5s": dist, "dist_final": dist, "collisions_after_grace": col,
            "obstacle_collisions_after_grace": obstacle, "room_contacts_after_grace": room,
            "success_rate": suc, "inter_collision_rate": icolr}


# Values chosen so that every mean and (population) std is exact in binary and no printed digit is a tie.
A_S1 = [episode(-2.0, 0.75, 0, 1.0, 0.0), episode(-4.0, 0.25, 2, 0.5, 0.25)]
B_S1 = [episode(-1.0, 0.25, 1, 1.0, 0.25), episode(-1.5, 0.25, 1, 1.0, 0.25)]
A_S2 = [episode(-6.0, 1.0, 4, 0.0, 0.5), episode(-8.0, 2.0, 0, 0.5, 0.25)]
GROUPS = [EpisodeGroup("A (deepsets)", 8, "s1", A_S1), EpisodeGroup("B (se3_graphormer)", 8, "s1", B_S1),
          EpisodeGroup("A (deepsets)", 8, "s2", A_S2)]


def test_table1_markdown_has_exact_cells_and_bolds_the_best_of_each_scenario():
    md = to_markdown(table1_rows(GROUPS), TABLE1_METRICS)
    assert md.splitlines() == [
        # no shaping reward in any row: no Shaping column; no reached_rate in the stats: no Reached column
        "| scenario | policy | Rew | Dist | Col | ColD | Suc % | IColR |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
        # s1: B has the higher reward, lower distance and higher success; A the lower IColR; Col ties at
        # the printed 1.00 (nothing to choose: no bold)
        "| s1 | A (deepsets) | -3.00 ± 1.00 | 0.50 ± 0.25 | 1.00 ± 1.00 | 1.00 ± 1.00 | 75.0 ± 25.0 "
        "| **0.125 ± 0.125** |",
        "| s1 | B (se3_graphormer) | **-1.25 ± 0.25** | **0.25 ± 0.00** | 1.00 ± 0.00 | 1.00 ± 0.00 "
        "| **100.0 ± 0.0** | 0.250 ± 0.000 |",
        # s2 has one policy: nothing to compare, nothing bold
        "| s2 | A (deepsets) | -7.00 ± 1.00 | 1.50 ± 0.50 | 2.00 ± 2.00 | 2.00 ± 2.00 | 25.0 ± 25.0 "
        "| 0.375 ± 0.125 |",
    ]


def test_table1_csv_has_full_precision_numbers_and_episode_counts():
    rows = list(csv.reader(to_csv(table1_rows(GROUPS), TABLE1_METRICS).splitlines()))
    assert rows[0] == ["scenario", "policy", "episodes", "reward_mean", "reward_std", "reward_shaping_mean",
                       "reward_shaping_std", "dist_mean", "dist_std", "collisions_mean", "collisions_std",
                       "collisions_drone_mean", "collisions_drone_std", "success_pct_mean", "success_pct_std",
                       "inter_collision_rate_mean", "inter_collision_rate_std"]
    assert rows[1] == ["s1", "A (deepsets)", "2", "-3.0", "1.0", "0.0", "0.0", "0.5", "0.25", "1.0", "1.0",
                       "1.0", "1.0", "75.0", "25.0", "0.125", "0.125"]
    assert rows[2] == ["s1", "B (se3_graphormer)", "2", "-1.25", "0.25", "0.0", "0.0", "0.25", "0.0", "1.0", "0.0",
                       "1.0", "0.0", "100.0", "0.0", "0.25", "0.0"]
    assert rows[3] == ["s2", "A (deepsets)", "2", "-7.0", "1.0", "0.0", "0.0", "1.5", "0.5", "2.0", "2.0",
                       "2.0", "2.0", "25.0", "25.0", "0.375", "0.125"]


def test_table2_pools_the_scenarios_of_each_swarm_size():
    groups = GROUPS + [EpisodeGroup("A (deepsets)", 16, "s1", A_S1)]
    rows = table2_rows(groups)
    assert [tuple(r.labels.values()) for r in rows] == [("8", "A (deepsets)"), ("8", "B (se3_graphormer)"),
                                                         ("16", "A (deepsets)")]
    pooled = [e["rew_pos"] - 0.5 for e in A_S1 + A_S2]  # the paper's terms: -2, -4, -6, -8
    mean = sum(pooled) / 4
    std = (sum((x - mean) ** 2 for x in pooled) / 4) ** 0.5
    assert rows[0].episodes == 4 and rows[0].values["rew"] == (mean, std) == (-5.0, math.sqrt(5.0))
    md = to_markdown(rows, TABLE2_METRICS).splitlines()
    assert md[0] == "| N | policy | Rew | Col | ColD | Suc % | IColR |"
    assert md[2] == "| 8 | A (deepsets) | -5.00 ± 2.24 | 1.50 ± 1.66 | 1.50 ± 1.66 | 50.0 ± 35.4 | 0.250 ± 0.177 |"
    assert md[3] == ("| 8 | B (se3_graphormer) | **-1.25 ± 0.25** | **1.00 ± 0.00** | **1.00 ± 0.00** "
                     "| **100.0 ± 0.0** | 0.250 ± 0.000 |")
    assert md[4] == "| 16 | A (deepsets) | -3.00 ± 1.00 | 1.00 ± 1.00 | 1.00 ± 1.00 | 75.0 ± 25.0 | 0.125 ± 0.125 |"


def test_rew_is_the_paper_terms_and_the_shaping_terms_are_reported_apart():
    # total return -10 = paper terms -3 + shaping -7 (floor); the other policy has no shaping
    shaped = [episode(-3.0, 1.0, 0, 0.0, 0.0, shaping=-7.0), episode(-3.0, 1.0, 0, 0.0, 0.0, shaping=-5.0)]
    assert shaped[0]["return"] == -10.0
    plain = [episode(-4.0, 1.0, 0, 0.0, 0.0)]
    rows = table1_rows([EpisodeGroup("shaped", 8, "s", shaped), EpisodeGroup("plain", 8, "s", plain)])
    assert rows[0].values["rew"] == (-3.0, 0.0) and rows[0].values["shaping"] == (-6.0, 1.0)
    assert rows[1].values["rew"] == (-4.0, 0.0) and rows[1].values["shaping"] == (0.0, 0.0)
    md = to_markdown(rows, TABLE1_METRICS).splitlines()
    assert md[0] == "| scenario | policy | Rew | Shaping | Dist | Col | ColD | Suc % | IColR |"
    # Rew -3 beats -4 although the shaped policy's total return (-11 on average) is lower
    assert md[2].startswith("| s | shaped | **-3.00 ± 0.00** | -6.00 ± 1.00 |")
    assert md[3].startswith("| s | plain | -4.00 ± 0.00 | **0.00 ± 0.00** |")
    (record,) = list(csv.DictReader(to_csv(rows[:1], TABLE1_METRICS).splitlines()))
    assert (record["reward_mean"], record["reward_shaping_mean"]) == ("-3.0", "-6.0")
    # the end-of-run evaluation reports the same two numbers
    summary = evaluate.summarize(shaped, "eval")
    assert (summary["eval/reward"], summary["eval/reward_shaping"]) == (-3.0, -6.0)
    assert set(PAPER_REWARD_TERMS) | set(SHAPING_REWARD_TERMS) == set(REWARD_TERMS)
    assert not set(PAPER_REWARD_TERMS) & set(SHAPING_REWARD_TERMS)


def test_the_goal_height_and_centre_terms_are_shaping_and_older_episodes_without_them_count_zero():
    with_goal = dict(episode(-3.0, 1.0, 0, 0.0, 0.0, shaping=-1.0), rew_goal=2.5, rew_height=-0.5,
                     rew_centre=-0.25)
    older = episode(-3.0, 1.0, 0, 0.0, 0.0, shaping=-1.0)  # written before those three terms existed
    assert "rew_goal" not in older and "rew_height" not in older and "rew_centre" not in older
    (row,) = table1_rows([EpisodeGroup("p", 8, "s", [with_goal, older])])
    assert row.values["shaping"] == (-0.125, 0.875)  # episodes: -1 + 2.5 - 0.5 - 0.25 and -1 + 0 + 0 + 0
    assert row.values["rew"] == (-3.0, 0.0)
    del older["rew_floor"]  # a term that always existed stays required
    with pytest.raises(KeyError, match="rew_floor"):
        table1_rows([EpisodeGroup("p", 8, "s", [older])])


def test_col_counts_room_and_obstacle_contacts_and_cold_drone_pairs_only():
    # 3 contacts after the grace: 2 drone-drone pairs + 1 obstacle; plus 2 room contacts -> Col 5, ColD 2
    eps = [episode(-1.0, 1.0, 3, 0.0, 0.25, room=2, obstacle=1), episode(-1.0, 1.0, 1, 0.0, 0.0, room=0, obstacle=1)]
    (row,) = table1_rows([EpisodeGroup("p", 8, "s", eps)])
    assert row.values["col"] == (3.0, 2.0)  # (5 + 1) / 2, population std
    assert row.values["cold"] == (1.0, 1.0)  # (2 + 0) / 2
    assert episode_columns(eps[0])["collisions"] == 5 and episode_columns(eps[0])["collisions_drone"] == 2
    summary = evaluate.summarize(eps, "eval")
    assert (summary["eval/collisions"], summary["eval/collisions_drone"]) == (3.0, 1.0)
    (row2,) = table2_rows([EpisodeGroup("p", 8, "s", eps)])
    assert row2.values["col"] == (3.0, 2.0) and row2.values["cold"] == (1.0, 1.0)


def test_reached_rate_goes_to_the_csv_when_every_episode_has_it():
    with_reached = [dict(e, reached_rate=r) for e, r in zip(A_S1, (1.0, 0.75))]
    rows = table1_rows([EpisodeGroup("A", 8, "s1", with_reached)])
    (record,) = list(csv.DictReader(to_csv(rows, TABLE1_METRICS).splitlines()))
    assert (record["reached_pct_mean"], record["reached_pct_std"]) == ("87.5", "12.5")
    assert record["success_pct_mean"] == "75.0"  # Suc stays the success_rate stat
    assert "Reached" not in to_markdown(rows, TABLE1_METRICS)  # CSV only
    assert evaluate.summarize(with_reached, "eval")["eval/reached_rate"] == 0.875
    # one episode without it (an older simulator): no column rather than a wrong mean
    rows = table1_rows([EpisodeGroup("A", 8, "s1", with_reached[:1] + A_S1[1:])])
    assert "reached_pct_mean" not in to_csv(rows, TABLE1_METRICS)
    assert "eval/reached_rate" not in evaluate.summarize(A_S1, "eval")


# --------------------------------------------------------------------------- the command line
def tiny_checkpoint(root: Path, name: str, encoder: str = "deepsets", num_agents: int = 3, seed: int = 0) -> Path:
    """An untrained tiny policy saved as a run's checkpoint (what the trainer writes); 0.3 s episodes."""
    overrides = [f"env.num_agents={num_agents}", "env.num_neighbors=2", "env.episode_duration=0.3",
                 f"model.encoder={encoder}", "model.head_hidden=16", "model.body_frame_obs=false"]
    return untrained_checkpoint(root, name, overrides, TINY_OPTIONS[encoder], seed)


def cli(*args) -> int:
    return evaluate.main([*map(str, args), "--no-progress"])


def read_csv(path: Path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_serial_and_ray_give_the_same_table_and_the_episodes_of_the_seeds(tmp_path):
    run = tiny_checkpoint(tmp_path, "q")
    common = ["--checkpoint", run, "--scenarios", "static_same_goal,swap_goals", "--episodes", 3,
              "--episodes-per-task", 2, "--seed", 11, "--no-pictures", "--wandb-mode", "disabled"]
    assert cli(*common, "--workers", 0, "--out", tmp_path / "serial") == 0
    assert cli(*common, "--workers", 2, "--out", tmp_path / "ray") == 0
    for name in ("table1_scenarios.csv", "table1_scenarios.md", "episodes.jsonl"):
        assert (tmp_path / "serial" / name).read_text() == (tmp_path / "ray" / name).read_text(), name
    assert not (tmp_path / "serial" / "table2_scaling.csv").exists()  # one N: no scaling table

    rows = read_csv(tmp_path / "serial" / "table1_scenarios.csv")
    assert [(r["scenario"], r["policy"], r["episodes"]) for r in rows] == [
        ("static_same_goal", "q (deepsets)", "3"), ("swap_goals", "q (deepsets)", "3")]
    # The same episodes flown directly: 2 with the seed itself, 1 with the second task's seed.
    cfg, model = evaluate.load_policy_from_checkpoint(str(run))
    env = evaluate.evaluation_env(cfg.env, scenario="swap_goals")
    policy = evaluate.model_policy(model)  # one torch thread, as the CLI (fixture)
    direct = (evaluate.run_episodes(env, policy, 2, 11)
              + evaluate.run_episodes(env, policy, 1, evaluate.task_seed(11, 1)))
    returns = [METRICS["rew"].value(e) for e in direct]
    assert float(rows[1]["reward_mean"]) == pytest.approx(statistics.fmean(returns), rel=1e-12)
    assert float(rows[1]["reward_std"]) == pytest.approx(statistics.pstdev(returns), rel=1e-9)
    records = [json.loads(line) for line in (tmp_path / "serial" / "episodes.jsonl").read_text().splitlines()]
    swap = [r for r in records if r["eval_scenario"] == "swap_goals"]
    assert [r["episode"] for r in swap] == [0, 1, 2] and [r["table_reward"] for r in swap] == returns
    assert [r["return"] for r in swap] == [e["return"] for e in direct]
    assert [r["task_seed"] for r in swap] == [11, 11, evaluate.task_seed(11, 1)]


def test_two_checkpoints_side_by_side_scaled_to_larger_swarms_with_pictures_and_wandb(tmp_path, capsys):
    a = tiny_checkpoint(tmp_path, "small", "deepsets", num_agents=3)
    b = tiny_checkpoint(tmp_path, "equi", "se3_graphormer", num_agents=3, seed=1)
    out = tmp_path / "out"
    assert cli("--checkpoint", a, b, "--scenarios", "static_diff_goal", "--episodes", 2, "--num-agents", "16,32",
               "--workers", 0, "--out", out) == 0
    printed = capsys.readouterr().out
    # the quickstart config has shaping terms (tilt, crash): a Shaping column
    assert "| N | policy | Rew | Shaping | Col | ColD | Suc % | IColR |" in printed

    t1 = read_csv(out / "table1_scenarios.csv")  # trained with 3 drones, flown with 16 and 32 (K = 2 slots)
    assert [(r["scenario"], r["num_agents"], r["policy"]) for r in t1] == [
        ("static_diff_goal", "16", "small (deepsets)"), ("static_diff_goal", "16", "equi (se3_graphormer)"),
        ("static_diff_goal", "32", "small (deepsets)"), ("static_diff_goal", "32", "equi (se3_graphormer)")]
    t2 = read_csv(out / "table2_scaling.csv")
    assert [(r["num_agents"], r["policy"], r["episodes"]) for r in t2] == [
        ("16", "small (deepsets)", "2"), ("16", "equi (se3_graphormer)", "2"),
        ("32", "small (deepsets)", "2"), ("32", "equi (se3_graphormer)", "2")]
    for r1, r2 in zip(t1, t2):  # one scenario: pooling changes nothing
        assert r1["reward_mean"] == r2["reward_mean"] and r1["success_pct_std"] == r2["success_pct_std"]
    md = (out / "table2_scaling.md").read_text()
    assert "| 32 | equi (se3_graphormer) |" in md and str(b) in md

    pictures = sorted(p.name for p in (out / "trajectories").iterdir())
    assert pictures == ["equi_se3_graphormer_static_diff_goal_n16.png", "equi_se3_graphormer_static_diff_goal_n32.png",
                        "small_deepsets_static_diff_goal_n16.png", "small_deepsets_static_diff_goal_n32.png"]
    assert (out / "trajectories" / pictures[0]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # the offline wandb run holds both tables (the CSV's numbers) and the pictures
    media = next((out / "wandb").glob("offline-run-*")) / "files" / "media"
    table = json.loads(next((media / "table" / "eval").glob("table2_scaling_*.table.json")).read_text())
    assert table["columns"] == list(t2[0]) and len(table["data"]) == 4
    assert table["data"][3][3] == pytest.approx(float(t2[3]["reward_mean"]), rel=1e-12)
    assert len(list((media / "images" / "eval" / "trajectory").glob("*.png"))) == 4


def test_bad_requests_get_clear_errors(tmp_path, capsys):
    run = tiny_checkpoint(tmp_path, "q")
    with pytest.raises(SystemExit):
        cli("--checkpoint", run, "--scenarios", "static_same_goal,nowhere", "--workers", 0)
    err = capsys.readouterr().err
    assert "nowhere" in err and "swap_goals" in err and "'all'" in err
    with pytest.raises(SystemExit):
        cli("--checkpoint", run, "--scenarios", "swarm_vs_swarm", "--num-agents", 1, "--workers", 0)
    assert "at least 2 drones" in capsys.readouterr().err
    other = tiny_checkpoint(tmp_path, "big", num_agents=5)
    with pytest.raises(SystemExit):
        cli("--checkpoint", run, other, "--workers", 0)
    assert "--num-agents" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli("--checkpoint", tmp_path / "missing", "--workers", 0)
    assert "missing" in capsys.readouterr().err


def test_an_address_without_a_ray_cluster_fails_at_once_with_a_clear_error(tmp_path, capsys):
    run = tiny_checkpoint(tmp_path, "q")
    # port 9 (discard): nothing listens; Ray itself would retry for minutes
    assert cli("--checkpoint", run, "--scenarios", "static_same_goal", "--address", "127.0.0.1:9",
               "--out", tmp_path / "out", "--no-progress") == 1
    err = capsys.readouterr().err
    assert "cannot join the Ray cluster at --address 127.0.0.1:9" in err and "no Ray cluster answers" in err
    assert not (tmp_path / "out" / "table1_scenarios.csv").exists()
    with pytest.raises(SystemExit):
        cli("--checkpoint", run, "--address", "auto", "--workers", 0)
    assert "cannot be combined with --address" in capsys.readouterr().err


def test_a_policy_meets_only_the_observation_layout_it_was_trained_on(tmp_path):
    spec, = evaluate.load_policy_specs([tiny_checkpoint(tmp_path, "q")])
    evaluate.check_layouts([spec], [1, 3, 20], ["static_same_goal"])  # any N: K slots padded and masked
    spec.layout = ObsLayout(4, "full")  # as if trained with K = 4 neighbour slots
    with pytest.raises(ValueError, match="num_neighbors=4.*num_neighbors=2"):
        evaluate.check_layouts([spec], [3], ["static_same_goal"])


def test_sampled_actions_are_seeded_and_differ_from_the_mean(tmp_path):
    spec, = evaluate.load_policy_specs([tiny_checkpoint(tmp_path, "q")])
    kw = dict(specs=[spec], num_agents=[3], scenarios=["static_same_goal"], episodes=2, episodes_per_task=2,
              seed=5, pictures=False)
    stochastic = evaluate.plan_tasks(**kw, deterministic=False)[0]
    mean = evaluate.plan_tasks(**kw, deterministic=True)[0]
    run = lambda t: [e["return"] for e in evaluate.run_task(t, spec.factory, spec.weights).episodes]  # noqa: E731
    assert run(stochastic) == run(stochastic)
    assert run(stochastic) != run(mean)


def test_two_checkpoints_of_one_run_are_told_apart_by_their_step(tmp_path):
    tiny_checkpoint(tmp_path, "q")  # step 1000
    run = untrained_checkpoint(tmp_path, "q", ["env.num_neighbors=2"], TINY_OPTIONS["deepsets"], agent_steps=2000)
    first, second = sorted((run / "checkpoints").glob("ckpt_*.pt"))
    specs = evaluate.load_policy_specs([first, second, second])
    assert [s.label for s in specs] == ["q@1000 (deepsets)", "q@2000 (deepsets) #1", "q@2000 (deepsets) #2"]
    assert [s.step for s in specs] == [1000, 2000, 2000]


def test_a_second_evaluation_does_not_overwrite_the_first(tmp_path):
    run = tiny_checkpoint(tmp_path, "twice")
    for _ in range(2):
        assert cli("--checkpoint", run, "--scenarios", "static_same_goal", "--episodes", 1, "--workers", 0,
                   "--no-pictures", "--wandb-mode", "disabled") == 0
    assert (run / "eval" / "episodes.jsonl").exists() and (run / "eval_2" / "episodes.jsonl").exists()
    assert not (run / "eval_3").exists()
