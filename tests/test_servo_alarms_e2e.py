"""Servo alarms end to end: `twin edge-sim` faults through a real mosquitto into the agent, read and
acknowledged over its HTTP API, logged as JSON lines, counted in /metrics and written as EMF lines.

One run carries three faults on three joints at once (docs/servo-health.md lists what each raises):
heat on wrist_roll, an overload on shoulder_lift, a contact on elbow_flex. The agent's temperature clear
time is shortened so the run takes seconds; every other threshold is the default.
"""

from __future__ import annotations

import json
import logging
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from conftest import get_metrics, metric, wait_for
from test_emf import validate_emf_line
from twin.core.alarms import what_to_do
from twin.edge.servo_faults import ServoFault
from twin.rig.local import LocalRig
from twin.service.state import AgentState, AlarmList

pytestmark = pytest.mark.slow

FAULTS = (
    ServoFault("heat", "wrist_roll", 1.0, 8.0),
    ServoFault("overload", "shoulder_lift", 1.0, 6.0),
    ServoFault("contact", "elbow_flex", 1.0, 6.0),
)
EXPECTED = {
    ("wrist_roll", "over_temperature"),
    ("wrist_roll", "over_temperature_critical"),
    ("shoulder_lift", "overload"),
    ("shoulder_lift", "over_current"),
    ("shoulder_lift", "model_mismatch"),
    ("shoulder_lift", "servo_error"),  # the overload bit, once the servo's own 2 s protection time passed
    ("elbow_flex", "model_mismatch"),
}


def alarms(url: str, everything: bool = False) -> AlarmList:
    with urllib.request.urlopen(url + "/alarms" + ("?all=1" if everything else ""), timeout=30) as resp:
        return AlarmList.from_json(resp.read())


def post(url: str) -> tuple[int, Any]:
    request = urllib.request.Request(url, data=b"", method="POST")
    try:
        with urllib.request.urlopen(request, timeout=30) as resp:
            return resp.status, json.loads(resp.read())
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read())


def by_key(listing: AlarmList) -> dict[tuple[str, str], str]:
    return {(a.joint, a.kind): a.state for a in listing.alarms}


