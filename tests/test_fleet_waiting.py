"""The Fleet page's "unacknowledged" filter: every arm with an alarm waiting for a person, not only the arms
whose worst alarm is ACTIVE. An operator who acknowledged an arm's critical alarm while its warning was
still ACTIVE saw the arm leave the filter, and so did an arm whose alarms had all cleared to LATCHED."""

from __future__ import annotations

import json
import time
import urllib.request
from typing import Any

import pytest
from conftest import wait_for
from test_alerts import hot, hot_arm_settings
from twin.service.agent import AgentService
from twin.service.config import load_config
from twin.service.events import EventQuery

pytestmark = pytest.mark.slow

CRITICAL = "arm-003/elbow_flex/over_temperature_critical"


def fleet_rows(url: str) -> dict[str, dict[str, Any]]:
    with urllib.request.urlopen(url + "/api/fleet", timeout=30) as response:
        document = json.load(response)
    return {row[0]: dict(zip(document["columns"], row, strict=True)) for row in document["rows"]}


def test_an_arm_whose_worst_alarm_is_acknowledged_still_shows_as_waiting(chromium_page: Any) -> None:
    settings = hot_arm_settings(**{"telemetry.devices": ["arm-003", "arm-004"], "http.listen": "127.0.0.1:0"})
    agent = AgentService(load_config(None, settings))
    agent.start()
    try:
        now_ms = int(time.time() * 1000)
        # 68 C raises the elbow's warning (60 C) and its critical alarm (65 C) at once; arm-004 is cool.
        agent.feed("dt/lerobot/arm-003/telemetry", hot("arm-003", now_ms, 68))
        agent.feed("dt/lerobot/arm-004/telemetry", hot("arm-004", now_ms, 35))
        wait_for(lambda: len(agent.alarms()) == 2, 30, "both of arm-003's alarms raised")
        agent.acknowledge_alarm(CRITICAL)
        url = agent.http_url
        wait_for(lambda: len(fleet_rows(url)) == 2, 30, "both arms listed")
        rows = fleet_rows(url)
        waiting = rows["arm-003"]
        # Its worst alarm is the acknowledged critical one; the warning still waits for a person.
        assert (waiting["alarm_severity"], waiting["alarm_state"]) == ("critical", "ACKNOWLEDGED")
        assert waiting["unacknowledged"] == 1 and rows["arm-004"]["unacknowledged"] == 0

        page = chromium_page
        page.goto(url + "/")
        page.wait_for_selector('#fleet-view [data-device="arm-004"]', timeout=30_000)
        # A critical alarm outlines its arm's card; a warning does not.
        outline = (
            "(d) => getComputedStyle(document.querySelector(`#fleet-view [data-device='${d}']`)).boxShadow"
        )
        assert page.evaluate(outline, "arm-003") != "none"
        assert page.evaluate(outline, "arm-004") == "none"
        page.select_option('select[aria-label="alarm"]', label="unacknowledged")
        page.wait_for_selector('#fleet-view [data-device="arm-004"]', state="detached", timeout=30_000)
        assert page.query_selector('#fleet-view [data-device="arm-003"]') is not None
    finally:
        agent.stop()


def test_acknowledging_a_latched_alarm_says_reset_as_the_events_do(chromium_page: Any) -> None:
    """A LATCHED alarm acknowledged goes to NORMAL, and the Events page records a "reset": the Arm page said
    "acknowledged", so a search on the Events page for what the page said found nothing."""
    settings = hot_arm_settings(**{"alarms.temperature_clear_after_s": 0.0, "http.listen": "127.0.0.1:0"})
    agent = AgentService(load_config(None, settings))
    agent.start()
    try:
        now_ms = int(time.time() * 1000)
        agent.feed("dt/lerobot/arm-003/telemetry", hot("arm-003", now_ms, 62))  # the warning only
        agent.feed("dt/lerobot/arm-003/telemetry", hot("arm-003", now_ms + 100, 35))  # cleared: LATCHED
        wait_for(lambda: [a.state for a in agent.alarms()] == ["LATCHED"], 30, "the warning LATCHED")
        (alarm,) = agent.alarms()
        page = chromium_page
        page.goto(agent.http_url + "/arm/arm-003")
        page.locator(f'#alarms tr[data-alarm="{alarm.alarm_id}"] button').click()
        said = page.wait_for_selector("#ack-result.ack-ok", timeout=30_000).inner_text()
        assert said == f"{alarm.alarm_id} reset (acknowledged after it cleared): now NORMAL", said
        # The events are collected every half second: the reset is among them soon after.
        reset = EventQuery(text="reset", kinds=frozenset({"alarm"}))
        wait_for(lambda: agent.events(reset), 30, "the reset among the events")
    finally:
        agent.stop()
