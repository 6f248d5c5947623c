"""When to tell of a failure that repeats: at once, then at most once an interval, with the count.

A host runs for weeks, and a failure that comes back every second (a full disk under a file the agent
writes, a broker that refuses every retry, a service on the viewer's port that is not the agent) must be
told to a person without burying the log: the first occurrence at once, so it is seen when it starts; then
one line per interval saying how many came since the last line, so the rate stays readable; and the next
occurrence after the condition ends at once again. `RateLimitedLog` (twin.service.logs) does the same for
keys that come from the network, with tables bounded against made-up keys; this is the one-condition case,
in `core` so that every layer can use it.

Not thread-safe: each user already holds the lock that guards the counters it reports.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable


class Throttle:
    """Decides, occurrence by occurrence, whether a repeating condition is told now.

    The first `first` occurrences of a streak are each told; later ones at most once per `interval_s`.
    `clear()` ends the streak (the condition is over), so the next occurrence is told at once.
    """

    def __init__(
        self, interval_s: float, *, first: int = 1, clock: Callable[[], float] = time.monotonic
    ) -> None:
        if interval_s <= 0 or first < 1:
            raise ValueError(f"Throttle needs interval_s > 0 and first >= 1, not {interval_s!r}, {first!r}")
        self.interval_s = interval_s
        self.first = first
        self._clock = clock
        self._told_at = -math.inf
        self._untold = 0
        # Occurrences and lines of the current streak: a caller says "again" or "from now on" by them.
        self.streak = 0
        self.told = 0

    def due(self, *, force: bool = False, now: float | None = None) -> int | None:
        """Count one occurrence. None when it is held back; otherwise it is to be told now, and the value is
        how many occurred since the last line, this one included (1 when none was held back). `force` tells
        it whatever the interval (a loss the caller must not hold back); `now` is the caller's reading of
        the clock, where it has one."""
        self.streak += 1
        self._untold += 1
        now = self._clock() if now is None else now
        # A reading behind the last line's (a wall clock stepped back, where a caller passes one) tells again:
        # held back, the condition would stay untold for as long as the step.
        if not force and self.streak > self.first and 0 <= now - self._told_at < self.interval_s:
            return None
        self._told_at = now
        self.told += 1
        since, self._untold = self._untold, 0
        return since

    def clear(self) -> int:
        """End the streak; returns how many of its occurrences were never told (0 if the last was)."""
        untold = self._untold
        self._told_at, self._untold, self.streak, self.told = -math.inf, 0, 0, 0
        return untold
