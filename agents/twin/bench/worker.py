"""Worker: what one worker process spends per message, without a broker, publishers or another process.

A `Mirror` is built as a worker process of `twin run --workers N` builds it (fed through a pipe, `PipeInbox`),
and this process writes the fleet's messages into the other end as the agent does (transport.pipe, batches of
up to shards.MAX_BATCH). The payloads are the edge's mock ones (raw ticks with every diagnostic,
as `twin edge-sim` sends them), each arm at its own phase of the mock motion, with 10 Hz edge timestamps. The
figure is the CPU time of this process (both threads; the pickling here is about what the receiving
process's sender pays) per message: for the fleet's first messages (every arm new) and for the rounds after
them, with the servo alarm engine on and off. No wall-clock rate is imposed: the worker runs flat out, so
this is the cost of a message, not a latency.

With `--batch N [N ...]` it measures instead what a batch costs whatever its size, with the alarm engine on:
the rounds go over in batches of N, each handed over only once the worker has handled the one before, so the
worker starts every batch from idle, as the agent's does between its sender's pauses (service.shards,
BATCH_TARGET). Per size: CPU per message in microseconds and in `json.loads` of the same edge message (timed
in this process before and after each size: the median of both); and a least-squares line through the sizes,
CPU per batch = fixed + per message x N, which says how much of a small batch's cost is the batch itself.

    twin bench worker [--arms 1000] [--rounds 40] [--batch N [N ...]] [--json]
"""

from __future__ import annotations

import json
import logging
import os
import random
import statistics
import time
from multiprocessing import Pipe
from multiprocessing.connection import Connection
from typing import Any

from twin.core.topics import DEFAULT_TOPIC_PREFIX, telemetry_topic
from twin.edge.payload import encode, make_payload
from twin.service.admission import DeviceBudget
from twin.service.config import AgentConfig, load_config
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


def _config(arms: int, *, alarms: bool) -> AgentConfig:
    """A worker's config for the whole fleet in ticks, the alarm engine on or off."""
    return load_config(
        None,
        {
            "telemetry.devices": ["*"],
            "telemetry.units": "ticks",
            "telemetry.max_devices": max(64, arms),
            "alarms.enabled": alarms,
            "log.level": "WARNING",
        },
    )


def _case(arms: int, rounds: int, *, alarms: bool) -> dict[str, Any]:
    config = _config(arms, alarms=alarms)
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


def run(*, arms: int = 1000, rounds: int = 40, batches: list[int] | None = None) -> dict[str, Any]:
    load_before = os.getloadavg()[0]
    # The mock's random currents raise and clear alarms; their log lines are not what is measured here.
    agent_log = logging.getLogger("twin")
    level = agent_log.level
    agent_log.setLevel(logging.CRITICAL + 1)
    try:
        if batches:
            return {
                "scenario": "worker-batches",
                "arms": arms,
                "rounds": rounds,
                **_by_batch(arms, rounds, batches),
                "load_average_1m": {"before": load_before, "after": os.getloadavg()[0]},
                "notes": "CPU time of one process (the worker thread and the pickling that feeds it) per "
                "message, each batch handed over once the one before was handled; alarms on",
            }
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


def _by_batch(arms: int, rounds: int, sizes: list[int]) -> dict[str, Any]:
    """CPU per message at each batch size (one mirror, its arms known from a first round), and the line
    through them."""
    config = _config(arms, alarms=True)
    fleet = _fleet(arms, 1 + rounds * len(sizes))
    probe_message = fleet[0][0][2]
    reader, writer = Pipe(duplex=False)
    service = Mirror(config, inbox=PipeInbox(reader), budget=DeviceBudget(config.telemetry.max_devices))
    service.start()
    rows: list[dict[str, Any]] = []
    try:
        _feed(service, writer, fleet[:1])  # every arm known: what follows is the steady state
        for n, size in enumerate(sizes):
            before = _loads_us(probe_message)
            message_us = _feed_one_by_one(service, writer, fleet[1 + n * rounds : 1 + (n + 1) * rounds], size)
            loads_us = statistics.median([before, _loads_us(probe_message)])
            rows.append(
                {
                    "batch": size,
                    "message_us": message_us,
                    "json_loads_us": loads_us,
                    "loads": message_us / loads_us,
                }
            )
    finally:
        send_end(writer)
        service.stop(timeout=30.0)
        writer.close()
    return {
        "errors": service.errors,
        "sizes": rows,
        "fit": _line([r["batch"] for r in rows], [r["message_us"] * r["batch"] for r in rows]),
    }


def _feed_one_by_one(
    service: Mirror, writer: Connection, rounds: list[list[tuple[str, str, bytes]]], size: int
) -> float:
    """CPU microseconds of this process per message, the rounds handed over `size` messages at a time, each
    batch once the worker has handled the one before (it waits idle in between, as in the agent)."""
    total = 0
    base = service.processed
    started = time.process_time()
    for messages in rounds:
        for i in range(0, len(messages), size):
            now_mono, now_wall = time.monotonic(), time.time()
            batch: list[Message] = [(d, (t, p, now_mono, now_wall)) for d, t, p in messages[i : i + size]]
            send_batch(writer, batch)
            total += len(batch)
            deadline = time.monotonic() + 30.0
            while service.processed < base + total:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the worker did not handle a batch of {len(batch)} in 30 s")
                time.sleep(0.0002)
    return (time.process_time() - started) / total * 1e6


def _loads_us(message: bytes, calls: int = 400) -> float:
    """Median CPU time (process clock) of one `json.loads` of the edge message, in microseconds."""
    times = []
    for _ in range(calls):
        started = time.process_time()
        json.loads(message)
        times.append(time.process_time() - started)
    return statistics.median(times) * 1e6


def _line(sizes: list[int], batch_us: list[float]) -> dict[str, float | None]:
    """Least squares CPU per batch = per_batch_us + per_message_us x size (None with fewer than two sizes)."""
    if len(set(sizes)) < 2:
        return {"per_batch_us": None, "per_message_us": None}
    slope, intercept = statistics.linear_regression(sizes, batch_us)
    return {"per_batch_us": intercept, "per_message_us": slope}
