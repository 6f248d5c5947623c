"""A pool of subscriber connections that stays under a per-connection publish budget.

AWS IoT Core delivers at most 100 publishes per second to one connection (inbound plus outbound) and discards
the rest silently (docs/aws-facts.md): one connection subscribed to a fleet of 10 Hz arms loses messages
from the eleventh arm on, and nothing tells the subscriber. So the agent receives over several connections,
each kept under a budget, used with a safety margin (SAFETY_MARGIN) because arrivals are bursty:

- Listed devices are spread over connections in the order they are listed (`plan_listed`): each connection
  carries at most budget x margin / rate devices, on IoT Core also at most 50 subscriptions (8 per SUBSCRIBE,
  which the subscriber already honours). A device is always on one connection, so its messages keep their
  order.
- The whole fleet (`*`) is a shared subscription, `$share/<group>/<prefix>/+/telemetry`, over K connections:
  the broker spreads the fleet's messages across the group's members. K grows as soon as the measured rate
  nears K x budget x margin (at once to what the rate needs; doubling when a connection sits at its raw
  budget, since then the real demand cannot be seen, once the connections the last growth added receive),
  shrinks by one after a sustained quiet spell, and stays within 1..max_connections. A shared subscription
  does not keep one device's messages on one connection, so order across connections is the twin's job (it
  orders by edge timestamp).

Each connection is a `TelemetrySubscriber`: it reconnects and re-subscribes on its own. Client ids are
`<client_id_prefix><12 random hex>-<index>`, the index below max_connections (or the listed plan's count),
which is exactly what the stack's IAM policy allows (`pool_client_ids`). Without a budget (a private
mosquitto) the pool is one connection with the plain filters, as before.
"""

from __future__ import annotations

import logging
import math
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from twin.core.topics import device_from_topic
from twin.transport.broker import IOT, BrokerConfig
from twin.transport.plan import (
    GROW_AT,
    GROW_TARGET,
    RATE_WINDOW_S,
    SAFETY_MARGIN,
    SATURATED_AT,
    SCALE_INTERVAL_S,
    SHRINK_AFTER_S,
    SHRINK_BELOW,
    PoolSettings,
    plan_listed,
    shared_filter,
)
from twin.transport.subscriber import MessageHandler, TelemetrySubscriber

__all__ = ["ConnectionInfo", "ConnectionPool", "PoolSettings"]

log = logging.getLogger(__name__)

Clock = Callable[[], float]

# The quota notice comes once connections have been at their budget this long (not one busy second) and
# goes once they have been under it this long (not one quiet second).
QUOTA_HELD_S = 10.0
QUOTA_CALM_S = 30.0
# A shared pool that grew doubles again on connections at their budget only once those it added receive
# (they take a moment, more on IoT Core, to connect and subscribe), or after this long without.
SETTLE_MAX_S = 10.0
# The quota notice names at most this many of the listed arms on connections at their budget.
NOTICE_ARMS = 16


@dataclass(frozen=True)
class ConnectionInfo:
    """One connection as /state and /metrics show it."""

    index: int
    client_id: str
    # "connected", "connecting", "stopped", or "refused": connected, but the broker refused a filter (an IoT
    # policy that does not allow it), whose telemetry does not arrive.
    state: str
    filters: tuple[str, ...]
    rate_hz: float
    messages: int
    connection_successes: int
    disconnections: int
    last_error: str
    refused: tuple[str, ...] = ()
    # Wall time of its latest connect (None: never connected).
    connected_at: float | None = None
    # Wall time of `last_error` (None: none yet).
    last_error_at: float | None = None


class _Connection:
    """A subscriber plus the message counter the pool rates it by (incremented on its CRT thread only)."""

    def __init__(self, index: int, subscriber: TelemetrySubscriber) -> None:
        self.index = index
        self.subscriber = subscriber
        self.messages = 0
        self.rate_hz = 0.0
        self._samples: list[tuple[float, int]] = []

    @property
    def never_connected(self) -> bool:
        """Not connected, and never was since it started: a broker refusing its client id, not a reconnect
        (IoT Core closes a WebSocket connection after 24 h)."""
        subscriber = self.subscriber
        return not subscriber.connected and subscriber.stats.connection_successes == 0

    def sample(self, now: float) -> float:
        samples = self._samples
        samples.append((now, self.messages))
        while len(samples) > 2 and samples[1][0] <= now - RATE_WINDOW_S:
            samples.pop(0)
        t0, n0 = samples[0]
        self.rate_hz = (self.messages - n0) / (now - t0) if now > t0 else 0.0
        return self.rate_hz

    def restart_window(self, now: float) -> None:
        """Measure from `now` on: before the pool grew, the fleet was split another way."""
        self._samples = [(now, self.messages)]


