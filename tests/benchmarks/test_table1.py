"""benchmarks.table1 end to end on a tiny budget: trains every row with the same seeds and budget, evaluates each,
writes the table and curves, and resumes where it stopped without retraining finished runs."""
import json

import pytest
import yaml

from benchmarks import table1

TINY = ["--set", "runner.serial=true", "--set", "runner.num_workers=1", "--set", "runner.envs_per_worker=2",
        "--set", "env.num_agents=3", "--set", "env.episode_duration=0.4", "--set", "algo.rollout=16",
        "--set", "algo.batch_size=32", "--set", "wandb.mode=disabled", "--set", "runner.checkpoint_every_s=0",
        "--agent-steps", "768", "--episodes", "2", "--no-results", "--no-progress"]


def run(tmp_path, *args):
    return table1.main(["--out", str(tmp_path / "exp"), "--figures", str(tmp_path / "fig"), *TINY, *args])


def test_tiny_experiment_trains_evaluates_tabulates_and_resumes(tmp_path, one_torch_thread, capsys):
    rows = "deepsets/none,deepsets/se3"
    assert run(tmp_path, "--rows", rows, "--seeds", "0") == 0
    exp = tmp_path / "exp"
    first = {}
    for row in ("deepsets-none", "deepsets-se3"):
        rd = exp / "runs" / "static_same_goal" / row / "seed0"
        done = json.loads((rd / "done.json").read_text())
        assert done["agent_steps"] >= 768
        cfg = (rd / "config.yaml").read_text()
        assert f"symmetry: {row.split('-')[1]}" in cfg and "total_agent_steps: 768" in cfg and "seed: 0" in cfg
        episodes = (rd / table1.EVAL_DIR / "episodes.jsonl").read_text().splitlines()
        assert len(episodes) == 2 and all(json.loads(e)["respawns"] == 0 for e in episodes)  # no training aids
        first[row] = sorted((rd / "checkpoints").glob("ckpt_*.pt"))[-1].stat().st_mtime_ns
    table = (exp / "table1.md").read_text()
    assert "| deepsets/none | 1 |" in table and "| deepsets/se3 | 1 |" in table
    assert "| row | seeds | Rew |" in table and "Suc %" in table and "ColD" in table
    first_fig = tmp_path / "fig" / "exp_static_same_goal_768_deepsets-none+deepsets-se3_seeds0.png"
    assert first_fig.stat().st_size > 1000  # <out>_<scenario>_<budget>_<rows>_<seeds>
    first_fig_bytes = first_fig.read_bytes()

    # a run killed before its first checkpoint (a run dir with a config only) starts again
    killed = exp / "runs" / "static_same_goal" / "deepsets-none" / "seed1"
    killed.mkdir(parents=True)
    (killed / "config.yaml").write_text("# half-made\n")
    # the same command with a second seed: seed 0 is not retrained, seed 1 is added for both rows
    assert run(tmp_path, "--rows", rows, "--seeds", "0,1") == 0
    for row in ("deepsets-none", "deepsets-se3"):
        rd0 = exp / "runs" / "static_same_goal" / row / "seed0"
        assert sorted((rd0 / "checkpoints").glob("ckpt_*.pt"))[-1].stat().st_mtime_ns == first[row]
        assert (exp / "runs" / "static_same_goal" / row / "seed1" / "done.json").exists()
    table = (exp / "table1.md").read_text()
    assert "| deepsets/none | 2 |" in table and "| deepsets/se3 | 2 |" in table
    assert "| deepsets/se3 − deepsets/none | 2 |" in table  # paired by seed under the table
    # ... and the learning speed of each row from its training curve, paired the same way
    speed = table.split("**learning speed, trained on `static_same_goal`**")[1]
    assert "| deepsets/none | 2 |" in speed and "| deepsets/se3 | 2 |" in speed and "Dist AUC (m)" in speed
    assert "| deepsets/se3 − deepsets/none | 2 |" in speed
    assert "- deepsets/none → deepsets/se3, seeds 0, 1: " in table
    out = capsys.readouterr().out
    assert out.count("training deepsets/") == 4  # 2 runs the first time, 2 new ones the second
    # the second report draws its own figure: the one the first report links still shows what that report saw
    assert (tmp_path / "fig" / "exp_static_same_goal_768_deepsets-none+deepsets-se3_seeds0+1.png").stat().st_size > 1000
    assert first_fig.read_bytes() == first_fig_bytes


