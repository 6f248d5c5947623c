"""The queue between the MQTT callback threads and the twin's worker.

The CRT event-loop threads must never block, and every message must be decoded and counted before anything
is coalesced (the worker coalesces valid messages when it catches up: service.mirror). So this is a plain
bounded FIFO: putting never waits, and memory is bounded by dropping the oldest item when full (counted per
key, so dropped work is visible in the metrics). Full means either bound: a number of messages, or the bytes
of their payloads (a few large messages weigh as much as many small ones).
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Generic, TypeVar

from twin.core.bounded import BoundedCounter

T = TypeVar("T")

# The key of messages whose topic names no device (cannot collide with a device id).
UNTRACKED_KEY = "\x00untracked"
# Drop counts are kept per key for at most this many keys (the most recent); the keys come from topics, which
# anyone who may publish chooses. The total stays exact (twin.core.bounded).
MAX_OVERFLOW_KEYS = 4096


class InboundQueue(Generic[T]):
    """A bounded FIFO between the MQTT callback threads and the worker, which decodes every message.

    Nothing is replaced before it was validated, so a garbage message can never displace a good one and every
    message is counted. When the worker falls `max_items` messages (or `max_bytes` of their payloads) behind,
    the oldest items are dropped (counted in `overflowed`, per key): memory stays bounded whatever the load.
    Thread-safe: any number of producers `put`, one consumer `take_all`.
    """

    def __init__(self, max_items: int = 100_000, *, max_bytes: int | None = None) -> None:
        if max_items < 1:
            raise ValueError(f"max_items must be >= 1, got {max_items}")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {max_bytes}")
        self.max_items = max_items
        self.max_bytes = max_bytes
        self._items: deque[tuple[str, T]] = deque()
        # The size of each item, in step with _items (only kept when bounded by bytes).
        self._sizes: deque[int] = deque()
        self._bytes = 0
        self._cond = threading.Condition(threading.Lock())
        self._closed = False
        self.put_count = 0
        self._overflowed: BoundedCounter[str] = BoundedCounter(MAX_OVERFLOW_KEYS)

    def put(self, key: str, item: T, nbytes: int = 0) -> None:
        """Append `item` (for `key`, a device; `nbytes`: its payload's size); never blocks beyond a short
        lock."""
        with self._cond:
            self.put_count += 1
            items = self._items
            items.append((key, item))
            if self.max_bytes is not None:
                self._sizes.append(nbytes)
                self._bytes += nbytes
            if len(items) > self.max_items or (self.max_bytes is not None and self._bytes > self.max_bytes):
                self._trim()
            if len(items) == 1:
                # The consumer sleeps only while empty, so one wake-up per empty->non-empty step is enough.
                self._cond.notify_all()

    def put_many(self, items: list[tuple[str, T]]) -> None:
        """Append (key, item) pairs in order under one lock (a batch that arrived together); counted at no
        size against max_bytes."""
        if not items:
            return
        with self._cond:
            self.put_count += len(items)
            queue = self._items
            was_empty = not queue
            queue.extend(items)
            if self.max_bytes is not None:
                self._sizes.extend(0 for _ in items)
            self._trim()
            if was_empty:
                self._cond.notify_all()

    def _trim(self) -> None:
        """Drop the oldest items while over either bound, but never the newest (lock held)."""
        items, sizes, by_bytes = self._items, self._sizes, self.max_bytes is not None
        while len(items) > 1 and (
            len(items) > self.max_items or (by_bytes and self._bytes > (self.max_bytes or 0))
        ):
            self._overflowed.add(items.popleft()[0])
            if by_bytes:
                self._bytes -= sizes.popleft()

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
            self._sizes.clear()
            self._bytes = 0
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
    def queued_bytes(self) -> int:
        """The payload bytes queued (0 unless bounded by bytes)."""
        with self._cond:
            return self._bytes

    @property
    def overflowed(self) -> dict[str, int]:
        """Items dropped per key because the queue was full (a copy; the most recently dropped keys only,
        MAX_OVERFLOW_KEYS of them: `overflowed_total` counts every one)."""
        with self._cond:
            return self._overflowed.counts()

    @property
    def overflowed_keys(self) -> int:
        with self._cond:
            return len(self._overflowed)

    @property
    def overflowed_total(self) -> int:
        with self._cond:
            return self._overflowed.total()
