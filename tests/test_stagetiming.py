"""The mirror's stage timers, sampled (twin.service.stagetiming): an untimed batch reads no CPU clock, and the
scaled figures estimate each stage's whole CPU.

The mirror is driven in this process through its inbox, with an injected CPU clock that counts its calls; the
assertions are on counts of calls and batches, never on how long anything took.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable, Iterator

import pytest
from conftest import NO_BROKER, wait_for
from twin.edge.payload import encode, make_payload
from twin.service.admission import DeviceBudget
from twin.service.config import load_config
from twin.service.mirror import STAGES, Mirror, QueuedMessage, QueueInbox
from twin.service.stagetiming import STAGE_TIMED_FROM, StageSampler
from twin.transport.mailbox import InboundQueue

DEVICE = "arm-001"
# Feeds a fresh mirror with this CPU clock and sampler n messages, one batch each; returns the mirror.
Feed = Callable[["CountingClock", StageSampler, int], Mirror]
TOPIC = f"dt/lerobot/{DEVICE}/telemetry"


class CountingClock:
    """The thread's real CPU clock, counting its calls (from any thread)."""

    def __init__(self) -> None:
        self.calls = 0
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            self.calls += 1
        return time.thread_time()


def _mirror(clock: CountingClock, sampler: StageSampler) -> tuple[Mirror, InboundQueue[QueuedMessage]]:
    config = load_config(
        None,
        {
            "broker.url": NO_BROKER,
            "telemetry.devices": [DEVICE],
            "telemetry.units": "ticks",
        },
    )
    queue: InboundQueue[QueuedMessage] = InboundQueue()
    mirror = Mirror(
        config,
        inbox=QueueInbox(queue),
        budget=DeviceBudget(config.telemetry.max_devices),
        cpu_clock=clock,
        stage_sampler=sampler,
    )
    return mirror, queue


@pytest.fixture
def fed() -> Iterator[Feed]:
    """A function feeding a fresh mirror `n` messages one batch at a time (each waits until the last was
    handled); returns the mirror, stopped afterwards."""
    started: list[Mirror] = []

    def feed(clock: CountingClock, sampler: StageSampler, n: int) -> Mirror:
        mirror, queue = _mirror(clock, sampler)
        started.append(mirror)
        mirror.start()
        rng = random.Random(7)
        t0 = int(time.time() * 1000)
        for i in range(n):
            payload = encode(make_payload(DEVICE, 0.1 * i, "ticks", rng, timestamp_ms=t0 + 100 * i))
            queue.put(DEVICE, (TOPIC, payload, time.monotonic(), time.time()))
            wait_for(lambda i=i: mirror.processed > i, 30, f"message {i} handled")
        return mirror

    yield feed
    for mirror in started:
        mirror.stop()


def test_every_batch_timed_when_sampling_every_turn(fed: Feed) -> None:
    # The counterpart of the next test: it shows the counting clock is the one the stage timers read.
    clock = CountingClock()
    mirror = fed(clock, StageSampler(every=1), 40)
    worker = mirror.report().worker
    assert worker.batches == 40 and worker.stage_timed_batches == 40
    # Each timed batch reads the clock at least twice for the hand-over and twice for decoding.
    assert clock.calls >= 4 * 40
    assert set(worker.stage_cpu_s) == set(STAGES)
    assert worker.stage_cpu_s["decode"] > 0 and worker.stage_cpu_s["health_alarms"] > 0


def test_untimed_batches_read_no_cpu_clock(fed: Feed) -> None:
    clock = CountingClock()
    sampler = StageSampler(every=16, rng=random.Random(1))
    mirror = fed(clock, sampler, 200)
    worker = mirror.report().worker
    assert worker.batches == 200
    # Batches of one message are timed on about 1 in 16 turns: under 2 clock reads a batch (timing every
    # batch reads it at least 4 times each), but some (the stage split is still there).
    assert 0 < worker.stage_timed_batches < 200 // 4
    assert 0 < clock.calls < 2 * 200
    assert worker.stage_cpu_s["decode"] > 0


def test_a_mirror_that_times_nothing_reads_no_cpu_clock(fed: Feed) -> None:
    clock = CountingClock()
    # A gap of about a billion turns: none of these is timed.
    mirror = fed(clock, StageSampler(every=10**9, rng=random.Random(2)), 30)
    worker = mirror.report().worker
    assert worker.batches == 30 and worker.stage_timed_batches == 0
    assert clock.calls == 0
    assert all(cpu == 0.0 for cpu in worker.stage_cpu_s.values())


def test_sampled_turns_are_about_one_in_every_whatever_the_pattern() -> None:
    # Turns alternating a heavy (1.0) and a light (0.01) kind: a fixed every-16th choice would time only
    # one kind; a random one estimates each kind's sum. 320,000 turns, 20,000 timed on average: the count's
    # standard deviation is under 1 %, so 5 % is five of them (and the generator is seeded).
    sampler = StageSampler(every=16, rng=random.Random(5))
    turns = 320_000
    estimate = {"heavy": 0.0, "light": 0.0}
    timed = 0
    for turn in range(turns):
        if sampler.sample():
            timed += 1
            kind, cost = ("heavy", 1.0) if turn % 2 else ("light", 0.01)
            estimate[kind] += cost * sampler.weight
    assert timed / (turns / 16) == pytest.approx(1.0, rel=0.05)
    assert estimate["heavy"] / (turns / 2 * 1.0) == pytest.approx(1.0, rel=0.05)
    assert estimate["light"] / (turns / 2 * 0.01) == pytest.approx(1.0, rel=0.05)


def test_batch_weights() -> None:
    sampler = StageSampler(every=16)
    assert sampler.batch_weight(True, 1) == 16.0
    assert sampler.batch_weight(False, 1) == 0.0
    # Large batches are always timed, each counting once (the clock costs little a message there).
    assert sampler.batch_weight(False, STAGE_TIMED_FROM) == 1.0
    assert sampler.batch_weight(True, STAGE_TIMED_FROM) == 1.0
    every = StageSampler(every=1)
    assert all(every.sample() for _ in range(100)) and every.batch_weight(True, 1) == 1.0
    with pytest.raises(ValueError, match="at least 1"):
        StageSampler(every=0)


class JumpingClock(CountingClock):
    """The thread's CPU clock, but the second reading jumps `jump_s` ahead: CPU time charged to the thread
    between two back-to-back readings, as an accounting tick or an interrupt under load can be."""

    def __init__(self, jump_s: float) -> None:
        super().__init__()
        self.jump_s = jump_s

    def __call__(self) -> float:
        now = super().__call__()
        return now + (self.jump_s if self.calls >= 2 else 0.0)


def test_a_clock_reading_that_jumps_never_makes_a_stage_negative(fed: Feed) -> None:
    # Each timed span has one reading's own cost taken off, measured by two readings in a row. A jump between
    # those two (the first timed turn here) once made that turn's spans negative, and scaled by the sampling
    # weight they outweighed a short run's whole stage: `twin bench cost` reported negative CPU under load.
    clock = JumpingClock(jump_s=0.05)
    mirror = fed(clock, StageSampler(every=1), 20)
    worker = mirror.report().worker
    assert worker.stage_timed_batches == 20
    assert all(cpu >= 0.0 for cpu in worker.stage_cpu_s.values()), worker.stage_cpu_s
    assert worker.stage_cpu_s["decode"] > 0
