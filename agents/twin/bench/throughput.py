"""Throughput: N simulated arms at R Hz through a private mosquitto into one agent process.

Two phases in one run, against the same broker with the same offered load:
1. ceiling: a subscriber built the way the agent builds its own, whose handler only counts;
2. agent: `twin run` (decode and validate every message, twin update, loss estimate, health) as a child
   process; forward kinematics and inverse dynamics are computed when read, which the benchmark does not.
The publishers run in their own processes so their CPU is not charged to either. All of it shares this
machine's cores, so the figures are for the whole pipeline on one host: say so when quoting them.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

from twin.bench.harness import (
    PREFIX,
    ProcessSampler,
    collect,
    drained,
    get_state,
    last_json_line,
    load_process,
    publishers,
    running_agent,
    stop_figures,
    sum_devices,
    wait_subscribed,
)
from twin.core.topics import ALL_DEVICES, topic_filters
from twin.rig.local import LocalRig


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
    assert noop.stdout is not None and noop.stderr is not None  # load_process pipes both
    ready = noop.stdout.readline()
    if '"ready"' not in ready:
        noop.kill()
        raise RuntimeError(f"the no-op subscriber did not start: {noop.stderr.read()[-800:]}")
    sampler = ProcessSampler(noop.pid).start()
    pubs = publishers(url, arms, rate, seconds)
    sent = collect(pubs, timeout=seconds + 60)
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
        pubs = publishers(rig.broker.url, arms, rate, seconds)
        sent = collect(pubs, timeout=seconds + 60)
        state = drained(base)
        usage = sampler.stop()
        if proc.poll() is not None:
            raise RuntimeError(f"the agent exited during the run (code {proc.returncode})")
        stopping = time.monotonic()
    stop = {
        # SIGTERM to exit (the rig waits out the agent's shutdown budget), and what the agent said it could
        # not write: its `agent stopped` line is logged only then (at ERROR; the run logs WARNING and up).
        "stop_s": round(time.monotonic() - stopping, 3),
        "exit_code": proc.returncode,
        **stop_figures(rig, base),
    }
    received = state.agent.broker.messages - before.agent.broker.messages
    applied = sum_devices(state, "applied")
    elapsed = sent["elapsed_s"]
    return {
        **sent,
        "received": received,
        "lost": max(0, sent["sent"] - received),
        "applied": applied,
        "decoded": sum_devices(state, "decoded"),
        "coalesced": sum_devices(state, "coalesced"),
        "overwritten": sum_devices(state, "overwritten"),
        # Per device, plus those counted before a device was known (e.g. units_undecided while `auto`
        # gathers evidence from a new arm's first messages).
        "rejected": sum_devices(state, "rejected_total") + sum(state.untracked_rejected.values()),
        "ignored_stale": sum_devices(state, "ignored_stale"),
        "devices_seen": len(state.devices),
        # Worker processes that mirrored the fleet (`--workers`; 1 = the agent in one process).
        "workers": len(state.agent.workers) or 1,
        "sustained_rate": received / elapsed if elapsed else 0.0,
        # Messages that reached the twin (decoded and applied) per second; the rest of `received` was
        # rejected, ignored as stale, coalesced while the worker caught up (decoded, counted, kept in history,
        # not applied), or dropped undecoded because the agent's queue was full ("overwritten").
        "mirrored_rate": applied / elapsed if elapsed else 0.0,
        "history": dataclasses.asdict(state.agent.history) if state.agent.history else None,
        "internal_latency_s": dataclasses.asdict(state.agent.latency.internal_s),
        "end_to_end_latency_s": dataclasses.asdict(state.agent.latency.end_to_end_s),
        "sinks": [dataclasses.asdict(sink) for sink in state.agent.sinks],
        "stop": stop,
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
