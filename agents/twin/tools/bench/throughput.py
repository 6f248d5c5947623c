"""Throughput: N simulated arms at R Hz through a private mosquitto into one agent process.

Two phases in one run, against the same broker with the same offered load:
1. ceiling: a subscriber built the way the agent builds its own, whose handler only counts;
2. agent: `twin run` (decode, validate, twin update with inverse dynamics, health) as a child process.
The publishers run in their own processes so their CPU is not charged to either. All of it shares this
machine's cores, so the figures are for the whole pipeline on one host: say so when quoting them.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

from twin.core.topics import ALL_DEVICES, topic_filters
from twin.service.state import AgentState
from twin.tools.bench.harness import (
    PREFIX,
    ProcessSampler,
    get_state,
    last_json_line,
    load_process,
    running_agent,
    start_publisher,
    wait_subscribed,
)
from twin.tools.rig import LocalRig

# One Python publisher process sustains well over 10,000 msg/s with pre-encoded payloads; beyond that the
# load is split so the publisher is not what limits the figure.
MSGS_PER_PUBLISHER = 10_000


def _publishers(url: str, arms: int, rate: float, seconds: float) -> list[Any]:
    count = max(1, min(4, math.ceil(arms * rate / MSGS_PER_PUBLISHER)))
    per = math.ceil(arms / count)
    procs = []
    for first in range(1, arms + 1, per):
        n = min(per, arms + 1 - first)
        procs.append(start_publisher(url, first, n, rate, seconds))
    return procs


def _collect(procs: list[Any], timeout: float) -> dict[str, Any]:
    sent = failures = late = 0
    elapsed = 0.0
    for proc in procs:
        out, err = proc.communicate(timeout=timeout)
        if proc.returncode != 0:
            raise RuntimeError(f"a publisher failed ({proc.returncode}): {err[-800:]}")
        result = last_json_line(out)
        sent += result["sent"]
        failures += result["publish_failures"]
        late += result["late_slots"]
        elapsed = max(elapsed, result["elapsed_s"])
    return {"sent": sent, "publish_failures": failures, "late_slots": late, "elapsed_s": elapsed}


def _ceiling(url: str, arms: int, rate: float, seconds: float) -> dict[str, Any]:
    noop = load_process(
        "noop",
        "--url",
        url,
        "--filter",
        *topic_filters(PREFIX, [ALL_DEVICES]),
        "--seconds",
        str(seconds + 30),
    )
    ready = noop.stdout.readline()
    if '"ready"' not in ready:
        noop.kill()
        raise RuntimeError(f"the no-op subscriber did not start: {noop.stderr.read()[-800:]}")
    sampler = ProcessSampler(noop.pid).start()
    pubs = _publishers(url, arms, rate, seconds)
    sent = _collect(pubs, timeout=seconds + 60)
    time.sleep(1.0)  # in-flight messages
    usage = sampler.stop()
    noop.terminate()
    out, _ = noop.communicate(timeout=30)
    result = last_json_line(out)
    received = result["received"]
    return {
        **sent,
        "received": received,
        "lost": max(0, sent["sent"] - received),
        "sustained_rate": received / sent["elapsed_s"] if sent["elapsed_s"] else 0.0,
        **usage,
    }


def _sum_devices(state: AgentState, counter: str) -> int:
    return sum(getattr(d.counters, counter) for d in state.devices.values())


def _drained(base: str) -> AgentState:
    """The state once the worker has drained what it already received (processed stops growing; bounded)."""
    deadline = time.monotonic() + 10
    state = get_state(base, timeout=30)
    while time.monotonic() < deadline:
        time.sleep(0.5)
        newer = get_state(base, timeout=30)
        if newer.agent.worker.processed == state.agent.worker.processed:
            return newer
        state = newer
    return state


def agent_phase(
    rig: LocalRig,
    arms: int,
    rate: float,
    seconds: float,
    *,
    history: str | None = None,
    config_text: str = "",
) -> dict[str, Any]:
    """The agent (`twin run`, with history at `history` and `config_text` sections) under the offered load;
    its figures from /state."""
    with running_agent(rig, history=history, config_text=config_text) as (proc, base):
        wait_subscribed(base, proc)
        before = get_state(base)
        sampler = ProcessSampler(proc.pid).start()
        pubs = _publishers(rig.broker.url, arms, rate, seconds)
        sent = _collect(pubs, timeout=seconds + 60)
        state = _drained(base)
        usage = sampler.stop()
        if proc.poll() is not None:
            raise RuntimeError(f"the agent exited during the run (code {proc.returncode})")
    received = state.agent.broker.messages - before.agent.broker.messages
    applied = _sum_devices(state, "applied")
    elapsed = sent["elapsed_s"]
    return {
        **sent,
        "received": received,
        "lost": max(0, sent["sent"] - received),
        "applied": applied,
        "coalesced": _sum_devices(state, "overwritten"),
        # Per device, plus those counted before a device was known (e.g. units_undecided while `auto`
        # gathers evidence from a new arm's first messages).
        "rejected": _sum_devices(state, "rejected_total") + sum(state.untracked_rejected.values()),
        "ignored_stale": _sum_devices(state, "ignored_stale"),
        "devices_seen": len(state.devices),
        "sustained_rate": received / elapsed if elapsed else 0.0,
        # Messages that reached the twin (decoded and applied) per second; the rest of `received` was
        # coalesced by the latest-value mailbox (a newer pose of the same arm replaced it) or rejected.
        "mirrored_rate": applied / elapsed if elapsed else 0.0,
        "history": dataclasses.asdict(state.agent.history) if state.agent.history else None,
        "internal_latency_s": dataclasses.asdict(state.agent.latency.internal_s),
        "end_to_end_latency_s": dataclasses.asdict(state.agent.latency.end_to_end_s),
        "sinks": [dataclasses.asdict(sink) for sink in state.agent.sinks],
        **usage,
    }


def run(*, arms: int = 2000, rate: float = 10.0, seconds: float = 20.0) -> dict[str, Any]:
    """Both phases with the same offered load; returns every figure as one JSON-ready dict."""
    with LocalRig() as rig:
        ceiling = _ceiling(rig.broker.url, arms, rate, seconds)
        agent = agent_phase(rig, arms, rate, seconds)
    ratio = agent["sustained_rate"] / ceiling["sustained_rate"] if ceiling["sustained_rate"] else None
    return {
        "scenario": "throughput",
        "arms": arms,
        "rate_hz": rate,
        "seconds": seconds,
        "offered_rate": arms * rate,
        "ceiling": ceiling,
        "agent": agent,
        "agent_to_ceiling_ratio": ratio,
        "notes": (
            "publishers, broker, no-op subscriber and agent share this host's cores; end-to-end latency is "
            "twin-updated wall time minus the publish timestamp (whole milliseconds, same host clock)"
        ),
    }
