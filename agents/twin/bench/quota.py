"""Quota: the same fleet into the agent through the quota proxy, one connection against the connection pool.

AWS IoT Core delivers at most 100 publishes per second to one connection and discards the rest silently.
Here publishers send N arms at R Hz straight to a private mosquitto; the agent (`twin run` as a child process)
connects through `twin.rig.quota_proxy`, which enforces that budget on each of the agent's connections and
counts what it drops. Three phases with the same offered load:

1. one connection (`--per-connection-limit 0`: the agent does not know the budget): the quota discards most
   of the fleet; the figures show how much and what the agent's loss estimate makes of it;
2. the pool for listed devices (`--devices arm-0001,...`, budget 100): fixed connections from the start;
3. the pool for the whole fleet (`*`, budget 100): a shared subscription that grows; measured after a warm-up
   during which it grows (the warm-up's drops are reported apart).

Each phase reports the messages sent, the proxy's drops, what the agent received and applied, and the
agent's loss estimate next to the proxy's count. Publishers, broker, proxy and agent share this host.
"""

from __future__ import annotations

import functools
import time
from typing import Any

from twin.bench.harness import (
    ProcessSampler,
    collect,
    drained,
    get_state,
    publishers,
    sum_devices,
    wait_subscribed,
)
from twin.bench.load import arm_name
from twin.rig.local import LocalRig
from twin.rig.quota_proxy import QuotaProxy
from twin.service.state import AgentState

BUDGET = 100
WARMUP_S = 8.0
# Each message reaches the broker 0..this many ms after its sample. The quota discards by arrival time: real
# arms arrive with their networks' jitter, and without it a perfectly periodic load would have the same few
# arms pass every time (the drops locked in phase with the devices), which no field fleet does.
JITTER_MS = 20.0


def _figures(before: AgentState, after: AgentState, drops: int) -> dict[str, Any]:
    estimated = after.agent.loss.lost - before.agent.loss.lost
    received = after.agent.broker.messages - before.agent.broker.messages
    # What the broker sent the agent in the window: what got through plus what the quota discarded.
    sent = received + drops
    return {
        "sent": sent,
        "proxy_dropped": drops,
        "proxy_dropped_ratio": drops / sent if sent else 0.0,
        "received": received,
        "applied": sum_devices(after, "applied") - sum_devices(before, "applied"),
        # Valid but overtaken by a newer message of the same arm (a shared subscription reorders).
        "ignored_stale": sum_devices(after, "ignored_stale") - sum_devices(before, "ignored_stale"),
        "estimated_lost": estimated,
        # The agent's estimate against what the proxy really dropped, as a share of what was sent.
        "estimate_error_of_sent": (estimated - drops) / sent if sent else 0.0,
        "estimated_loss_ratio": after.agent.loss.loss_ratio,
        "devices_seen": len(after.devices),
        "devices_losing": after.agent.loss.devices_losing,
        "connections": len(after.agent.broker.connections),
        "connection_rates_hz": [round(c.rate_hz, 1) for c in after.agent.broker.connections],
        "internal_latency_s": {
            "p50": after.agent.latency.internal_s.p50,
            "p99": after.agent.latency.internal_s.p99,
        },
    }


def _phase(
    rig: LocalRig,
    name: str,
    args: tuple[str, ...],
    *,
    arms: int,
    rate: float,
    seconds: float,
    warmup: float,
) -> dict[str, Any]:
    # Enough pool connections for the whole fleet (200 arms x 10 Hz needs 25 at 80 msg/s each).
    config = f'[telemetry]\nmax_devices = {max(64, arms)}\nunits = "ticks"\n[broker]\nmax_connections = 64\n'
    with QuotaProxy("127.0.0.1", rig.broker.port, budget=BUDGET) as proxy:  # noqa: SIM117 - args need its port
        with rig.agent_process(
            config_text=config,
            extra_args=("--broker", proxy.url, "--log-level", "WARNING", *args),
            log_name=f"quota-{name}",
        ) as (proc, base):
            wait_subscribed(base, proc)
            pubs = publishers(rig.broker.url, arms, rate, warmup + seconds, jitter_ms=JITTER_MS)
            time.sleep(warmup)
            before = get_state(base)
            dropped_before = proxy.totals()["dropped"]
            sampler = ProcessSampler(proc.pid).start()
            sent = collect(pubs, timeout=warmup + seconds + 60)
            after = drained(base)
            usage = sampler.stop()
            if proc.poll() is not None:
                raise RuntimeError(f"the agent exited during the {name} phase (code {proc.returncode})")
            dropped = proxy.totals()["dropped"] - dropped_before
    return {
        "phase": name,
        "warmup_s": warmup,
        "warmup_dropped": dropped_before,
        "published": sent["sent"],
        **_figures(before, after, dropped),
        "cpu_percent": usage["cpu_percent"],
        "rss_max_mb": usage["rss_max_mb"],
    }


def run(*, arms: int = 200, rate: float = 10.0, seconds: float = 20.0) -> dict[str, Any]:
    """The three phases (module doc); every figure as one JSON-ready dict."""
    listed = ",".join(arm_name(i) for i in range(1, arms + 1))
    limit = ("--per-connection-limit", str(BUDGET))
    with LocalRig() as rig:
        phase = functools.partial(_phase, rig, arms=arms, rate=rate, seconds=seconds)
        phases = [
            phase("one_connection", ("--per-connection-limit", "0"), warmup=2.0),
            phase("pool_listed", (*limit, "--devices", listed), warmup=2.0),
            phase("pool_fleet", limit, warmup=WARMUP_S),
        ]
    return {
        "scenario": "quota",
        "arms": arms,
        "rate_hz": rate,
        "seconds": seconds,
        "budget_per_connection": BUDGET,
        "publish_jitter_ms": JITTER_MS,
        "offered_rate": arms * rate,
        "phases": phases,
        "notes": (
            "the proxy drops PUBLISH packets over 100/s per agent connection (one-second token bucket); "
            "'sent' is what the broker sent the agent in the measured window (received + proxy drops; "
            "'published' includes the warm-up); estimate_error_of_sent is (estimated lost - proxy drops) / "
            "sent"
        ),
    }
