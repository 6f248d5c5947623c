"""Agents that do not collide: each has client ids and a shared-subscription group of its own (the twin
host's named for its stack, any other agent's for its machine, or given), so an agent on a laptop beside the
twin host, both mirroring the whole fleet, each receive every message. Real mosquitto, with the fleet on a
shared subscription as on IoT Core (a per-connection budget turns it on)."""

from __future__ import annotations

import socket
from typing import Any

import pytest
from conftest import wait_for
from twin.rig.local import LocalRig
from twin.transport.broker import (
    CLIENT_ID_PREFIX_MAX,
    DEFAULT_CLIENT_ID_PREFIX,
    BrokerConfig,
    agent_client_id_prefix,
)
from twin.transport.plan import shared_group

from stacks.settings import TwinSettings

FLEET = [f"arm-{i:03d}" for i in range(1, 11)]


def test_an_agent_is_named_for_its_machine_unless_told() -> None:
    host = socket.gethostname()
    assert BrokerConfig().client_id_prefix == agent_client_id_prefix(host)
    assert BrokerConfig(client_id_prefix="lab-a-").client_id_prefix == "lab-a-"
    assert agent_client_id_prefix("ip-10-0-0-12.ec2.internal") == "so101-twin-ip-10-0-0-12.ec2.internal-"
    assert agent_client_id_prefix("Jo's laptop") == "so101-twin-Jo-s-laptop-"
    assert agent_client_id_prefix("") == "so101-twin-agent-"
    long = agent_client_id_prefix("x" * 300)
    assert len(long) <= CLIENT_ID_PREFIX_MAX and long.startswith(DEFAULT_CLIENT_ID_PREFIX)
    # The twin host's is named for its stack: two stacks, or a laptop beside one, never share a group.
    host_prefix = TwinSettings(client_cidr="203.0.113.7/32", stack_name="LabTwin").client_id_prefix
    assert host_prefix == "so101-twin-LabTwin-"
    assert shared_group(host_prefix) == "so101-twin-LabTwin"
    assert shared_group(host_prefix) != shared_group(BrokerConfig().client_id_prefix)


def fleet_agent(rig: LocalRig, prefix: str) -> Any:
    return rig.start_agent(
        {
            "broker.client_id_prefix": prefix,
            # A budget puts the whole fleet on a shared subscription, as on IoT Core.
            "broker.per_connection_limit": 100,
            "telemetry.devices": ["*"],
            "telemetry.units": "ticks",
        }
    )


def received(agent: Any) -> dict[str, int]:
    return {d: s.health.counters.received for d, s in agent.state().devices.items()}


def run_fleet(
    rig: LocalRig, prefixes: tuple[str, str]
) -> tuple[dict[str, int], dict[str, int], dict[str, int]]:
    laptop, host = (fleet_agent(rig, p) for p in prefixes)
    report = rig.start_edge(FLEET, seconds=3.0, rate_hz=10.0).join(60)
    total = sum(report.per_device.values())
    wait_for(
        lambda: (
            sum(received(laptop).values()) + sum(received(host).values()) >= total
            and (
                prefixes[0] == prefixes[1] or min(sum(received(a).values()) for a in (laptop, host)) >= total
            )
        ),
        60,
        "the fleet's messages at both agents",
    )
    return dict(report.per_device), received(laptop), received(host)


def test_a_laptop_beside_the_host_each_receive_the_whole_fleet(rig: LocalRig) -> None:
    """Done when: two agents on one broker with devices = "*" each receive 100 % of a 10-arm fleet."""
    published, laptop, host = run_fleet(
        rig, ("", TwinSettings(client_cidr="203.0.113.7/32").client_id_prefix)
    )
    assert set(published) == set(FLEET) and all(n > 0 for n in published.values())
    assert laptop == published
    assert host == published


def test_one_group_for_both_splits_the_fleet_which_is_what_the_own_names_prevent(rig: LocalRig) -> None:
    """The control: the same prefix for both (as every agent had before) puts them in one group, and the
    broker hands each message to one of them."""
    published, first, second = run_fleet(rig, ("so101-twin-", "so101-twin-"))
    total = sum(published.values())
    assert sum(first.values()) + sum(second.values()) == total
    assert 0 < sum(first.values()) < total and 0 < sum(second.values()) < total


@pytest.mark.parametrize("prefix", ["so101-twin-", ""])
def test_the_pool_subscribes_under_the_agents_own_group(rig: LocalRig, prefix: str) -> None:
    agent = fleet_agent(rig, prefix)
    group = shared_group(prefix or agent_client_id_prefix(socket.gethostname()))
    assert agent.topic_filters == [f"$share/{group}/dt/lerobot/+/telemetry"]
