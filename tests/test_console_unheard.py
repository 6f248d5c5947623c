"""The fleet page while no arm has been heard from: what a new user sees first after a deploy or `twin run`.

An empty page said only "no arm has been heard from yet", whatever the cause. IoT Core drops, without a word,
the messages an identity may subscribe to but not receive, so the agent cannot tell that from arms that are
off; what it can say is what it listens on and whether it is connected, and the page says both (the fleet
document's "listening"), in chromium against a real agent and broker."""

from __future__ import annotations

import json
import socket
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_for
from twin.edge.servo_faults import ServoFault
from twin.edge.simulator import FaultConfig
from twin.rig.local import LocalRig
from twin.service.console import HeldArm, Listening, fleet_summary, held_arms

pytestmark = pytest.mark.slow


def fleet_document(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url + "/api/fleet", timeout=60) as response:
        document: dict[str, Any] = json.load(response)
    return document


def empty_text(page: Any) -> str:
    """The empty fleet page's text once the agent's first document has arrived (before it, the page says it
    is loading: a slow first answer must not be read as the agent's word)."""
    text: str = page.wait_for_selector('#fleet-empty[data-loaded="true"]', timeout=60_000).inner_text()
    return text


def test_the_document_says_what_the_agent_listens_on_or_nothing() -> None:
    said = json.loads(fleet_summary([], 1.0, listening=Listening(("dt/lerobot/+/telemetry",), False)))
    assert said["listening"] == {"filters": ["dt/lerobot/+/telemetry"], "connected": False, "stopping": False}
    assert json.loads(fleet_summary([], 1.0))["listening"] is None  # a source that does not say
    stopping = Listening(("dt/lerobot/+/telemetry",), False, stopping=True)
    assert json.loads(fleet_summary([], 1.0, listening=stopping))["listening"]["stopping"] is True


def test_a_held_arm_says_how_many_of_its_messages_were_refused() -> None:
    """A held arm publishing with no twin and one switched off were listed alike: each says how many of its
    messages were refused, 0 for none heard."""
    said = held_arms({"arm-007": "bad file", "arm-008": "bad file"}, [], {"arm-007": 5})
    assert [(h.device, h.refused) for h in said] == [("arm-007", 5), ("arm-008", 0)]
    assert json.loads(fleet_summary([], 1.0, held=said))["held"][0]["refused"] == 5


def test_a_held_arms_alarm_counts_among_the_alarmed_arms() -> None:
    """A held arm has no row, yet its servos' alarms are raised: the Fleet page counted fewer arms alarmed
    than /alarms listed. Its worst alarm counts as a row's does, and the document lists it for its link."""
    held = [HeldArm("arm-007", "bad file", 2, "critical"), HeldArm("arm-008", "bad file", 0, None)]
    said = json.loads(fleet_summary([], 1.0, held=held))
    assert said["counts"]["alarmed_devices"] == {"critical": 1, "warning": 0}, said["counts"]
    assert said["counts"]["devices"] == 0  # arms with a card
    assert said["held"][0] == {
        "device": "arm-007",
        "why": "bad file",
        "unacknowledged": 2,
        "alarm_severity": "critical",
        "refused": 0,
    }
    assert [h["device"] for h in said["held"]] == ["arm-007", "arm-008"]
    assert json.loads(fleet_summary([], 1.0))["held"] == []


