"""The agent's one admission rule: a device counts against `telemetry.max_devices` once it has sent a valid
message, in every mirror of the fleet alike.

A mirror (service.mirror) decides after decoding, so messages that never decode (not JSON, an invented topic,
a payload for another device) take no place, however many topics they name. Mirrors in other processes
(`twin run --workers N`) take from the same count: an array in shared memory, one slot per mirror, under one
lock, so the limit holds across the whole fleet whichever worker a device lands on. A mirror whose process
died and is started again gives its places back (`release`): its devices start over and count again from their
next valid message.

Light on purpose: the receiving process builds the budget and must not load MuJoCo.
"""

from __future__ import annotations

import multiprocessing
from multiprocessing.context import BaseContext

# Counted (untracked, by reason) for each valid message of a device refused because the budget is spent.
TOO_MANY_DEVICES = "too_many_devices"


class DeviceBudget:
    """`limit` places shared by `mirrors` mirrors; a mirror takes one per device it admits.

    Taking is atomic across processes (one lock over the shared array); it happens once per new device, and
    for each message of a device refused, so it stays off the path of an admitted device's messages. Picklable
    only while a process is being started (it travels to a worker as an argument of its process)."""

    def __init__(self, limit: int, mirrors: int = 1, context: BaseContext | None = None) -> None:
        if limit < 1 or mirrors < 1:
            raise ValueError(
                f"a device budget needs a limit and mirrors of at least 1, got {limit}, {mirrors}"
            )
        self.limit = limit
        ctx = context if context is not None else multiprocessing.get_context("spawn")
        self._taken = ctx.Array("q", mirrors)

    def take(self, mirror: int) -> bool:
        """One place for a new device of `mirror`; False when `limit` devices hold one already."""
        with self._taken.get_lock():
            if sum(self._taken[:]) >= self.limit:
                return False
            self._taken[mirror] += 1
            return True

    def give_back(self, mirror: int) -> None:
        """Give back one place of `mirror` (one of its devices was forgotten by an operator)."""
        with self._taken.get_lock():
            if self._taken[mirror] > 0:
                self._taken[mirror] -= 1

    def release(self, mirror: int) -> None:
        """Give back every place `mirror` holds (its devices are gone: its process is started again)."""
        with self._taken.get_lock():
            self._taken[mirror] = 0

    @property
    def taken(self) -> int:
        """Places held across every mirror."""
        with self._taken.get_lock():
            return int(sum(self._taken[:]))
