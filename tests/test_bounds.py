"""Bounds: tables keyed by device ids the network chooses stay within their caps, queues are bounded by bytes
as well as by count, and a rejected message keeps only what its counters and history need.

The last test floods a running agent with 100,000 invented device ids (garbage and valid telemetry alike) and
checks every per-device table of the mirror, the decoder, the queue and the log limiter against its cap.
"""

from __future__ import annotations

import logging
import random
import threading

import pytest
from conftest import NO_BROKER, wait_for
from twin.core.bounded import BoundedCounter, merged_counts
from twin.core.telemetry import MAX_DECIDED_DEVICES, DecoderConfig, TelemetryDecoder
from twin.core.units import Units
from twin.edge.payload import encode, make_payload
from twin.output.sinks import (
    REJECTED_PAYLOAD_KEPT,
    SAMPLE_OVERHEAD_BYTES,
    QueuedSink,
    RejectedSample,
    rejected_sample,
)
from twin.service.agent import MAX_ROUTES, AgentService
from twin.service.config import load_config
from twin.service.events import MAX_THROTTLE_KEYS
from twin.service.logs import RateLimitedLog
from twin.transport.mailbox import MAX_OVERFLOW_KEYS, UNTRACKED_KEY, InboundQueue

# --- the bounded counter --------------------------------------------------------------------------------


def test_a_bounded_counter_keeps_the_recent_keys_and_an_exact_total() -> None:
    counter: BoundedCounter[str] = BoundedCounter(3)
    for key in ["a", "b", "a", "c", "d", "a", "e"]:
        counter.add(key)
    # "b" and "c" were counted least recently when "d" and "e" came: pushed out, their counts kept in total.
    assert counter.counts() == {"d": 1, "a": 3, "e": 1}
    assert counter.evicted == 2 and counter.total() == 7 and len(counter) == 3
    assert merged_counts({"a": 1}, counter.counts()) == {"a": 4, "d": 1, "e": 1}
    with pytest.raises(ValueError, match="max_keys"):
        BoundedCounter(0)
    # A key discarded (its arm forgotten) is counted afresh; the total keeps what it had.
    counter.discard("a")
    counter.discard("never")
    assert counter.counts() == {"d": 1, "e": 1} and counter.total() == 7
    counter.add("a")
    assert counter.get("a") == 1 and counter.total() == 8


# --- queues bounded by bytes ----------------------------------------------------------------------------


def test_the_inbound_queue_drops_the_oldest_beyond_its_bytes_and_keeps_the_newest() -> None:
    queue: InboundQueue[bytes] = InboundQueue(max_items=100, max_bytes=1000, size_of=len)
    for i in range(5):
        queue.put(f"d{i}", b"x" * 300)
    # 5 x 300 bytes is over 1000: the two oldest went, counted per key; the rest is within the bound.
    assert queue.overflowed == {"d0": 1, "d1": 1} and queue.queued_bytes == 900
    queue.put("big", b"x" * 5000)
    # One message larger than the whole bound is still delivered (the newest is never dropped).
    assert [key for key, _ in queue.take_all(0)] == ["big"]
    assert queue.queued_bytes == 0 and queue.overflowed_total == 5


def test_the_inbound_queue_keeps_drop_counts_for_a_bounded_number_of_keys() -> None:
    queue: InboundQueue[int] = InboundQueue(max_items=1)
    n = MAX_OVERFLOW_KEYS * 3
    for i in range(n + 1):
        queue.put(f"junk-{i}", i)
    assert queue.overflowed_keys == MAX_OVERFLOW_KEYS
    assert queue.overflowed_total == n


class _Stalled:
    def __init__(self) -> None:
        self.gate = threading.Event()
        self.entered = threading.Event()
        self.rejected: list[RejectedSample] = []

    def handle_applied(self, sample: object) -> None:
        raise AssertionError("no applied samples here")

    def handle_rejected(self, sample: RejectedSample) -> None:
        self.entered.set()
        self.gate.wait(30)
        self.rejected.append(sample)

    def idle(self) -> None:
        return

    def close(self) -> None:
        return


