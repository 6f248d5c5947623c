"""A subscription the broker refuses, as AWS IoT Core refuses a topic filter the agent's IAM identity does not
allow (SUBACK reason 0x87, Not authorized). mosquitto's ACLs cannot show this (they acknowledge and withhold),
so the agent subscribes through the quota proxy's policy stand-in (twin.rig.quota_proxy, `denied_filters`):
the refusal is named in the log, /healthz, /state, /metrics, the console's events and its fleet page, the
other arms are mirrored as before, and a corrected policy takes effect without a restart."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import get_health, get_metrics, metric, wait_for
from twin.core.topics import telemetry_topic
from twin.rig.local import LocalRig
from twin.rig.quota_proxy import QuotaProxy
from twin.service.agent import AgentService
from twin.service.events import Event, EventQuery
from twin.transport import subscriber

pytestmark = pytest.mark.slow

REFUSED, ALLOWED = "arm-001", "arm-002"
REFUSED_FILTER = telemetry_topic("dt/lerobot", REFUSED)


def broker_events(agent: AgentService) -> list[Event]:
    return agent.events(EventQuery(kinds=frozenset({"broker"})))


@pytest.fixture
def proxy(rig: LocalRig) -> Iterator[QuotaProxy]:
    # No publish budget: only the policy, which denies the first arm's topic.
    with QuotaProxy("127.0.0.1", rig.broker.port, budget=None, denied_filters=[REFUSED_FILTER]) as p:
        yield p


def test_a_refused_subscription_is_reported_and_a_corrected_policy_is_taken_up(
    rig: LocalRig,
    proxy: QuotaProxy,
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
    chromium_page: Any,
) -> None:
    # The refused filter is asked for again every second here (30 s in service), so the test sees the retry.
    monkeypatch.setattr(subscriber, "RESUBSCRIBE_S", 1.0)
    caplog.set_level(logging.INFO, logger="twin.transport.subscriber")
    agent = rig.start_agent(
        {"broker.url": proxy.url, "telemetry.devices": [REFUSED, ALLOWED], "telemetry.units": "ticks"},
        wait_subscribed=False,
    )
    edge = rig.start_edge([REFUSED, ALLOWED], seconds=None, rate_hz=10.0)
    try:
        # The allowed arm is mirrored; the refused one's messages never reach the agent.
        wait_for(
            lambda: agent.state().devices[ALLOWED].timestamp_ms is not None, 30, "the allowed arm mirrored"
        )
        broker = wait_for(
            lambda: (b := agent.state().agent.broker).subscriptions_refused == 1 and b, 30, "the refusal"
        )
        (connection,) = broker.connections
        assert connection.state == "refused" and connection.refused == (REFUSED_FILTER,)
        assert "refused by the broker (NOT_AUTHORIZED)" in broker.last_error
        assert agent.state().devices[REFUSED].health.counters.received == 0  # listed, never heard
        status, health = get_health(agent.http_url)
        assert status == 503 and health["broker_connected"] is True
        (reason,) = [r for r in health["reasons"] if "refused" in r]
        assert REFUSED_FILTER in reason and "iot:Subscribe" in reason
        samples = get_metrics(agent.http_url)
        labels = {"connection": "0", "client_id": connection.client_id}
        assert metric(samples, "twin_connection_refused_filters", **labels) == 1
        assert metric(samples, "twin_connection_up", **labels) == 1  # connected: only the filter is refused
        errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
        (logged,) = [m for m in errors if REFUSED_FILTER in m]  # once, not once per retry
        assert "NOT_AUTHORIZED" in logged and f"iot:Subscribe on topicfilter/{REFUSED_FILTER}" in logged
        wait_for(lambda: proxy.connections()[0].subscriptions_denied >= 2, 30, "a retry, refused again")
        # The console's Events page: one error for the refusal, however often it is refused again.
        wait_for(lambda: any("refused" in e.message for e in broker_events(agent)), 30, "the refusal event")
        refusals = [e for e in broker_events(agent) if "refused" in e.message]
        assert len(refusals) == 1 and refusals[0].level == "error" and REFUSED_FILTER in refusals[0].message

        # The console's fleet page says it above the arms, where an operator looks first.
        page = chromium_page
        page.goto(agent.http_url + "/")
        notice = page.wait_for_selector("#fleet-notices p", timeout=30_000)
        assert notice is not None
        assert REFUSED_FILTER in notice.inner_text() and "iot:Subscribe" in notice.inner_text()

        proxy.allow(REFUSED_FILTER)  # the policy corrected
        wait_for(
            lambda: agent.state().devices[REFUSED].timestamp_ms is not None,
            30,
            "the arm mirrored once allowed",
        )
        broker = agent.state().agent.broker
        assert broker.subscriptions_refused == 0 and broker.connections[0].state == "connected"
        wait_for(lambda: get_health(agent.http_url)[0] == 200, 30, "healthy once nothing is refused")
        assert any(f"{REFUSED_FILTER} granted now" in r.getMessage() for r in caplog.records)
        wait_for(lambda: any("granted now" in e.message for e in broker_events(agent)), 30, "the grant event")
        # The page's live stream takes the notice away.
        page.wait_for_selector("#fleet-notices", state="hidden", timeout=30_000)
    finally:
        edge.stop()
        edge.join(30)
        agent.stop()  # before the proxy closes under its connection
