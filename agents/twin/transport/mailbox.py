"""The queue between the MQTT callback threads and the twin's worker.

The CRT event-loop threads must never block, and every message must be decoded and counted before anything
is coalesced (the worker coalesces valid messages when it catches up: service.mirror). So this is a plain
bounded FIFO: putting never waits, and memory is bounded by dropping the oldest item when full (counted per
key, so dropped work is visible in the metrics). Full means either bound: a number of messages, or the bytes
of their payloads (a few large messages weigh as much as many small ones).

A put is on the receive path of every message, so it takes as little as it can: appending to a deque and
popping from its other end are each atomic in CPython, and the consumer is woken through an Event only on its
way from empty to not empty (a producer that finds no wake-up pending sets one). A queue bounded by bytes adds
the item's size to its total under a plain lock (no wake-up, held for one addition); a drop takes the same
lock, for its count.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
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
    message is counted. When the worker falls `max_items` messages (or, with `size_of`, `max_bytes` of what
    it measures: the payloads) behind, the oldest items are dropped (counted in `overflowed`, per key; the
    newest is never dropped): memory stays bounded whatever the load. Thread-safe: any number of producers
    `put`, one consumer `take_all`.
    """

    def __init__(
        self,
        max_items: int = 100_000,
        *,
        max_bytes: int | None = None,
        size_of: Callable[[T], int] | None = None,
    ) -> None:
        if max_items < 1:
            raise ValueError(f"max_items must be >= 1, got {max_items}")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"max_bytes must be >= 1, got {max_bytes}")
        if (max_bytes is None) != (size_of is None):
            raise ValueError("max_bytes and size_of go together: the bound needs each item's size")
        self.max_items = max_items
        self.max_bytes = max_bytes
        self._size_of = size_of
        self._items: deque[tuple[str, T]] = deque()
        # Set when there may be something to take; `_wake_pending` spares producers the Event's own lock
        # while the consumer has not yet taken what woke it.
        self._ready = threading.Event()
        self._wake_pending = False
        self._closed = False
        self._taken = 0  # written by the one consumer only
        # The bytes of what is queued (or being appended) and the drop counts change under it.
        self._lock = threading.Lock()
        self._bytes = 0
        self._overflowed: BoundedCounter[str] = BoundedCounter(MAX_OVERFLOW_KEYS)

    def put(self, key: str, item: T) -> None:
        """Append `item` (for `key`, a device); never blocks beyond a short lock."""
        items = self._items
        if len(items) >= self.max_items:
            self._drop_oldest(len(items) + 1 - self.max_items)
        size_of = self._size_of
        if size_of is None:
            items.append((key, item))
        else:
            size = size_of(item)
            with self._lock:
                self._bytes += size
                over = self._bytes > (self.max_bytes or 0)
            items.append((key, item))
            if over:
                self._drop_over_bytes()
        if not self._wake_pending:
            self._wake_pending = True
            self._ready.set()

    def put_many(self, items: list[tuple[str, T]]) -> None:
        """Append (key, item) pairs in order (a batch that arrived together)."""
        if not items:
            return
        queue = self._items
        size_of = self._size_of
        over = False
        if size_of is not None:
            size = sum(size_of(item) for _, item in items)
            with self._lock:
                self._bytes += size
                over = self._bytes > (self.max_bytes or 0)
        queue.extend(items)
        excess = len(queue) - self.max_items
        if excess > 0:
            self._drop_oldest(excess)
        if over:
            self._drop_over_bytes()
        if not self._wake_pending:
            self._wake_pending = True
            self._ready.set()

    def _drop_oldest(self, count: int) -> None:
        size_of = self._size_of
        with self._lock:
            for _ in range(count):
                try:
                    key, item = self._items.popleft()
                except IndexError:  # the consumer took them meanwhile
                    return
                self._overflowed.add(key)
                if size_of is not None:
                    self._bytes -= size_of(item)

    def _drop_over_bytes(self) -> None:
        """Drop the oldest items while the queue holds more than max_bytes, but never the newest."""
        size_of = self._size_of
        assert size_of is not None
        items = self._items
        with self._lock:
            while self._bytes > (self.max_bytes or 0) and len(items) > 1:
                try:
                    key, item = items.popleft()
                except IndexError:  # the consumer took them meanwhile
                    return
                self._overflowed.add(key)
                self._bytes -= size_of(item)

    def take_all(self, timeout: float | None = None) -> list[tuple[str, T]]:
        """Wait up to `timeout` seconds (None = forever) for anything, then take everything, oldest first.

        Returns [] on timeout, or once closed and drained."""
        items = self._items
        if not items and not self._closed:
            self._ready.wait(timeout)
        # Re-armed before taking: a producer appending after the count below finds no wake-up pending and
        # sets one, so nothing waits unseen (at worst the next call wakes once for nothing).
        self._ready.clear()
        self._wake_pending = False
        count = len(items)
        if not count:
            return []
        popleft = items.popleft
        taken: list[tuple[str, T]] = []
        append = taken.append
        try:
            for _ in range(count):
                append(popleft())
        except IndexError:  # a producer dropped the oldest of a full queue meanwhile
            pass
        self._taken += len(taken)
        size_of = self._size_of
        if size_of is not None:
            size = sum(size_of(item) for _, item in taken)
            with self._lock:
                self._bytes -= size
        return taken

    def close(self) -> None:
        self._closed = True
        self._ready.set()

    @property
    def closed(self) -> bool:
        return self._closed

    def __len__(self) -> int:
        return len(self._items)

    @property
    def put_count(self) -> int:
        """Items put since start: taken, waiting, or dropped (exact once the producers are quiet)."""
        return self._taken + len(self._items) + self.overflowed_total

    @property
    def queued_bytes(self) -> int:
        """The bytes queued (0 unless bounded by bytes)."""
        with self._lock:
            return self._bytes

    @property
    def overflowed(self) -> dict[str, int]:
        """Items dropped per key because the queue was full (a copy; the most recently dropped keys only,
        MAX_OVERFLOW_KEYS of them: `overflowed_total` counts every one)."""
        with self._lock:
            return self._overflowed.counts()

    def forget(self, key: str) -> None:
        """Drop `key`'s own count of dropped items (its device was forgotten); `overflowed_total` keeps it."""
        with self._lock:
            self._overflowed.discard(key)

    @property
    def overflowed_keys(self) -> int:
        with self._lock:
            return len(self._overflowed)

    @property
    def overflowed_total(self) -> int:
        with self._lock:
            return self._overflowed.total()
