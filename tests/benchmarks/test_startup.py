"""benchmarks.startup: the real command line, timed by the trainer's own perf/startup_s."""
import json

import pytest

from benchmarks import startup
from quad_env.jit_cache import cache_root


def test_one_start_reads_the_trainers_startup_figure(tmp_path):
    # the suite's warm numba cache: a warm start of the quickstart, one learner iteration
    r = startup.start_once("quickstart", cache_root(), tmp_path, "s")
    assert 0 < r["startup_s"] < r["wall_s"], r
    records = [json.loads(line) for line in (tmp_path / "s" / "metrics.jsonl").read_text().splitlines()]
    assert [k for rec in records for k in rec if k == "perf/startup_s"] == ["perf/startup_s"]  # once, first record
    assert "perf/startup_s" in records[0]


def test_bad_options_are_usage_errors(capsys):
    with pytest.raises(SystemExit) as e:
        startup.main(["--configs", "quick", "--no-append"])
    assert e.value.code == 2 and "--configs: unknown ['quick']" in capsys.readouterr().err
