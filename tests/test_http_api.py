"""The agent HTTP API over a real socket: JSON state, Prometheus format, health codes, SSE, disconnects."""

from __future__ import annotations

import json
import math
import re
import socket
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from conftest import fed_agent, http_get, metric, parse_metrics, wait_for
from twin.core.health import DeviceCounters, DeviceStatus, HealthSnapshot, WindowLatency
from twin.robot import so101
from twin.service.http_api import AgentHttpServer
from twin.service.metrics import render_metrics
from twin.service.state import AgentInfo, AgentState, DeviceState, HealthReport, WorkerState


class StubSource:
    """A StateSource whose state changes on every call, like the live agent's (for the server mechanics:
    content types, SSE pacing, disconnects). What the agent itself publishes is tested on a real AgentService
    below."""

    def __init__(self) -> None:
        self.calls = 0
        self.healthy = True
        self.lock = threading.Lock()

    def state(self) -> AgentState:
        with self.lock:
            self.calls += 1
            n = self.calls
        device = DeviceState(
            device_id="arm-001",
            health=HealthSnapshot(
                status=DeviceStatus.ONLINE,
                rate_hz=10.0,
                counters=DeviceCounters(received=n, applied=n, rejected={"not_json": 3, 'we"ird\\': 1}),
            ),
            joints_rad={"shoulder_pan": 0.25, "gripper": -0.1},
        )
        odd = DeviceState(device_id='we"ird\ndevice', health=HealthSnapshot(rate_hz=float("nan")))
        return AgentState(
            agent=AgentInfo(running=True, uptime_s=1.5, worker=WorkerState(batches=n)),
            devices={"arm-001": device, 'we"ird\ndevice': odd},
            untracked_rejected={"bad_device_id": 4},
        )

    def healthz(self) -> HealthReport:
        return HealthReport(status="ok" if self.healthy else "unavailable")


@pytest.fixture
def server():
    source = StubSource()
    srv = AgentHttpServer(source, "127.0.0.1", 0, stream_rate_hz=50.0)
    srv.start()
    try:
        yield srv, source
    finally:
        srv.stop()


def get(url: str) -> tuple[int, str, str]:
    status, ctype, body = http_get(url)
    return status, ctype, body.decode()


def test_state_json(server) -> None:
    srv, _ = server
    status, ctype, body = get(srv.url + "/state")
    assert status == 200 and ctype == "application/json"
    state = json.loads(body)
    assert state["devices"]["arm-001"]["joints_rad"]["shoulder_pan"] == 0.25
    assert (
        state["devices"]['we"ird\ndevice']["health"]["rate_hz"] is None
    )  # NaN is published as null, still valid JSON


# One sample line: name, optional {label="value",...}, a float value (Prometheus text format 0.0.4).
SAMPLE = re.compile(
    r'^[a-zA-Z_:][a-zA-Z0-9_:]*(\{([a-zA-Z_][a-zA-Z0-9_]*="([^"\\\n]|\\["\\n])*",?)*\})? '
    r"(-?[0-9.]+(e[+-]?[0-9]+)?|NaN|[+-]Inf)$"
)
HELP = re.compile(r"^# HELP [a-zA-Z_:][a-zA-Z0-9_:]* \S.*$")
TYPE = re.compile(r"^# TYPE ([a-zA-Z_:][a-zA-Z0-9_:]*) (counter|gauge|summary|histogram|untyped)$")


def check_exposition(body: str) -> dict[str, str]:
    """Line-level checks of the 0.0.4 text format; returns {family: type}."""
    assert body.endswith("\n")
    typed: dict[str, str] = {}
    for line in body.splitlines():
        if line.startswith("# HELP"):
            assert HELP.match(line), line
        elif line.startswith("# TYPE"):
            m = TYPE.match(line)
            assert m, line
            assert m.group(1) not in typed, f"family {m.group(1)} declared twice"
            typed[m.group(1)] = m.group(2)
        else:
            assert SAMPLE.match(line), line
            name = line.split("{")[0].split(" ")[0]
            assert name in typed, f"sample {name} before its TYPE line"
    for name, kind in typed.items():
        assert (kind == "counter") == name.endswith("_total"), name
    return typed


