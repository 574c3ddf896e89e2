"""benchmarks.gpu_learner on the CPU (how it is checked without a GPU): one batch of real fragments, the
learner timed in each precision, the thread count it was asked for, and the profile of one call."""
from __future__ import annotations

import re

import pytest
import torch

from benchmarks import gpu_learner

TINY = ["env.num_agents=2", "env.num_neighbors=1", "env.scenario=static_same_goal", "model.size=small",
        "algo.rollout=16", "algo.batch_size=64", "algo.num_epochs=2", "runner.envs_per_worker=2"]


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_times_each_precision_with_the_threads_asked_and_profiles_one_call(capsys, restore_threads):
    assert gpu_learner.main(["--device", "cpu", "--seconds", "0", "--encoders", "deepsets", "--precisions",
                             "fp32,bf16", "--threads", "1", "--profile", "--no-append", *TINY]) == 0
    assert torch.get_num_threads() == 1
    out = capsys.readouterr().out
    rows = {}
    for line in out.splitlines():
        m = re.match(r"\| deepsets \| (fp32|bf16) \| off \| ([\d,]+) \| (\d+) \| [\d.]+ \| ([\d.]+) \| ([\d,]+) \| "
                     r"(\S+) \|", line)
        if m:
            rows[m[1]] = m.groups()[1:]
    assert set(rows) == {"fp32", "bf16"}
    for precision, (steps, updates, call_s, rate, ratio) in rows.items():
        # one fragment of 2 swarms x 2 drones x 16 steps fills the 64-step batch: 2 epochs x 1 minibatch
        assert (steps, updates) == ("64", "2")
        call, rate = float(call_s), float(rate.replace(",", ""))
        assert rate > 0
        # rate = steps / call time; the call time is printed to the millisecond
        assert 64 / (call + 0.0005) - 1 <= rate <= (64 / (call - 0.0005) + 1 if call > 0.0005 else float("inf"))
    assert rows["fp32"][4] == "-" and rows["bf16"][4].endswith("x")
    for precision in ("fp32", "bf16"):
        assert re.search(rf"profile deepsets/{precision}/compile off: wall [\d,]+ ms .* 1 CPU thread\(s\)", out)
    assert "aten::" in out  # the operator table


def test_unknown_precision_compile_mode_and_negative_threads_are_refused():
    with pytest.raises(SystemExit, match="fp16"):
        gpu_learner.main(["--device", "cpu", "--precisions", "fp16", "--no-append"])
    with pytest.raises(SystemExit, match="--compile.*max"):
        gpu_learner.main(["--device", "cpu", "--compile", "off,max", "--no-append"])
    with pytest.raises(SystemExit, match="--threads"):
        gpu_learner.main(["--device", "cpu", "--threads", "-2", "--no-append"])
