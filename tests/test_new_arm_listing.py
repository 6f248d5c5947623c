"""A discovered arm is listed once its first message is counted, not when its record is made.

The mirror admits a new arm while decoding a batch and counts the arm's message a stage later (service.mirror,
`_admit`, then `_record_all`). A reader between the two saw the arm with nothing received and status OFFLINE.
The mirror is driven in this process: the test admits an arm as decoding does, reads it as the console and the
agent's state do, then lets its first message through and waits until it is counted.
"""

from __future__ import annotations

import random
import time
from collections.abc import Iterator

import pytest
from conftest import NO_BROKER, wait_for
from twin.edge.payload import encode, make_payload
from twin.service.admission import DeviceBudget
from twin.service.config import load_config
from twin.service.mirror import Mirror, QueuedMessage, QueueInbox
from twin.transport.mailbox import InboundQueue

NEW = "arm-new"


@pytest.fixture
def mirror() -> Iterator[tuple[Mirror, InboundQueue[QueuedMessage]]]:
    config = load_config(
        None, {"broker.url": NO_BROKER, "telemetry.devices": ["*"], "telemetry.units": "ticks"}
    )
    queue: InboundQueue[QueuedMessage] = InboundQueue()
    service = Mirror(config, inbox=QueueInbox(queue), budget=DeviceBudget(config.telemetry.max_devices))
    yield service, queue
    service.stop()


def test_an_admitted_arm_is_not_listed_before_its_first_message_is_counted(
    mirror: tuple[Mirror, InboundQueue[QueuedMessage]],
) -> None:
    service, queue = mirror
    # What decoding a new arm's first valid message does, before the health stage counts it.
    assert service._admit(NEW) is not None
    assert [row.device for row in service.fleet_rows()] == []
    assert NEW not in service.report().devices
    assert NEW not in service.statuses()
    assert service.arm(NEW).state is None

    service.start()
    payload = encode(make_payload(NEW, 0.0, "ticks", random.Random(3), timestamp_ms=int(time.time() * 1000)))
    queue.put(NEW, (f"dt/lerobot/{NEW}/telemetry", payload, time.monotonic(), time.time()))
    wait_for(lambda: service.processed >= 1, 30, "the arm's first message handled")
    rows = service.fleet_rows()
    assert [row.device for row in rows] == [NEW]
    assert rows[0].status == "ONLINE"
    state = service.arm(NEW).state
    assert state is not None and state.health.counters.received == 1
    assert service.report().devices[NEW].health.counters.received == 1
