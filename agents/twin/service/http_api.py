"""The agent's local HTTP interface: state as JSON, Prometheus metrics, a health probe and a live SSE stream.

Standard library only (`http.server.ThreadingHTTPServer`): the agent binds it to 127.0.0.1 by default, and
viewers, curl and a Prometheus scrape are its only clients. The server knows nothing about MQTT or MuJoCo; it
asks a `StateSource` (the agent service) for a JSON-ready state and renders every endpoint from that one dict,
so /state, /metrics and /stream always agree.

Endpoints (docs/agent.md has examples):
- GET /state    the state dict as JSON
- GET /metrics  Prometheus text exposition format 0.0.4
- GET /healthz  200 {"status": "ok", ...} or 503 {"status": "unavailable", "reasons": [...]}
- GET /stream   Server-Sent Events, `data: {state json}` at most `stream_rate_hz` times a second
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import threading
from collections.abc import Iterator
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Protocol
from urllib.parse import urlsplit

log = logging.getLogger(__name__)

PROMETHEUS_CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
# Errors a client hanging up produces mid-write; never worth more than a debug line.
_DISCONNECTS = (BrokenPipeError, ConnectionResetError, ConnectionAbortedError, TimeoutError)


class StateSource(Protocol):
    def state(self) -> dict[str, Any]:
        """The agent state (see docs/agent.md, GET /state)."""
        ...

    def healthz(self) -> tuple[bool, dict[str, Any]]:
        """(healthy, body) for GET /healthz."""
        ...


# ---------------------------------------------------------------------------------------------------- metrics


def _escape_label(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _format_value(value: float) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, int):
        return str(value)
    if math.isnan(value):
        return "NaN"
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    return repr(float(value))


class _Family:
    def __init__(self, name: str, kind: str, help_text: str) -> None:
        self.name = name
        self.kind = kind
        self.help = help_text
        self.samples: list[tuple[dict[str, str], float]] = []

    def add(self, value: float | None, **labels: str) -> None:
        if value is None:
            return  # an unknown value (no samples yet) is absent, not a fake zero
        self.samples.append((labels, value))

    def render(self) -> Iterator[str]:
        yield f"# HELP {self.name} {self.help}"
        yield f"# TYPE {self.name} {self.kind}"
        for labels, value in self.samples:
            label_text = ",".join(f'{k}="{_escape_label(str(v))}"' for k, v in labels.items())
            yield (
                f"{self.name}{{{label_text}}} {_format_value(value)}"
                if label_text
                else (f"{self.name} {_format_value(value)}")
            )


def render_metrics(state: dict[str, Any]) -> str:
    """The state dict as Prometheus text exposition format (every family with HELP and TYPE)."""
    agent = state.get("agent", {})
    broker = agent.get("broker", {})
    devices: dict[str, dict[str, Any]] = state.get("devices", {})
    families: list[_Family] = []

    def family(name: str, kind: str, help_text: str) -> _Family:
        fam = _Family(name, kind, help_text)
        families.append(fam)
        return fam

    family("twin_up", "gauge", "1 while the agent service is running.").add(1 if agent.get("running") else 0)
    family("twin_uptime_seconds", "gauge", "Seconds since the agent service started.").add(
        agent.get("uptime_s")
    )
    family("twin_broker_connected", "gauge", "1 while the MQTT connection is up.").add(
        1 if broker.get("connected") else 0
    )
    for key, help_text in (
        ("connection_successes", "MQTT connections established (the first and every reconnect)."),
        ("connection_failures", "MQTT connection attempts that failed."),
        ("disconnections", "MQTT connections lost."),
        ("subscribes", "SUBSCRIBE requests acknowledged by the broker."),
        ("messages", "PUBLISH packets received from the broker (all devices, before decoding)."),
    ):
        if key in broker:
            family(f"twin_broker_{key}_total", "counter", help_text).add(broker[key])
    mailbox = agent.get("mailbox", {})
    family(
        "twin_mailbox_overwritten_total", "counter", "Messages replaced in the mailbox before decoding."
    ).add(mailbox.get("overwritten_total"))
    family(
        "twin_mailbox_refused_keys_total", "counter", "Messages refused: too many distinct topics pending."
    ).add(mailbox.get("refused_keys"))
    worker = agent.get("worker", {})
    family("twin_worker_batches_total", "counter", "Batches the twin worker took from the mailbox.").add(
        worker.get("batches")
    )

    status = family("twin_device_status", "gauge", "Device health status (1 for the current status).")
    age = family(
        "twin_device_last_message_age_seconds", "gauge", "Seconds since the last valid message (agent clock)."
    )
    rate = family("twin_device_message_rate_hz", "gauge", "Valid messages per second over the health window.")
    counters = {
        key: family(f"twin_messages_{key}_total", "counter", help_text)
        for key, help_text in (
            ("received", "Messages taken from the mailbox for decoding."),
            ("decoded", "Messages that decoded into valid telemetry."),
            ("applied", "Messages applied to the twin (newer than the last applied one)."),
            (
                "ignored_stale",
                "Valid messages ignored because their timestamp was not newer (duplicate or reordered).",
            ),
            ("overwritten", "Messages replaced in the latest-value mailbox before the worker took them."),
        )
    }
    rejected = family(
        "twin_messages_rejected_total", "counter", "Messages rejected by the decoder, by reason."
    )
    errors = family("twin_worker_errors_total", "counter", "Unexpected errors while processing a message.")
    resets = family(
        "twin_edge_clock_resets_total", "counter", "Edge clock jumps backwards that re-based the twin."
    )
    edge_p50 = family(
        "twin_edge_clock_latency_p50_seconds",
        "gauge",
        "Median of receive wall time minus edge timestamp; includes edge clock offset (not NTP-disciplined).",
    )
    edge_p99 = family(
        "twin_edge_clock_latency_p99_seconds", "gauge", "p99 of receive wall time minus edge timestamp."
    )
    offset = family(
        "twin_edge_clock_offset_seconds",
        "gauge",
        "Window minimum of receive wall time minus edge timestamp: clock offset plus the fastest transit.",
    )
    int_p50 = family(
        "twin_internal_latency_p50_seconds", "gauge", "Median time from receive to twin updated."
    )
    int_p99 = family("twin_internal_latency_p99_seconds", "gauge", "p99 time from receive to twin updated.")
    joints = family("twin_joint_position_radians", "gauge", "Joint angle of the twin, radians.")
    torques = family(
        "twin_joint_torque_newton_metres", "gauge", "Inverse-dynamics joint torque of the measured pose."
    )

    for device, d in sorted(devices.items()):
        for name in ("ONLINE", "STALE", "OFFLINE"):
            status.add(1 if d.get("status") == name else 0, device=device, status=name)
        age.add(d.get("age_s"), device=device)
        rate.add(d.get("rate_hz"), device=device)
        c = d.get("counters", {})
        for key, fam in counters.items():
            fam.add(c.get(key), device=device)
        for reason, count in sorted(c.get("rejected", {}).items()):
            rejected.add(count, device=device, reason=reason)
        errors.add(c.get("errors"), device=device)
        resets.add(c.get("clock_resets"), device=device)
        edge = d.get("edge_clock_latency_s") or {}
        edge_p50.add(edge.get("p50"), device=device)
        edge_p99.add(edge.get("p99"), device=device)
        offset.add(d.get("edge_clock_offset_s"), device=device)
        internal = d.get("internal_latency_s") or {}
        int_p50.add(internal.get("p50"), device=device)
        int_p99.add(internal.get("p99"), device=device)
        for joint, value in (d.get("joints_rad") or {}).items():
            joints.add(value, device=device, joint=joint)
        for joint, value in (d.get("torques_nm") or {}).items():
            torques.add(value, device=device, joint=joint)
    for reason, count in sorted(state.get("untracked_rejected", {}).items()):
        rejected.add(count, device="_untracked", reason=reason)

    lines: list[str] = []
    for fam in families:
        lines.extend(fam.render())
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------------- server


class _Handler(BaseHTTPRequestHandler):
    server: _AgentHTTPServer
    server_version = "so101-twin"

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("http %s", format % args)

    def _send(self, status: int, body: bytes, content_type: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)

    def _send_json(self, status: int, payload: Any) -> None:
        self._send(status, json.dumps(payload, allow_nan=False, default=str).encode(), "application/json")

    def do_GET(self) -> None:
        path = urlsplit(self.path).path.rstrip("/") or "/"
        try:
            if path == "/state":
                self._send_json(HTTPStatus.OK, _json_safe(self.server.source.state()))
            elif path == "/metrics":
                self._send(
                    HTTPStatus.OK,
                    render_metrics(self.server.source.state()).encode(),
                    PROMETHEUS_CONTENT_TYPE,
                )
            elif path == "/healthz":
                healthy, body = self.server.source.healthz()
                self._send_json(
                    HTTPStatus.OK if healthy else HTTPStatus.SERVICE_UNAVAILABLE, _json_safe(body)
                )
            elif path == "/stream":
                self._stream()
            elif path == "/":
                self._send_json(HTTPStatus.OK, {"endpoints": ["/state", "/metrics", "/healthz", "/stream"]})
            else:
                self._send_json(
                    HTTPStatus.NOT_FOUND,
                    {
                        "error": "not_found",
                        "path": path,
                        "endpoints": ["/state", "/metrics", "/healthz", "/stream"],
                    },
                )
        except _DISCONNECTS:
            log.debug("http client went away during %s", path)
        except Exception:
            log.exception("http handler failed", extra={"path": path})
            with contextlib.suppress(OSError):
                self._send_json(HTTPStatus.INTERNAL_SERVER_ERROR, {"error": "internal_error", "path": path})

    def do_POST(self) -> None:
        self._send_json(HTTPStatus.METHOD_NOT_ALLOWED, {"error": "method_not_allowed", "allowed": ["GET"]})

    do_PUT = do_DELETE = do_PATCH = do_POST  # noqa: N815

    def _stream(self) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Accel-Buffering", "no")
        self.end_headers()
        stop = self.server.stopping
        interval = 1.0 / self.server.stream_rate_hz
        self.wfile.write(b"retry: 1000\n\n")
        self.server.stream_clients_inc(1)
        try:
            while not stop.is_set():
                data = json.dumps(_json_safe(self.server.source.state()), allow_nan=False, default=str)
                self.wfile.write(f"event: state\ndata: {data}\n\n".encode())
                self.wfile.flush()
                stop.wait(interval)
        finally:
            self.server.stream_clients_inc(-1)


def _json_safe(value: Any) -> Any:
    """NaN/inf are not JSON: publish them as null rather than emitting invalid documents."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


