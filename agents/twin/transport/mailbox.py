"""The queue between the MQTT callback threads and the twin's worker.

The CRT event-loop threads must never block, and every message must be decoded and counted before anything
is coalesced (the worker coalesces valid messages when it catches up: service.mirror). So this is a plain
bounded FIFO: putting never waits, and memory is bounded by dropping the oldest item when full (counted per
key, so dropped work is visible in the metrics).

A put is on the receive path of every message, so it takes no lock: appending to a deque and popping from
its other end are each atomic in CPython, and the consumer is woken through an Event only on its way from
empty to not empty (a producer that finds no wake-up pending sets one). Only the rare drop of a full queue
takes a lock, for its count.
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
        # Set when there may be something to take; `_wake_pending` spares producers the Event's own lock
        # while the consumer has not yet taken what woke it.
        self._ready = threading.Event()
        self._wake_pending = False
        self._closed = False
        self._taken = 0  # written by the one consumer only
        self._overflow_lock = threading.Lock()
        self._overflowed: Counter[str] = Counter()

    def put(self, key: str, item: T) -> None:
        """Append `item` (for `key`, a device); never blocks (a full queue drops its oldest under a short
        lock)."""
        items = self._items
        if len(items) >= self.max_items:
            self._drop_oldest(len(items) + 1 - self.max_items)
        items.append((key, item))
        if not self._wake_pending:
            self._wake_pending = True
            self._ready.set()

    def put_many(self, items: list[tuple[str, T]]) -> None:
        """Append (key, item) pairs in order (a batch that arrived together)."""
        if not items:
            return
        queue = self._items
        queue.extend(items)
        excess = len(queue) - self.max_items
        if excess > 0:
            self._drop_oldest(excess)
        if not self._wake_pending:
            self._wake_pending = True
            self._ready.set()

    def _drop_oldest(self, count: int) -> None:
        with self._overflow_lock:
            for _ in range(count):
                try:
                    key, _ = self._items.popleft()
                except IndexError:  # the consumer took them meanwhile
                    return
                self._overflowed[key] += 1

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
    def overflowed(self) -> Counter[str]:
        """Items dropped per key because the queue was full (a snapshot)."""
        with self._overflow_lock:
            return self._overflowed.copy()

    @property
    def overflowed_total(self) -> int:
        with self._overflow_lock:
            return self._overflowed.total()
