"""A latest-value mailbox between the MQTT callback thread and the twin's worker.

The CRT event-loop thread must never block, and a twin only ever wants the newest pose of each arm: so each
device key holds at most one pending item and a newer one replaces it (counted, so dropped work is visible
in the metrics). Memory is bounded by the number of keys, not by how far the consumer falls behind.
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from typing import Generic, TypeVar

T = TypeVar("T")


class LatestValueMailbox(Generic[T]):
    """Thread-safe: any number of producers `put`, one or more consumers `take_all`."""

    def __init__(self, max_keys: int = 10_000) -> None:
        if max_keys < 1:
            raise ValueError(f"max_keys must be >= 1, got {max_keys}")
        self.max_keys = max_keys
        self._pending: dict[str, T] = {}
        self._cond = threading.Condition(threading.Lock())
        self._closed = False
        self._overwritten: Counter[str] = Counter()
        self.put_count = 0
        # Keys refused because max_keys were already pending: a flood of made-up device ids on a "+"
        # subscription must not grow memory without bound.
        self.refused_keys = 0

    def put(self, key: str, item: T) -> None:
        """Store `item` as the newest value for `key`; never blocks beyond a short lock."""
        with self._cond:
            self.put_count += 1
            pending = self._pending
            if key in pending:
                self._overwritten[key] += 1
                # Re-insert so take_all's order follows when the newest value arrived.
                del pending[key]
            elif len(pending) >= self.max_keys:
                self.refused_keys += 1
                return
            was_empty = not pending
            pending[key] = item
            if was_empty:
                # Waiters sleep only while empty, so one wake-up per empty->non-empty step is enough.
                self._cond.notify_all()

    def take_all(self, timeout: float | None = None) -> list[tuple[str, T]]:
        """Wait up to `timeout` seconds (None = forever) for anything, then take everything pending.

        Returns [] on timeout, or once closed and drained.
        """
        with self._cond:
            if not self._pending and not self._closed:
                self._cond.wait_for(lambda: self._pending or self._closed, timeout)
            if not self._pending:
                return []
            items = list(self._pending.items())
            self._pending.clear()
            return items

    def close(self) -> None:
        """Wake every waiter; later take_all calls return what is left, then [] without waiting."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    def __len__(self) -> int:
        with self._cond:
            return len(self._pending)

    @property
    def overwritten(self) -> Counter[str]:
        """Overwrites per key, as a snapshot: safe to iterate while producers keep putting (0 if none)."""
        with self._cond:
            return self._overwritten.copy()

    @property
    def overwritten_total(self) -> int:
        with self._cond:
            return self._overwritten.total()


class InboundQueue(Generic[T]):
    """A bounded FIFO between the MQTT callback threads and the worker, which decodes every message.

    Unlike the latest-value mailbox nothing is replaced before it was validated, so a garbage message can
    never displace a good one and every message is counted. When the worker falls `max_items` behind, the
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
