"""Worker: what one worker process spends per message, without a broker, publishers or another process.

A `Mirror` is built as a worker process of `twin run --workers N` builds it (fed through a pipe, `PipeInbox`),
and this process writes the fleet's messages into the other end as the agent does (transport.pipe, batches of
up to shards.MAX_BATCH). The payloads are the edge's mock ones (raw ticks with every diagnostic,
as `twin edge-sim` sends them), each arm at its own phase of the mock motion, with 10 Hz edge timestamps. The
figure is the CPU time of this process (both threads; the pickling here is about what the receiving
process's sender pays) per message: for the fleet's first messages (every arm new) and for the rounds after
them, with the servo alarm engine on and off. No wall-clock rate is imposed: the worker runs flat out, so
this is the cost of a message, not a latency.

    twin bench worker [--arms 1000] [--rounds 40] [--json]
"""

from __future__ import annotations

import logging
import os
import random
import time
from multiprocessing import Pipe
from multiprocessing.connection import Connection
from typing import Any

from twin.core.topics import DEFAULT_TOPIC_PREFIX, telemetry_topic
from twin.edge.payload import encode, make_payload
from twin.service.admission import DeviceBudget
from twin.service.config import load_config
from twin.service.mirror import Mirror, PipeInbox
from twin.service.shards import MAX_BATCH
from twin.transport.pipe import Message, send_batch, send_end

POSES = 64
T0_MS = 1_764_000_000_000
MARKER = 1_111_111_111_111


def _fleet(arms: int, rounds: int, seed: int = 1) -> list[list[tuple[str, str, bytes]]]:
    """One list of (device, topic, payload) per round: every arm once, in arm order."""
    rng = random.Random(seed)
    devices = [f"arm-{i:04d}" for i in range(1, arms + 1)]
    templates = {
        d: [
            encode(make_payload(d, k * 0.1, "ticks", rng, timestamp_ms=MARKER)).split(b"%d" % MARKER)
            for k in range(POSES)
        ]
        for d in devices
    }
    phase = {d: rng.randrange(POSES) for d in devices}
    topics = {d: telemetry_topic(DEFAULT_TOPIC_PREFIX, d) for d in devices}
    out = []
    for r in range(rounds):
        stamp = b"%d" % (T0_MS + r * 100)
        messages = []
        for d in devices:
            before, after = templates[d][(r + phase[d]) % POSES]
            messages.append((d, topics[d], before + stamp + after))
        out.append(messages)
    return out


def _case(arms: int, rounds: int, *, alarms: bool) -> dict[str, Any]:
    config = load_config(
        None,
        {
            "telemetry.devices": ["*"],
            "telemetry.units": "ticks",
            "telemetry.max_devices": max(64, arms),
            "alarms.enabled": alarms,
            "log.level": "WARNING",
        },
    )
    fleet = _fleet(arms, rounds)
    reader, writer = Pipe(duplex=False)
    service = Mirror(config, inbox=PipeInbox(reader), budget=DeviceBudget(config.telemetry.max_devices))
    service.start()
    try:
        first = _feed(service, writer, fleet[:1])
        rest = _feed(service, writer, fleet[1:])
    finally:
        send_end(writer)
        service.stop(timeout=30.0)
        writer.close()
    return {
        "alarms": alarms,
        "first_message_us": first,
        "message_us": rest,
        "errors": service.errors,
    }


def _feed(service: Mirror, writer: Connection, rounds: list[list[tuple[str, str, bytes]]]) -> float:
    """CPU microseconds of this process per message while the worker handles `rounds`."""
    total = sum(len(r) for r in rounds)
    target = service.processed + total
    started = time.process_time()
    for messages in rounds:
        now_mono, now_wall = time.monotonic(), time.time()
        for i in range(0, len(messages), MAX_BATCH):
            batch: list[Message] = [
                (d, (t, p, now_mono, now_wall)) for d, t, p in messages[i : i + MAX_BATCH]
            ]
            send_batch(writer, batch)
    deadline = time.monotonic() + 120.0
    while service.processed < target and time.monotonic() < deadline:
        time.sleep(0.001)
    if service.processed < target:
        raise RuntimeError(f"the worker handled {service.processed} of {target} messages in 120 s")
    return (time.process_time() - started) / total * 1e6


def run(*, arms: int = 1000, rounds: int = 40) -> dict[str, Any]:
    load_before = os.getloadavg()[0]
    # The mock's random currents raise and clear alarms; their log lines are not what is measured here.
    agent_log = logging.getLogger("twin")
    level = agent_log.level
    agent_log.setLevel(logging.CRITICAL + 1)
    try:
        cases = [_case(arms, rounds, alarms=True), _case(arms, rounds, alarms=False)]
    finally:
        agent_log.setLevel(level)
    return {
        "scenario": "worker",
        "arms": arms,
        "rounds": rounds,
        "payload": "edge mock, ticks, every diagnostic; arms at their own phase of the motion",
        "cases": cases,
        "load_average_1m": {"before": load_before, "after": os.getloadavg()[0]},
        "notes": "CPU time of one process (the worker thread and the pickling that feeds it) per message",
    }
