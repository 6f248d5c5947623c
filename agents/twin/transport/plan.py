"""Connection-pool planning, pure (standard library and the topic rules only): how many connections the agent
opens and what each subscribes. The stack imports it to write an IAM policy that allows exactly the pool's
client ids and filters, without awscrt or MuJoCo. twin.transport.pool explains the pool itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from twin.core.topics import ALL_DEVICES, TELEMETRY_SUFFIX, check_devices, topic_filters
from twin.transport.broker import IOT, BrokerConfig

# IoT Core's per-connection quotas (docs/aws-facts.md, "IoT Core quotas").
IOT_PUBLISHES_PER_CONNECTION = 100
IOT_SUBSCRIPTIONS_PER_CONNECTION = 50
# The share of a connection's budget the pool plans to use: bursts (devices in step, a reconnect backlog) must
# not push a connection over the quota, where the excess is lost.
SAFETY_MARGIN = 0.8
# Shared subscriptions: grow when the measured rate reaches this share of K x budget x margin, aiming for
# GROW_TARGET after growing; a connection at this share of its raw budget is saturated (the broker may be
# discarding), so the pool doubles instead. Shrink by one when the rate has stayed under SHRINK_BELOW of what
# K - 1 connections carry for SHRINK_AFTER_S.
GROW_AT = 0.9
GROW_TARGET = 0.7
SATURATED_AT = 0.95
SHRINK_BELOW = 0.5
SHRINK_AFTER_S = 30.0
# How often the pool measures and rescales, and over how long it averages the rate.
SCALE_INTERVAL_S = 1.0
RATE_WINDOW_S = 3.0
DEFAULT_MAX_CONNECTIONS = 8


@dataclass(frozen=True)
class ConnectionLimit:
    """The broker's publishes per second per connection, and where an operator looks that figure up: the two
    travel together so that a warning never names a limit without its source."""

    per_s: float
    source: str


def connection_limit(config: BrokerConfig) -> ConnectionLimit | None:
    """The per-connection budget in force: the configured one, else IoT Core's quota on "iot", else none."""
    if config.per_connection_limit > 0:
        return ConnectionLimit(float(config.per_connection_limit), "[broker] per_connection_limit")
    if config.kind == IOT:
        return ConnectionLimit(float(IOT_PUBLISHES_PER_CONNECTION), "IoT Core's quota")
    return None


def default_limit(config: BrokerConfig) -> float | None:
    """`connection_limit`'s figure alone (None: no limit), for the pool's plan."""
    limit = connection_limit(config)
    return None if limit is None else limit.per_s


def shared_group(client_id_prefix: str) -> str:
    """The shared-subscription group name: the client id prefix without trailing separators."""
    return client_id_prefix.rstrip("-_.:") or "so101-twin"


def shared_filter(prefix: str, client_id_prefix: str) -> str:
    return f"$share/{shared_group(client_id_prefix)}/{prefix}/+/{TELEMETRY_SUFFIX}"


def devices_per_connection(rate_hz: float, limit: float | None, *, iot: bool) -> int | None:
    """How many listed devices one connection carries (None: all of them)."""
    cap = IOT_SUBSCRIPTIONS_PER_CONNECTION if iot else None
    if limit is None:
        return cap
    per = max(1, math.floor(limit * SAFETY_MARGIN / rate_hz))
    return per if cap is None else min(per, cap)


def plan_listed(
    prefix: str, devices: Sequence[str], *, rate_hz: float, limit: float | None, iot: bool
) -> list[list[str]]:
    """Topic filters per connection for listed devices, in the listed order; deterministic."""
    filters = topic_filters(prefix, list(devices))
    per = devices_per_connection(rate_hz, limit, iot=iot) or len(filters)
    return [filters[i : i + per] for i in range(0, len(filters), per)]


def listed_connections(devices: Sequence[str], *, rate_hz: float, limit: float | None, iot: bool) -> int:
    """How many connections `plan_listed` makes (the stack's IAM policy allows exactly these client ids)."""
    per = devices_per_connection(rate_hz, limit, iot=iot) or len(devices)
    return max(1, math.ceil(len(devices) / per))


def pool_client_ids(client_id_prefix: str, connections: int) -> list[str]:
    """IAM resource patterns for the pool's client ids `<prefix>*-<index>` that match exactly the indexes
    0..connections-1 (index_patterns), so a policy for 250 connections stays short."""
    return [f"{client_id_prefix}*-{p}" for p in index_patterns(connections)]


def index_patterns(count: int) -> list[str]:
    """IAM patterns ('?' is one character) matching exactly the decimal strings of 0..count-1: 250 gives
    "?", "1?".."9?", "1??", "20?".."24?". A block of 10**j numbers becomes one pattern only where its leading
    digits are fixed, so no pattern matches a number with a leading zero, which the pool never uses."""
    patterns, n = [], 0
    while n < count:
        digits, j = str(n), 0
        # Widen the block while it starts on its boundary, fits below count and keeps a fixed leading digit
        # (the single digits 0-9 are the exception: "?" is exactly them).
        while n % 10 ** (j + 1) == 0 and n + 10 ** (j + 1) <= count and (len(digits) > j + 1 or n == 0 == j):
            j += 1
        patterns.append(digits[: len(digits) - j] + "?" * j if j else digits)
        n += 10**j
    return patterns


@dataclass(frozen=True)
class PoolSettings:
    """What the pool needs beyond the broker: the devices, their rate, the budget and the bound on K."""

    prefix: str
    devices: tuple[str, ...]
    rate_hz: float = 10.0
    limit: float | None = None
    max_connections: int = DEFAULT_MAX_CONNECTIONS

    def __post_init__(self) -> None:
        check_devices(self.devices)
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz {self.rate_hz!r} must be positive")
        if self.limit is not None and not self.limit > 0:
            raise ValueError(f"per-connection limit {self.limit!r} must be positive (or None: unlimited)")
        if self.max_connections < 1:
            raise ValueError(f"max_connections {self.max_connections} must be at least 1")

    @property
    def fleet(self) -> bool:
        return self.devices == (ALL_DEVICES,)

    @property
    def shared(self) -> bool:
        """The whole fleet under a budget: a shared subscription over K connections."""
        return self.fleet and self.limit is not None

    def most_connections(self, *, iot: bool) -> int:
        """The most connections the pool opens, so the client id indexes 0..n-1 a broker policy must allow:
        the shared pool's bound, the listed plan's connections, or one without a budget."""
        if self.limit is None:
            return 1
        if self.shared:
            return self.max_connections
        return listed_connections(self.devices, rate_hz=self.rate_hz, limit=self.limit, iot=iot)
