"""Load processes for the benchmarks: a fleet publisher, a no-op subscriber (the ceiling), a ROS 2 reader,
and the yardstick the cost benchmark measures the agent's CPU in (`json.loads` of one edge message, timed
again and again while the agent runs).

Each runs as its own process (`python -m twin.bench.load publish|noop ...`) so its CPU is not charged to
the agent under test, and prints one JSON line with its counts on exit. The publisher writes its packets
straight to the broker's socket (twin.bench.wire), so the load takes little of the cores it shares with
the agent. The no-op subscriber uses the project's own client construction (twin.transport.subscriber), so
the ceiling measures the same broker and client the agent uses, minus the agent's work.
"""

from __future__ import annotations

import argparse
import heapq
import itertools
import json
import logging
import random
import signal
import sys
import threading
import time
from typing import Any

from twin.bench.wire import WireError, WirePublisher, publish_packet, topic_field
from twin.core.topics import DEFAULT_TOPIC_PREFIX, telemetry_topic
from twin.edge.payload import encode, make_payload
from twin.transport.broker import BrokerConfig, new_client_id
from twin.transport.subscriber import TelemetrySubscriber

log = logging.getLogger(__name__)

# Distinct poses the publisher cycles through, so the twin really moves while the message cost stays that
# of one bytes concatenation (building each payload from scratch would make the publisher the bottleneck).
POSES = 64
# Each period is cut into this many slots; devices are spread over them, as a real fleet is not in lock step.
SLOTS_PER_PERIOD = 50


def _templates(device: str, topic: str, rng: random.Random) -> list[tuple[bytes, bytes]]:
    """Each pose's whole PUBLISH packet on `topic`, as (before, after) the timestamp digits: epoch
    milliseconds have 13 digits until the year 2286, so the packet's length is known without them."""
    marker = 1_111_111_111_111
    field = topic_field(topic)
    out = []
    for k in range(POSES):
        payload = make_payload(device, k * 0.1, "ticks", rng, timestamp_ms=marker)
        before, after = publish_packet(field, encode(payload)).split(str(marker).encode(), 1)
        out.append((before, after))
    return out


def publish(
    url: str,
    devices: list[str],
    rate_hz: float,
    seconds: float,
    prefix: str,
    *,
    seed: int = 1,
    jitter_ms: float = 0.0,
) -> dict[str, Any]:
    """Publish every device at rate_hz for `seconds`; timestamps are the wall clock of each sample's slot
    (milliseconds), as an edge stamps a sample when it takes it.

    `jitter_ms` delays each message by a random 0..jitter_ms after its sample, as the networks between real
    arms and the broker do (the timestamps stay on the sampling grid). Through `WirePublisher`: one write per
    time slot, so the load costs the shared cores little (its module doc says why)."""
    rng = random.Random(seed)
    schedule = _Schedule(devices, prefix, rng, jitter_ms)
    publisher = WirePublisher(url, new_client_id("bench-pub-"))
    publisher.connect()
    period = 1.0 / rate_hz
    slot_len = period / SLOTS_PER_PERIOD
    counts = {"sent": 0, "failures": 0}
    late_slots = 0
    start = time.monotonic()
    # Each sample is stamped with its slot's time on the wall clock, not the moment it goes out: an edge
    # stamps a sample when it takes it, and a publisher starved of CPU for a moment (late slots) must not
    # bunch its arms' timestamps, which the agent's loss estimate would read as gaps.
    wall_start = time.time()
    end = start + seconds
    k = 0
    while True:
        due = start + k * slot_len
        if due >= end:
            break
        now = time.monotonic()
        if due > now:
            time.sleep(due - now)
        elif now - due > period:
            late_slots += 1
        stamp = str(round((wall_start + (due - start)) * 1000)).encode()
        _send(publisher, schedule.slot(k, due, stamp), counts)
        k += 1
    _send(publisher, schedule.rest(), counts)
    elapsed = time.monotonic() - start
    publisher.close()  # returns once the broker has read everything (DISCONNECT, then its close)
    return {
        "sent": counts["sent"],
        "publish_failures": counts["failures"],
        "elapsed_s": elapsed,
        "late_slots": late_slots,
        "offered_rate": counts["sent"] / elapsed if elapsed else 0.0,
        "jitter_ms": jitter_ms,
    }