def test_an_empty_fleet_page_names_the_filter_and_what_to_check_until_an_arm_is_heard(
    rig: LocalRig, chromium_page: Any
) -> None:
    agent = rig.start_agent({"telemetry.devices": ["*"], "telemetry.units": "ticks"})
    # A local broker has no per-connection quota, so one connection subscribes the plain fleet filter.
    (topic_filter,) = agent.topic_filters
    assert topic_filter == "dt/lerobot/+/telemetry"
    listening = {"filters": [topic_filter], "connected": True, "stopping": False}
    assert fleet_document(agent.http_url)["listening"] == listening

    page = chromium_page
    # The agent's first document held back (a loaded host answers late): the page says it is loading, not
    # that no arm has been heard from, which it cannot know yet.
    held: list[Any] = []

    def fleet_url(url: str) -> bool:
        return url.endswith("/api/fleet") or "/api/stream/fleet" in url

    def hold(route: Any) -> None:
        held.append(route)

    page.route(fleet_url, hold)
    page.goto(agent.http_url + "/")
    loading = page.wait_for_selector('#fleet-empty[data-loaded="false"]', timeout=60_000)
    assert loading.inner_text() == "loading the fleet…"
    assert held  # the page asked, and waits
    page.unroute(fleet_url)  # lets the held requests go on
    text = empty_text(page)
    assert text.startswith("no arm has been heard from yet.") and topic_filter in text, text
    assert "iot:Receive" in text and "docs/agent.md" in text

    rig.start_edge(["arm-001"], seconds=None, rate_hz=10.0)
    page.wait_for_selector("text=arm-001", timeout=60_000)
    wait_for(lambda: page.query_selector("#fleet-empty") is None, 60, "the empty-page text gone")


def test_an_arm_whose_every_message_is_refused_is_named_above_the_empty_page(
    rig: LocalRig, chromium_page: Any
) -> None:
    """A walk's arm whose edge sent what the agent refuses had no card, and the empty page pointed at the
    topic and IAM: the reasons were only on the Events page. Now a notice names the arm and says where."""
    agent = rig.start_agent({"telemetry.devices": ["*"], "telemetry.units": "ticks"})
    rig.start_edge(["arm-009"], seconds=None, rate_hz=10.0, faults=FaultConfig(malformed=1.0))

    def named() -> list[str]:
        return [n for n in fleet_document(agent.http_url)["notices"] if n.startswith("arm-009 publishes")]

    wait_for(named, 60, "a notice naming arm-009")
    (notice,) = named()
    assert "refused all" in notice and "no card" in notice and "Events page" in notice, notice
    page = chromium_page
    page.goto(agent.http_url + "/")
    page.wait_for_selector("#fleet-notices >> text=arm-009 publishes, but the agent refused", timeout=60_000)
    # Not "no arm has been heard from yet" under a notice that names one heard.
    assert empty_text(page) == "no arm has a twin yet: the notices above say why"


def test_an_arm_held_by_its_refused_calibration_has_a_page_that_says_so(
    rig: LocalRig, chromium_page: Any, tmp_path: Path
) -> None:
    """A walk's arm whose file in the store was bad at the agent's start: with the whole fleet subscribed it
    is never admitted, and its page said "not known to this agent ... check the id", though the id was
    right and the fix is a push."""
    store = tmp_path / "cal"
    store.mkdir()
    (store / "arm-007.json").write_text('{"shoulder_pan": {}}')
    agent = rig.start_agent(
        {"telemetry.devices": ["*"], "telemetry.units": "ticks", "telemetry.calibrations": str(store)}
    )
    # A stalled wrist: its servo alarms are raised from the refused messages, and no card shows them.
    stall = (ServoFault("overload", "wrist_roll", 0.0, 600.0),)
    rig.start_edge(["arm-007"], seconds=None, rate_hz=10.0, servo_faults=stall)

    def named() -> list[str]:
        return [n for n in fleet_document(agent.http_url)["notices"] if n.startswith("arm-007's calibration")]

    wait_for(named, 60, "the Fleet page's notice naming arm-007")

    def alarmed() -> dict[str, Any] | None:
        doc = fleet_document(agent.http_url)
        return doc if doc["held"] and doc["held"][0]["unacknowledged"] == 2 else None

    # The document lists it with its two alarms waiting (the stall's current and load), and counts it among
    # the arms alarmed, as /alarms does.
    doc = wait_for(alarmed, 60, "arm-007 held with its two alarms waiting")
    (held,) = doc["held"]
    assert held["device"] == "arm-007" and "shoulder_pan" in held["why"], held
    assert held["alarm_severity"] == "critical", held
    assert doc["counts"]["alarmed_devices"][held["alarm_severity"]] == 1, doc["counts"]
    page = chromium_page
    page.goto(agent.http_url + "/")
    # Its notice leads to its page, where its alarms are: the Fleet page has no card for it.
    page.click('#fleet-notices a.held-arm[data-device="arm-007"]', timeout=60_000)
    page.wait_for_url("**/arm/arm-007", timeout=60_000)
    said = page.wait_for_selector("#unknown", timeout=60_000).inner_text()
    assert said.startswith("This agent holds this arm: its calibration in the store is refused ("), said
    assert f"twin calibration push arm-007 FILE --store {store}" in said, said
    assert "alarms are still checked" in said, said
    assert "held" in page.locator("h1").inner_text()
    # Its alarms are listed, and one acknowledged there is acknowledged in the agent.
    alarm_id = "arm-007/wrist_roll/overload"
    button = page.wait_for_selector(f'button[data-alarm="{alarm_id}"]', timeout=60_000)
    button.click()
    page.wait_for_selector(f"#ack-result.ack-ok >> text={alarm_id} acknowledged", timeout=60_000)
    with urllib.request.urlopen(agent.http_url + "/alarms?device=arm-007", timeout=60) as response:
        states = {a["alarm_id"]: a["state"] for a in json.load(response)["alarms"]}
    assert states[alarm_id] == "ACKNOWLEDGED", states


