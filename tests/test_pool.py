"""Connection-pool planning (pure): how listed devices spread over connections, the shared filter, the ids."""

from __future__ import annotations

import re

import pytest
from twin.transport.broker import BrokerConfig
from twin.transport.plan import (
    PoolSettings,
    default_limit,
    devices_per_connection,
    index_patterns,
    listed_connections,
    plan_listed,
    pool_client_ids,
    shared_filter,
)

ARMS = [f"arm-{i:03d}" for i in range(1, 201)]


def test_listed_devices_fill_connections_in_order_under_the_margin() -> None:
    plan = plan_listed("dt/lerobot", ARMS, rate_hz=10.0, limit=100, iot=True)
    assert [len(p) for p in plan] == [8] * 25  # 80 % of 100 msg/s at 10 Hz
    assert plan[0][0] == "dt/lerobot/arm-001/telemetry" and plan[-1][-1] == "dt/lerobot/arm-200/telemetry"
    flat = [f for chunk in plan for f in chunk]
    assert flat == [f"dt/lerobot/{a}/telemetry" for a in ARMS]  # each device on exactly one connection
    assert plan == plan_listed("dt/lerobot", ARMS, rate_hz=10.0, limit=100, iot=True)  # deterministic
    assert listed_connections(ARMS, rate_hz=10.0, limit=100, iot=True) == 25


def test_iot_core_caps_subscriptions_per_connection() -> None:
    # 1 Hz arms: the budget would allow 80 per connection, IoT Core's 50 subscriptions do not.
    assert devices_per_connection(1.0, 100, iot=True) == 50
    assert devices_per_connection(1.0, 100, iot=False) == 80
    assert [len(p) for p in plan_listed("dt/lerobot", ARMS, rate_hz=1.0, limit=100, iot=True)] == [50] * 4
    # Without a budget: one connection, still at most 50 filters on IoT Core.
    assert devices_per_connection(10.0, None, iot=False) is None
    assert len(plan_listed("dt/lerobot", ARMS, rate_hz=10.0, limit=None, iot=False)) == 1
    # An arm faster than the budget still gets a connection of its own.
    assert devices_per_connection(500.0, 100, iot=False) == 1


def test_budget_defaults_follow_the_broker() -> None:
    assert default_limit(BrokerConfig(url="iot")) == 100
    assert default_limit(BrokerConfig(url="mqtt://127.0.0.1:1883")) is None
    assert default_limit(BrokerConfig(url="mqtt://127.0.0.1:1883", per_connection_limit=40)) == 40


def test_shared_filter_and_client_ids() -> None:
    assert shared_filter("dt/lerobot", "so101-twin-") == "$share/so101-twin/dt/lerobot/+/telemetry"
    assert pool_client_ids("so101-twin-", 3) == ["so101-twin-*-0", "so101-twin-*-1", "so101-twin-*-2"]
    assert PoolSettings("dt/lerobot", ("*",), limit=100).shared
    assert not PoolSettings("dt/lerobot", ("*",), limit=None).shared
    assert not PoolSettings("dt/lerobot", ("arm-001",), limit=100).shared


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [({"rate_hz": 0}, "rate_hz"), ({"limit": -5}, "limit"), ({"max_connections": 0}, "max_connections")],
)
def test_bad_pool_settings(kwargs: dict[str, float], needle: str) -> None:
    with pytest.raises(ValueError, match=needle):
        PoolSettings("dt/lerobot", ("*",), **kwargs)


class _Counted:
    """A connection as the pool rates it: a message count, no subscriber (rescale reads nothing else)."""

    def __init__(self, index: int, *, connected: bool = True, filters: tuple[str, ...] = ()) -> None:
        from types import SimpleNamespace

        from twin.transport.pool import _Connection

        stats = SimpleNamespace(connection_successes=1 if connected else 0)
        subscriber = SimpleNamespace(connected=connected, stats=stats, topic_filters=list(filters))
        self.connection = _Connection(index, subscriber=subscriber)  # type: ignore[arg-type]


def _pool_at(settings: PoolSettings, connections: int) -> tuple[object, list[object]]:
    from twin.transport.pool import ConnectionPool

    pool = ConnectionPool(BrokerConfig(url="mqtt://127.0.0.1:1"), settings, lambda *_: None)
    held = [_Counted(i).connection for i in range(connections)]
    pool._connections = held  # type: ignore[attr-defined]
    return pool, held


