"""benchmarks.weights_memory: its growth measurement against a callable that keeps a known amount."""
from __future__ import annotations

import mmap

import numpy as np
import pytest

from benchmarks.weights_memory import growth_per_version, main


def test_growth_per_version_measures_what_each_call_keeps():
    kept = []

    def keep_256_kib(version: int) -> None:
        # fresh anonymous pages, touched: resident whatever the allocator holds from earlier tests (a numpy array
        # of this size may reuse freed heap that is already resident and not grow RSS at all)
        block = mmap.mmap(-1, 256 * 1024)
        block.write(b"\x01" * len(block))
        kept.append(block)

    m = growth_per_version(keep_256_kib, versions=40, warmup=2)
    assert len(kept) == 42
    assert m["bytes_per_version"] == pytest.approx(256 * 1024, rel=0.1)
    assert m["rss_after_mb"] > m["rss_before_mb"]


def test_growth_per_version_of_a_call_that_keeps_nothing_is_small():
    scratch = np.ones(1024 * 1024, np.uint8)
    m = growth_per_version(lambda v: scratch.sum(), versions=1000, warmup=10)
    assert abs(m["bytes_per_version"]) < 2048


@pytest.mark.parametrize("argv", [["--versions", "0"], ["--warmup", "-1"], ["--config", "no_such.yaml"]])
def test_bad_counts_are_usage_errors(argv):
    with pytest.raises(SystemExit) as exc:
        main(argv + ["--no-append"])
    assert exc.value.code == 2
