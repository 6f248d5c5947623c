"""The fleet under IoT Core's per-connection quota, against a real mosquitto behind the quota proxy.

The edge simulator publishes straight to mosquitto; the agent connects through the proxy, which drops every
PUBLISH beyond 100 a second on each of the agent's connections, as IoT Core does. So the agent only mirrors
the whole fleet if its connection pool keeps each connection under the budget. And a new user's fleet: `twin
run` with no config beside a 200-arm `twin edge-sim`, straight to mosquitto.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator

import pytest
from conftest import get_state, wait_for
from twin.edge.simulator import FaultConfig, device_ids
from twin.rig.local import LocalRig, child_env
from twin.rig.quota_proxy import QuotaProxy
from twin.service.agent import AgentService
from twin.service.state import AgentState
from twin.transport.plan import plan_listed

pytestmark = pytest.mark.slow

BUDGET = 100
FLEET = [f"arm-{i:03d}" for i in range(1, 31)]  # 30 arms x 10 Hz = 300 msg/s: three connections' worth


@pytest.fixture
def proxy(rig: LocalRig) -> Iterator[QuotaProxy]:
    with QuotaProxy("127.0.0.1", rig.broker.port, budget=BUDGET) as p:
        yield p


def start_agent(rig: LocalRig, proxy: QuotaProxy, devices: list[str], **overrides: object) -> AgentService:
    return rig.start_agent(
        {
            "broker.url": proxy.url,
            "broker.per_connection_limit": BUDGET,
            "telemetry.devices": devices,
            "telemetry.units": "ticks",
            "telemetry.max_devices": 100,
            **overrides,
        }
    )


def settle(agent: AgentService, expected: int, timeout: float = 15.0) -> None:
    """Wait until the worker has decoded `expected` messages and stopped moving."""
    wait_for(
        lambda: agent.state().agent.worker.processed >= expected, timeout, f"{expected} messages processed"
    )
    time.sleep(0.5)


def test_a_listed_fleet_through_the_quota_has_no_loss(rig: LocalRig, proxy: QuotaProxy) -> None:
    plan = plan_listed("dt/lerobot", FLEET, rate_hz=10.0, limit=BUDGET, iot=False)
    assert [len(p) for p in plan] == [8, 8, 8, 6]  # 80 msg/s (the margin) per connection, listed order
    agent = start_agent(rig, proxy, FLEET)
    edge = rig.start_edge(FLEET, seconds=4.0, rate_hz=10.0)
    report = edge.join(30)
    settle(agent, report.published)
    state = agent.state()
    totals = proxy.totals()
    assert totals["dropped"] == 0, totals
    assert len(state.agent.broker.connections) == 4
    # Each device's messages arrive on one connection, so all of them are applied, in order.
    for device in FLEET:
        d = state.devices[device]
        assert d.health.counters.applied == report.per_device[device], device
        assert d.health.counters.ignored_stale == 0
        assert d.loss.lost == 0
    assert state.agent.loss.lost == 0
    assert state.agent.loss.received == report.published
    assert {c.filters for c in state.agent.broker.connections} == {8, 6}


def test_a_wildcard_fleet_grows_its_shared_subscription(rig: LocalRig, proxy: QuotaProxy) -> None:
    agent = start_agent(rig, proxy, ["*"])
    assert agent.topic_filters == ["$share/so101-rig-agent/dt/lerobot/+/telemetry"]
    edge = rig.start_edge(FLEET, seconds=10.0, rate_hz=10.0)
    size = wait_for(lambda: len(agent.state().agent.broker.connections) >= 4 or None, 10, "the pool to grow")
    assert size
    # Grown: from now on no connection is over its budget, so the proxy drops nothing more.
    time.sleep(1.5)
    dropped_after_growth = proxy.totals()["dropped"]
    report = edge.join(30)
    settle(agent, 1)
    state = agent.state()
    assert proxy.totals()["dropped"] == dropped_after_growth
    assert len(state.devices) == len(FLEET)
    connections = state.agent.broker.connections
    assert 4 <= len(connections) <= 8
    assert all(c.rate_hz <= BUDGET for c in connections)
    # What the quota discarded before the pool grew shows up as estimated loss, close to the proxy's count.
    lost, dropped = state.agent.loss.lost, proxy.totals()["dropped"]
    assert abs(lost - dropped) <= max(10, 0.1 * dropped), (lost, dropped)
    applied = sum(d.health.counters.applied for d in state.devices.values())
    assert applied + dropped + sum(d.health.counters.ignored_stale for d in state.devices.values()) >= (
        report.published - 5 * len(FLEET)
    )


def test_loss_estimates_on_a_stream_with_known_drops(rig: LocalRig) -> None:
    devices = FLEET[:5]
    agent = rig.start_agent({"telemetry.devices": devices, "telemetry.units": "ticks"})
    edge = rig.start_edge(devices, seconds=6.0, rate_hz=20.0, faults=FaultConfig(drop=0.2))
    report = edge.join(30)
    settle(agent, report.published)
    state = agent.state()
    lost = state.agent.loss.lost
    # Drops before a device's first or after its last delivered message leave no hole (at most a few each).
    assert report.dropped - 4 * len(devices) <= lost <= report.dropped, (lost, report.dropped)
    assert state.agent.loss.received == report.published
    assert 0.15 < state.agent.loss.loss_ratio < 0.25
    assert all(d.loss.period_s == pytest.approx(0.05, rel=0.02) for d in state.devices.values())
    metrics = agent_metrics(agent)
    assert f"twin_fleet_messages_lost_total {float(lost)}" in metrics


def test_garbage_interleaved_with_good_messages_is_counted_exactly(rig: LocalRig) -> None:
    devices = FLEET[:3]
    agent = rig.start_agent({"telemetry.devices": devices, "telemetry.units": "ticks"})
    edge = rig.start_edge(devices, seconds=3.0, rate_hz=50.0, faults=FaultConfig(malformed=0.3), seed=5)
    report = edge.join(30)
    settle(agent, report.published)
    state = agent.state()
    rejected = sum(d.health.counters.rejected_total for d in state.devices.values())
    rejected += sum(state.untracked_rejected.values())
    good = report.published - report.malformed_total
    assert report.malformed_total > 50
    assert rejected == report.malformed_total
    assert sum(d.health.counters.decoded for d in state.devices.values()) == good
    # Every good message was applied: none was displaced by the garbage queued around it.
    assert sum(d.health.counters.applied for d in state.devices.values()) == good
    # A rejected message arrived, so the hole it leaves is not counted as transit loss.
    assert state.agent.loss.lost == 0


def agent_metrics(agent: AgentService) -> str:
    from twin.service.metrics import render_metrics

    return render_metrics(agent.state())


def test_a_new_user_sees_a_200_arm_fleet_mirrored_whole(rig: LocalRig) -> None:
    """`twin run --devices '*'` with no config beside `twin edge-sim --devices 200`: every arm has a twin."""
    arms = device_ids(200)
    with rig.agent_process(devices="*", config_text=None) as (_proc, base):

        def up() -> AgentState | None:
            try:
                state = get_state(base)
            except OSError:
                return None
            return state if state.agent.broker.subscribes else None

        wait_for(up, 60, "the agent subscribed", interval=0.2)
        edge_log = rig.workdir / "edge-sim-200.log"
        edge_sim = ["edge-sim", "--devices", "200", "--broker", rig.broker.url]
        with edge_log.open("wb") as out:
            edge = subprocess.Popen(
                [sys.executable, "-m", "twin.cli", *edge_sim],
                stdout=out,
                stderr=subprocess.STDOUT,
                env=child_env(),
            )
            try:

                def mirrored() -> AgentState | None:
                    state = get_state(base)
                    whole = len(state.devices) == len(arms)
                    return (
                        state
                        if whole and all(d.health.counters.applied for d in state.devices.values())
                        else None
                    )

                state = wait_for(mirrored, 120, "all 200 arms mirrored", interval=0.5)
            finally:
                edge.terminate()
                edge.wait(15)
    assert sorted(state.devices) == arms
    assert "too_many_devices" not in state.untracked_rejected
    agent_log = next(rig.workdir.glob("agent-*.log")).read_text()
    assert "device ignored" not in agent_log