@pytest.mark.parametrize("shared", [True, False])
def test_a_pool_held_at_its_budget_says_so_once_and_when_it_is_under_again(
    shared: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """A walk: a shared pool at max_connections warned every second (55 in a minute), a listed one at its
    budget said nothing, and /healthz and the Fleet page said nothing either way."""
    devices = ("*",) if shared else tuple(ARMS[:16])
    settings = PoolSettings("dt/lerobot", devices, limit=100.0, max_connections=2)
    pool, held = _pool_at(settings, 2)
    caplog.set_level("INFO", logger="twin.transport.pool")

    def run(seconds: int, start: int, per_second: int) -> None:
        for t in range(start, start + seconds):
            for c in held:
                c.messages += per_second  # type: ignore[attr-defined]
            pool.rescale(float(t))  # type: ignore[attr-defined]

    run(8, 0, 100)  # at the budget, not yet for QUOTA_HELD_S
    assert pool.quota_notice == ""  # type: ignore[attr-defined]
    run(20, 8, 100)
    notice = pool.quota_notice  # type: ignore[attr-defined]
    assert notice.startswith("the broker's per-connection quota discards messages:"), notice
    expected = (
        "maxConnections in twin.settings.toml sets both" if shared else "Set expected_rate_hz to their rate"
    )
    assert expected in notice
    assert [r.levelname for r in caplog.records].count("WARNING") == 1  # once, not every second
    run(20, 28, 50)  # under it, not yet for QUOTA_CALM_S
    assert pool.quota_notice == notice  # type: ignore[attr-defined]
    run(20, 48, 50)
    assert pool.quota_notice == ""  # type: ignore[attr-defined]
    assert "every connection is under its budget again" in caplog.text


def test_a_shared_pool_whose_extra_connections_are_refused_says_raising_them_is_the_cause() -> None:
    """A walk raised max_connections in agent.local.toml above what the stack's role allows: the broker
    refused the extra client ids, the rest ran at their budget, and the notice said to raise
    max_connections."""
    settings = PoolSettings("dt/lerobot", ("*",), limit=100.0, max_connections=4)
    pool, held = _pool_at(settings, 2)
    refused = [_Counted(i, connected=False).connection for i in (2, 3)]
    # One connected before and is reconnecting now (IoT Core ends a connection after 24 h): not refused.
    reconnecting = _Counted(4).connection
    reconnecting.subscriber.connected = False
    pool._connections = held + refused + [reconnecting]  # type: ignore[attr-defined]
    for t in range(20):
        for c in held:
            c.messages += 100  # type: ignore[attr-defined]
        pool.rescale(float(t))  # type: ignore[attr-defined]
    notice = pool.quota_notice  # type: ignore[attr-defined]
    assert "2 of 5 connections (broker.max_connections) receive at their budget" in notice, notice
    assert "2 of them could not connect" in notice and "Take it out of that file" in notice
    assert "Raise broker.max_connections" not in notice


def test_the_shared_quota_notice_counts_the_connections_at_their_budget() -> None:
    """A review's run: one connection of eight at its budget, the rest connected and silent, was told as
    "all 8 connections ... receive at their budget"."""
    settings = PoolSettings("dt/lerobot", ("*",), limit=100.0, max_connections=8)
    pool, held = _pool_at(settings, 8)
    for t in range(1, 20):  # past QUOTA_HELD_S, before the idle pool would shrink (30 s)
        held[0].messages += 100  # type: ignore[attr-defined]
        pool.rescale(float(t))  # type: ignore[attr-defined]
    notice = pool.quota_notice  # type: ignore[attr-defined]
    assert "1 of 8 connections (broker.max_connections) receive at their budget" in notice, notice
    # And kept current: a second connection at its budget is counted on the next look, not left as it was.
    for t in range(20, 25):
        for c in held[:2]:
            c.messages += 100  # type: ignore[attr-defined]
        pool.rescale(float(t))  # type: ignore[attr-defined]
    notice = pool.quota_notice  # type: ignore[attr-defined]
    assert "2 of 8 connections (broker.max_connections) receive at their budget" in notice, notice


def test_a_shared_pool_that_can_still_grow_gives_no_notice() -> None:
    settings = PoolSettings("dt/lerobot", ("*",), limit=100.0, max_connections=8)
    pool, held = _pool_at(settings, 2)
    pool._add_connection = lambda filters: held.append(_Counted(len(held)).connection)  # type: ignore[attr-defined]
    for t in range(30):
        for c in held:  # the fleet's 200 msg/s, shared by however many connections there are
            c.messages += 200 // len(held)  # type: ignore[attr-defined]
        pool.rescale(float(t))  # type: ignore[attr-defined]
    assert len(held) > 2 and pool.quota_notice == ""  # type: ignore[attr-defined]


@pytest.mark.parametrize("count", [1, 8, 10, 19, 64, 100, 250, 1234])
def test_index_patterns_match_exactly_the_pools_indexes(count: int) -> None:
    """IAM's '?' stands for one character: the patterns let connect every index below count and nothing else,
    not even the same numbers written with a leading zero."""
    patterns = index_patterns(count)
    rules = [re.compile(p.replace("?", "[0-9]") + "$") for p in patterns]
    candidates = [str(i) for i in range(20_000)] + [f"0{i}" for i in range(2_000)]
    assert [c for c in candidates if any(r.match(c) for r in rules)] == [str(i) for i in range(count)]
    # Compact: a handful a digit, not one an index.
    assert len(patterns) <= 10 * len(str(count))


# Quarter seconds to subscribe: 7 and 11 end the wait late in a rate window (a review's finding: the old
# connections' rates then still held seconds at their budget from before the new ones took their share).
@pytest.mark.parametrize("subscribe_ticks", [3, 6, 7, 11, 15, 19, 23])
def test_a_growing_shared_pool_waits_for_its_new_connections_before_it_doubles_again(
    subscribe_ticks: int,
) -> None:
    """A walk's 40 arms (400 msg/s) under a budget of 100 a connection ended on 16 connections, where 8
    carry them: a connection takes a moment to subscribe, and the pool doubled again on the old connections,
    still at their budget (and measured over seconds from before it grew), before the new ones took their
    share."""
    settings = PoolSettings("dt/lerobot", ("*",), limit=100.0, max_connections=64)
    pool, held = _pool_at(settings, 1)
    pool._add_connection = lambda filters: held.append(_Counted(len(held)).connection)  # type: ignore[attr-defined]
    added = {0: -4}
    for tick in range(1, 120):  # quarter seconds; the pool rescales every fourth
        # A connection receives once it has subscribed, 0.75 s or 1.5 s (IoT Core's handshakes) after it was
        # added; the broker spreads the fleet over the group's subscribed members, its quota caps each.
        members = [c for i, c in enumerate(held) if added.setdefault(i, tick) + subscribe_ticks <= tick]
        for c in members:
            c.messages += min(25, 100 // len(members))  # type: ignore[attr-defined]
        if tick % 4 == 0:
            pool.rescale(tick / 4)  # type: ignore[attr-defined]
    assert 5 <= len(held) <= 8, len(held)


def test_a_shared_pool_with_a_connection_that_never_receives_still_grows() -> None:
    """A connection the broker refuses receives nothing: the pool must not wait on it for ever before it
    grows on the others at their budget."""
    settings = PoolSettings("dt/lerobot", ("*",), limit=100.0, max_connections=8)
    pool, held = _pool_at(settings, 1)
    pool._add_connection = lambda filters: held.append(_Counted(len(held)).connection)  # type: ignore[attr-defined]
    for t in range(1, 30):
        held[0].messages += 100  # type: ignore[attr-defined]  # the rest are refused: they receive nothing
        pool.rescale(float(t))  # type: ignore[attr-defined]
    assert len(held) > 2, len(held)


def test_the_quota_notice_is_in_state_and_metrics_not_only_in_healthz() -> None:
    """A walk's fleet over the pool's budget: /healthz and the console said so, but /state had no field for
    it and /metrics no series, so a scraper saw the loss and not its cause."""
    from twin.service.agent import broker_state
    from twin.service.metrics import render_metrics
    from twin.service.state import AgentInfo, AgentState

    settings = PoolSettings("dt/lerobot", ("*",), limit=100.0, max_connections=2)
    pool, _ = _pool_at(settings, 0)

    def seen() -> tuple[str, str]:
        broker = broker_state("mqtt://127.0.0.1:1", settings, pool, True)  # type: ignore[arg-type]
        text = render_metrics(AgentState(agent=AgentInfo(broker=broker), devices={}))
        gauge = next(line for line in text.splitlines() if line.startswith("twin_broker_quota"))
        return broker.quota_notice, gauge

    assert seen() == ("", "twin_broker_quota_discarding 0.0")
    pool.quota_notice = "the broker's per-connection quota discards messages: ..."  # type: ignore[attr-defined]
    assert seen() == (pool.quota_notice, "twin_broker_quota_discarding 1.0")  # type: ignore[attr-defined]


def test_a_listed_plan_at_its_budget_names_the_arms_on_the_connections_at_it() -> None:
    """A walk's one arm at 50 Hz among 16 listed at 10 Hz took its connection's budget: the notice said to
    set expected_rate_hz for every arm and named none, while its seven neighbours lost messages."""
    settings = PoolSettings("dt/lerobot", tuple(ARMS[:16]), limit=100.0)
    pool, _ = _pool_at(settings, 0)
    plan = plan_listed("dt/lerobot", ARMS[:16], rate_hz=10.0, limit=100.0, iot=False)
    held = [_Counted(i, filters=tuple(filters)).connection for i, filters in enumerate(plan)]
    pool._connections = held  # type: ignore[attr-defined]
    for t in range(20):
        held[0].messages += 80  # type: ignore[attr-defined]
        held[1].messages += 100  # type: ignore[attr-defined]  # arm-016 at 50 Hz, seven arms at 10 Hz
        pool.rescale(float(t))  # type: ignore[attr-defined]
    notice = pool.quota_notice  # type: ignore[attr-defined]
    assert "1 of 2 connections" in notice, notice
    assert "carry arm-009, arm-010, arm-011, arm-012, arm-013, arm-014, arm-015, arm-016:" in notice
    assert "arm-001" not in notice and "slow that edge down" in notice