class ConnectionPool:
    """The agent's subscriber connections (module doc). `on_message(topic, payload, received)` runs on the
    connections' CRT threads and must not block. `start()`, `stop()`; `connections()` and `rate_hz` from any
    thread."""

    def __init__(
        self,
        config: BrokerConfig,
        settings: PoolSettings,
        on_message: MessageHandler,
        *,
        clock: Clock = time.monotonic,
    ) -> None:
        self.config = config
        self.settings = settings
        self._on_message = on_message
        self._clock = clock
        self._instance = secrets.token_hex(6)
        self._lock = threading.Lock()
        self._connections: list[_Connection] = []
        self._stop = threading.Event()
        self._scaler: threading.Thread | None = None
        self._quiet_since: float | None = None
        self.rate_hz = 0.0
        self._removed_messages = 0
        self.grown = 0
        self._grown_at = -math.inf
        # The connections the last growth added, until each has received (or SETTLE_MAX_S is over).
        self._joining: list[_Connection] = []
        self.shrunk = 0
        # What the agent shows (console, /healthz) while the broker's quota discards messages the pool cannot
        # take on: "" otherwise (`_watch_quota`).
        self.quota_notice = ""
        self._full_since: float | None = None
        self._calm_since: float | None = None
        if settings.shared:
            self._plan: list[list[str]] = []
            self._shared = shared_filter(settings.prefix, config.client_id_prefix)
        else:
            self._shared = ""
            self._plan = plan_listed(
                settings.prefix,
                settings.devices,
                rate_hz=settings.rate_hz,
                limit=settings.limit,
                iot=config.kind == IOT,
            )

    # -- lifecycle ------------------------------------------------------------------------------------------

    def start(self) -> None:
        if self._connections:
            return
        if self.settings.shared:
            self._add_connection([self._shared])
        else:
            for filters in self._plan:
                self._add_connection(filters)
        log.info(
            "connection pool: %d connection(s), %s",
            len(self._connections),
            "unlimited" if self.settings.limit is None else f"{self.settings.limit:g} publishes/s each",
        )
        self._stop.clear()
        self._scaler = threading.Thread(target=self._scale_loop, name="twin-pool", daemon=True)
        self._scaler.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._scaler is not None:
            self._scaler.join(timeout)
            self._scaler = None
        with self._lock:
            connections, self._connections = self._connections, []
        for connection in connections:
            connection.subscriber.stop(timeout)

    # -- readings -------------------------------------------------------------------------------------------

    @property
    def size(self) -> int:
        with self._lock:
            return len(self._connections)

    @property
    def connected(self) -> bool:
        """True while every connection is up."""
        with self._lock:
            connections = list(self._connections)
        return bool(connections) and all(c.subscriber.connected for c in connections)

    @property
    def messages(self) -> int:
        """Messages received on every connection since start, those since removed included."""
        with self._lock:
            return self._removed_messages + sum(c.messages for c in self._connections)

    def subscribers(self) -> list[TelemetrySubscriber]:
        with self._lock:
            return [c.subscriber for c in self._connections]

    @property
    def topic_filters(self) -> list[str]:
        return [self._shared] if self.settings.shared else [f for chunk in self._plan for f in chunk]

    def wait_subscribed(self, timeout: float) -> bool:
        """Block (not from a callback) until every current connection's subscriptions are acknowledged."""
        deadline = time.monotonic() + timeout
        with self._lock:
            connections = list(self._connections)
        return bool(connections) and all(
            c.subscriber.wait_subscribed(max(0.0, deadline - time.monotonic())) for c in connections
        )

    def refused(self) -> dict[str, str]:
        """The topic filters the broker refused, over every connection, each with the SUBACK's reason."""
        with self._lock:
            connections = list(self._connections)
        return {f: reason for c in connections for f, reason in c.subscriber.refused.items()}

    def connections(self) -> list[ConnectionInfo]:
        with self._lock:
            connections = list(self._connections)
        out = []
        for c in connections:
            sub = c.subscriber
            stats = sub.stats
            refused = tuple(sub.refused)
            connected = "refused" if refused else "connected"
            out.append(
                ConnectionInfo(
                    index=c.index,
                    client_id=sub.client_id,
                    state=connected if sub.connected else "connecting",
                    filters=tuple(sub.topic_filters),
                    rate_hz=c.rate_hz,
                    messages=stats.messages_received,
                    connection_successes=stats.connection_successes,
                    disconnections=stats.disconnects,
                    last_error=stats.last_error,
                    refused=refused,
                    connected_at=stats.last_connected_at,
                    last_error_at=stats.last_error_at,
                )
            )
        return out

    # -- scaling --------------------------------------------------------------------------------------------

    def _add_connection(self, filters: list[str]) -> None:
        index = len(self._connections)
        client_id = f"{self.config.client_id_prefix}{self._instance}-{index}"

        def on_message(topic: str, payload: bytes, received: float) -> None:
            connection.messages += 1
            self._on_message(topic, payload, received)

        subscriber = TelemetrySubscriber(
            self.config, filters, on_message, client_id=client_id, clock=self._clock
        )
        connection = _Connection(index, subscriber)
        with self._lock:
            self._connections.append(connection)
        subscriber.start()

    def _scale_loop(self) -> None:
        while not self._stop.wait(SCALE_INTERVAL_S):
            try:
                self.rescale(self._clock())
            except Exception:
                log.exception("connection pool: rescaling failed (the pool keeps its size)")
            with self._lock:
                subscribers = [c.subscriber for c in self._connections]
            for subscriber in subscribers:
                try:
                    subscriber.retry_refused()  # each waits RESUBSCRIBE_S between its own tries
                except Exception:
                    log.exception("connection pool: asking again for a refused subscription failed")

    def rescale(self, now: float) -> int:
        """Measure each connection's rate and, for a shared subscription, grow or shrink K; returns K."""
        with self._lock:
            connections = list(self._connections)
        total = sum(c.sample(now) for c in connections)
        self.rate_hz = total
        limit = self.settings.limit
        if limit is None:
            return len(connections)
        # The connections at their raw budget: the broker is discarding, and the real demand cannot be seen.
        full = sum(c.rate_hz >= SATURATED_AT * limit for c in connections)
        # Those that never connected (a broker refusing their client ids) carry none of it.
        unconnected = sum(c.never_connected for c in connections)
        self._watch_quota(now, full, (len(connections), unconnected), limit)
        if not self.settings.shared:
            return len(connections)
        k = len(connections)
        capacity = limit * SAFETY_MARGIN
        saturated = full > 0 and not self._settling(now, connections)
        target = k
        if saturated:
            target = 2 * k
        if total >= GROW_AT * k * capacity:
            target = max(target, k + 1, math.ceil(total / (GROW_TARGET * capacity)))
        target = min(target, self.settings.max_connections)
        if target > k:
            self._quiet_since = None
            log.info(
                "connection pool: %.0f msg/s on %d connection(s) of %g/s: growing to %d",
                total,
                k,
                limit,
                target,
            )
            for _ in range(target - k):
                self._add_connection([self._shared])
            with self._lock:
                self._joining = self._connections[k:]
            self._grown_at = now
            self.grown += 1
            return target
        if k > 1 and total < SHRINK_BELOW * (k - 1) * capacity:
            if self._quiet_since is None:
                self._quiet_since = now
            elif now - self._quiet_since >= SHRINK_AFTER_S:
                self._quiet_since = None
                self._remove_last()
                self.shrunk += 1
                return k - 1
        else:
            self._quiet_since = None
        return k

    def _settling(self, now: float, connections: list[_Connection]) -> bool:
        """Whether the last growth is still settling: a connection it added has received nothing yet (it is
        connecting or subscribing), so the others stay at their budget, which says nothing of what the pool
        as grown carries. Not for ever: one the broker refuses never receives. The tick it ends judges
        nothing either: every rate then still holds seconds from before all took their share (doubling on
        them took a walk's 400 msg/s to 16 connections, where 8 carry it), so each is measured afresh."""
        if not self._joining:
            return False
        if now - self._grown_at < SETTLE_MAX_S and any(c.messages == 0 for c in self._joining):
            return True
        self._joining = []
        for c in connections:
            c.restart_window(now)
        return True

    def _watch_quota(self, now: float, full: int, pool: tuple[int, int], limit: float) -> None:
        """Set `quota_notice` once connections have received at their budget for QUOTA_HELD_S while the pool
        cannot take the load on (a shared pool at max_connections, or a listed plan, which does not grow),
        and clear it after QUOTA_CALM_S without; each change is logged once. It was a warning every second
        (a walk counted 55 in a minute), and a listed plan at its budget said nothing at all. `full` of the
        pool's k connections receive at their budget; `pool` is (k, how many of them are not connected)."""
        k = pool[0]
        stuck = full > 0 and (not self.settings.shared or k >= self.settings.max_connections)
        if stuck:
            self._calm_since = None
            if self._full_since is None:
                self._full_since = now
            if now - self._full_since >= QUOTA_HELD_S:
                said = self.quota_notice
                # Kept current (how many are at their budget, which arms), logged once: written once, its
                # count and arms went stale while the load moved.
                self.quota_notice = self._quota_text(full, pool, limit)
                if not said:
                    log.warning("connection pool: %s", self.quota_notice)
            return
        self._full_since = None
        if self.quota_notice:
            if self._calm_since is None:
                self._calm_since = now
            elif now - self._calm_since >= QUOTA_CALM_S:
                self.quota_notice = ""
                self._calm_since = None
                log.info("connection pool: every connection is under its budget again")

    def _quota_text(self, full: int, pool: tuple[int, int], limit: float) -> str:
        settings = self.settings
        k, unconnected = pool
        if settings.shared and unconnected:
            # More connections than the broker admits: raising max_connections is what got here (a walk
            # raised it in agent.local.toml above what the stack's role allows, and was told to raise it).
            return (
                f"the broker's per-connection quota discards messages: {full} of {k} connections "
                f"(broker.max_connections) receive at their budget of {limit:g} msg/s, and {unconnected} of "
                "them could not connect (/state: each connection's last_error). On IoT Core that is a client "
                "id the role does not allow: the stack's role allows maxConnections of them, so a larger "
                "broker.max_connections in agent.local.toml adds only refused connections. Take it out of "
                "that file and raise maxConnections in twin.settings.toml, or list the fleet's devices"
            )
        if settings.shared:
            arms = k * limit * SAFETY_MARGIN / settings.rate_hz
            return (
                f"the broker's per-connection quota discards messages: {full} of {k} connections "
                f"(broker.max_connections) receive at their budget of {limit:g} msg/s, about {arms:.0f} arms "
                f"at {settings.rate_hz:g} Hz, so arms are mirrored below their rate and the rest counted as "
                "lost. Raise broker.max_connections (up to 64), which needs a broker policy that allows that "
                "many client ids: on the stack, maxConnections in twin.settings.toml sets both. Or list the "
                "fleet's devices ([telemetry] devices; on the stack, devices, at most 150): the plan then "
                "takes the connections they need and the stack allows them"
            )
        return (
            f"the broker's per-connection quota discards messages: {full} of {k} connections receive at "
            f"their budget of {limit:g} msg/s, planned for arms at {settings.rate_hz:g} Hz ([health] "
            "expected_rate_hz): the arms publish faster, or more of them share a connection than its budget "
            "carries. Set expected_rate_hz to their rate, so the plan spreads them over more connections (on "
            "the stack, armRateHz in twin.settings.toml sets it and the client ids its IAM policy allows). "
            f"Those connections carry {self._arms_at_budget(limit)}: if one of them publishes far faster "
            "than the rest (the console's Events page names an arm above its rate), slow that edge down "
            "instead, as the others on its connection lose what it takes"
        )

    def _arms_at_budget(self, limit: float) -> str:
        """The listed arms on connections at their budget, for the quota notice (a walk's one arm at 50 Hz
        took its connection's budget, and the notice named no arm: only its neighbours' loss showed)."""
        with self._lock:
            full = [c for c in self._connections if c.rate_hz >= SATURATED_AT * limit]
        prefix = self.settings.prefix
        arms = [d for c in full for f in c.subscriber.topic_filters if (d := device_from_topic(f, prefix))]
        shown = ", ".join(arms[:NOTICE_ARMS])
        return shown if len(arms) <= NOTICE_ARMS else f"{shown} and {len(arms) - NOTICE_ARMS} more"

    def _remove_last(self) -> None:
        with self._lock:
            connection = self._connections.pop()
            self._removed_messages += connection.messages
        log.info("connection pool: quiet, shrinking to %d connection(s)", connection.index)
        connection.subscriber.stop()