def test_a_queued_sink_is_bounded_by_bytes_as_well_as_by_samples() -> None:
    worker = _Stalled()
    per_sample = 4096 + SAMPLE_OVERHEAD_BYTES
    sink = QueuedSink("bytes", worker, max_pending=1000, max_pending_bytes=10 * per_sample)
    sink.rejected(RejectedSample(None, "t", 0.0, "not_json", "held", b"x" * 4096))
    assert worker.entered.wait(30)
    for i in range(100):
        sink.rejected(RejectedSample(None, "t", 0.0, "not_json", str(i), b"x" * 4096))
    # 100 samples of 6 KiB each: far under the count bound, but only 10 fit the bytes.
    assert sink.stats().pending == 1 + 10 and sink.stats().dropped == 90
    worker.gate.set()
    sink.close()
    assert [s.detail for s in worker.rejected] == ["held", *map(str, range(90, 100))]


def test_a_rejected_sample_keeps_the_first_bytes_and_the_full_size() -> None:
    payload = b"{" + b"x" * 200_000
    sample = rejected_sample(
        "arm-001",
        "dt/lerobot/arm-001/telemetry",
        received_wall_s=1.0,
        reason="too_large",
        detail="d" * 5000,
        payload=payload,
    )
    assert sample.payload == payload[:REJECTED_PAYLOAD_KEPT] and sample.size == len(payload)
    assert len(sample.detail) == 1024


# --- the log limiter ------------------------------------------------------------------------------------


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_invented_keys_do_not_defeat_the_log_limit_or_grow_its_tables() -> None:
    logger = logging.getLogger("test.bounds.limiter")
    lines = _Lines()
    logger.addHandler(lines)
    logger.propagate = False
    now = [0.0]
    limiter = RateLimitedLog(logger, interval_s=10.0, clock=lambda: now[0], max_lines=5, max_keys=100)
    try:
        for i in range(10_000):
            limiter.log(("junk", i), logging.WARNING, "telemetry rejected")
        # One line per key would be 10,000: the overall budget allowed 5 in the interval.
        assert len(lines.records) == 5 and limiter.keys <= 100
        now[0] = 10.0
        limiter.log(("junk", "next"), logging.WARNING, "telemetry rejected")
        # The next line says how many were held back elsewhere.
        assert lines.records[-1].suppressed_elsewhere == 9_995  # type: ignore[attr-defined]
        # The per-key limit still holds for a key that repeats.
        assert not limiter.log(("junk", "next"), logging.WARNING, "telemetry rejected")
    finally:
        logger.removeHandler(lines)


# --- the decoder's units=auto table ---------------------------------------------------------------------


def _valid(device: str, i: int) -> bytes:
    return encode(
        make_payload(device, 0.1 * i, "ticks", random.Random(i), timestamp_ms=1_763_000_000_000 + i)
    )


def test_the_decoder_forgets_a_device_and_caps_what_it_decided() -> None:
    decoder = TelemetryDecoder(DecoderConfig(units=Units.AUTO, auto_evidence_messages=1))
    decoder.decode(_valid("arm-001", 1))
    assert decoder.units_for("arm-001") is Units.TICKS
    decoder.forget("arm-001")
    assert decoder.units_for("arm-001") is Units.AUTO
    decoder.restore_units({"arm-002": Units.TICKS})
    assert decoder.decided_units() == {"arm-002": Units.TICKS}
    for i in range(MAX_DECIDED_DEVICES + 10):
        decoder.restore_units({f"junk-{i}": Units.TICKS})
    assert len(decoder.decided_units()) == MAX_DECIDED_DEVICES


# --- a running agent flooded with invented device ids -----------------------------------------------------

JUNK_IDS = 100_000
VALID_JUNK_IDS = 3_000  # of them, this many send valid telemetry (3 messages each: units=auto decides)
MAX_DEVICES = 50


