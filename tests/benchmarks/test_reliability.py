"""benchmarks.reliability: the soak's RSS growth is robust to the learner's swings and sees a real leak."""
import pytest

from benchmarks.reliability import rss_growth


def test_a_swing_at_the_last_sample_is_not_growth():
    samples = [(m / 2, 600.0) for m in range(0, 121)]  # 60 min, a sample every 30 s, flat
    samples[-1] = (60.0, 800.0)  # one high sample at the end: fragments held at that moment
    r = rss_growth(samples, 60)
    assert r["rss_growth_endpoints_pct"] == pytest.approx(100 * (800 / 600 - 1))
    assert r["rss_growth_pct"] == 0.0


def test_a_steady_leak_is_measured():
    samples = [(m / 2, 500.0 + 2.0 * (m / 2)) for m in range(0, 121)]  # +2 MB per minute
    r = rss_growth(samples, 60)
    # medians of minutes 5-10 (~515 MB) and 55-60 (~615 MB)
    assert r["rss_mb_median_first_5min"] == pytest.approx(515.0, abs=1.0)
    assert r["rss_mb_median_last_5min"] == pytest.approx(615.0, abs=1.0)
    assert r["rss_growth_pct"] == pytest.approx(100 * (615 / 515 - 1), abs=0.5)
