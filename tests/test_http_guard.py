"""What the agent's HTTP server refuses, each with a clear status, against a real AgentService over a real
socket: a foreign Host, a browser POST from another origin or without the CSRF token, a body over the limit,
a request head that never completes, a client that stops reading its stream, one connection too many. And
what it still lets through: curl-like clients on loopback, the console's own requests, percent-encoded ids."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator
from typing import Any

import pytest
from conftest import fed_agent, wait_for
from twin.service.agent import AgentService
from twin.service.http_api import alarm_id_of
from twin.service.http_guard import host_allowed, host_name

pytestmark = pytest.mark.slow

TIMEOUT_S = 1.0
MAX_CONNECTIONS = 4


@pytest.fixture(scope="module")
def agent() -> Iterator[AgentService]:
    with fed_agent(
        **{
            "http.timeout_s": TIMEOUT_S,
            "http.max_connections": MAX_CONNECTIONS,
            "http.max_body_bytes": 2048,
            "http.stream_rate_hz": 500.0,
            "http.allowed_hosts": ["twin.example.internal"],
        }
    ) as service:
        yield service


def address(agent: AgentService) -> tuple[str, int]:
    host, port = agent.http_url.removeprefix("http://").rsplit(":", 1)
    return host, int(port)


def request(agent: AgentService, raw: bytes, timeout: float = 10.0) -> tuple[int, dict[str, str], bytes]:
    """One raw HTTP/1.1 exchange; the server closes or answers with Content-Length."""
    with socket.create_connection(address(agent), timeout=timeout) as sock:
        sock.sendall(raw)
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
        head, _, body = data.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
        length = int(headers.get("content-length", "0"))
        while len(body) < length:
            chunk = sock.recv(65536)
            if not chunk:
                break
            body += chunk
    return status, headers, body


def post(
    agent: AgentService, path: str, headers: dict[str, str] | None = None, body: bytes = b""
) -> tuple[int, Any]:
    host, port = address(agent)
    lines = [
        f"POST {path} HTTP/1.1",
        f"Host: {host}:{port}",
        f"Content-Length: {len(body)}",
        "Connection: close",
    ]
    lines += [f"{k}: {v}" for k, v in (headers or {}).items()]
    status, _, payload = request(agent, ("\r\n".join(lines) + "\r\n\r\n").encode() + body)
    return status, json.loads(payload) if payload else None


def get(agent: AgentService, path: str, host: str | None = None) -> tuple[int, Any]:
    h, port = address(agent)
    raw = f"GET {path} HTTP/1.1\r\nHost: {host or f'{h}:{port}'}\r\nConnection: close\r\n\r\n".encode()
    status, _, payload = request(agent, raw)
    return status, json.loads(payload)


# An id no alarm has (the fed agent has arm-001 and arm-002): a request the guard lets through gets 404.
ACK = "/alarms/arm-009/elbow_flex/over_temperature/ack"


def test_a_foreign_host_is_refused(agent: AgentService) -> None:
    status, body = get(agent, "/state", host="evil.example:8080")
    assert status == 400 and body["error"] == "host_not_allowed"
    assert "allowed_hosts" in body["detail"]
    # Loopback names and what [http] allowed_hosts adds are answered.
    for host in (
        "localhost:1",
        "127.0.0.1",
        "[::1]:8080",
        "twin.example.internal:8080",
        "TWIN.example.internal.",
    ):
        assert get(agent, "/healthz", host=host)[0] in (200, 503), host


def test_a_browser_post_from_another_origin_is_refused(agent: AgentService) -> None:
    status, body = post(agent, ACK, {"Origin": "http://evil.example", "X-CSRF-Token": "x"})
    assert status == 403 and body["error"] == "origin_not_allowed"
    status, body = post(agent, ACK, {"Origin": "null"})
    assert status == 403 and body["error"] == "origin_not_allowed"
    status, body = post(agent, ACK, {"Sec-Fetch-Site": "cross-site"})
    assert status == 403 and body["error"] == "cross_site"


def test_a_page_of_another_site_may_link_to_the_console_but_not_fetch_from_it(agent: AgentService) -> None:
    host, port = address(agent)

    def get_as(path: str, fetch: dict[str, str]) -> tuple[int, bytes]:
        lines = [f"GET {path} HTTP/1.1", f"Host: {host}:{port}", "Connection: close"]
        lines += [f"Sec-Fetch-{k}: {v}" for k, v in fetch.items()]
        status, _, body = request(agent, ("\r\n".join(lines) + "\r\n\r\n").encode())
        return status, body

    for fetch in (
        {"Site": "cross-site", "Mode": "cors", "Dest": "empty"},  # fetch() of the API
        {"Site": "cross-site", "Mode": "no-cors", "Dest": "image"},  # <img src=...>
        {"Site": "cross-site", "Mode": "navigate", "Dest": "iframe"},
        {"Site": "same-site", "Mode": "cors", "Dest": "empty"},  # a page on another port of the host
        {"Site": "same-site", "Mode": "no-cors", "Dest": "image"},
    ):
        status, body = get_as("/api/fleet", fetch)
        assert status == 403 and json.loads(body)["error"] == "cross_site", (fetch, body)
    # A link followed from elsewhere (the Rerun viewer's port too), the console's own requests, and curl.
    for fetch in (
        {"Site": "cross-site", "Mode": "navigate", "Dest": "document"},
        {"Site": "same-site", "Mode": "navigate", "Dest": "document"},
        {"Site": "same-origin", "Mode": "cors", "Dest": "empty"},
        {"Site": "none", "Mode": "navigate", "Dest": "document"},
        {},
    ):
        assert get_as("/api/fleet", fetch)[0] == 200, fetch


def test_a_browser_post_needs_the_csrf_token(agent: AgentService) -> None:
    host, port = address(agent)
    origin = f"http://{host}:{port}"
    status, body = post(agent, ACK, {"Origin": origin})
    assert status == 403 and body["error"] == "csrf_token_missing"
    status, body = post(agent, ACK, {"Sec-Fetch-Site": "same-origin", "X-CSRF-Token": "wrong"})
    assert status == 403 and body["error"] == "csrf_token_invalid"
    # The console's page carries the token; with it, the request reaches the alarms (none is raised here).
    status, page = request(
        agent,
        f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nAccept: text/html\r\nConnection: close\r\n\r\n".encode(),
    )[::2]
    assert status == 200
    token = page.decode().split('name="csrf-token" content="', 1)[1].split('"', 1)[0]
    status, body = post(
        agent, ACK, {"Origin": origin, "Sec-Fetch-Site": "same-origin", "X-CSRF-Token": token}
    )
    assert status == 404 and body["error"] == "alarm_not_found"


def test_a_loopback_client_without_browser_marks_needs_no_token(agent: AgentService) -> None:
    status, body = post(agent, ACK)
    assert status == 404 and body["error"] == "alarm_not_found"
    assert "no alarm has this id" in body["detail"] and "GET /alarms?all=1" in body["detail"], body


def test_alarm_ids_are_accepted_literally_or_percent_encoded(agent: AgentService) -> None:
    for path in (
        ACK,
        "/alarms/arm-009%2Felbow_flex%2Fover_temperature/ack",
        "/alarms/arm%2D009/elbow_flex/over_temperature/ack",
    ):
        status, body = post(agent, path)
        assert status == 404 and body["alarm_id"] == "arm-009/elbow_flex/over_temperature", path
    assert alarm_id_of({"raw_path": b"/alarms/a%25b/j/k/ack", "path": "/alarms/a%b/j/k/ack"}) == "a%b/j/k"


def test_a_body_over_the_limit_is_refused(agent: AgentService) -> None:
    status, body = post(agent, ACK, body=b"x" * 4096)
    assert status == 413 and body["error"] == "body_too_large"
    # A chunked body has no length to check first: it is counted as it arrives.
    host, port = address(agent)
    chunk = b"x" * 3000
    raw = (
        f"POST {ACK} HTTP/1.1\r\nHost: {host}:{port}\r\nTransfer-Encoding: chunked\r\n"
        "Connection: close\r\n\r\n".encode()
        + f"{len(chunk):x}\r\n".encode()
        + chunk
        + b"\r\n0\r\n\r\n"
    )
    status, _, payload = request(agent, raw)
    assert status == 413 and json.loads(payload)["error"] == "body_too_large"
    # A negative length never reaches a handler (it hung the old server until the client left).
    raw = f"POST {ACK} HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Length: -1\r\n\r\n".encode()
    assert request(agent, raw)[0] == 400


def closed_by_server(sock: socket.socket, timeout: float) -> bool:
    """True once the server has closed or reset the connection (reads what it still sends)."""
    sock.settimeout(timeout)
    try:
        while sock.recv(65536):
            pass
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False
    return True


def test_a_request_head_that_stalls_is_cut_off(agent: AgentService) -> None:
    with socket.create_connection(address(agent), timeout=10) as sock:
        sock.sendall(b"GET /sta")
        assert closed_by_server(sock, 20 * TIMEOUT_S)
    assert get(agent, "/healthz")[0] in (200, 503)


def test_a_client_that_stops_reading_is_cut_off(agent: AgentService) -> None:
    http = agent._http
    assert http is not None
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    # A small receive window, so the server's buffers fill within a second at 500 states a second.
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        sock.connect(address(agent))
        host, port = address(agent)
        sock.sendall(f"GET /stream HTTP/1.1\r\nHost: {host}:{port}\r\n\r\n".encode())
        wait_for(lambda: http.stream_clients >= 1, 30, "the stream to open")
        # Never read: the server aborts the connection after timeout_s of not being able to write.
        wait_for(lambda: http.stream_clients == 0, 60, "the server to drop the stalled stream")
        assert closed_by_server(sock, 10)
    finally:
        sock.close()
    assert get(agent, "/healthz")[0] in (200, 503)


def test_one_connection_too_many_gets_503(agent: AgentService) -> None:
    http = agent._http
    assert http is not None
    host, port = address(agent)
    streams = []
    try:
        for _ in range(MAX_CONNECTIONS):
            sock = socket.create_connection((host, port), timeout=10)
            sock.sendall(f"GET /stream HTTP/1.1\r\nHost: {host}:{port}\r\n\r\n".encode())
            streams.append(sock)
        wait_for(lambda: http.stream_clients == MAX_CONNECTIONS, 30, "every stream to open")
        status, _, _ = request(
            agent, f"GET /state HTTP/1.1\r\nHost: {host}:{port}\r\nConnection: close\r\n\r\n".encode()
        )
        assert status == 503
    finally:
        for sock in streams:
            sock.close()
    wait_for(lambda: http.stream_clients == 0, 30, "the streams to close")
    wait_for(lambda: get(agent, "/healthz")[0] in (200, 503), 30, "the server to answer again")


@pytest.mark.parametrize(
    ("header", "name", "allowed"),
    [
        ("127.0.0.1:8080", "127.0.0.1", True),
        ("127.9.9.9", "127.9.9.9", True),
        ("[::1]:8080", "::1", True),
        ("LOCALHOST.", "localhost", True),
        ("localhost.evil.example", "localhost.evil.example", False),
        ("10.0.0.5:8080", "10.0.0.5", False),
        ("example.com", "example.com", False),
        # A walk: what follows the colon was dropped whatever it was, so these read as 127.0.0.1. Only a port
        # is a port; anything else is part of the name, which no rule allows.
        ("127.0.0.1:8080@evil.example", "127.0.0.1:8080@evil.example", False),
        ("127.0.0.1:8080,evil.example", "127.0.0.1:8080,evil.example", False),
        ("[::1]:8080@evil.example", "[::1]:8080@evil.example", False),
        ("127.0.0.1:", "127.0.0.1:", False),
    ],
)
def test_host_names(header: str, name: str, allowed: bool) -> None:
    assert host_name(header) == name
    assert host_allowed(name, frozenset()) is allowed


def test_stop_leaves_no_thread_behind() -> None:
    import threading

    def started_by_python() -> list[threading.Thread]:
        # awscrt's event-loop threads are the library's, shared by every client in the process and living as
        # long as it: once one runs a Python callback it is listed as a dummy thread for good (the subscriber
        # keeps its thread state, twin.transport.subscriber). Whether this test or an earlier one in the same
        # process made the first callback depends on the order, so they are not the agent's to stop.
        return [t for t in threading.enumerate() if not isinstance(t, threading._DummyThread)]

    before = {t.ident for t in started_by_python()}
    with fed_agent(messages=2):
        pass
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        extra = [t for t in started_by_python() if t.ident not in before and t.is_alive()]
        if not extra:
            break
        time.sleep(0.05)
    assert not extra, [t.name for t in extra]