def test_metrics_endpoint_serves_the_text_format(server) -> None:
    srv, _ = server
    status, ctype, body = get(srv.url + "/metrics")
    assert status == 200
    assert ctype.startswith("text/plain; version=0.0.4")
    check_exposition(body)
    samples = parse_metrics(body)
    # Label values with a quote, a backslash and a newline survive the escaping.
    assert metric(samples, "twin_messages_rejected_total", device="arm-001", reason='we"ird\\') == 1
    assert metric(samples, "twin_device_status", device='we"ird\ndevice', status="OFFLINE") == 1
    assert metric(samples, "twin_messages_rejected_total", device="_untracked", reason="bad_device_id") == 4


def test_metrics_hands_its_renders_freed_memory_back_after_answering(server, monkeypatch) -> None:
    """A large fleet's render peaks at several times its body; the freed pages go back to the system once
    the answer is sent (the process's RSS stayed at that peak between scrapes)."""
    from twin.core import heap

    trims: list[bool] = []
    monkeypatch.setattr(heap, "trim", lambda *, force=False: trims.append(force) or True)
    srv, _ = server
    assert get(srv.url + "/metrics")[0] == 200
    wait_for(lambda: trims, 10, "a trim after the answer")
    assert get(srv.url + "/state")[0] == 200
    # Only a metrics render asks for one, and past the shared rate limit: a scraper every 30 s had every
    # other render's pages kept.
    assert trims == [True]


def test_healthz_codes(server) -> None:
    srv, source = server
    assert get(srv.url + "/healthz")[0] == 200
    source.healthy = False
    status, _, body = get(srv.url + "/healthz")
    assert status == 503 and json.loads(body)["status"] == "unavailable"


def test_unknown_path_and_method(server) -> None:
    srv, _ = server
    status, ctype, body = get(srv.url + "/nope")
    assert status == 404 and ctype == "application/json"
    assert json.loads(body)["error"] == "not_found"
    req = urllib.request.Request(srv.url + "/state", data=b"{}", method="POST")
    with pytest.raises(urllib.error.HTTPError) as info:
        urllib.request.urlopen(req, timeout=5)
    assert info.value.code == 405


def read_events(url: str, n: int) -> list[dict[str, Any]]:
    events: list[dict[str, Any]] = []
    with urllib.request.urlopen(url, timeout=5) as resp:
        assert resp.headers["Content-Type"] == "text/event-stream"
        for raw in resp:
            line = raw.decode().rstrip("\n")
            if line.startswith("data: "):
                events.append(json.loads(line[len("data: ") :]))
                if len(events) == n:
                    break
    return events


def test_stream_yields_fresh_events_at_a_bounded_rate(server) -> None:
    srv, _ = server
    t0 = time.monotonic()
    events = read_events(srv.url + "/stream", 10)
    elapsed = time.monotonic() - t0
    batches = [e["agent"]["worker"]["batches"] for e in events]
    assert batches == sorted(batches) and len(set(batches)) == 10  # each event is a new state
    assert elapsed >= 9 / 50.0 * 0.9  # 50 Hz cap: 10 events need at least ~9 intervals


def test_client_disconnects_do_not_hurt_the_server(server) -> None:
    srv, _ = server
    for _ in range(5):
        # Open the stream, read a little, hang up mid-stream (RST by closing with unread data).
        sock = socket.create_connection((srv.host, srv.port), timeout=30)
        sock.sendall(b"GET /stream HTTP/1.1\r\nHost: x\r\n\r\n")
        assert sock.recv(64).startswith(b"HTTP/1.")
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        sock.close()
        # And a client that sends half a request and leaves.
        sock = socket.create_connection((srv.host, srv.port), timeout=30)
        sock.sendall(b"GET /sta")
        sock.close()
    # Every stream loop notices its client left.
    wait_for(lambda: srv.stream_clients == 0, 30, "the stream loops to see their clients gone")
    assert get(srv.url + "/state")[0] == 200


def test_stop_ends_open_streams(server) -> None:
    srv, _ = server
    got: list[int] = []

    def reader() -> None:
        # A read timeout far beyond the join below: only the server ending the stream ends this thread.
        try:
            with urllib.request.urlopen(srv.url + "/stream", timeout=300) as resp:
                for raw in resp:
                    if raw.startswith(b"data: "):
                        got.append(1)
        except OSError:
            pass

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    wait_for(lambda: got, 30, "the first event")
    srv.stop()
    thread.join(timeout=30)
    assert not thread.is_alive()


