"""A latest-value mailbox between the MQTT callback thread and the twin's worker.

The CRT event-loop thread must never block, and a twin only ever wants the newest pose of each arm: so each
device key holds at most one pending item and a newer one replaces it (counted, so dropped work is visible
in the metrics). Memory is bounded by the number of keys, not by how far the consumer falls behind.
"""

from __future__ import annotations

import threading
from collections import Counter
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
