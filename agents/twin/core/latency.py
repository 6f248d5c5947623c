"""A fixed-memory latency histogram for fleet-wide percentiles.

Per-device windows (twin.core.health) answer "how is this arm doing now"; a fleet of 2,000 arms at 10 Hz needs
one distribution over every message since start that costs O(1) per message and the same memory at any rate.
Buckets are log-spaced (about 2 % wide), so a percentile is exact to within one bucket, and the true maximum
is kept alongside.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

_MIN_S = 1e-6  # 1 microsecond: anything faster lands in the first bucket
_MAX_S = 100.0  # beyond this lands in the last bucket (max is still exact)
_GROWTH = 1.02
_LOG_GROWTH = math.log(_GROWTH)
_BUCKETS = int(math.log(_MAX_S / _MIN_S) / _LOG_GROWTH) + 2
# From this many values on, add_many bins them with numpy in one pass instead of one add() each.
_VECTOR_FROM = 16


@dataclass(frozen=True, slots=True)
class LatencySummary:
    """Count, mean, p50, p99 and max of a histogram, in seconds; None while it holds no sample."""

    count: int = 0
    mean: float | None = None
    p50: float | None = None
    p99: float | None = None
    max: float | None = None


class LatencyHistogram:
    """Counts of latencies (seconds) in log-spaced buckets; not thread-safe (one writer, snapshot readers)."""

    __slots__ = ("count", "counts", "max", "min", "total")

    def __init__(self) -> None:
        # A list, not an array: the agent's receiving process merges its workers' histograms and must not
        # load numpy for it (about 11 MB of its memory).
        self.counts = [0] * _BUCKETS
        self.count = 0
        self.total = 0.0
        self.max = 0.0
        self.min = math.inf

    def add(self, seconds: float) -> None:
        if seconds <= _MIN_S:
            index = 0
        else:
            index = min(_BUCKETS - 1, 1 + int(math.log(seconds / _MIN_S) / _LOG_GROWTH))
        self.counts[index] += 1
        self.count += 1
        self.total += seconds
        self.max = max(self.max, seconds)
        self.min = min(self.min, seconds)

    def add_many(self, seconds: Sequence[float]) -> None:
        """add() each of `seconds`; a batch's worth at once (the mirror adds one per applied message)."""
        if len(seconds) < _VECTOR_FROM:
            for value in seconds:
                self.add(value)
            return
        import numpy as np  # noqa: PLC0415 - the mirrors have it loaded (MuJoCo); the receiving process must not

        values = np.asarray(seconds, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            index = 1 + (np.log(values / _MIN_S) / _LOG_GROWTH).astype(np.int64, copy=False)
        index = np.where(values <= _MIN_S, 0, np.minimum(index, _BUCKETS - 1))
        counts = self.counts
        for i in index.tolist():
            counts[i] += 1
        self.count += len(values)
        self.total += float(values.sum())
        self.max = max(self.max, float(values.max()))
        self.min = min(self.min, float(values.min()))

    def copy(self) -> LatencyHistogram:
        out = LatencyHistogram()
        out.merge(self)
        return out

    def merge(self, other: LatencyHistogram) -> None:
        """Add `other`'s samples to this one (the fleet's histogram from its worker processes' histograms)."""
        if len(other.counts) != len(self.counts):
            raise ValueError(
                f"cannot merge a histogram of {len(other.counts)} buckets into {len(self.counts)}"
            )
        self.counts = [a + b for a, b in zip(self.counts, other.counts, strict=True)]
        self.count += other.count
        self.total += other.total
        self.max = max(self.max, other.max)
        self.min = min(self.min, other.min)

    def quantile(self, q: float) -> float | None:
        """The upper edge of the bucket holding the q-quantile (capped by the true maximum)."""
        if self.count == 0:
            return None
        rank = max(1, math.ceil(q * self.count))
        seen = 0
        for index, n in enumerate(self.counts):
            seen += n
            if seen >= rank:
                upper = _MIN_S * _GROWTH**index
                return min(upper, self.max)
        return self.max

    def summary(self) -> LatencySummary:
        if not self.count:
            return LatencySummary()
        return LatencySummary(
            count=self.count,
            mean=self.total / self.count,
            p50=self.quantile(0.50),
            p99=self.quantile(0.99),
            max=self.max,
        )
