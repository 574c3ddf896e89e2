"""benchmarks.table1_archive: slim copies of finished Table 1 runs rebuild the same table elsewhere, are restored
only for the same recipe, and never overwrite a local run."""
import gzip
import json

import pytest
import yaml

from benchmarks import table1, table1_archive
from tests.benchmarks.test_table1 import TINY

ROWS = ["--rows", "deepsets/none", "--seeds", "0"]


def tables(text: str) -> str:
    """The report without its header (command, load average) and figure links (named after --out)."""
    return text.split("- cells:", 1)[1].split("![", 1)[0]


def test_an_archive_rebuilds_the_table_on_a_fresh_folder_without_training(tmp_path, one_torch_thread, monkeypatch,
                                                                          capsys):
    arc = tmp_path / "archive"
    assert table1.main(["--out", str(tmp_path / "a"), "--figures", str(tmp_path / "fig"), *TINY, *ROWS,
                        "--archive", str(arc)]) == 0
    src = tmp_path / "a" / "runs" / "static_same_goal" / "deepsets-none" / "seed0"
    dst = arc / "runs" / "static_same_goal" / "deepsets-none" / "seed0"
    assert sorted(p.name for p in dst.iterdir()) == ["config.yaml", "done.json", "eval_table1", "metrics.jsonl.gz"]
    curve = [json.loads(line) for line in gzip.open(dst / "metrics.jsonl.gz", "rt")]
    full = [json.loads(line) for line in (src / "metrics.jsonl").read_text().splitlines()]
    assert curve and all(set(r) <= set(table1_archive.CURVE_KEYS) and "global_step" in r for r in curve)
    assert [r["global_step"] for r in curve] == [r["global_step"] for r in full if "swarm/dist" in r]
    assert (src / "metrics.jsonl").stat().st_size > 5 * (dst / "metrics.jsonl.gz").stat().st_size
    first = tables((tmp_path / "a" / "table1.md").read_text())

    # a fresh folder: the run comes from the archive, nothing trains or evaluates, and the table is the same
    monkeypatch.setattr(table1, "train_run", lambda *a, **k: pytest.fail("an archived run was trained again"))
    from swarm_appo import evaluate
    monkeypatch.setattr(evaluate, "main", lambda *a, **k: pytest.fail("an archived run was evaluated again"))
    assert table1.main(["--out", str(tmp_path / "b"), "--figures", str(tmp_path / "fig"), *TINY, *ROWS,
                        "--archive", str(arc)]) == 0
    assert "restored deepsets/none on static_same_goal, seed 0" in capsys.readouterr().out
    assert tables((tmp_path / "b" / "table1.md").read_text()) == first
    # ... and the archive itself is an experiment folder the report reads (gzipped files)
    assert table1.main(["--out", str(arc), "--figures", str(tmp_path / "fig"), *TINY, *ROWS, "--report-only"]) == 0
    assert tables((arc / "table1.md").read_text()) == first


def test_an_archived_run_of_another_recipe_is_refused_before_anything_runs(tmp_path, one_torch_thread, capsys):
    arc = tmp_path / "archive"
    assert table1.main(["--out", str(tmp_path / "a"), "--figures", str(tmp_path / "fig"), *TINY, *ROWS,
                        "--archive", str(arc)]) == 0
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        table1.main(["--out", str(tmp_path / "b"), "--figures", str(tmp_path / "fig"), *TINY, *ROWS,
                     "--archive", str(arc), "--set", "algo.lr=0.001"])
    assert e.value.code == 2 and "algo.lr" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()
    with pytest.raises(SystemExit):  # the archive is not the experiment folder it copies from
        table1.main(["--out", str(arc), *TINY, *ROWS, "--archive", str(arc)])
    capsys.readouterr()
    # runs archived with their last checkpoint's evaluation cannot stand in for --select (no checkpoints to choose
    # from): refused before anything is written
    with pytest.raises(SystemExit) as e:
        table1.main(["--out", str(tmp_path / "c"), "--figures", str(tmp_path / "fig"), *TINY, *ROWS,
                     "--archive", str(arc), "--select"])
    assert e.value.code == 2 and "eval_table1_selected" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


