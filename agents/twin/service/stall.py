"""Whether a thread that should keep turning its loop is stuck, judged from another thread: the in-process
mirror's worker (service.mirror, LocalShard) and the agent's supervisor (service.agent). A stuck one fails
the agent, so `twin run` exits and systemd starts it again (service.systemd)."""

from __future__ import annotations


class StallWatch:
    """Whether a thread that counts the turns of its loop is stuck, from looks at its count now and then: no
    turn for `after_s` (at least three of its waits, for a thread that waits longer: a slow physics rate).
    A whole process paused (SIGSTOP, a suspended VM) wakes its threads in any order: after a gap between two
    looks of half that, the window starts again rather than judge a thread that had no time to turn. Not
    thread-safe: one thread looks, or the caller holds a lock."""

    def __init__(self, after_s: float) -> None:
        self.after_s = after_s
        self._turned: tuple[int, float] | None = None  # the count when last seen to change, and when
        self._looked = float("-inf")

    def look(self, turns: int, now: float, wait_s: float) -> float | None:
        """How long the thread has not turned, once that is a stall; else None. `wait_s`: its longest wait
        between two turns when idle."""
        paused, self._looked = now - self._looked > self.after_s / 2, now
        if self._turned is None or self._turned[0] != turns or paused:
            self._turned = (turns, now)
            return None
        still = now - self._turned[1]
        return still if still >= max(self.after_s, 3 * wait_s) else None