@pytest.mark.slow
def test_100000_junk_device_ids_leave_every_per_device_table_within_its_cap() -> None:
    config = load_config(
        None,
        {
            "broker.url": NO_BROKER,  # never answers: the test feeds the agent
            "http.listen": "127.0.0.1:0",
            "telemetry.units": "auto",
            "telemetry.max_devices": MAX_DEVICES,
        },
    )
    agent = AgentService(config)
    agent.start()
    try:
        mirror = agent._in_process()
        fed = 0
        for i in range(JUNK_IDS):
            device = f"junk-{i:06d}"
            topic = f"dt/lerobot/{device}/telemetry"
            if i < VALID_JUNK_IDS:
                for k in range(3):
                    agent.feed(topic, _valid(device, 3 * i + k))
                    fed += 1
            else:
                agent.feed(topic, b"{not json" if i % 2 else b'{"device_id": 5}')
                fed += 1
        agent.feed("dt/lerobot/too/many/levels", b"{}")  # a topic that names no device
        fed += 1

        def drained() -> bool:
            state = agent.state()
            return state.agent.worker.processed + state.agent.mailbox.overwritten_total == fed

        wait_for(drained, 120, "the agent to handle (or drop, counted) every message", interval=0.2)
        state = agent.state()
        decoder = mirror._decoder
        assert len(mirror._devices) <= MAX_DEVICES and len(state.devices) <= MAX_DEVICES
        assert len(mirror._fleet.devices) <= MAX_DEVICES and len(mirror._loss) <= MAX_DEVICES
        # The alarm engine has a row per device it evaluated: admitted devices only.
        assert len(mirror._alarms._devices) <= MAX_DEVICES
        # The agent's routes from topics to shards start over at their cap.
        assert len(agent._routes) <= MAX_ROUTES
        # units=auto decided for the admitted devices only: every refused one was forgotten.
        assert len(decoder.decided_units()) <= MAX_DEVICES
        assert len(decoder._streaks) <= 4096 and len(decoder._known_ids) <= 4096
        assert mirror._mailbox.queue.overflowed_keys <= MAX_OVERFLOW_KEYS  # the in-process queue
        assert mirror._reject_log.keys <= 1024 and mirror._error_log.keys <= 1024
        # The console's rejection events are throttled per (device, reason), for the most recent keys only.
        assert len(mirror._rejections._next) <= MAX_THROTTLE_KEYS
        assert len(mirror._rejections._pending) <= MAX_THROTTLE_KEYS
        # Untracked rejections are counted by reason, not by device.
        assert len(state.untracked_rejected) <= 32
        assert UNTRACKED_KEY not in state.devices
        # Every message is accounted for: against its device, untracked by reason, or dropped (counted) by
        # the full queue.
        counted = sum(d.health.counters.received for d in state.devices.values())
        untracked = sum(state.untracked_rejected.values())
        assert counted + untracked == state.agent.worker.processed
        assert counted + untracked + state.agent.mailbox.overwritten_total == fed
    finally:
        agent.stop()


def test_every_valid_message_of_an_arm_kept_out_by_max_devices_counts_as_too_many_devices(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A walk's 40 arms under max_devices = 30, units=auto: each refusal forgot the arm's units, so units=auto
    gathered them again, two of every three of its messages were counted as units_undecided instead of
    too_many_devices (the CloudWatch count the DeviceLimitReached alarm reads), and its units decision was
    logged three times a second."""
    config = load_config(
        None,
        {
            "broker.url": NO_BROKER,
            "http.listen": "127.0.0.1:0",
            "telemetry.units": "auto",
            "telemetry.max_devices": 2,
        },
    )
    agent = AgentService(config)
    caplog.set_level(logging.INFO, logger="twin.core.telemetry")
    agent.start()
    try:
        fed = 0
        for device in ("arm-001", "arm-002", "arm-003"):  # the third finds both places taken
            for i in range(9):
                agent.feed(f"dt/lerobot/{device}/telemetry", _valid(device, i))
                fed += 1
        wait_for(lambda: agent.state().messages_handled() == fed, 30, "every message counted", interval=0.05)
        untracked = agent.state().untracked_rejected
    finally:
        agent.stop()
    # units=auto turns away the first two messages of each admitted arm; each of the third is refused.
    assert untracked == {"units_undecided": 4, "too_many_devices": 9}
    assert not [r for r in caplog.records if "arm-003: units=auto decided" in r.getMessage()]
    # A fleet whose ids come and go fills its places with arms that left: the advice says how to free them.
    (refusal,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("device ignored")]
    assert "telemetry.forget_offline_after_s" in refusal, refusal
