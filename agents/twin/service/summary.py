"""What the agent does the same way in one process (service.agent) and in several (service.shards): the
connection pool's plan from the config, the broker side of /state, the order of /alarms, and the CloudWatch
metrics' totals, and the rejection reason for a device over `telemetry.max_devices`.

Light on purpose: the receiving process of a sharded agent imports it, and must not load MuJoCo or usd-core.
"""

from __future__ import annotations

from twin.core.alarms import worst_first
from twin.core.health import DeviceStatus
from twin.output.emf import FleetTotals
from twin.service.config import AgentConfig
from twin.service.state import AgentState, AlarmInfo, BrokerState, ConnectionState
from twin.transport.plan import PoolSettings, default_limit
from twin.transport.pool import ConnectionPool

# Counted for a valid message from a device beyond `telemetry.max_devices` (docs/agent.md).
TOO_MANY_DEVICES = "too_many_devices"


def fleet_totals(state: AgentState, expected_rate_hz: float) -> FleetTotals:
    """The CloudWatch metrics' running totals and gauges, from one state document (docs/servo-health.md)."""
    statuses = [d.status for d in state.devices.values()]
    live = [d for d in state.devices.values() if d.status is not DeviceStatus.OFFLINE]
    # Per arm, the share of the expected rate that did not arrive, averaged over arms that are not OFFLINE
    # (an OFFLINE arm is counted as such, not as 100 % loss).
    loss = (
        100.0 * sum(max(0.0, 1.0 - d.rate_hz / expected_rate_hz) for d in live) / len(live) if live else 0.0
    )
    p99s = [d.internal_latency_s.p99 for d in state.devices.values() if d.internal_latency_s.p99]
    return FleetTotals(
        decoded=sum(d.counters.decoded for d in state.devices.values()),
        rejected=sum(d.counters.rejected_total for d in state.devices.values())
        + sum(state.untracked_rejected.values()),
        devices_online=statuses.count(DeviceStatus.ONLINE),
        devices_stale=statuses.count(DeviceStatus.STALE),
        devices_offline=statuses.count(DeviceStatus.OFFLINE),
        loss_percent=loss,
        internal_latency_p99_ms=max(p99s) * 1000.0 if p99s else None,
        active_alarms=state.agent.alarms.present,
    )


def alarm_order(info: AlarmInfo) -> tuple[int, int, str]:
    """Worst first, as ServoAlarms.views orders them (core.alarms.worst_first)."""
    return worst_first(info.severity, info.state, info.alarm_id)


def broker_state(url: str, settings: PoolSettings, pool: ConnectionPool, started: bool) -> BrokerState:
    """The broker side of /state: the pool's connections, summed and one by one."""
    limit = settings.limit
    if not started:
        return BrokerState(url=url, per_connection_limit=limit)
    infos = pool.connections()
    stats = [c.stats for c in pool.subscribers()]
    return BrokerState(
        url=url,
        client_id=infos[0].client_id if infos else None,
        connected=pool.connected,
        connection_successes=sum(st.connection_successes for st in stats),
        connection_failures=sum(st.connection_failures for st in stats),
        disconnections=sum(st.disconnects for st in stats),
        subscribes=sum(st.subscribes_acked for st in stats),
        messages=pool.messages,
        last_error=next((st.last_error for st in stats if st.last_error), ""),
        per_connection_limit=limit,
        rate_hz=pool.rate_hz,
        connections=tuple(
            ConnectionState(
                index=c.index,
                client_id=c.client_id,
                state=c.state,
                filters=len(c.filters),
                rate_hz=c.rate_hz,
                messages=c.messages,
                connection_successes=c.connection_successes,
                disconnections=c.disconnections,
                last_error=c.last_error,
            )
            for c in infos
        ),
    )


def pool_settings(config: AgentConfig) -> PoolSettings:
    """The connection pool's settings from the agent's config (the broker's budget, the fleet to plan for)."""
    t = config.telemetry
    return PoolSettings(
        prefix=t.topic_prefix,
        devices=tuple(t.devices),
        rate_hz=config.health.expected_rate_hz,
        limit=default_limit(config.broker),
        max_connections=config.broker.max_connections,
    )