def test_recipe_differences_name_recipe_keys_only():
    base = {"env": {"num_agents": 8, "reward": {"pos": 0.5}}, "model": {"encoder": "deepsets"},
            "algo": {"lr": 1e-4}, "runner": {"seed": 0, "run_dir": "runs/a", "device": "cpu", "serial": True},
            "wandb": {"group": "x"}}
    other = json.loads(json.dumps(base))
    other["runner"].update(run_dir="elsewhere", device="cuda")
    other["wandb"]["group"] = "y"
    assert table1_archive.recipe_differences(base, other) == []  # paths, devices, wandb: not the recipe
    other["env"]["reward"]["pos"] = 1.0
    other["runner"]["seed"] = 1
    other["model"]["symmetry"] = "se3"
    assert table1_archive.recipe_differences(base, other) == ["env.reward.pos", "model.symmetry", "runner.seed"]
    # the weight EMA is a read-out (training is bit-identical with it): neither its value nor its absence differs
    other["algo"]["weight_ema"] = [2000000.0]
    assert table1_archive.recipe_differences(base, other) == ["env.reward.pos", "model.symmetry", "runner.seed"]
    other["algo"]["lr"] = 3e-4  # ... while the algo section's training keys still count
    assert "algo.lr" in table1_archive.recipe_differences(base, other)


def test_a_key_added_after_a_run_was_archived_matches_only_the_value_that_run_had_in_effect():
    """A config archived before ``env.reward.goal`` existed lacks the key: it counts as goal 0 (the term paid nothing),
    so the planned recipe with the default matches, and one with the bonus switched on is named as different."""
    planned = {"env": {"reward": {"pos": 0.5, "goal": 0.0, "goal_radius": 0.5}}, "model": {}, "algo": {},
               "runner": {"seed": 0}}
    archived = {"env": {"reward": {"pos": 0.5}}, "model": {}, "algo": {}, "runner": {"seed": 0}}
    assert table1_archive.KEYS_ADDED_LATER == {"env.reward.goal": 0.0, "env.reward.goal_radius": 0.5,
                                               "env.reward.height": 0.0, "env.reward.centre": 0.0}
    assert table1_archive.recipe_differences(planned, archived) == []
    assert "goal" not in archived["env"]["reward"]  # the archived config itself is not changed
    planned["env"]["reward"].update(goal=0.5, goal_radius=0.3)
    assert table1_archive.recipe_differences(planned, archived) == ["env.reward.goal", "env.reward.goal_radius"]
    archived["env"]["reward"]["goal"] = 0.5  # written after the key existed: compared as it is
    assert table1_archive.recipe_differences(planned, archived) == ["env.reward.goal_radius"]
    other = {"env": {"reward": {"pos": 0.5}}, "model": {}, "algo": {}, "runner": {"seed": 0}}
    assert table1_archive.recipe_differences(other, archived) == ["env.reward.goal"]  # either side may lack it


def test_restore_leaves_a_local_run_alone_and_archive_skips_unfinished_runs(tmp_path):
    src, rd = tmp_path / "src", tmp_path / "rd"
    src.mkdir()
    (src / "done.json").write_text("{}")
    rd.mkdir()
    (rd / "config.yaml").write_text("# a partial local run\n")
    assert table1_archive.restore_run(src, rd, {}, "eval_table1") is False
    assert [p.name for p in rd.iterdir()] == ["config.yaml"]
    assert table1_archive.archive_run(rd, tmp_path / "dest", "eval_table1") is False  # no done.json, no episodes
    assert not (tmp_path / "dest").exists()


def test_restore_runs_checks_every_recipe_before_restoring_any(tmp_path):
    planned = {"env": {"num_agents": 8}, "model": {"symmetry": "se3"}, "algo": {"lr": 1e-4}, "runner": {"seed": 0}}
    items = []
    for name, lr in (("good", 1e-4), ("other", 3e-4)):  # the matching run comes first
        src = tmp_path / "arc" / name
        src.mkdir(parents=True)
        (src / "done.json").write_text("{}")
        (src / "config.yaml").write_text(yaml.safe_dump({**planned, "algo": {"lr": lr}}))
        (src / "eval_table1").mkdir()
        (src / "eval_table1" / "episodes.jsonl").write_text("")
        items.append((src, tmp_path / "out" / name, planned))
    with pytest.raises(ValueError, match="algo.lr"):
        table1_archive.restore_runs(items, "eval_table1")
    assert not (tmp_path / "out").exists()
    assert table1_archive.restore_runs(items[:1], "eval_table1") == [0]
    assert (tmp_path / "out" / "good" / "config.yaml").exists()


def test_read_jsonl_skips_a_torn_last_line_plain_and_gzipped(tmp_path):
    text = '{"a": 1}\n{"a": 2}\n{"a": '
    (tmp_path / "m.jsonl").write_text(text)
    with gzip.open(tmp_path / "m.jsonl.gz", "wt") as f:
        f.write(text)
    for name in ("m.jsonl", "m.jsonl.gz"):
        assert table1_archive.read_jsonl(tmp_path / name) == [{"a": 1}, {"a": 2}]
    assert table1_archive.existing(tmp_path / "m.jsonl") == tmp_path / "m.jsonl"
    (tmp_path / "m.jsonl").unlink()
    assert table1_archive.existing(tmp_path / "m.jsonl") == tmp_path / "m.jsonl.gz"
