"""The worker catching up: a backlog is decoded and counted whole; each arm shows its newest valid message.

A gate sink holds the worker inside its first applied sample while a backlog queues behind it (the sink
contract forbids blocking; here it is the tool that makes the worker fall behind deterministically). The
service is fed through `AgentService.feed`; no broker is needed. Its clock is the test's (ManualClock): a
batch is "behind" when the clock says so, never because this busy machine was slow to run the worker.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Iterator

import pytest
from conftest import ManualClock, one_arm_agent, wait_for
from twin.edge.payload import encode, make_payload
from twin.output.sinks import AppliedSample, RejectedSample, SinkStats
from twin.service.agent import AgentService
from twin.service.mirror import CATCH_UP_AFTER_S

TOPIC = "dt/lerobot/arm-001/telemetry"


class GateSink:
    """Blocks the worker in the first applied sample until released (at most `hold_s`); records what it was
    handed."""

    name = "gate"

    def __init__(self, hold_s: float = 10.0) -> None:
        self.hold_s = hold_s
        self.entered = threading.Event()
        self.release = threading.Event()
        self.applied_ms: list[int] = []
        self.rejected_reasons: list[str] = []

    def applied(self, sample: AppliedSample) -> None:
        self.applied_ms.append(sample.timestamp_ms)
        if not self.entered.is_set():
            self.entered.set()
            self.release.wait(self.hold_s)

    def rejected(self, sample: RejectedSample) -> None:
        self.rejected_reasons.append(sample.reason)

    def stats(self) -> SinkStats:
        return SinkStats(name=self.name, delivered=len(self.applied_ms))

    def close(self, timeout: float = 5.0) -> None:
        self.release.set()


@pytest.fixture
def gated() -> Iterator[tuple[AgentService, GateSink, ManualClock]]:
    gate = GateSink()
    clock = ManualClock()
    service = one_arm_agent([gate], clock)
    try:
        yield service, gate, clock
    finally:
        gate.release.set()
        service.stop()


def test_a_backlog_is_counted_whole_and_the_newest_valid_message_is_shown(
    gated: tuple[AgentService, GateSink, ManualClock],
) -> None:
    service, gate, clock = gated
    rng = random.Random(3)
    t0 = int(time.time() * 1000)

    def message(i: int) -> bytes:
        return encode(make_payload("arm-001", 0.1 * i, "ticks", rng, timestamp_ms=t0 + 100 * i))

    service.feed(TOPIC, message(0))
    assert gate.entered.wait(30), "the worker never applied the first message"
    # The backlog: nine good messages, then garbage last, all queued while the worker is held.
    for i in range(1, 10):
        service.feed(TOPIC, message(i))
    service.feed(TOPIC, b"{not json")
    # feed() stamps each message with the agent's clock: moved on by twice the threshold, the backlog is
    # behind to the worker.
    clock.advance(CATCH_UP_AFTER_S * 2)
    gate.release.set()

    # The twin's pose is published after the whole batch, so it is the last thing the backlog changes.
    wait_for(lambda: service.state().devices["arm-001"].timestamp_ms == t0 + 900, 30, "the backlog")
    counters = service.state().devices["arm-001"].health.counters
    assert (counters.received, counters.decoded, counters.rejected_total) == (11, 10, 1)
    # Only the newest valid message of the backlog moved the twin; the garbage after it displaced nothing.
    assert (counters.applied, counters.coalesced) == (2, 8)
    assert gate.applied_ms == [t0, t0 + 900]
    assert gate.rejected_reasons == ["not_json"]
    assert service.state().devices["arm-001"].timestamp_ms == t0 + 900
    # Coalesced messages arrived: they are no transit loss.
    assert service.state().devices["arm-001"].loss.lost == 0


def test_a_worker_keeping_up_applies_every_message(gated: tuple[AgentService, GateSink, ManualClock]) -> None:
    # The clock stands still, so no batch is ever behind, however late the worker takes it.
    service, gate, _clock = gated
    gate.release.set()
    rng = random.Random(4)
    t0 = int(time.time() * 1000)
    for i in range(20):
        payload = encode(make_payload("arm-001", 0.1 * i, "ticks", rng, timestamp_ms=t0 + 100 * i))
        service.feed(TOPIC, payload)
    wait_for(lambda: service.state().devices["arm-001"].timestamp_ms == t0 + 1900, 30, "the last message")
    counters = service.state().devices["arm-001"].health.counters
    assert (counters.applied, counters.coalesced) == (20, 0)
    assert gate.applied_ms == [t0 + 100 * i for i in range(20)]
