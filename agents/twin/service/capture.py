"""A worker's checkpoint taken across batches: every arm as it was at one instant, without holding the worker
for all of them at once.

The agent takes each worker's checkpoint every second (service.shards, `MirrorCheckpoint`): the state a
restarted worker starts from, and `taken`, the count of messages it reflects, after which the agent sends the
new worker the rest again. Built in one go between two batches, the rows of 1,000 arms held the worker for
20-60 ms each second, and every message that arrived meanwhile waited: that stall was most of the fleet's
internal p99 (docs/performance.md).

A `Capture` starts between two batches, where the mirror's counters, alarms and units are copied at once
(they are few) and `taken` is fixed; the arms' rows are then taken a chunk at a time between the batches
that follow. What keeps the picture at one instant is copy before write: before a batch changes an arm
whose row is still to take, the mirror takes that row first (`before`). So every row is its arm as it was
at `taken`, as if the worker had stopped there, and the rows go over as a few pickled chunks
(`PackedDevices`) instead of one.

Used on the worker thread only (the mirror's), like the state it reads.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable, Iterable

from twin.service.shards import DeviceRow, MirrorCheckpoint, PackedDevices

# Rows taken per worker turn while messages arrive (the mirror takes all that are left when it is idle), and
# rows pickled together.
CHUNK = 64


class Capture:
    """One checkpoint being taken: `head` holds everything but the devices, taken at its start; `devices`
    are the arms that existed then, and `row_of` reads one arm's row as it is now."""

    def __init__(
        self, head: MirrorCheckpoint, devices: Iterable[str], row_of: Callable[[str], DeviceRow]
    ) -> None:
        self._head = head
        self._order = list(devices)
        self._pending = set(self._order)
        self._next = 0
        self._row_of = row_of
        self._rows: list[DeviceRow] = []
        self._blobs: list[bytes] = []
        self.done = threading.Event()
        self.result: MirrorCheckpoint | None = None
        self.error: BaseException | None = None

    @property
    def pending(self) -> int:
        """Rows still to take."""
        return len(self._pending)

    def before(self, devices: Iterable[str]) -> None:
        """Before a batch changes `devices`: the rows of those still to take (copy before write)."""
        pending = self._pending
        if not pending:
            return
        for device in devices:
            if device in pending:
                pending.discard(device)
                self._rows.append(self._row_of(device))

    def step(self, limit: int | None = CHUNK) -> bool:
        """Take up to `limit` more rows (None: all that are left); True once every row is taken and `result`
        holds the checkpoint."""
        order, pending = self._order, self._pending
        i, taken = self._next, 0
        while pending and (limit is None or taken < limit):
            device = order[i]
            i += 1
            if device in pending:
                pending.discard(device)
                self._rows.append(self._row_of(device))
                taken += 1
        self._next = i
        rows = self._rows
        if len(rows) >= CHUNK or (rows and not pending):
            self._blobs.append(PackedDevices.pack_chunk(rows))
            self._rows = []
        if pending:
            return False
        self.result = dataclasses.replace(self._head, devices=PackedDevices(tuple(self._blobs)))
        self.done.set()
        return True

    def fail(self, error: BaseException) -> None:
        """Give the waiting caller `error` instead of a checkpoint."""
        self.error = error
        self.done.set()


__all__ = ["CHUNK", "Capture"]