class _Schedule:
    """What each time slot sends: the packets of the arms whose sample falls in it, each held back
    0..jitter_ms after its sample, as pieces (before the timestamp, the timestamp, after it)."""

    def __init__(self, devices: list[str], prefix: str, rng: random.Random, jitter_ms: float) -> None:
        self._rng = rng
        self._jitter_s = jitter_ms / 1000.0
        self._templates = {d: _templates(d, telemetry_topic(prefix, d), rng) for d in devices}
        # Each arm moves on its own: a real fleet's arms are not in step, and a fleet that is turns every
        # arm's still moments (the alarm engine's model check) into one burst.
        self._phase = {d: rng.randrange(POSES) for d in devices}
        self._slots = [devices[i::SLOTS_PER_PERIOD] for i in range(SLOTS_PER_PERIOD)]
        self._delayed: list[tuple[float, int, tuple[bytes, bytes, bytes]]] = []  # (send at, order, pieces)
        self._order = itertools.count()

    def slot(self, k: int, due: float, stamp: bytes) -> list[bytes]:
        """Slot k's samples stamped `stamp` (those not held back), then every held-back one now due."""
        step = k // SLOTS_PER_PERIOD
        packets: list[bytes] = []
        for device in self._slots[k % SLOTS_PER_PERIOD]:
            before, after = self._templates[device][(step + self._phase[device]) % POSES]
            if self._jitter_s:
                send_at = due + self._rng.uniform(0.0, self._jitter_s)
                heapq.heappush(self._delayed, (send_at, next(self._order), (before, stamp, after)))
            else:
                packets += (before, stamp, after)
        delayed = self._delayed
        while delayed and delayed[0][0] <= time.monotonic():
            packets += heapq.heappop(delayed)[2]
        return packets

    def rest(self) -> list[bytes]:
        """Whatever is still held back, in order."""
        return [piece for _, _, pieces in sorted(self._delayed) for piece in pieces]


def _send(publisher: WirePublisher, packets: list[bytes], counts: dict[str, int]) -> None:
    """Write the pieces (three per message) in one go; count them as sent or failed."""
    if not packets:
        return
    try:
        publisher.send(packets)
        counts["sent"] += len(packets) // 3
    except WireError:
        counts["failures"] += len(packets) // 3


def noop(url: str, filters: list[str], seconds: float) -> dict[str, Any]:
    """Subscribe like the agent does and count messages, doing nothing else with them (the ceiling)."""
    count = [0]
    first: list[float] = []
    last = [0.0]

    def on_message(_topic: str, _payload: bytes, recv: float) -> None:
        if not first:
            first.append(recv)
        count[0] += 1
        last[0] = recv

    sub = TelemetrySubscriber(BrokerConfig(url=url, client_id_prefix="bench-noop-"), filters, on_message)
    sub.start()
    if not sub.wait_subscribed(10):
        raise SystemExit(f"noop subscriber: could not subscribe on {url}")
    print(json.dumps({"ready": True}), flush=True)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    stop.wait(seconds)
    sub.stop()
    span = (last[0] - first[0]) if first else 0.0
    return {"received": count[0], "active_s": span, "rate": count[0] / span if span > 0 else 0.0}


def ros2_reader(arms: list[str], seconds: float) -> dict[str, Any]:
    """Subscribe to every arm's JointState over DDS, as a ROS 2 node would (default QoS), and count samples.

    Runs only inside a loopback-only namespace (the ros2 scenario puts it there); needs the ros2 extra.
    """
    from cyclonedds.core import Listener, Policy, Qos  # noqa: PLC0415 - the optional ros2 extra
    from cyclonedds.domain import Domain, DomainParticipant  # noqa: PLC0415
    from cyclonedds.sub import DataReader  # noqa: PLC0415
    from cyclonedds.topic import Topic  # noqa: PLC0415
    from cyclonedds.util import duration  # noqa: PLC0415

    from twin.output.ros2 import Ros2Settings, cyclone_config, dds_topic_name, resolve_topic  # noqa: PLC0415
    from twin.output.ros2_idl import JointState_  # noqa: PLC0415

    settings = Ros2Settings()
    domain_id = settings.effective_domain_id()
    domain = Domain(domain_id, cyclone_config(settings))
    participant = DomainParticipant(domain_id)
    qos = Qos(
        Policy.Reliability.Reliable(duration(milliseconds=100)),
        Policy.Durability.Volatile,
        Policy.History.KeepLast(10),
    )
    lock = threading.Lock()
    count = [0]
    first: list[float] = []
    last = [0.0]

    def on_data_available(reader: Any) -> None:
        # Cyclone's listener thread: take (and so deserialize) what arrived, as a ROS 2 subscriber would.
        # Only data: a writer that leaves (the agent stopping) delivers one invalid sample per topic.
        got = sum(isinstance(sample, JointState_) for sample in reader.take(N=256))
        now = time.monotonic()
        with lock:
            if not first:
                first.append(now)
            count[0] += got
            last[0] = now

    listener = Listener(on_data_available=on_data_available)
    readers = []
    for arm in arms:
        topic = Topic(participant, dds_topic_name(resolve_topic(settings.topic, arm)), JointState_)
        readers.append(DataReader(participant, topic, qos=qos, listener=listener))
    print(json.dumps({"ready": True}), flush=True)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    stop.wait(seconds)
    with lock:
        received, span = count[0], (last[0] - first[0]) if first else 0.0
    readers.clear()
    del participant, domain
    return {"received": received, "active_s": span, "rate": received / span if span > 0 else 0.0}


