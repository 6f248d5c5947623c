"""The agent's local HTTP interface: state as JSON, Prometheus metrics, a health probe and a live SSE stream.

`http.server.ThreadingHTTPServer`: the agent binds it to 127.0.0.1 by default, and viewers, curl and a
Prometheus scrape are its only clients. The server knows nothing about MQTT or MuJoCo; it asks a `StateSource`
(the agent service) for its typed `AgentState` and renders every endpoint from that one snapshot, so /state,
/metrics and /stream always agree.

Endpoints (docs/agent.md has examples):
- GET /state    `AgentState.to_json()`
- GET /metrics  Prometheus text exposition format 0.0.4 (twin.service.metrics)
- GET /healthz  200 {"status": "ok", ...} or 503 {"status": "unavailable", "reasons": [...]}
- GET /stream   Server-Sent Events, `data: {state json}` at most `stream_rate_hz` times a second
- GET /alarms   servo alarms that are not NORMAL, worst first (`?all=1`: every alarm)
- POST /alarms/<device>/<joint>/<kind>/ack   acknowledge one (ACTIVE -> ACKNOWLEDGED, LATCHED -> NORMAL);
                from loopback clients only, whatever address the server listens on: the API has no
                authentication, and an acknowledgement silences an alarm for everyone
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import logging
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Protocol
from urllib.parse import parse_qs, unquote, urlsplit

from twin.core.alarms import AlarmNotFound, NothingToAcknowledge
from twin.service.config import DEFAULT_HTTP_HOST, DEFAULT_HTTP_PORT
from twin.service.metrics import CONTENT_TYPE as PROMETHEUS_CONTENT_TYPE
from twin.service.metrics import render_metrics
from twin.service.state import AgentState, AlarmInfo, AlarmList, HealthReport

log = logging.getLogger(__name__)

ENDPOINTS = ("/state", "/metrics", "/healthz", "/stream", "/alarms")
JSON_CONTENT_TYPE = "application/json"
# Errors a client hanging up produces mid-write; never worth more than a debug line.
_DISCONNECTS = (BrokenPipeError, ConnectionResetError, ConnectionAbortedError, TimeoutError)


class StateSource(Protocol):
    def state(self) -> AgentState:
        """The agent state (see docs/agent.md, GET /state)."""
        ...

    def healthz(self) -> HealthReport:
        """The body of GET /healthz (200 when `healthy`, else 503)."""
        ...


class AlarmSource(Protocol):
    """What /alarms needs besides the state (the agent service has both; a source without them has no
    /alarms endpoint)."""

    def alarms(self, *, include_normal: bool = False) -> tuple[AlarmInfo, ...]: ...

    def acknowledge_alarm(self, alarm_id: str) -> AlarmInfo: ...


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
        self._send(status, json.dumps(payload, allow_nan=False).encode(), JSON_CONTENT_TYPE)

    def do_GET(self) -> None:
        path = urlsplit(self.path).path.rstrip("/") or "/"
        try:
            if path == "/state":
                self._send(HTTPStatus.OK, self.server.source.state().to_json(), JSON_CONTENT_TYPE)
            elif path == "/metrics":
                body = render_metrics(self.server.source.state()).encode()
                self._send(HTTPStatus.OK, body, PROMETHEUS_CONTENT_TYPE)
            elif path == "/healthz":
                report = self.server.source.healthz()
                status = HTTPStatus.OK if report.healthy else HTTPStatus.SERVICE_UNAVAILABLE
                self._send(status, report.to_json(), JSON_CONTENT_TYPE)
            elif path == "/stream":
                self._stream()
            elif path == "/alarms" and hasattr(self.server.source, "alarms"):
                query = parse_qs(urlsplit(self.path).query)
                include_normal = query.get("all", ["0"])[-1] not in ("", "0", "false")
                alarms = self.server.source.alarms(include_normal=include_normal)  # type: ignore[attr-defined]
                self._send(HTTPStatus.OK, AlarmList(alarms=alarms).to_json(), JSON_CONTENT_TYPE)
            elif path == "/":
                self._send_json(HTTPStatus.OK, {"endpoints": list(ENDPOINTS)})
            else:
                self._send_json(
                    HTTPStatus.NOT_FOUND, {"error": "not_found", "path": path, "endpoints": list(ENDPOINTS)}
                )
        except _DISCONNECTS:
            log.debug("http client went away during %s", path)
        except Exception:
            log.exception("http handler failed", extra={"path": path})
            with contextlib.suppress(OSError):
                self._send_json(HTTPStatus.INTERNAL_SERVER_ERROR, {"error": "internal_error", "path": path})

    def do_POST(self) -> None:
        path = urlsplit(self.path).path.rstrip("/")
        parts = path.split("/")
        # /alarms/<device>/<joint>/<kind>/ack: device ids never hold '/', so the id is the middle three.
        if len(parts) != 6 or parts[1] != "alarms" or parts[5] != "ack":
            self._send_json(
                HTTPStatus.METHOD_NOT_ALLOWED,
                {"error": "method_not_allowed", "allowed": ["GET", "POST /alarms/<id>/ack"]},
            )
            return
        try:
            self._acknowledge("/".join(unquote(p) for p in parts[2:5]))
        except _DISCONNECTS:
            log.debug("http client went away during %s", path)
        except Exception:
            log.exception("http handler failed", extra={"path": path})
            with contextlib.suppress(OSError):
                self._send_json(HTTPStatus.INTERNAL_SERVER_ERROR, {"error": "internal_error", "path": path})

    def _acknowledge(self, alarm_id: str) -> None:
        # The body, if any, is not used; read it so the connection stays in step.
        length = int(self.headers.get("Content-Length") or 0)
        if length:
            self.rfile.read(min(length, 65536))
        client = self.client_address[0]
        if not is_loopback_client(client):
            self._send_json(
                HTTPStatus.FORBIDDEN,
                {
                    "error": "forbidden",
                    "detail": f"acknowledging alarms is allowed from this host only (loopback), not "
                    f"{client}; open a shell on the host (the stack's SsmSessionCommand) and ask there",
                },
            )
            return
        source = self.server.source
        if not hasattr(source, "acknowledge_alarm"):
            self._send_json(
                HTTPStatus.NOT_FOUND, {"error": "not_found", "detail": "this source has no alarms"}
            )
            return
        try:
            info = source.acknowledge_alarm(alarm_id)  # type: ignore[attr-defined]
        except AlarmNotFound:
            self._send_json(
                HTTPStatus.NOT_FOUND,
                {
                    "error": "alarm_not_found",
                    "alarm_id": alarm_id,
                    "detail": "GET /alarms?all=1 lists every id",
                },
            )
            return
        except NothingToAcknowledge as exc:
            self._send_json(HTTPStatus.CONFLICT, {"error": "nothing_to_acknowledge", "detail": str(exc)})
            return
        self._send(HTTPStatus.OK, AlarmList(alarms=(info,)).to_json(), JSON_CONTENT_TYPE)

    def do_PUT(self) -> None:
        self._send_json(
            HTTPStatus.METHOD_NOT_ALLOWED,
            {"error": "method_not_allowed", "allowed": ["GET", "POST /alarms/<id>/ack"]},
        )

    do_DELETE = do_PATCH = do_PUT  # noqa: N815

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
                # One event = one JSON document on one line (msgspec never emits a newline inside it).
                self.wfile.write(b"event: state\ndata: " + self.server.source.state().to_json() + b"\n\n")
                self.wfile.flush()
                stop.wait(interval)
        finally:
            self.server.stream_clients_inc(-1)


def is_loopback_client(address: str) -> bool:
    """True for a loopback peer: 127.0.0.0/8, ::1, and IPv4 loopback seen through a dual-stack socket
    (::ffff:127.0.0.1). Anything unparsable is not loopback."""
    try:
        ip = ipaddress.ip_address(address.split("%", 1)[0])
    except ValueError:
        return False
    mapped = getattr(ip, "ipv4_mapped", None)
    return (mapped or ip).is_loopback


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
        self,
        source: StateSource,
        host: str = DEFAULT_HTTP_HOST,
        port: int = DEFAULT_HTTP_PORT,
        *,
        stream_rate_hz: float = 30.0,
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