def test_port_in_use_error_names_the_fix() -> None:
    first = AgentHttpServer(StubSource(), "127.0.0.1", 0)
    try:
        with pytest.raises(OSError, match="--http HOST:PORT"):
            AgentHttpServer(StubSource(), "127.0.0.1", first.port)
    finally:
        first.stop()


def test_json_maps_non_finite_numbers_to_null() -> None:
    state = AgentState(
        agent=AgentInfo(uptime_s=math.inf),
        devices={
            "a": DeviceState(
                health=HealthSnapshot(rate_hz=math.nan, edge_clock_latency_s=WindowLatency(p50=-math.inf))
            )
        },
    )
    doc = json.loads(state.to_json(), parse_constant=_refuse)
    assert doc["agent"]["uptime_s"] is None
    assert doc["devices"]["a"]["health"]["rate_hz"] is None
    assert doc["devices"]["a"]["health"]["edge_clock_latency_s"]["p50"] is None


def _refuse(token: str) -> Any:
    raise AssertionError(f"{token} is not JSON")


# -- what a real agent publishes ---------------------------------------------------------------------------


def test_real_state_is_strict_json_and_round_trips() -> None:
    with fed_agent() as service:
        state = service.state()
        status, ctype, body = http_get(service.http_url + "/state")
    assert status == 200 and ctype == "application/json"
    json.loads(body, parse_constant=_refuse)  # NaN/Infinity would be invalid JSON
    assert AgentState.from_json(state.to_json()) == state  # every field survives the JSON round trip
    again = AgentState.from_json(body)
    assert again.untracked_rejected == {"not_utf8": 1}
    arm = again.devices["arm-001"]
    assert arm.health.counters.applied == 12 and arm.health.counters.rejected == {"not_json": 1}
    assert arm.joints_rad is not None and set(arm.joints_rad) == set(so101.JOINT_NAMES)
    silent = again.devices["arm-002"]
    assert silent.joints_rad is None and silent.health.age_s is None and silent.timestamp_ms is None
    assert again.agent.broker.connected is False


def test_metrics_of_a_real_state_agree_with_it() -> None:
    with fed_agent() as service:
        state = service.state()
        text = render_metrics(state)
    typed = check_exposition(text)
    assert typed["twin_messages_applied_total"] == "counter"
    samples = parse_metrics(text)
    arm = state.devices["arm-001"]
    assert arm.joints_rad is not None and arm.torques_nm is not None
    assert metric(samples, "twin_up") == 1
    assert metric(samples, "twin_broker_connected") == 0
    assert metric(samples, "twin_worker_behind_seconds") == state.agent.worker.behind_s
    assert metric(samples, "twin_messages_applied_total", device="arm-001") == arm.health.counters.applied
    assert metric(samples, "twin_messages_received_total", device="arm-001") == arm.health.counters.received
    assert metric(samples, "twin_messages_rejected_total", device="arm-001", reason="not_json") == 1
    assert metric(samples, "twin_messages_rejected_total", device="_untracked", reason="not_utf8") == 1
    for joint in so101.JOINT_NAMES:
        assert metric(samples, "twin_joint_position_radians", device="arm-001", joint=joint) == pytest.approx(
            arm.joints_rad[joint], abs=1e-12
        )
        assert metric(samples, "twin_joint_torque_newton_metres", device="arm-001", joint=joint) == (
            pytest.approx(arm.torques_nm[joint], abs=1e-12)
        )
    for status in DeviceStatus:
        expected = 1 if arm.health.status is status else 0
        assert metric(samples, "twin_device_status", device="arm-001", status=status.value) == expected
    # arm-002 has never sent: its latencies and age are unknown, so absent rather than a made-up 0.
    assert ("twin_device_last_message_age_seconds", (("device", "arm-002"),)) not in samples
    assert ("twin_internal_latency_p50_seconds", (("device", "arm-002"),)) not in samples
    assert metric(samples, "twin_internal_latency_p50_seconds", device="arm-001") == pytest.approx(
        arm.health.internal_latency_s.p50
    )


