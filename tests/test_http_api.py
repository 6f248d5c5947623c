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
from typing import Any

import pytest
from twin.service.http_api import AgentHttpServer, render_metrics


class StubSource:
    """A StateSource with a state that changes on every call, like the live agent's."""

    def __init__(self) -> None:
        self.calls = 0
        self.healthy = True
        self.lock = threading.Lock()

    def state(self) -> dict[str, Any]:
        with self.lock:
            self.calls += 1
            n = self.calls
        return {
            "agent": {
                "running": True,
                "uptime_s": 1.5,
                "broker": {"url": "mqtt://127.0.0.1:1", "connected": True, "connection_successes": 2},
                "worker": {"batches": n},
            },
            "devices": {
                "arm-001": {
                    "status": "ONLINE",
                    "age_s": 0.05,
                    "rate_hz": 10.0,
                    "joints_rad": {"shoulder_pan": 0.25, "gripper": -0.1},
                    "torques_nm": {"shoulder_pan": 0.0},
                    "counters": {
                        "received": n,
                        "applied": n,
                        "rejected": {"not_json": 3, 'we"ird\\': 1},
                        "errors": 0,
                    },
                    "edge_clock_latency_s": {"p50": 0.02, "p99": 0.05, "samples": 10},
                    "edge_clock_offset_s": 0.015,
                    "internal_latency_s": {"p50": None, "p99": None, "samples": 0},
                },
                'we"ird\ndevice': {"status": "OFFLINE", "age_s": None, "rate_hz": float("nan")},
            },
            "untracked_rejected": {"bad_device_id": 4},
        }

    def healthz(self) -> tuple[bool, dict[str, Any]]:
        return self.healthy, {"status": "ok" if self.healthy else "unavailable"}


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
    try:
        with urllib.request.urlopen(url, timeout=5) as resp:
            return resp.status, resp.headers.get("Content-Type", ""), resp.read().decode()
    except urllib.error.HTTPError as err:
        return err.code, err.headers.get("Content-Type", ""), err.read().decode()


def test_state_json(server) -> None:
    srv, _ = server
    status, ctype, body = get(srv.url + "/state")
    assert status == 200 and ctype == "application/json"
    state = json.loads(body)
    assert state["devices"]["arm-001"]["joints_rad"]["shoulder_pan"] == 0.25
    assert state["devices"]['we"ird\ndevice']["rate_hz"] is None  # NaN is published as null, still valid JSON


# One sample line: name, optional {label="value",...}, a float value (Prometheus text format 0.0.4).
SAMPLE = re.compile(
    r'^[a-zA-Z_:][a-zA-Z0-9_:]*(\{([a-zA-Z_][a-zA-Z0-9_]*="([^"\\\n]|\\["\\n])*",?)*\})? '
    r"(-?[0-9.]+(e[+-]?[0-9]+)?|NaN|[+-]Inf)$"
)
HELP = re.compile(r"^# HELP [a-zA-Z_:][a-zA-Z0-9_:]* \S.*$")
TYPE = re.compile(r"^# TYPE ([a-zA-Z_:][a-zA-Z0-9_:]*) (counter|gauge|summary|histogram|untyped)$")


def test_metrics_is_prometheus_text(server) -> None:
    srv, _ = server
    status, ctype, body = get(srv.url + "/metrics")
    assert status == 200
    assert ctype.startswith("text/plain; version=0.0.4")
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
    assert 'twin_messages_rejected_total{device="arm-001",reason="not_json"} 3' in body
    assert 'reason="we\\"ird\\\\"' in body  # quote and backslash escaped in label values
    assert 'device="we\\"ird\\ndevice"' in body
    assert 'twin_device_status{device="arm-001",status="ONLINE"} 1' in body
    assert 'twin_messages_rejected_total{device="_untracked",reason="bad_device_id"} 4' in body
    assert 'twin_joint_position_radians{device="arm-001",joint="shoulder_pan"} 0.25' in body
    # Unknown values are absent rather than a made-up zero.
    assert "twin_internal_latency_p50_seconds{" not in body


def test_render_metrics_of_empty_state() -> None:
    text = render_metrics({})
    assert "twin_up 0" in text.splitlines()


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
        sock = socket.create_connection((srv.host, srv.port), timeout=5)
        sock.sendall(b"GET /stream HTTP/1.1\r\nHost: x\r\n\r\n")
        assert sock.recv(64).startswith(b"HTTP/1.")
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        sock.close()
        # And a client that sends half a request and leaves.
        sock = socket.create_connection((srv.host, srv.port), timeout=5)
        sock.sendall(b"GET /sta")
        sock.close()
    deadline = time.monotonic() + 3
    while srv.stream_clients and time.monotonic() < deadline:
        time.sleep(0.05)
    assert srv.stream_clients == 0  # every stream loop noticed its client left
    assert get(srv.url + "/state")[0] == 200


def test_stop_ends_open_streams(server) -> None:
    srv, _ = server
    got: list[int] = []

    def reader() -> None:
        try:
            with urllib.request.urlopen(srv.url + "/stream", timeout=5) as resp:
                for raw in resp:
                    if raw.startswith(b"data: "):
                        got.append(1)
        except OSError:
            pass

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    deadline = time.monotonic() + 3
    while not got and time.monotonic() < deadline:
        time.sleep(0.02)
    srv.stop()
    thread.join(timeout=3)
    assert got and not thread.is_alive()


def test_port_in_use_error_names_the_fix() -> None:
    first = AgentHttpServer(StubSource(), "127.0.0.1", 0)
    try:
        with pytest.raises(OSError, match="--http HOST:PORT"):
            AgentHttpServer(StubSource(), "127.0.0.1", first.port)
    finally:
        first.stop()


def test_json_has_no_nan() -> None:
    # Sanity of the stub: the NaN really is there, so the /state test above checks the conversion.
    assert math.isnan(StubSource().state()["devices"]['we"ird\ndevice']["rate_hz"])
