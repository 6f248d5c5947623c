"""LatestValueMailbox: newest value per key, counted overwrites, waiting, closing, many threads."""

from __future__ import annotations

import threading
import time

import pytest
from twin.transport.mailbox import LatestValueMailbox


def test_latest_value_wins_and_overwrites_are_counted() -> None:
    box: LatestValueMailbox[int] = LatestValueMailbox()
    box.put("arm-001", 1)
    box.put("arm-002", 10)
    box.put("arm-001", 2)
    box.put("arm-001", 3)
    # arm-001's newest value arrived last, so it comes last.
    assert box.take_all(timeout=0) == [("arm-002", 10), ("arm-001", 3)]
    assert box.overwritten["arm-001"] == 2
    assert box.overwritten["arm-002"] == 0
    assert box.overwritten_total == 2
    assert box.put_count == 4
    assert box.take_all(timeout=0) == []
    box.put("arm-001", 4)
    assert box.take_all(timeout=0) == [("arm-001", 4)]
    assert box.overwritten["arm-001"] == 2


def test_take_all_times_out_empty() -> None:
    box: LatestValueMailbox[int] = LatestValueMailbox()
    start = time.monotonic()
    assert box.take_all(timeout=0.1) == []
    assert 0.08 <= time.monotonic() - start < 1.0


def test_take_all_wakes_on_put_from_another_thread() -> None:
    box: LatestValueMailbox[str] = LatestValueMailbox()
    timer = threading.Timer(0.05, box.put, args=("arm-001", "pose"))
    timer.start()
    start = time.monotonic()
    assert box.take_all(timeout=5) == [("arm-001", "pose")]
    assert time.monotonic() - start < 2.0
    timer.join()


def test_close_wakes_waiters_and_drains() -> None:
    box: LatestValueMailbox[int] = LatestValueMailbox()
    results: list[list[tuple[str, int]]] = []
    waiter = threading.Thread(target=lambda: results.append(box.take_all(timeout=10)))
    waiter.start()
    time.sleep(0.05)
    box.close()
    waiter.join(timeout=2)
    assert not waiter.is_alive()
    assert results == [[]]
    assert box.closed
    box.put("arm-001", 1)
    assert box.take_all(timeout=10) == [("arm-001", 1)]
    start = time.monotonic()
    assert box.take_all(timeout=10) == []
    assert time.monotonic() - start < 0.5


def test_key_bound_refuses_new_keys() -> None:
    box: LatestValueMailbox[int] = LatestValueMailbox(max_keys=2)
    box.put("a", 1)
    box.put("b", 1)
    box.put("c", 1)
    box.put("a", 2)  # an existing key still updates
    assert box.refused_keys == 1
    assert dict(box.take_all(timeout=0)) == {"a": 2, "b": 1}
    with pytest.raises(ValueError, match="max_keys"):
        LatestValueMailbox(max_keys=0)


def test_concurrent_producers_lose_nothing_but_overwrites() -> None:
    """Every put is either taken or counted as overwritten; per key, values taken only increase."""
    box: LatestValueMailbox[int] = LatestValueMailbox()
    producers, per_producer = 4, 5000
    taken: dict[str, list[int]] = {}
    done = threading.Event()

    def produce(index: int) -> None:
        key = f"arm-{index:03d}"
        for value in range(per_producer):
            box.put(key, value)

    def consume() -> None:
        while not (done.is_set() and len(box) == 0):
            for key, value in box.take_all(timeout=0.01):
                taken.setdefault(key, []).append(value)

    consumer = threading.Thread(target=consume)
    consumer.start()
    threads = [threading.Thread(target=produce, args=(i,)) for i in range(producers)]
    start = time.monotonic()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    elapsed = time.monotonic() - start
    done.set()
    consumer.join(timeout=5)
    assert not consumer.is_alive()

    assert box.put_count == producers * per_producer
    assert len(taken) == producers
    for key, values in taken.items():
        assert values == sorted(values) and len(set(values)) == len(values)
        assert values[-1] == per_producer - 1  # the newest value is never lost
        assert len(values) + box.overwritten[key] == per_producer
    # 20,000 puts from 4 threads on a 2-core box: well under a second even under load.
    assert elapsed < 2.0
