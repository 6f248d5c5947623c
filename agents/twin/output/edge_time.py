"""Each arm's time line in the outputs (Rerun's `edge_time`, the ROS 2 `header.stamp`, the USD recording's
time codes): the edge's own timestamps, never running backwards per arm.

The mirror applies a sample older than the arm's last one only after an edge clock reset (docs/agent.md,
"Ordering and edge clock resets"). At its own time it would land behind the arm's earlier samples: Rerun's
live end would show the pose from before the reset until the clock caught up, and a ROS 2 stamp that goes
backwards breaks tf buffers and bag players that expect one frame's stamps in order. So from a reset on,
the arm's samples follow its last one, as far after it as the agent received them after it (the time that
really passed: a stamp 1 ms after a pose 2 s older gave a subscriber that differentiates positions a spike),
and keep the edge's spacing. Once the edge's own time is past the arm's last one again (its clock set right,
by NTP once it is up) they are back at it: a shift kept for good left the arm ahead of every other arm.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from twin.core.throttle import Throttle

log = logging.getLogger(__name__)

WARN_EVERY_S = 60.0


@dataclass(slots=True)
class EdgeTime:
    """One arm's place on its time line (module doc). `place` is called once per applied sample, in the
    order the mirror applied them."""

    last_ms: int = -(2**62)
    shift_ms: int = 0
    last_received_s: float = math.nan
    # A clock that stands still is rebuilt on every 2 s by the mirror: one warning a minute per output, with
    # how many were not told, rather than three every 2 s beside the mirror's own.
    warnings: Throttle = field(default_factory=lambda: Throttle(WARN_EVERY_S))

    def place(self, edge_ms: int, received_s: float, *, device: str, output: str) -> int:
        """The sample's time (ms) on the arm's line, from its edge timestamp and the agent's receive time
        (monotonic live; a session export's are wall-clock); `device` and `output` name the arm and the
        output in the warning a reset logs."""
        if self.shift_ms and edge_ms > self.last_ms:
            self.shift_ms = 0
        ms = edge_ms + self.shift_ms
        # Equal counts as behind: two samples at one stamp are one frame twice to tf, a bag and Rerun.
        if ms <= self.last_ms:
            passed_s = received_s - self.last_received_s
            # A receive clock that stood still (or no earlier receive time, NaN): at least 1 ms on.
            after = self.last_ms + (max(1, round(passed_s * 1000)) if passed_s > 0 else 1)
            self.shift_ms += after - ms
            self._warn(received_s, (after - ms) / 1000, device, output)
            ms = after
        self.last_ms = ms
        self.last_received_s = received_s
        return ms

    def _warn(self, received_s: float, behind_s: float, device: str, output: str) -> None:
        since = self.warnings.due(now=received_s)
        if since is None:
            return
        log.warning(
            "%s: the edge clock of %s went back or stood still (%.1f s behind the arm's time line%s); its "
            "samples now follow its last one. Fix: keep the edge's clock set by NTP (docs/agent.md, "
            "'Ordering and edge clock resets')",
            output,
            device,
            behind_s,
            f"; {since - 1} more such since the last warning" if since > 1 else "",
        )

    def after_last(self, at_s: float) -> int:
        """The time (ms) on the arm's line of something the agent saw at `at_s` (monotonic, the receive
        times' clock) after the arm's last sample, such as its going STALE: as long after that sample as the
        agent saw it after receiving it, never before it. The line does not move: the arm's next sample is
        placed as if this had not been."""
        passed_s = at_s - self.last_received_s
        return self.last_ms + (round(passed_s * 1000) if passed_s > 0 else 0)