def loads_probe(seconds: float, *, calls: int = 200, every_s: float = 0.25) -> None:
    """Time `json.loads` of one edge message (the fleet publisher's payload) in rounds of `calls`, every
    `every_s`, for `seconds` or until SIGTERM: one JSON line per round, {"at": monotonic s, "us": CPU us per
    call}. CPU time of this thread, not wall time: a round the scheduler interrupts still measures how fast
    the machine runs the call, which is what the agent's CPU time is divided by. Monotonic time is the whole
    host's, so the reader can keep the rounds of a window of its own."""
    payload = encode(make_payload("arm-0001", 1.0, "ticks", random.Random(1), timestamp_ms=1_764_000_000_000))
    loads = json.loads
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    print(json.dumps({"ready": True, "payload_bytes": len(payload)}), flush=True)
    end = time.monotonic() + seconds
    while not stop.is_set() and time.monotonic() < end:
        started = time.thread_time_ns()
        for _ in range(calls):
            loads(payload)
        spent = time.thread_time_ns() - started
        print(json.dumps({"at": time.monotonic(), "us": spent / calls / 1000.0}), flush=True)
        stop.wait(every_s)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twin.bench.load")
    sub = parser.add_subparsers(dest="role", required=True)
    p = sub.add_parser("publish")
    p.add_argument("--url", required=True)
    p.add_argument("--first", type=int, required=True, help="index of the first arm (arm-NNNN naming)")
    p.add_argument("--count", type=int, required=True)
    p.add_argument("--rate", type=float, required=True)
    p.add_argument("--seconds", type=float, required=True)
    p.add_argument("--prefix", default=DEFAULT_TOPIC_PREFIX)
    p.add_argument("--jitter-ms", type=float, default=0.0, help="network delay 0..J ms after each sample")
    n = sub.add_parser("noop")
    n.add_argument("--url", required=True)
    n.add_argument("--filter", action="append", required=True)
    n.add_argument("--seconds", type=float, required=True)
    r = sub.add_parser("ros2-reader")
    r.add_argument("--first", type=int, required=True, help="index of the first arm (arm-NNNN naming)")
    r.add_argument("--count", type=int, required=True)
    r.add_argument("--seconds", type=float, required=True)
    lp = sub.add_parser("loads-probe")
    lp.add_argument("--seconds", type=float, required=True)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    if args.role == "publish":
        devices = [arm_name(i) for i in range(args.first, args.first + args.count)]
        result = publish(args.url, devices, args.rate, args.seconds, args.prefix, jitter_ms=args.jitter_ms)
    elif args.role == "loads-probe":
        loads_probe(args.seconds)
        return 0
    elif args.role == "ros2-reader":
        arms = [arm_name(i) for i in range(args.first, args.first + args.count)]
        result = ros2_reader(arms, args.seconds)
    else:
        result = noop(args.url, args.filter, args.seconds)
    print(json.dumps(result), flush=True)
    return 0


def arm_name(index: int) -> str:
    """arm-0001 ..: four digits so a 2,000-arm fleet sorts and stays within the device-id rules."""
    return f"arm-{index:04d}"


if __name__ == "__main__":
    sys.exit(main())