def test_bad_rows_and_recipe_errors_before_training(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        run(tmp_path, "--rows", "deepsets/so2")
    assert e.value.code == 2 and "architecture/symmetry" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run(tmp_path, "--rows", "deepsets/none", "--train-scenarios", "statc")
    assert "env.scenario" in capsys.readouterr().err
    assert not (tmp_path / "exp").exists()


def test_compare_trains_every_row_once_per_value(tmp_path, one_torch_thread):
    assert run(tmp_path, "--rows", "deepsets/none", "--seeds", "0", "--compare", "runner.precision=fp32,bf16") == 0
    runs = tmp_path / "exp" / "runs" / "static_same_goal"
    assert sorted(p.name for p in runs.iterdir()) == ["deepsets-none-precision-bf16", "deepsets-none-precision-fp32"]
    for value in ("fp32", "bf16"):
        cfg = yaml.safe_load((runs / f"deepsets-none-precision-{value}" / "seed0" / "config.yaml").read_text())
        assert cfg["runner"]["precision"] == value
    table = (tmp_path / "exp" / "table1.md").read_text()
    assert "| deepsets/none precision=fp32 | 1 |" in table and "| deepsets/none precision=bf16 | 1 |" in table
    assert "compared: runner.precision=fp32,bf16" in table


def test_the_papers_other_baselines_are_rows(tmp_path, one_torch_thread):
    """rMAPPO (a preset: mlp + GRU core + central critic) and InfoMARL (an encoder) train like every other row."""
    assert run(tmp_path, "--rows", "rmappo/none,infomarl/none", "--seeds", "0") == 0
    runs = tmp_path / "exp" / "runs" / "static_same_goal"
    rmappo = yaml.safe_load((runs / "rmappo-none" / "seed0" / "config.yaml").read_text())["model"]
    assert (rmappo["encoder"], rmappo["core"], rmappo["critic"]) == ("mlp", "gru", "central")
    infomarl = yaml.safe_load((runs / "infomarl-none" / "seed0" / "config.yaml").read_text())["model"]
    assert (infomarl["encoder"], infomarl["core"], infomarl["critic"]) == ("infomarl", "none", "local")
    table = (tmp_path / "exp" / "table1.md").read_text()
    assert "| rmappo/none | 1 |" in table and "| infomarl/none | 1 |" in table


@pytest.mark.parametrize("bad", ["runner.precision", "runner.precision=bf16", "=a,b"])
def test_compare_needs_a_key_and_two_values(bad):
    with pytest.raises(ValueError, match="KEY=V1,V2"):
        table1.parse_compare(bad)


def test_table_markdown_mean_std_over_seeds_and_best_in_bold():
    cells = {"a/none": [{"rew": -2.0, "suc": 50.0}, {"rew": -4.0, "suc": 70.0}], "a/se3": [{"rew": -1.0, "suc": 90.0}]}
    md = table1.table_markdown(["a/none", "a/se3"], cells, {"a/none": [100.0, 300.0]}, {"a/none": 2, "a/se3": 1})
    lines = md.splitlines()
    assert lines[0] == "| row | seeds | Rew | Suc % | agent-steps/s |"
    assert lines[2] == "| a/none | 2 | -3.00 ± 1.00 | 60.0 ± 10.0 | 200 |"
    assert lines[3] == "| a/se3 | 1 | **-1.00 ± 0.00** | **90.0 ± 0.0** | - |"


def test_a_larger_budget_trains_finished_runs_on(tmp_path, one_torch_thread):
    assert run(tmp_path, "--rows", "deepsets/none", "--seeds", "0") == 0
    rd = tmp_path / "exp" / "runs" / "static_same_goal" / "deepsets-none" / "seed0"
    assert json.loads((rd / "done.json").read_text())["agent_steps"] < 1536
    argv = [a if a != "768" else "1536" for a in TINY]
    assert table1.main(["--out", str(tmp_path / "exp"), "--figures", str(tmp_path / "fig"), *argv,
                        "--rows", "deepsets/none", "--seeds", "0"]) == 0
    done = json.loads((rd / "done.json").read_text())
    assert done["agent_steps"] >= 1536 and done["resumed"]
    steps = [json.loads(line)["global_step"] for line in (rd / "metrics.jsonl").read_text().splitlines()]
    assert steps == sorted(steps) and len(set(steps)) == len(steps)  # one history, no step twice
    # each budget has its own curves figure: the one an earlier report links is not overwritten
    assert sorted(f.name for f in (tmp_path / "fig").glob("*.png")) == [
        "exp_static_same_goal_1536_deepsets-none_seeds0.png", "exp_static_same_goal_768_deepsets-none_seeds0.png"]


@pytest.mark.parametrize("steps, label", [(768, "768"), (1536, "1536"), (50_000, "50k"), (1_500, "1.5k"),
                                          (3_000_000, "3M"), (30_000_000, "30M"), (1_500_000, "1.5M"),
                                          (1_234_567, "1234567")])
def test_budget_label(steps, label):
    assert table1.budget_label(steps) == label


@pytest.mark.parametrize("seeds, label", [([0], "seeds0"), ([1, 0], "seeds0+1"), ([3, 1, 2, 0], "seeds0-3"),
                                          ([0, 2, 5], "seeds0+2+5"), ([2, 2, 3, 4], "seeds2-4")])
def test_seeds_label(seeds, label):
    assert table1.seeds_label(seeds) == label


def test_figure_name_tells_rows_and_seeds_apart():
    rows = table1.parse_rows("deepsets/none,kattention/se3")
    name = table1.figure_name("quality_mix_15m", "mix", 15_000_000, rows, [0, 1, 2, 3])
    assert name == "quality_mix_15m_mix_15M_deepsets-none+kattention-se3_seeds0-3.png"
    compared = table1.parse_rows("deepsets/none", "runner.precision=fp32,bf16")
    assert table1.figure_name("e", "mix", 768, compared, [0]) == \
        "e_mix_768_deepsets-none-precision-fp32+deepsets-none-precision-bf16_seeds0.png"
    names = {table1.figure_name("e", "mix", 768, r, s) for r in (rows, rows[:1]) for s in ([0], [0, 1])}
    assert len(names) == 4  # another row set or seed set is another file


def test_a_larger_budget_is_refused_for_runs_whose_lr_decays_to_their_budget(tmp_path, one_torch_thread, capsys):
    linear = ["--rows", "deepsets/none", "--seeds", "0", "--set", "algo.lr_schedule=linear"]
    assert run(tmp_path, *linear) == 0
    rd = tmp_path / "exp" / "runs" / "static_same_goal" / "deepsets-none" / "seed0"
    before = (rd / "done.json").read_text()
    argv = [a if a != "768" else "1536" for a in TINY]
    with pytest.raises(SystemExit) as e:
        table1.main(["--out", str(tmp_path / "exp"), "--figures", str(tmp_path / "fig"), *argv, *linear])
    assert e.value.code == 2 and "restart the decay" in capsys.readouterr().err
    assert (rd / "done.json").read_text() == before and (rd / "eval_table1").exists()  # nothing touched


def test_smooth_is_a_centred_running_mean():
    import numpy as np

    y = np.array([0.0, 0.0, 3.0, 0.0, 0.0])
    assert np.allclose(table1.smooth(y, 3), [0.0, 1.0, 1.0, 1.0, 0.0])
    assert np.allclose(table1.smooth(y, 1), y)


def test_pooled_row_weights_every_scenario_equally_and_counts_episodes():
    per_scenario = {"a": {"dist": 1.0, "suc": 10.0, "episodes": 20}, "b": {"dist": 3.0, "suc": 30.0, "episodes": 20}}
    assert table1.pooled_means(per_scenario) == {"dist": 2.0, "suc": 20.0, "episodes": 20.0}
    assert table1.episodes_label({"r": [{"episodes": 20}, {"episodes": 20}]}) == "20"
    assert table1.episodes_label({"r": [{"episodes": 20}], "s": [{"episodes": 50}]}) == "20-50"


def test_select_reports_the_checkpoint_chosen_on_validation_episodes(tmp_path, one_torch_thread, capsys):
    # a checkpoint every update: 8 updates, the last 3 kept, all candidates
    assert run(tmp_path, "--rows", "deepsets/se3", "--seeds", "0", "--select", "--select-episodes", "2",
               "--set", "runner.checkpoint_every_updates=1") == 0
    rd = tmp_path / "exp" / "runs" / "static_same_goal" / "deepsets-se3" / "seed0"
    selection = json.loads((rd / "selection.json").read_text())
    kept = sorted(p.name for p in (rd / "checkpoints").glob("ckpt_*.pt"))
    assert len(kept) == 3 and [c["checkpoint"] for c in selection["candidates"]] == kept + [
        "mean of the last 2", "mean of the last 3"]  # the files and the means of their weights
    assert selection["scenarios"] == ["static_same_goal"] and selection["episodes"] == 2
    assert selection["seed"] != 2024  # validation episodes are not the reported ones
    from swarm_appo.evaluation import load_checkpoint_policy

    assert load_checkpoint_policy(str(rd / "checkpoints" / "selected.pt")).agent_steps == selection["selected_step"]
    # the table reads the selected checkpoint's evaluation; the last checkpoint's is not made
    assert not (rd / table1.EVAL_DIR).exists()
    episodes = [json.loads(x) for x in (rd / table1.SELECTED_EVAL_DIR / "episodes.jsonl").read_text().splitlines()]
    assert len(episodes) == 2
    table = (tmp_path / "exp" / "table1.md").read_text()
    assert "final policy: each run's checkpoint chosen by `swarm_appo.select_checkpoint`" in table
    assert f"selected {selection['selected']} on 2 validation episodes" in capsys.readouterr().out
    # the same command without --select evaluates the last checkpoint beside it, and says so
    assert run(tmp_path, "--rows", "deepsets/se3", "--seeds", "0", "--set", "runner.checkpoint_every_updates=1") == 0
    assert (rd / table1.EVAL_DIR / "episodes.jsonl").exists()
    assert "final policy: each run's last checkpoint" in (tmp_path / "exp" / "table1.md").read_text()
    with pytest.raises(SystemExit):
        run(tmp_path, "--rows", "deepsets/se3", "--seeds", "0", "--select", "--select-episodes", "0")


def test_figures_stay_out_of_the_repository_when_results_do(tmp_path):
    out = tmp_path / "exp"
    parse = table1.build_parser().parse_args
    assert table1.figures_dir(parse(["--no-results"]), out) == out / "figures"
    assert table1.figures_dir(parse([]), out) == table1.ROOT / "benchmarks" / "figures"
    assert table1.figures_dir(parse(["--no-results", "--figures", str(tmp_path / "f")]), out) == tmp_path / "f"