def test_an_agent_without_an_emf_file_states_no_clock_steps() -> None:
    """The count is set where the agent's own state is made (not patched in after the merge): an agent that
    publishes no CloudWatch metrics says it does not know (null), and /metrics leaves the figure out."""
    with fed_agent() as service:
        assert service._emf is None
        assert service.state().agent.emf_clock_steps is None
        text = http_get(service.http_url + "/metrics")[2].decode()
    assert ("twin_emf_clock_steps_total", ()) not in parse_metrics(text)


def test_the_wall_clock_steps_the_emf_publisher_saw_are_in_state_and_metrics(tmp_path: Path) -> None:
    """They were only logged: a host whose time sync kept stepping its clock for weeks showed it nowhere a
    person looks. Without an EMF file the count is unknown, so /metrics leaves it out (no made-up 0)."""
    with fed_agent(**{"cloudwatch.emf_file": str(tmp_path / "emf.log")}) as service:
        assert service.state().agent.emf_clock_steps == 0
        assert service._emf is not None
        service._emf.clock_steps = 3  # as the publisher counts the steps it sees
        body = http_get(service.http_url + "/state")[2]
        text = http_get(service.http_url + "/metrics")[2].decode()
    assert AgentState.from_json(body).agent.emf_clock_steps == 3
    assert metric(parse_metrics(text), "twin_emf_clock_steps_total") == 3
    without = parse_metrics(render_metrics(AgentState(AgentInfo(), {})))
    assert ("twin_emf_clock_steps_total", ()) not in without


def test_an_arms_rate_not_known_is_absent_from_the_metrics() -> None:
    # Read from a restarting worker's checkpoint an arm's rate is not known (None): absent, not a fake 0,
    # and the rest of /metrics is served.
    arm = DeviceState(device_id="arm-001", health=HealthSnapshot(rate_hz=None))
    samples = parse_metrics(
        render_metrics(AgentState(agent=AgentInfo(running=True), devices={"arm-001": arm}))
    )
    assert ("twin_device_message_rate_hz", (("device", "arm-001"),)) not in samples
    assert metric(samples, "twin_device_status", device="arm-001", status="OFFLINE") == 1


@pytest.mark.parametrize(
    ("address", "loopback"),
    [
        ("127.0.0.1", True),
        ("127.0.0.2", True),
        ("::1", True),
        ("::ffff:127.0.0.1", True),  # IPv4 loopback through a dual-stack socket
        ("10.0.0.5", False),
        ("203.0.113.7", False),
        ("::ffff:203.0.113.7", False),
        ("fe80::1%eth0", False),
        ("not-an-address", False),
    ],
)
def test_only_loopback_clients_may_acknowledge_alarms(address: str, loopback: bool) -> None:
    from twin.service.http_api import is_loopback_client

    assert is_loopback_client(address) is loopback


def test_a_browser_gets_a_page_for_an_unknown_path(server) -> None:
    """A mistyped address in the browser is a page that names it and links to the console's pages, not a raw
    JSON error; a script still gets the JSON one."""
    srv, _ = server
    req = urllib.request.Request(srv.url + "/arms/%3Cb%3Ex", headers={"Accept": "text/html,*/*;q=0.8"})
    with pytest.raises(urllib.error.HTTPError) as info:
        urllib.request.urlopen(req, timeout=5)
    assert info.value.code == 404
    assert info.value.headers["content-type"].startswith("text/html")
    assert "content-security-policy" in info.value.headers
    page = info.value.read().decode()
    assert "/arms/&lt;b&gt;x" in page and "<b>" not in page  # the path is shown as text, never as markup
    assert '<a href="/">Fleet</a>' in page and "/arm/&lt;device&gt;" in page
    status, ctype, body = get(srv.url + "/arms/x")
    assert status == 404 and ctype == "application/json" and json.loads(body)["error"] == "not_found"


def test_a_source_without_alarms_has_no_alarm_endpoints(server) -> None:
    srv, _ = server
    status, _, body = get(srv.url + "/alarms")
    assert status == 404 and json.loads(body)["error"] == "not_found"
    req = urllib.request.Request(srv.url + "/alarms/arm-001/elbow_flex/overload/ack", data=b"", method="POST")
    with pytest.raises(urllib.error.HTTPError) as info:
        urllib.request.urlopen(req, timeout=5)
    assert info.value.code == 404
    assert json.loads(info.value.read())["detail"] == "this source has no alarms"