def test_each_servo_fault_raises_and_clears_its_alarms(
    rig: LocalRig, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    emf_file = tmp_path / "emf.log"
    agent = rig.start_agent(
        {
            "telemetry.devices": ["arm-001"],
            "telemetry.units": "ticks",
            "alarms.temperature_clear_after_s": 2.0,
            "cloudwatch.emf_file": str(emf_file),
            "cloudwatch.agent_name": "e2e",
            "cloudwatch.interval_s": 0.5,
        }
    )
    url = agent.http_url
    caplog.set_level(logging.INFO, logger="twin.service")
    rig.start_edge(["arm-001"], variant="ticks", rate_hz=10.0, servo_faults=FAULTS, model_loads=True)

    # Raised: every expected alarm ACTIVE (and nothing else). The wrist's temperature gauge is read on each
    # look: the heat is over 60 C only from about 2 to 7.5 s into the run, and a busy machine may take most
    # of that to see every alarm raised, so the hottest reading seen is what is checked.
    hottest = [float("-inf")]

    def all_raised() -> dict[tuple[str, str], str] | None:
        samples = get_metrics(url)
        key = ("twin_servo_temperature_celsius", (("device", "arm-001"), ("joint", "wrist_roll")))
        hottest[0] = max(hottest[0], samples.get(key, float("-inf")))
        seen = by_key(alarms(url))
        return seen if set(seen) >= EXPECTED else None

    raised = wait_for(all_raised, 60, "every fault's alarms to be raised", interval=0.1)
    assert set(raised) == EXPECTED, raised
    # Each says what to do at the arm about its kind, as its e-mail and the Arm page do (a servo error's
    # about the bits its value holds: test_alerts).
    listed = alarms(url).alarms
    assert all(a.advice == what_to_do(a.kind, a.joint, a.value, a.message) != "" for a in listed), listed

    # The readings are in /state and /metrics while the faults run: read first, as the faults end about 7 s
    # into the run.
    with urllib.request.urlopen(url + "/state", timeout=30) as resp:
        state = AgentState.from_json(resp.read())
    servos = state.devices["arm-001"].servos
    assert servos is not None and servos["shoulder_lift"].voltage_v == 5.0
    assert servos["elbow_flex"].model_load_percent is not None
    metrics = get_metrics(url)
    assert hottest[0] >= 60.0, f"the wrist's temperature gauge read at most {hottest[0]} C during the heat"
    assert abs(metric(metrics, "twin_servo_load_percent", device="arm-001", joint="shoulder_lift")) <= 100.0
    assert metric(metrics, "twin_servo_alarms_raised_total", kind="overload") == 1.0
    assert metric(metrics, "twin_servo_alarms_present", severity="critical") >= 1.0
    # Each alarm by its servo: one series each (ACTIVE, or LATCHED if it cleared meanwhile; none is
    # acknowledged yet), so an alerting rule on /metrics can say which servo.
    series = {
        (labels["joint"], labels["kind"]): (labels["state"], value)
        for (name, pairs), value in metrics.items()
        if name == "twin_servo_alarm"
        for labels in [dict(pairs)]
        if labels["device"] == "arm-001"
    }
    assert set(series) == EXPECTED, series
    assert all(state in ("ACTIVE", "LATCHED") and value == 1.0 for state, value in series.values()), series

    # Acknowledge the over-current while it lasts: ACKNOWLEDGED; again: 409; an unknown id: 404.
    ack_url = f"{url}/alarms/arm-001/shoulder_lift/over_current/ack"
    status, body = post(ack_url)
    assert status == 200, body
    assert body["alarms"][0]["state"] in ("ACKNOWLEDGED", "NORMAL")
    status, body = post(ack_url)
    assert status == 409 and body["error"] == "nothing_to_acknowledge"
    status, body = post(f"{url}/alarms/arm-001/shoulder_lift/melting/ack")
    assert status == 404 and body["error"] == "alarm_not_found"

    # Cleared: the acknowledged alarm returns to NORMAL, the others wait LATCHED for a person.
    def all_cleared() -> dict[tuple[str, str], str] | None:
        seen = by_key(alarms(url))
        return seen if seen and all(s == "LATCHED" for s in seen.values()) else None

    cleared = wait_for(all_cleared, 60, "every alarm to clear", interval=0.1)
    assert set(cleared) == EXPECTED - {("shoulder_lift", "over_current")}
    for joint, kind in cleared:
        status, body = post(f"{url}/alarms/arm-001/{joint}/{kind}/ack")
        assert status == 200 and body["alarms"][0]["state"] == "NORMAL"
    assert alarms(url).alarms == ()
    assert {(a.joint, a.kind) for a in alarms(url, everything=True).alarms} >= EXPECTED

    # Every state change was a JSON log line with its fields.
    events = [r for r in caplog.records if getattr(r, "event", None) == "servo_alarm"]
    actions = {(r.joint, r.kind, r.action) for r in events}  # type: ignore[attr-defined]
    for joint, kind in EXPECTED:
        assert (joint, kind, "raised") in actions
        assert (joint, kind, "cleared") in actions
    assert any(r.levelno == logging.ERROR and r.severity == "critical" for r in events)  # type: ignore[attr-defined]
    # The text names the arm too: a plain-text log (twin demo's) shows none of the fields.
    assert all(r.getMessage().startswith(f"servo alarm {r.action} on arm-001: ") for r in events)  # type: ignore[attr-defined]

    # CloudWatch: valid EMF lines, and a critical alarm counted while the faults ran.
    def critical_seen() -> bool:
        if not emf_file.exists():
            return False
        docs = [validate_emf_line(line) for line in emf_file.read_text().splitlines()]
        return any(d.get("Severity") == "critical" and d["ActiveAlarms"] >= 1 for d in docs)

    assert wait_for(critical_seen, 30, "an EMF line counting a critical alarm", interval=0.2)