def test_an_arm_kept_out_by_max_devices_is_named(rig: LocalRig) -> None:
    agent = rig.start_agent(
        {"telemetry.devices": ["*"], "telemetry.units": "ticks", "telemetry.max_devices": 1}
    )
    rig.start_edge(["arm-001"], seconds=None, rate_hz=10.0)
    wait_for(lambda: fleet_document(agent.http_url)["rows"], 60, "arm-001's card")
    rig.start_edge(["arm-002"], seconds=None, rate_hz=10.0, seed=7)

    def named() -> list[str]:
        return [n for n in fleet_document(agent.http_url)["notices"] if n.startswith("arm-002 publishes")]

    wait_for(named, 60, "a notice naming arm-002")
    assert "(the last: too_many_devices)" in named()[0]
    assert [row[0] for row in fleet_document(agent.http_url)["rows"]] == ["arm-001"]


def test_an_empty_fleet_page_says_when_the_agent_is_not_connected(rig: LocalRig, chromium_page: Any) -> None:
    with socket.socket() as closed:  # a loopback port nothing listens on: every connect is refused
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    agent = rig.start_agent(
        {"broker.url": f"mqtt://127.0.0.1:{port}", "telemetry.devices": ["*"]}, wait_subscribed=False
    )
    assert fleet_document(agent.http_url)["listening"]["connected"] is False
    page = chromium_page
    page.goto(agent.http_url + "/")
    text = empty_text(page)
    assert "the agent is not connected to its broker" in text and "/healthz" in text, text


def test_an_empty_fleet_page_says_the_agent_is_not_connected_under_a_held_arms_notice(
    rig: LocalRig, chromium_page: Any, tmp_path: Path
) -> None:
    """A notice naming a held arm (its calibration refused at the start) is no reason that no arm is heard
    while the broker is down: the empty page said "the notices above say why", and no notice said that."""
    store = tmp_path / "cal"
    store.mkdir()
    (store / "arm-007.json").write_text('{"shoulder_pan": {}}')
    with socket.socket() as closed:  # a loopback port nothing listens on: every connect is refused
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    agent = rig.start_agent(
        {
            "broker.url": f"mqtt://127.0.0.1:{port}",
            "telemetry.devices": ["*"],
            "telemetry.calibrations": str(store),
        },
        wait_subscribed=False,
    )

    def named() -> list[str]:
        return [n for n in fleet_document(agent.http_url)["notices"] if n.startswith("arm-007's calibration")]

    wait_for(named, 60, "the Fleet page's notice naming arm-007")
    page = chromium_page
    page.goto(agent.http_url + "/")
    page.wait_for_selector("#fleet-notices >> text=arm-007's calibration", timeout=60_000)
    text = empty_text(page)
    assert "the agent is not connected to its broker" in text and "/healthz" in text, text
