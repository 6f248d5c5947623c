"""`twin view`: pure parts (SSE parsing, state intake, picker, overlay) and the real window under Xvfb.

The end-to-end test runs the real chain: a private mosquitto, the edge simulator publishing two arms, the
agent service, and `twin view` as a subprocess on a private Xvfb display. It reads the X framebuffer (Xvfb
-fbdir writes it as an XWD file) and checks that the arm is drawn and moves. The screenshot is kept under
out/viewer/.
"""

from __future__ import annotations

import dataclasses
import json
import os
import random
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
import urllib.parse
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import http_get, unbrokered_agent, wait_for
from twin.core.health import DeviceStatus, HealthSnapshot, WindowLatency
from twin.edge.payload import encode, make_payload
from twin.rig.local import LocalRig
from twin.robot import so101
from twin.service.state import (
    AgentInfo,
    AgentState,
    DeviceState,
    DeviceView,
    LossSnapshot,
    ServoState,
    attention_mark,
    device_attention,
)
from twin.viewer.config import ViewerConfig
from twin.viewer.feed import AgentFeed, describe_error, iter_sse_data, iter_sse_events
from twin.viewer.fleet import (
    KEY_PAGE_DOWN,
    KEY_PAGE_UP,
    LINK_STREAM,
    LINK_UNREACHABLE,
    DevicePicker,
    FleetView,
)
from twin.viewer.window import (
    ALARM_COLOURS,
    JointTint,
    ViewerError,
    check_display,
    device_window,
    others_line,
    overlay_lines,
    servo_rows,
)

REPO = Path(__file__).resolve().parents[1]
TWIN = Path(sys.executable).with_name("twin")
OUT = REPO / "out" / "viewer"


def device_state(stamp: int, angle: float) -> DeviceState:
    return DeviceState(
        health=HealthSnapshot(
            status=DeviceStatus.ONLINE,
            age_s=0.05,
            rate_hz=10.0,
            edge_clock_latency_s=WindowLatency(p50=0.012, p99=0.034, samples=40),
        ),
        timestamp_ms=stamp,
        joints_rad=dict.fromkeys(so101.JOINT_NAMES, angle),
    )


def state_of(**devices: DeviceState) -> AgentState:
    return AgentState(agent=AgentInfo(), devices={k.replace("_", "-"): v for k, v in devices.items()})


# ------------------------------------------------------------------------------------------------ pure parts


def test_sse_events_are_split_and_comments_skipped():
    lines = [b"retry: 1000\n", b"\n", b": keep-alive\n", b"event: state\n", b'data: {"a":\n', b"data: 1}\n"]
    lines += [b"\n", b"data: 2\r\n", b"\r\n", b"data: partial"]
    assert list(iter_sse_data(lines)) == ['{"a":\n1}', "2"]


def test_fleet_feeds_estimators_and_ignores_repeats():
    fleet = FleetView()
    base = 1_706_000_000_000
    for k in range(5):
        # The agent streams at 30 Hz while telemetry arrives at 10 Hz: each sample is seen three times.
        for rep in range(3):
            # Through the JSON the stream carries, as the feed hands it over.
            document = state_of(arm_001=device_state(base + 100 * k, 0.1 * k)).to_json()
            assert fleet.update_json(document, 50.0 + 0.1 * k + 0.033 * rep) == 1
    assert fleet.devices() == ["arm-001"]
    info = fleet.info("arm-001")
    assert info is not None and info.status == "ONLINE" and info.latency_p99_s == pytest.approx(0.034)
    pose = fleet.pose("arm-001", 50.4)
    assert pose is not None and pose["shoulder_pan"] == pytest.approx(0.4, abs=1e-9)
    # A linear ramp is predicted exactly between samples, so repeats did not distort the estimate.
    assert fleet.pose("arm-001", 50.45)["elbow_flex"] == pytest.approx(0.45, abs=1e-6)
    assert fleet.pose("arm-002", 50.4) is None


def test_sse_events_carry_their_names():
    lines = [b"event: device\n", b'data: {"a": 1}\n', b"\n", b"data: 2\n", b"\n"]
    lines += [b"event: state\n", b"data: 3\n", b"\n"]
    assert list(iter_sse_events(lines)) == [("device", '{"a": 1}'), ("message", "2"), ("state", "3")]


