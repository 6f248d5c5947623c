import random

import pytest
from twin.core.latency import LatencyHistogram, LatencySummary


def test_empty_histogram_has_no_percentiles():
    h = LatencyHistogram()
    assert h.summary() == LatencySummary(count=0, mean=None, p50=None, p99=None, max=None)


def test_percentiles_within_one_bucket_of_exact():
    rng = random.Random(3)
    values = [rng.lognormvariate(-7, 1.0) for _ in range(20_000)]  # around 1 ms, long tail
    h = LatencyHistogram()
    for v in values:
        h.add(v)
    values.sort()
    for q in (0.5, 0.99):
        exact = values[int(q * len(values)) - 1]
        assert h.quantile(q) == pytest.approx(exact, rel=0.025)
    assert h.summary().max == values[-1]
    assert h.count == len(values)


def test_extremes_land_in_edge_buckets_and_max_stays_exact():
    h = LatencyHistogram()
    h.add(0.0)
    h.add(500.0)
    assert h.quantile(0.5) == pytest.approx(1e-6)
    assert h.summary().max == 500.0
