"""The queue between the MQTT callback threads and the twin's worker.

The CRT event-loop threads must never block, and every message must be decoded and counted before anything
is coalesced (the worker coalesces valid messages when it catches up: service.mirror). So this is a plain
bounded FIFO: putting never waits, and memory is bounded by dropping the oldest item when full (counted per
key, so dropped work is visible in the metrics).
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from typing import Generic, TypeVar

T = TypeVar("T")

# The key of messages whose topic names no device (cannot collide with a device id).
UNTRACKED_KEY = "\x00untracked"


class InboundQueue(Generic[T]):
    """A bounded FIFO between the MQTT callback threads and the worker, which decodes every message.

    Nothing is replaced before it was validated, so a garbage message can never displace a good one and every
    message is counted. When the worker falls `max_items` behind, the
    oldest items are dropped (counted in `overflowed`, per key): memory stays bounded whatever the load.
    Thread-safe: any number of producers `put`, one consumer `take_all`.
    """

    def __init__(self, max_items: int = 100_000) -> None:
        if max_items < 1:
            raise ValueError(f"max_items must be >= 1, got {max_items}")
        self.max_items = max_items
        self._items: deque[tuple[str, T]] = deque()
        self._cond = threading.Condition(threading.Lock())
        self._closed = False
        self.put_count = 0
        self._overflowed: Counter[str] = Counter()

    def put(self, key: str, item: T) -> None:
        """Append `item` (for `key`, a device); never blocks beyond a short lock."""
        with self._cond:
            self.put_count += 1
            items = self._items
            if len(items) >= self.max_items:
                self._overflowed[items.popleft()[0]] += 1
            items.append((key, item))
            if len(items) == 1:
                # The consumer sleeps only while empty, so one wake-up per empty->non-empty step is enough.
                self._cond.notify_all()

    def put_many(self, items: list[tuple[str, T]]) -> None:
        """Append (key, item) pairs in order under one lock (a batch that arrived together)."""
        if not items:
            return
        with self._cond:
            self.put_count += len(items)
            queue = self._items
            was_empty = not queue
            queue.extend(items)
            excess = len(queue) - self.max_items
            for _ in range(max(0, excess)):
                self._overflowed[queue.popleft()[0]] += 1
            if was_empty:
                self._cond.notify_all()

    def take_all(self, timeout: float | None = None) -> list[tuple[str, T]]:
        """Wait up to `timeout` seconds (None = forever) for anything, then take everything, oldest first.

        Returns [] on timeout, or once closed and drained."""
        with self._cond:
            if not self._items and not self._closed:
                self._cond.wait_for(lambda: self._items or self._closed, timeout)
            if not self._items:
                return []
            items = list(self._items)
            self._items.clear()
            return items

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    @property
    def overflowed(self) -> Counter[str]:
        """Items dropped per key because the queue was full (a snapshot)."""
        with self._cond:
            return self._overflowed.copy()

    @property
    def overflowed_total(self) -> int:
        with self._cond:
            return self._overflowed.total()