def test_a_view_updates_its_arm_and_lists_the_fleet():
    """`/stream?device=` frames: the shown arm's figures and pose, and the agent's ids (which replace the
    list: an arm the agent forgot drops out)."""
    fleet = FleetView()
    base = 1_706_000_000_000
    for k in range(3):
        arm = dataclasses.replace(device_state(base + 100 * k, 0.1 * k), device_id="arm-001")
        view = DeviceView(1.0, arm, ["arm-001", "arm-002", "arm-003"])
        assert fleet.update_view_json(view.to_json(), 50.0 + 0.1 * k) == 1
    assert fleet.devices() == ["arm-001", "arm-002", "arm-003"]
    assert fleet.info("arm-001").status == "ONLINE"
    assert fleet.info("arm-002") is None  # listed, not streamed
    assert fleet.pose("arm-001", 50.2)["shoulder_pan"] == pytest.approx(0.2, abs=1e-9)
    assert fleet.update_view_json(DeviceView(2.0, None, ["arm-001", "arm-003"]).to_json(), 51.0) == 0
    assert fleet.devices() == ["arm-001", "arm-003"]
    assert fleet.update_view_json(b'{"time": 1.0, "device": 3, "devices": []}', 52.0) == 0
    assert fleet.bad_snapshots == 1 and fleet.snapshots == 4