class _AgentHTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    # Port reuse so a restarted agent can bind at once while old sockets sit in TIME_WAIT.
    allow_reuse_address = True

    def __init__(self, address: tuple[str, int], source: StateSource, stream_rate_hz: float) -> None:
        super().__init__(address, _Handler)
        self.source = source
        self.stream_rate_hz = stream_rate_hz
        self.stopping = threading.Event()
        self._clients_lock = threading.Lock()
        self.stream_clients = 0

    def stream_clients_inc(self, n: int) -> None:
        with self._clients_lock:
            self.stream_clients += n

    def handle_error(self, request: Any, client_address: Any) -> None:
        # The default prints a traceback to stderr; a client dropping mid-response is routine, not an error.
        log.debug("http connection error from %s", client_address, exc_info=True)


class AgentHttpServer:
    """Serves a StateSource on host:port in a background thread; `port=0` binds a free port (see `.port`)."""

    def __init__(
        self, source: StateSource, host: str = "127.0.0.1", port: int = 8080, *, stream_rate_hz: float = 30.0
    ):
        if stream_rate_hz <= 0:
            raise ValueError(f"stream_rate_hz = {stream_rate_hz} must be > 0")
        try:
            self._server = _AgentHTTPServer((host, port), source, stream_rate_hz)
        except OSError as exc:
            raise OSError(
                exc.errno,
                f"cannot listen on {host}:{port} ({exc.strerror}); another agent may be running there: "
                "stop it or choose another address with --http HOST:PORT",
            ) from exc
        self._thread: threading.Thread | None = None

    @property
    def host(self) -> str:
        return str(self._server.server_address[0])

    @property
    def port(self) -> int:
        return int(self._server.server_address[1])

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @property
    def stream_clients(self) -> int:
        return self._server.stream_clients

    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(
            target=self._server.serve_forever, kwargs={"poll_interval": 0.2}, name="twin-http", daemon=True
        )
        self._thread.start()
        log.info("http listening", extra={"url": self.url})

    def stop(self) -> None:
        """Stop accepting, end open streams, close the socket. Idempotent."""
        self._server.stopping.set()
        if self._thread is not None:
            self._server.shutdown()
            self._thread.join(timeout=5)
            self._thread = None
        self._server.server_close()

    def __enter__(self) -> AgentHttpServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
