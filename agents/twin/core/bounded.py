"""Tables keyed by something the network chooses (a device id in a topic), with a bound on their size.

A topic names its device, and anyone who can publish can invent a new one for every message: a table with
one entry per device id seen grows for as long as the junk keeps coming. `BoundedCounter` keeps the counts
of the keys counted most recently, at most `max_keys` of them, and adds the counts of the keys it pushes out
to `evicted`, so the total stays exact while the per-key detail is kept for the devices that are active.

Pure and not thread-safe: callers hold their own lock, as they do for the plain Counter this replaces.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable, Iterator, Mapping
from typing import Generic, TypeVar

K = TypeVar("K", bound=Hashable)


class BoundedCounter(Generic[K]):
    """Counts per key for at most `max_keys` keys (least recently counted pushed out first); `total()` stays
    exact: what a pushed-out key had counted is kept in `evicted`."""

    __slots__ = ("_counts", "evicted", "max_keys")

    def __init__(self, max_keys: int) -> None:
        if max_keys < 1:
            raise ValueError(f"max_keys must be >= 1, got {max_keys}")
        self.max_keys = max_keys
        self._counts: OrderedDict[K, int] = OrderedDict()
        self.evicted = 0

    def add(self, key: K, n: int = 1) -> None:
        counts = self._counts
        if key in counts:
            counts[key] += n
            counts.move_to_end(key)
            return
        counts[key] = n
        if len(counts) > self.max_keys:
            _, count = counts.popitem(last=False)
            self.evicted += count

    def update(self, keys: Iterator[K] | list[K] | tuple[K, ...]) -> None:
        for key in keys:
            self.add(key)

    def discard(self, key: K) -> None:
        """Stop counting `key` apart (an arm forgotten): its count moves to `evicted`, so `total()` stays
        exact and a later count of `key` starts from nothing."""
        self.evicted += self._counts.pop(key, 0)

    def get(self, key: K, default: int = 0) -> int:
        return self._counts.get(key, default)

    def total(self) -> int:
        return sum(self._counts.values()) + self.evicted

    def counts(self) -> dict[K, int]:
        """A copy of the per-key counts kept (the most recent keys)."""
        return dict(self._counts)

    def __len__(self) -> int:
        return len(self._counts)

    def __bool__(self) -> bool:
        return bool(self._counts) or self.evicted > 0

    def __contains__(self, key: object) -> bool:
        return key in self._counts


def merged_counts(*parts: Mapping[K, int]) -> dict[K, int]:
    """The sum of several per-key count tables."""
    out: dict[K, int] = {}
    for part in parts:
        for key, count in part.items():
            out[key] = out.get(key, 0) + count
    return out