@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_the_viewer_asks_the_agent_for_the_arm_it_shows(
    tmp_path: Path, workers: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The feed reads `/stream?device=<shown>`: the agent sends that arm and the fleet's ids, asked of the
    arm's own mirror, and never builds its whole state for it (most of a core at 1,000 arms);
    paging to another arm switches the stream."""
    devices = ["arm-001", "arm-002", "arm-003"]
    agent = unbrokered_agent(tmp_path, workers)
    try:
        rng = random.Random(2)
        for device in devices:
            agent.feed(f"dt/lerobot/{device}/telemetry", encode(make_payload(device, 0.0, "ticks", rng)))
        wait_for(
            lambda: all((d := agent.state().devices.get(n)) and d.health.counters.applied for n in devices),
            30,
            "three arms mirrored",
        )
        whole = []
        state = agent.state
        monkeypatch.setattr(agent, "state", lambda: whole.append(1) or state())
        fleet = FleetView()
        picker = DevicePicker("arm-002")
        feed = AgentFeed(ViewerConfig(agent_url=agent.http_url), fleet, wanted=lambda: picker.selected)
        feed.start()
        try:
            wait_for(lambda: fleet.info("arm-002") is not None, 30, "arm-002 in the viewer")
            assert fleet.devices() == devices and fleet.link == LINK_STREAM
            assert fleet.info("arm-001") is None and fleet.info("arm-003") is None  # the shown arm only
            assert fleet.pose("arm-002", time.monotonic()) is not None
            picker.on_key(KEY_PAGE_DOWN)
            assert picker.current(fleet.devices()) == "arm-003"
            wait_for(lambda: fleet.info("arm-003") is not None, 30, "arm-003 in the viewer after paging")
        finally:
            feed.stop()
        assert whole == []  # no whole state was built for the viewer
    finally:
        agent.stop()


def test_a_bad_device_in_the_stream_request_is_refused_with_the_rule(tmp_path: Path) -> None:
    agent = unbrokered_agent(tmp_path, 1)
    try:
        status, _, body = http_get(agent.http_url + "/stream?device=" + urllib.parse.quote("a/b", safe=""))
    finally:
        agent.stop()
    assert status == 400
    answer = json.loads(body)
    assert answer["error"] == "bad_device" and "MQTT topic character" in answer["detail"], answer


def test_fleet_tolerates_bad_documents():
    fleet = FleetView()
    assert fleet.update_json(b'{"nope": 1}', 1.0) == 0  # not an agent state: no "agent", no "devices"
    assert fleet.update_json(b"[1, 2]", 1.0) == 0
    assert fleet.update_json(b'{"agent": {}, "devices": {"x": 3}}', 1.0) == 0  # a device must be an object
    assert fleet.update_json(b'{"agent": {}, "devices": {', 1.0) == 0  # truncated
    assert fleet.bad_snapshots == 4 and fleet.snapshots == 0
    # A device not yet mirrored (no snapshot) is listed with its health but has no pose.
    document = b'{"agent": {}, "devices": {"arm-009": {"status": "OFFLINE", "age_s": null}}}'
    assert fleet.update_json(document, 2.0) == 1
    assert fleet.devices() == ["arm-009"]
    assert fleet.pose("arm-009", 2.0) is None
    assert fleet.info("arm-009").status == "OFFLINE"


def test_picker_defaults_to_first_and_cycles_with_page_keys():
    picker = DevicePicker()
    assert picker.current([]) is None
    devices = ["arm-001", "arm-002", "arm-003"]
    assert picker.current(devices) == "arm-001"
    picker.on_key(KEY_PAGE_DOWN)
    assert picker.current(devices) == "arm-002"
    picker.on_key(KEY_PAGE_UP)
    picker.on_key(KEY_PAGE_UP)
    assert picker.current(devices) == "arm-003"
    picker.on_key(ord("A"))  # not ours: simulate's own shortcut
    assert picker.current(devices) == "arm-003"
    preferred = DevicePicker("arm-002")
    assert preferred.current([]) == "arm-002"  # waits for its device rather than jumping to another
    assert preferred.current(devices) == "arm-002"


def test_the_devices_line_shows_the_arms_around_the_shown_one_at_fleet_scale():
    fleet = [f"arm-{i:04d}" for i in range(1, 1001)]
    assert device_window(fleet, "arm-0501") == (
        "(497 before)  arm-0498  arm-0499  arm-0500  [arm-0501]  arm-0502  arm-0503  arm-0504  (496 after)"
    )
    assert device_window(fleet, "arm-0001").startswith("[arm-0001]  arm-0002")
    assert device_window(fleet, "arm-0001").endswith("arm-0007  (993 after)")
    assert device_window(fleet, "arm-1000") == (
        "(993 before)  arm-0994  arm-0995  arm-0996  arm-0997  arm-0998  arm-0999  [arm-1000]"
    )
    assert device_window(["arm-001", "arm-002", "arm-003"], "arm-002") == "arm-001  [arm-002]  arm-003"
    # An arm the agent no longer lists: the start of the list, none in brackets.
    assert device_window(fleet, "arm-9999").endswith("(993 after)")


def attention_state(status: DeviceStatus, *alarms: tuple[str, str]) -> DeviceState:
    """An arm with `status` and servo alarms given as (severity, state), one joint each."""
    servos = {
        joint: ServoState(temperature_c=40.0, alarm_severity=severity, alarm_state=state)
        for joint, (severity, state) in zip(so101.JOINT_NAMES, alarms, strict=False)
    }
    health = HealthSnapshot(status=status, age_s=0.05, rate_hz=10.0)
    return DeviceState(health=health, servos=servos or None)


def test_the_arms_that_want_a_look_are_marked_worst_alarm_first() -> None:
    """The desktop shows one arm: another's alarm or silence was nowhere on it until someone paged there."""
    assert attention_mark("ONLINE", None, None) is None
    assert attention_mark("OFFLINE", None, None) == "OFFLINE"
    assert attention_mark("ONLINE", "critical", "LATCHED") == "CRITICAL"
    assert attention_mark("STALE", "warning", "ACKNOWLEDGED") == "STALE, warning ack"
    online = DeviceStatus.ONLINE
    assert device_attention(attention_state(online)) is None
    # The worse severity wins; of one severity, the alarm no one has acknowledged.
    both = attention_state(online, ("warning", "ACTIVE"), ("critical", "ACKNOWLEDGED"))
    assert device_attention(both) == "critical ack"
    same = attention_state(online, ("critical", "ACKNOWLEDGED"), ("critical", "ACTIVE"))
    assert device_attention(same) == "CRITICAL"
    fleet = FleetView()
    state = state_of(
        arm_001=attention_state(online),
        arm_002=attention_state(DeviceStatus.OFFLINE),
        arm_003=attention_state(online, ("critical", "ACTIVE")),
        arm_004=attention_state(online, ("warning", "ACKNOWLEDGED")),
    )
    fleet.update(state, 10.0)
    marks = {"arm-002": "OFFLINE", "arm-003": "CRITICAL", "arm-004": "warning ack"}
    assert fleet.attention() == marks
    # The same marks come in an arm's view (what `twin view` follows), as the agent sends them.
    view = DeviceView(0.0, None, ["arm-001", "arm-002"], {"arm-002": "OFFLINE"})
    assert fleet.update_view_json(view.to_json(), 11.0) == 0
    assert fleet.attention() == {"arm-002": "OFFLINE"}
    # An older agent's view has no marks: none shown, rather than the last ones kept.
    older = b'{"time": 0.0, "device": null, "devices": ["arm-001"]}'
    assert fleet.update_view_json(older, 12.0) == 0 and fleet.attention() == {}


def test_the_overlay_names_the_other_arms_that_want_a_look() -> None:
    devices = [f"arm-{i:03d}" for i in range(1, 13)]
    marks = {"arm-002": "warning ack", "arm-004": "OFFLINE", "arm-009": "CRITICAL", "arm-011": "STALE"}
    assert device_window(devices[:5], "arm-003", attention=marks) == (
        "arm-001  arm-002 (warning ack)  [arm-003]  arm-004 (OFFLINE)  arm-005"
    )
    assert others_line(devices, "arm-003", marks) == (
        "4 of 11 want a look: arm-009 CRITICAL, arm-004 OFFLINE, arm-011 STALE (+1 more)"
    )
    # The shown arm is not an "other"; an id the agent no longer lists is not counted.
    assert others_line(devices, "arm-009", {"arm-009": "CRITICAL", "arm-099": "OFFLINE"}) == (
        "all 11 others: ONLINE, no alarm"
    )
    assert others_line(devices[:2], "arm-001", {}) == "the other arm: ONLINE, no alarm"
    assert others_line(devices[:3], "arm-001", {"arm-003": "STALE"}) == "1 of 2 wants a look: arm-003 STALE"
    # Shown an arm the agent does not list: every listed arm is an other.
    assert others_line(devices[:2], "arm-099", {}) == "all 2 others: ONLINE, no alarm"
    config, fleet = ViewerConfig(), FleetView()
    fleet.update_view(DeviceView(0.0, device_state(1000, 0.0), devices, marks), 10.0)
    labels, values = overlay_lines(config, fleet, device="arm-001", devices=fleet.devices(), now=10.5, fps=60)
    table = dict(zip(labels.split("\n"), values.split("\n"), strict=True))
    assert table["Others"].startswith("4 of 11 want a look: arm-009 CRITICAL")
    assert "arm-004 (OFFLINE)" in table["Devices"]
    fleet.set_link(LINK_UNREACHABLE, "connection refused", now=11.0)
    labels, values = overlay_lines(config, fleet, device="arm-001", devices=fleet.devices(), now=12.0, fps=60)
    table = dict(zip(labels.split("\n"), values.split("\n"), strict=True))
    assert table["Others"] == "unknown while the agent is out of reach"


def test_overlay_shows_figures_and_unreachable_agent():
    config = ViewerConfig()
    fleet = FleetView()
    fleet.update(state_of(arm_001=device_state(1000, 0.0), arm_002=device_state(1000, 0.0)), 10.0)
    labels, values = overlay_lines(
        config, fleet, device="arm-002", devices=fleet.devices(), now=10.5, fps=59.7
    )
    table = dict(zip(labels.split("\n"), values.split("\n"), strict=True))
    assert table["Device"] == "arm-002 (2/2)"
    assert table["Status"] == "ONLINE"
    assert table["Age"] == "0.55 s"  # the agent's age plus the time since the snapshot arrived
    assert table["Rate"] == "10.0 Hz"
    assert table["Latency"] == "p50 12 ms / p99 34 ms (edge clock)"
    assert table["Lost"] == "0 messages (estimated from edge timestamp gaps)"
    assert "[arm-002]" in table["Devices"] and "Page Up" in table["Keys"]
    assert table["View"] == "60 fps, smoothing predict"
    fleet.set_link(LINK_UNREACHABLE, "connection refused", now=10.0)
    labels, values = overlay_lines(config, fleet, device=None, devices=[], now=13.0, fps=60.0)
    table = dict(zip(labels.split("\n"), values.split("\n"), strict=True))
    assert table["Agent"] == "agent unreachable (connection refused); retrying [3 s]"
    assert table["Device"] == "waiting for devices"


def test_while_the_agent_is_out_of_reach_the_arms_status_is_not_shown_as_live() -> None:
    """A walk stopped the agent: the overlay kept 'Status ONLINE', 'Rate 10.2 Hz' for 22 s of silence."""
    config, fleet = ViewerConfig(), FleetView()
    fleet.update(state_of(arm_001=device_state(1000, 0.0)), 10.0)
    fleet.set_link(LINK_UNREACHABLE, "connection refused", now=10.0)
    labels, values = overlay_lines(config, fleet, device="arm-001", devices=fleet.devices(), now=32.0, fps=60)
    table = dict(zip(labels.split("\n"), values.split("\n"), strict=True))
    assert table["Status"] == "unknown while the agent is out of reach (it said ONLINE)"
    assert "Rate" not in table and "Age" not in table


def test_an_arm_the_agent_forgot_leaves_the_view_and_paging_starts_from_the_ends() -> None:
    """A walk forgot the arm on screen: it stayed, OFFLINE, six minutes; Page Down skipped the first arm."""
    config, fleet, picker = ViewerConfig(), FleetView(), DevicePicker("arm-999")
    fleet.update(state_of(arm_001=device_state(1000, 0.0), arm_999=device_state(1000, 0.0)), 10.0)
    fleet.update(state_of(arm_001=device_state(1100, 0.0)), 11.0)  # arm-999 forgotten
    assert fleet.info("arm-999") is None and fleet.pose("arm-999", 11.0) is None
    labels, values = overlay_lines(config, fleet, device="arm-999", devices=fleet.devices(), now=11.0, fps=60)
    table = dict(zip(labels.split("\n"), values.split("\n"), strict=True))
    assert table["Status"] == "not listed by the agent: not heard from yet, or forgotten"
    devices = ["arm-001", "arm-002", "arm-003"]
    picker.on_key(KEY_PAGE_DOWN)
    assert picker.current(devices) == "arm-001"
    gone = DevicePicker("arm-999")
    gone.on_key(KEY_PAGE_UP)
    assert gone.current(devices) == "arm-003"


def test_another_service_on_the_agents_port_is_told_once_a_minute_and_on_screen(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """An HTTP server that is not the agent got 160 warning lines in 14 s, and the overlay said 'polling'."""
    config, fleet = ViewerConfig(), FleetView()
    caplog.set_level("WARNING", logger="twin.viewer")
    for _ in range(160):
        fleet.update_json(b'{"hello": 1}', 1.0)
    assert len([r for r in caplog.records if "not understood" in r.getMessage()]) == 1
    labels, values = overlay_lines(config, fleet, device=None, devices=[], now=2.0, fps=60)
    table = dict(zip(labels.split("\n"), values.split("\n"), strict=True))
    assert table["Agent"].endswith(": 160 answers that are not a twin agent's state"), table


def test_servo_overlay_lists_each_servo_with_its_worst_alarm():
    hot = ServoState(
        temperature_c=66.0,
        load_percent=-31.3,
        model_load_percent=30.9,
        current_a=0.65,
        alarm_severity="critical",
        alarm_state="ACTIVE",
        errors=("temperature", "overload"),
    )
    d = DeviceState(
        health=HealthSnapshot(status=DeviceStatus.ONLINE),
        servos={"elbow_flex": hot, "gripper": ServoState(errors=())},
    )
    fleet = FleetView()
    fleet.update(state_of(arm_001=d), 1.0)
    info = fleet.info("arm-001")
    assert info is not None
    table = dict(servo_rows(info.servos))
    assert servo_rows(None) == []
    assert table["elbow_flex"] == (
        "66 C  load -31 % (model 31 %)  0.65 A  [critical ACTIVE]  servo error: temperature, overload"
    )
    assert table["gripper"] == "-  load -  -"


def test_joint_tint_colours_the_moving_part_and_restores_it():
    from twin.robot.model import RobotModel

    robot = RobotModel.load()
    model = robot.model
    tint = JointTint(model, robot.body_ids)
    body = robot.body_ids["lower_arm"]  # elbow_flex moves the lower arm
    geoms = range(int(model.body_geomadr[body]), int(model.body_geomadr[body] + model.body_geomnum[body]))
    before = [(int(model.geom_matid[g]), tuple(model.geom_rgba[g])) for g in geoms]
    assert geoms
    tint.apply({"elbow_flex": ServoState(alarm_severity="critical", alarm_state="ACTIVE")})
    for g in geoms:
        assert model.geom_matid[g] == -1
        assert tuple(model.geom_rgba[g]) == pytest.approx(ALARM_COLOURS[("critical", "ACTIVE")])
    other = robot.body_ids["wrist"]
    assert tuple(model.geom_rgba[model.body_geomadr[other]]) != pytest.approx(
        ALARM_COLOURS[("critical", "ACTIVE")]
    )
    tint.apply({"elbow_flex": ServoState(alarm_severity="warning", alarm_state="ACKNOWLEDGED")})
    assert tuple(model.geom_rgba[geoms[0]]) == pytest.approx(ALARM_COLOURS[("warning", "ACKNOWLEDGED")])
    tint.apply({"elbow_flex": ServoState()})  # back to NORMAL: the model's own look
    assert [(int(model.geom_matid[g]), tuple(model.geom_rgba[g])) for g in geoms] == before
    assert tint.tinted == {}


def test_overlay_marks_a_device_losing_data():
    losing = dataclasses.replace(
        device_state(1000, 0.0),
        loss=LossSnapshot(lost=42, recent_lost=40, recent_loss_ratio=0.8, losing=True),
    )
    fleet = FleetView()
    # Through the JSON the stream carries, as the feed hands it over.
    fleet.update_json(state_of(arm_001=losing, arm_002=device_state(1000, 0.0)).to_json(), 10.0)
    tables = {}
    for device in ("arm-001", "arm-002"):
        labels, values = overlay_lines(
            ViewerConfig(), fleet, device=device, devices=fleet.devices(), now=10.0, fps=60.0
        )
        tables[device] = dict(zip(labels.split("\n"), values.split("\n"), strict=True))
    assert tables["arm-001"]["Status"] == "ONLINE  LOSING DATA (80% recently)"
    assert tables["arm-001"]["Lost"].startswith("42 messages")
    assert tables["arm-002"]["Status"] == "ONLINE"


def test_describe_error_and_config_validation():
    assert describe_error(ConnectionRefusedError(111, "Connection refused")) == "connection refused"
    assert describe_error(TimeoutError()) == "timed out"
    with pytest.raises(ValueError, match="http"):
        ViewerConfig(agent_url="127.0.0.1:8080")
    with pytest.raises(ValueError, match="fps"):
        ViewerConfig(fps=0)


# ------------------------------------------------------------------------------------------------ under Xvfb


def read_xwd(path: Path) -> np.ndarray:
    """RGB pixels of an XWD file (the format Xvfb -fbdir keeps its framebuffer in)."""
    raw = path.read_bytes()
    fields = struct.unpack(">25I", raw[:100])
    header_size, version, _fmt, _depth, width, height = fields[:6]
    byte_order, bits_per_pixel, bytes_per_line, ncolors = fields[7], fields[11], fields[12], fields[19]
    assert version == 7 and bits_per_pixel == 32, f"unexpected XWD v{version}, {bits_per_pixel} bpp"
    offset = header_size + 12 * ncolors
    rows = np.frombuffer(raw, np.uint8, count=bytes_per_line * height, offset=offset)
    pixels = rows.reshape(height, bytes_per_line)[:, : width * 4].reshape(height, width, 4)
    return pixels[..., [2, 1, 0]] if byte_order == 0 else pixels[..., [1, 2, 3]]


def arm_mask(rgb: np.ndarray) -> np.ndarray:
    """Pixels of the arm's yellow plastic (rgba 0.96 0.76 0.13, lit): nothing else in the scene is yellow."""
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    return (r > 120) & (g > 80) & (b < 90) & (r - b > 90) & (g - b > 50)


@pytest.fixture
def xvfb(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """A private Xvfb display (number chosen by Xvfb itself) whose framebuffer is a file."""
    if shutil.which("Xvfb") is None:
        pytest.fail("Xvfb is not installed: run `make setup` (APT_PACKAGES has xvfb)")
    fbdir = tmp_path / "fb"
    fbdir.mkdir()
    read_fd, write_fd = os.pipe()
    proc = subprocess.Popen(
        [
            *("Xvfb", "-displayfd", str(write_fd), "-screen", "0", "1280x800x24"),
            *("-fbdir", str(fbdir), "-nolisten", "tcp", "-noreset"),
        ],
        pass_fds=(write_fd,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(write_fd)
    try:
        with os.fdopen(read_fd) as pipe:
            display = pipe.readline().strip()
        assert display.isdigit(), f"Xvfb did not report a display (exit {proc.poll()})"
        yield f":{display}", fbdir / "Xvfb_screen0"
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.fixture
def live_agent(rig: LocalRig) -> Iterator[str]:
    """The real agent service fed by the edge simulator (two arms, ticks); yields the agent URL."""
    devices = ["arm-001", "arm-002"]
    service = rig.start_agent({"telemetry.devices": devices, "telemetry.units": "ticks"})
    rig.start_edge(devices, seed=1)
    yield service.http_url


def start_view(display: str, *args: str, log_path: Path) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    env["DISPLAY"] = display
    with log_path.open("wb") as log:
        return subprocess.Popen(
            [str(TWIN), "view", "--log-level", "INFO", *args], env=env, stdout=log, stderr=subprocess.STDOUT
        )


def wait_for_arm(fb: Path, proc: subprocess.Popen, log_path: Path, min_pixels: int, timeout: float = 60.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"twin view exited {proc.returncode}:\n{log_path.read_text()}"
        rgb = read_xwd(fb)
        if arm_mask(rgb).sum() >= min_pixels:
            return rgb
        time.sleep(0.5)
    pytest.fail(f"no arm on screen after {timeout:.0f} s:\n{log_path.read_text()}")


def stop_view(proc: subprocess.Popen, log_path: Path) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        rc = proc.wait(15)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"twin view ignored SIGTERM:\n{log_path.read_text()}")
    assert rc == 0, f"twin view exited {rc} on SIGTERM:\n{log_path.read_text()}"


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_view_draws_the_live_arm_under_xvfb(xvfb, live_agent, tmp_path):
    from PIL import Image

    display, fb = xvfb
    log_path = tmp_path / "view.log"
    proc = start_view(display, "--agent", live_agent, "--device", "arm-001", log_path=log_path)
    try:
        first = wait_for_arm(fb, proc, log_path, min_pixels=3000)
        mask_a = arm_mask(first)

        def moved() -> tuple[np.ndarray] | None:
            # Not a blank or frozen frame: the arm is still there and its silhouette changes as the twin
            # follows the edge motion (the mock motion moves every joint by several degrees a second).
            assert proc.poll() is None, f"twin view exited {proc.returncode}:\n{log_path.read_text()}"
            rgb = read_xwd(fb)
            mask = arm_mask(rgb)
            return (rgb,) if mask.sum() >= 3000 and np.logical_xor(mask_a, mask).sum() >= 200 else None

        (second,) = wait_for(moved, 60, "the arm on screen to move with the agent", interval=0.5)
    finally:
        stop_view(proc, log_path)
    OUT.mkdir(parents=True, exist_ok=True)
    Image.fromarray(second).save(OUT / "screenshot.png")
    # The picture is more than the arm: the floor and overlay are drawn too (not a cleared buffer).
    assert len(np.unique(second.reshape(-1, 3)[::97], axis=0)) > 50
    log_text = log_path.read_text()
    assert "agent link: stream" in log_text
    assert "Traceback" not in log_text


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_view_survives_an_unreachable_agent(xvfb, tmp_path):
    display, fb = xvfb
    log_path = tmp_path / "view.log"
    # Bound but not listening, and held for the test: connections are refused, and no other process (an
    # xdist worker's server) can take the port meanwhile, as it could a port picked free and closed.
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    proc = start_view(display, "--agent", f"http://127.0.0.1:{port}", log_path=log_path)
    try:
        # The model is drawn in its initial pose while the feed keeps retrying.
        wait_for_arm(fb, proc, log_path, min_pixels=1000)
        wait_for(
            lambda: "unreachable" in log_path.read_text(), 60, "the feed to report the agent unreachable"
        )
        # The behaviour under test: the view keeps running (and retrying) after that, here for 2 s.
        time.sleep(2.0)
        assert proc.poll() is None, f"twin view exited {proc.returncode}:\n{log_path.read_text()}"
    finally:
        stop_view(proc, log_path)
        closed.close()
    text = log_path.read_text()
    assert "agent link: unreachable (connection refused)" in text
    assert "Traceback" not in text


def test_view_without_display_fails_with_a_clear_message(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MUJOCO_GL")}
    proc = subprocess.run(
        [str(TWIN), "view", "--agent", "http://127.0.0.1:9"],
        check=False,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1, proc.stderr
    assert "DISPLAY is not set" in proc.stderr and "needs a desktop session" in proc.stderr
    assert "Traceback" not in proc.stderr
    with pytest.raises(ViewerError, match="no X server on DISPLAY=:987"):
        check_display({"DISPLAY": ":987"})
    check_display({"WAYLAND_DISPLAY": "wayland-0"})
