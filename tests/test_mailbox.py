"""InboundQueue: arrival order kept, the oldest dropped and counted when full, waiting, closing, threads."""

from __future__ import annotations

import threading
import time

import pytest
from twin.service.mirror import QueueInbox
from twin.transport.mailbox import InboundQueue


def test_items_come_out_in_arrival_order_nothing_replaced() -> None:
    queue: InboundQueue[int] = InboundQueue()
    queue.put("arm-001", 1)
    queue.put("arm-002", 10)
    queue.put("arm-001", 2)
    assert len(queue) == 3
    assert queue.take_all(timeout=0) == [("arm-001", 1), ("arm-002", 10), ("arm-001", 2)]
    assert queue.put_count == 3 and queue.overflowed_total == 0
    assert queue.take_all(timeout=0) == []


def test_a_full_queue_drops_the_oldest_and_counts_it_per_key() -> None:
    queue: InboundQueue[int] = InboundQueue(max_items=3)
    for key, value in [("a", 1), ("b", 1), ("a", 2), ("c", 1), ("a", 3)]:
        queue.put(key, value)
    # ("a", 1) then ("b", 1) went to make room; the newest three remain, in order.
    assert queue.take_all(timeout=0) == [("a", 2), ("c", 1), ("a", 3)]
    assert queue.overflowed == {"a": 1, "b": 1}
    assert queue.overflowed_total == 2 and queue.put_count == 5
    with pytest.raises(ValueError, match="max_items"):
        InboundQueue(max_items=0)


def test_take_all_times_out_empty() -> None:
    queue: InboundQueue[int] = InboundQueue()
    start = time.monotonic()
    assert queue.take_all(timeout=0.1) == []
    assert time.monotonic() - start >= 0.08


def test_take_all_wakes_on_put_from_another_thread() -> None:
    queue: InboundQueue[str] = InboundQueue()
    timer = threading.Timer(0.05, queue.put, args=("arm-001", "payload"))
    timer.start()
    assert queue.take_all(timeout=10) == [("arm-001", "payload")]
    timer.join()


def test_close_wakes_waiters_and_drains() -> None:
    queue: InboundQueue[int] = InboundQueue()
    results: list[list[tuple[str, int]]] = []
    waiter = threading.Thread(target=lambda: results.append(queue.take_all(timeout=10)))
    waiter.start()
    # Most likely the waiter is blocked by now, the case this is about; if not, take_all on a closed, empty
    # queue returns [] at once, so the checks below hold either way.
    time.sleep(0.05)
    queue.close()
    waiter.join(timeout=30)
    assert not waiter.is_alive()
    assert results == [[]]
    assert queue.closed
    queue.put("arm-001", 1)
    assert queue.take_all(timeout=10) == [("arm-001", 1)]
    # Closed and drained: returns at once instead of waiting out the timeout.
    assert queue.take_all(timeout=10) == []


def test_concurrent_producers_lose_nothing_under_the_bound() -> None:
    """Every put is taken exactly once, and each producer's items come out in the order it put them."""
    queue: InboundQueue[int] = InboundQueue()
    producers, per_producer = 4, 5000
    taken: dict[str, list[int]] = {}
    done = threading.Event()

    def produce(index: int) -> None:
        key = f"arm-{index:03d}"
        for value in range(per_producer):
            queue.put(key, value)

    def consume() -> None:
        while not (done.is_set() and len(queue) == 0):
            for key, value in queue.take_all(timeout=0.01):
                taken.setdefault(key, []).append(value)

    consumer = threading.Thread(target=consume)
    consumer.start()
    threads = [threading.Thread(target=produce, args=(i,)) for i in range(producers)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    done.set()
    consumer.join(timeout=10)
    assert not consumer.is_alive()
    assert queue.put_count == producers * per_producer and queue.overflowed_total == 0
    assert {key: values for key, values in taken.items()} == {
        f"arm-{i:03d}": list(range(per_producer)) for i in range(producers)
    }


def test_a_closed_gate_holds_the_messages_and_opening_hands_them_over_in_order() -> None:
    """An in-process mirror's inbox made shut (the agent opens it once the state file and the calibrations
    are in): nothing is handed over, a take returns at its timeout, then everything in arrival order."""
    queue: InboundQueue[tuple[str, bytes, float, float]] = InboundQueue(100)
    gate = QueueInbox(queue, opened=False)
    for k in range(3):
        queue.put("arm-001", ("t", b"%d" % k, float(k), float(k)))
    assert gate.take(0.01).payloads == ()
    assert len(gate) == 3
    gate.open()
    assert gate.take(0.01).payloads == (b"0", b"1", b"2")


def test_closing_a_shut_gate_lets_what_it_held_drain() -> None:
    queue: InboundQueue[tuple[str, bytes, float, float]] = InboundQueue(100)
    gate = QueueInbox(queue, opened=False)
    queue.put("arm-001", ("t", b"x", 0.0, 0.0))
    gate.close()
    assert gate.take(0.01).payloads == (b"x",)
    assert gate.take(0.01).payloads == () and gate.closed
