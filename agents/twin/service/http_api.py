"""The agent's HTTP server: the JSON API (state, metrics, health, alarms, a live stream) and the operator
console's pages (docs/console.md), on one port, loopback by default.

Starlette routes the requests; uvicorn serves them on a thread of its own with its own event loop, inside the
agent's process, so the agent starts and stops it like any of its threads (`start()`, `stop()`). The server
knows nothing about MQTT or MuJoCo: it asks its source (the agent service) for its typed `AgentState` and
renders /state, /metrics and /stream from it, so they always agree.

Endpoints (docs/http-api.md has examples; docs/console.md the console's own API):
- GET /state    `AgentState.to_json()`
- GET /metrics  Prometheus text exposition format 0.0.4 (twin.service.metrics)
- GET /healthz  200 {"status": "ok", ...} or 503 {"status": "unavailable", "reasons": [...]}
- GET /stream   Server-Sent Events, `data: {state json}` at most `stream_rate_hz` times a second
- GET /alarms   servo alarms that are not NORMAL, worst first (`?all=1`: every alarm; `?device=`: one arm's)
- POST /alarms/<device>/<joint>/<kind>/ack  acknowledge one (ACTIVE -> ACKNOWLEDGED, LATCHED -> NORMAL); the
                id may also come percent-encoded as one segment. Loopback clients only; a browser's request
                only from the console's origin with its CSRF token (twin.service.http_guard)
- POST /alarms/ack  acknowledge many: the body a JSON list of alarm ids (at most ACK_MANY_MAX), each id's
                outcome in one answer, the state file written once for them all; guarded like the single one
- POST /api/arm/<device>/forget  remove an OFFLINE arm (its twin, health, alarms) from the fleet; guarded
                like the acknowledgement
- GET /  (a browser) the console; (anything else) the list of endpoints, as before

Bounded (each limit a `[http]` key): at most `max_connections` connections (more get 503), a request head or
body that stalls, or a client that stops reading what it is sent, is cut off after `timeout_s`, and a body
over `max_body_bytes` gets 413, and the Sessions page's files kept on disk stay under `session_files_mb`
(twin.service.session_files). Live updates are built once per tick and shared by every client
(twin.service.stream_hub).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import json
import logging
import re
import socket
import threading
import time
from collections.abc import Awaitable, Callable, Sequence
from typing import Protocol, TypeVar, cast, runtime_checkable
from urllib.parse import unquote

import h11
import uvicorn
from starlette.applications import Starlette
from starlette.background import BackgroundTask
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.types import Receive, Scope, Send
from uvicorn.protocols.http.h11_impl import H11Protocol

from twin.core import heap
from twin.core.alarms import AlarmNotFound, NothingToAcknowledge
from twin.core.topics import device_id_problem
from twin.service import session_files
from twin.service.config import DEFAULT_HTTP_HOST, DEFAULT_HTTP_PORT, MAX_EVENTS_CAPACITY, HttpSection
from twin.service.console import (
    ASSETS,
    SESSION_FILE_KINDS,
    AlarmHorizon,
    EventSource,
    SessionCatalog,
    SessionInfo,
    arm_document,
    arm_view_of,
    fleet_parts,
    fleet_summary,
    not_found_page,
    render_page,
)
from twin.service.events import (
    Event,
    EventKind,
    EventLevel,
    EventQuery,
    events_csv,
    events_json,
    export_name,
)
from twin.service.http_guard import (
    BodyTooLarge,
    GuardSettings,
    RequestGuard,
    is_loopback_client,
    new_csrf_token,
)
from twin.service.metrics import CONTENT_TYPE as PROMETHEUS_CONTENT_TYPE
from twin.service.metrics import render_metrics
from twin.service.persist import NotSavedError
from twin.service.session_files import SessionFiles
from twin.service.shards import (
    ACK_MANY_MAX,
    ALARM_NOT_FOUND_DETAIL,
    AckOutcome,
    AckResult,
    ArmForgotten,
    ArmNotForgettableError,
    ArmNotFoundError,
    ForgetTimedOutError,
    WorkerError,
)
from twin.service.state import AgentState, AlarmInfo, AlarmList, HealthReport
from twin.service.stream_hub import (
    ARM_PREFIX,
    FLEET,
    STATE,
    VIEW_PREFIX,
    StreamHub,
    Subscription,
    encode_events,
    newest_event_id,
)

log = logging.getLogger(__name__)

__all__ = [
    "ENDPOINTS",
    "AgentHttpServer",
    "AlarmSource",
    "ArmSource",
    "StateSource",
    "is_loopback_client",
]

ENDPOINTS = ("/state", "/metrics", "/healthz", "/stream", "/alarms")
CONSOLE_PAGES = ("/", "/arm/<device>", "/sessions", "/events")
JSON_CONTENT_TYPE = "application/json"
# How long a list of sessions is reused: reading them scans the history table.
SESSIONS_REUSE_S = 5.0
# Alarm events read to count the sessions' raises: as many as the largest store holds (config).
EVENTS_READ_FOR_SESSIONS = MAX_EVENTS_CAPACITY
# The most events one GET /api/events answers (the exports take up to 100,000).
EVENTS_ANSWERED = 1000
# Answers every page and API response carries: nothing is cached, nothing may frame the console, scripts and
# styles come from this server only (the console ships its own; no inline script, no CDN).
SECURITY_HEADERS = {
    "cache-control": "no-store",
    "x-content-type-options": "nosniff",
    "x-frame-options": "DENY",
    "referrer-policy": "no-referrer",
}
PAGE_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; connect-src 'self'; "
    "frame-ancestors 'none'; base-uri 'none'; form-action 'self'"
)
_DEVICE_FILE = re.compile(r"[^A-Za-z0-9_.-]")
_T = TypeVar("_T")


class StateSource(Protocol):
    def state(self) -> AgentState:
        """The agent state (see docs/http-api.md, GET /state)."""
        ...

    def healthz(self) -> HealthReport:
        """The body of GET /healthz (200 when `healthy`, else 503)."""
        ...


@runtime_checkable
class AlarmSource(Protocol):
    """What /alarms needs besides the state (the agent service has both; a source without them has no
    /alarms endpoint)."""

    def alarms(self, *, include_normal: bool = False) -> tuple[AlarmInfo, ...]: ...

    def acknowledge_alarm(self, alarm_id: str) -> AlarmInfo: ...


@runtime_checkable
class BulkAlarmSource(Protocol):
    """What POST /alarms/ack needs (the agent service has it; a source without it answers 404)."""

    def acknowledge_alarms(self, alarm_ids: Sequence[str]) -> tuple[AckResult, ...]: ...


@runtime_checkable
class ArmSource(Protocol):
    """What forgetting an arm needs (the agent service has it; a source without it answers 404)."""

    def forget_arm(self, device: str) -> ArmForgotten: ...


# ------------------------------------------------------------------------------------------- connections


class _GuardedH11(H11Protocol):
    """uvicorn's HTTP/1.1 connection, cut off when it stalls: a request head that does not arrive, or a
    client that stops reading what it is sent. uvicorn waits forever on both (its keep-alive timeout covers
    only an idle connection between requests): a client that stops reading would hold its connection and its
    stream open for good, and closing it gracefully waits for the unsent data, so it is aborted instead."""

    stall_timeout_s = 10.0

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # asyncio hands a server protocol a stream transport; uvicorn's signature says so, asyncio's does not.
        super().connection_made(cast(asyncio.Transport, transport))
        self._head_timer: asyncio.TimerHandle | None = None
        self._write_timer: asyncio.TimerHandle | None = None
        self._arm_head_timer()

    def _arm_head_timer(self) -> None:
        self._cancel(self._head_timer)
        self._head_timer = self.loop.call_later(self.stall_timeout_s, self._head_stalled)

    def _head_stalled(self) -> None:
        # Still no complete request head on this connection (a response completing re-arms the timer).
        if self.conn.their_state in (h11.IDLE, h11.SEND_BODY) and not self.transport.is_closing():
            log.debug("http connection from %s stalled before its request; closed", self.client)
            self.transport.abort()

    def handle_events(self) -> None:
        cycle = self.cycle
        super().handle_events()
        if self.cycle is not cycle and self.conn.their_state is not h11.SEND_BODY:
            self._cancel(self._head_timer)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_head_timer()

    def pause_writing(self) -> None:
        super().pause_writing()
        self._cancel(self._write_timer)
        self._write_timer = self.loop.call_later(self.stall_timeout_s, self._write_stalled)

    def resume_writing(self) -> None:
        super().resume_writing()
        self._cancel(self._write_timer)

    def _write_stalled(self) -> None:
        log.info(
            "http client %s stopped reading for %.0f s; connection aborted", self.client, self.stall_timeout_s
        )
        self.transport.abort()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel(self._head_timer)
        self._cancel(self._write_timer)
        super().connection_lost(exc)

    @staticmethod
    def _cancel(timer: asyncio.TimerHandle | None) -> None:
        if timer is not None:
            timer.cancel()


def _protocol_class(stall_timeout_s: float) -> type[_GuardedH11]:
    return type("GuardedH11", (_GuardedH11,), {"stall_timeout_s": stall_timeout_s})


# ------------------------------------------------------------------------------------------- responses


def _json(status: int, body: bytes) -> Response:
    return Response(body, status_code=status, media_type=JSON_CONTENT_TYPE, headers=SECURITY_HEADERS)


def _attachment(extension: str) -> str:
    return f'attachment; filename="{export_name(extension, time.time())}"'


def _error(status: int, error: str, **fields: object) -> Response:
    return JSONResponse({"error": error, **fields}, status_code=status, headers=SECURITY_HEADERS)


class _EventStream(Response):
    """A Server-Sent Events response fed by one hub subscription; ends when the client leaves, the server
    stops, or the subscription closes."""

    def __init__(self, subscription: Subscription, release: Callable[[Subscription], None]) -> None:
        super().__init__(
            # Exactly this type (Starlette would add a charset to a text/* media type; SSE is UTF-8 anyway).
            headers={**SECURITY_HEADERS, "content-type": "text/event-stream", "x-accel-buffering": "no"},
        )
        # A stream has no length: Starlette declares the empty body's 0, which h11 would then enforce.
        self.raw_headers = [(k, v) for k, v in self.raw_headers if k != b"content-length"]
        self.subscription = subscription
        self._release = release

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        sub = self.subscription
        try:
            await send({"type": "http.response.start", "status": 200, "headers": self.raw_headers})
            await send({"type": "http.response.body", "body": b"retry: 1000\n\n", "more_body": True})
            gone = asyncio.ensure_future(_disconnected(receive))
            try:
                while True:
                    frame = asyncio.ensure_future(sub.next())
                    done, _ = await asyncio.wait({frame, gone}, return_when=asyncio.FIRST_COMPLETED)
                    if gone in done:
                        frame.cancel()
                        return
                    data = frame.result()
                    if data is None:
                        break
                    await send({"type": "http.response.body", "body": data, "more_body": True})
                await send({"type": "http.response.body", "body": b"", "more_body": False})
            finally:
                gone.cancel()
        finally:
            self._release(sub)


async def _disconnected(receive: Receive) -> None:
    while (await receive())["type"] != "http.disconnect":
        pass


# ------------------------------------------------------------------------------------------------- server


class AgentHttpServer:
    """Serves a StateSource on host:port in a background thread; `port=0` binds a free port (see `.port`).

    `settings` is the config's `[http]` section (limits, allowed hosts, the console's rates); `sessions` the
    history's sessions for the console (none: the Sessions page says history is off); `rerun_url` the Rerun
    web viewer the arm page links to (empty: no link)."""

    def __init__(
        self,
        source: StateSource,
        host: str = DEFAULT_HTTP_HOST,
        port: int = DEFAULT_HTTP_PORT,
        *,
        stream_rate_hz: float = 30.0,
        settings: HttpSection | None = None,
        sessions: SessionCatalog | None = None,
        rerun_url: str = "",
    ):
        if stream_rate_hz <= 0:
            raise ValueError(f"stream_rate_hz = {stream_rate_hz} must be > 0")
        self.settings = settings or HttpSection()
        self._source = source
        self._stream_rate_hz = stream_rate_hz
        self._sessions = sessions
        self.rerun_url = rerun_url
        self.csrf_token = new_csrf_token()
        self._socket = _listen(host, port)
        self._host, self._port = self._socket.getsockname()[:2]
        self._guard = RequestGuard(
            self._build_app(),
            GuardSettings.of(self.settings.allowed_hosts, self.settings.max_body_bytes, host),
            self.csrf_token,
        )
        self._uvicorn = uvicorn.Server(
            uvicorn.Config(
                self._guard,
                lifespan="off",
                log_config=None,
                log_level=logging.WARNING,
                access_log=False,
                http=_protocol_class(self.settings.timeout_s),
                ws="none",
                # uvicorn counts the connection asking, so one more than the connections to serve.
                limit_concurrency=self.settings.max_connections + 1,
                timeout_keep_alive=5,
                timeout_graceful_shutdown=2,
                h11_max_incomplete_event_size=16 * 1024,
                server_header=False,
            )
        )
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._hub: StreamHub | None = None
        self._started = threading.Event()
        self._session_files = SessionFiles(self.settings.session_files_mb * 2**20)
        self._file_locks: dict[str, asyncio.Lock] = {}
        self._sessions_cache: tuple[float, list[SessionInfo], float | None] | None = None

    # --------------------------------------------------------------------------------------------- lifecycle

    @property
    def host(self) -> str:
        return str(self._host)

    @property
    def port(self) -> int:
        return int(self._port)

    @property
    def url(self) -> str:
        host = self.host if ":" not in self.host else f"[{self.host}]"
        return f"http://{host}:{self.port}"

    @property
    def stream_clients(self) -> int:
        """Open live streams (/stream and the console's)."""
        return self._hub.clients if self._hub is not None else 0

    @property
    def refused(self) -> dict[str, int]:
        """Requests the guard refused, by reason."""
        return dict(self._guard.refused)

    def start(self) -> None:
        if self._thread is not None:
            return
        # What a killed agent's server left in /tmp (its session files) goes now, not at the first download.
        session_files.remove_orphans()
        self._thread = threading.Thread(target=self._serve, name="twin-http", daemon=True)
        self._thread.start()
        if not self._started.wait(10.0):
            log.error("http server did not start within 10 s")
        log.info("http listening", extra={"url": self.url})

    def _serve(self) -> None:
        try:
            asyncio.run(self._main())
        except Exception:
            log.exception("http server failed")
        finally:
            self._started.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        hub = self._hub = StreamHub(
            self._source, state_rate_hz=self._stream_rate_hz, console_rate_hz=self.settings.console_rate_hz
        )
        ticker = asyncio.create_task(hub.run(), name="twin-http-hub")
        self._started.set()
        try:
            await self._uvicorn.serve(sockets=[self._socket])
        finally:
            hub.close()
            ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await ticker

    def stop(self) -> None:
        """End open streams, stop accepting, close the socket. Idempotent."""
        loop, thread = self._loop, self._thread
        if loop is not None and thread is not None and thread.is_alive():
            with contextlib.suppress(RuntimeError):  # the loop already closed
                loop.call_soon_threadsafe(self._shutdown)
            thread.join(timeout=10)
            if thread.is_alive():
                log.error("http server thread did not stop within 10 s")
        self._thread = None
        self._socket.close()
        self._session_files.close()

    def _shutdown(self) -> None:
        if self._hub is not None:
            self._hub.close()
        self._uvicorn.should_exit = True

    def __enter__(self) -> AgentHttpServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------------------------------------ routes

    def _build_app(self) -> Starlette:
        r = self._guarded
        routes = [
            Route("/", r(self._root)),
            Route("/state", r(self._state)),
            Route("/metrics", r(self._metrics)),
            Route("/healthz", r(self._healthz)),
            Route("/stream", r(self._stream)),
            Route("/alarms", r(self._alarms)),
            Route("/alarms/ack", r(self._acknowledge_many), methods=["POST"]),
            Route("/alarms/{alarm_id:path}/ack", r(self._acknowledge), methods=["POST"]),
            Route("/arm/{device}", r(self._page_arm)),
            Route("/sessions", r(self._page("sessions"))),
            Route("/events", r(self._page("events"))),
            Route("/api/fleet", r(self._api_fleet)),
            Route("/api/arm/{device}", r(self._api_arm)),
            Route("/api/arm/{device}/forget", r(self._forget), methods=["POST"]),
            Route("/api/stream/fleet", r(self._stream_fleet)),
            Route("/api/stream/arm/{device}", r(self._stream_arm)),
            Route("/api/events", r(self._api_events)),
            Route("/api/events.csv", r(self._export_events_csv)),
            Route("/api/events.json", r(self._export_events_json)),
            Route("/api/stream/events", r(self._stream_events)),
            Route("/api/sessions", r(self._api_sessions)),
            Route("/api/sessions/{device}/{start}/{kind}", r(self._session_file)),
            Mount("/static", app=StaticFiles(directory=ASSETS), name="static"),
        ]
        return Starlette(
            routes=routes,
            exception_handlers={404: self._not_found, 405: self._not_allowed},
        )

    def _guarded(
        self, handler: Callable[[Request], Awaitable[Response]]
    ) -> Callable[[Request], Awaitable[Response]]:
        """A handler whose failure is a logged 500 with a JSON body, and a client gone mid-answer nothing."""

        async def run(request: Request) -> Response:
            try:
                return await handler(request)
            except HTTPException:
                raise
            except Exception:
                log.exception("http handler failed", extra={"path": request.url.path})
                return _error(500, "internal_error", path=request.url.path)

        return run

    async def _not_found(self, request: Request, exc: Exception) -> Response:
        if request.method not in ("GET", "HEAD"):
            return await self._not_allowed(request, exc)
        if "text/html" in request.headers.get("accept", ""):
            # A mistyped address in the browser: a page that says where to go, not a JSON error shown raw.
            return self._html(not_found_page(request.url.path), status_code=404)
        return _error(404, "not_found", path=request.url.path, endpoints=list(ENDPOINTS))

    async def _not_allowed(self, request: Request, exc: Exception) -> Response:
        return _error(
            405,
            "method_not_allowed",
            allowed=["GET", "POST /alarms/<id>/ack", "POST /alarms/ack", "POST /api/arm/<device>/forget"],
        )

    async def _call(self, fn: Callable[[], _T]) -> _T:
        """Run a blocking source call off the event loop (the state of a sharded agent asks its workers)."""
        return await asyncio.to_thread(fn)

    # ---------------------------------------------------------------------------------------------- the API

    async def _root(self, request: Request) -> Response:
        if "text/html" in request.headers.get("accept", ""):
            return self._html(render_page("fleet", csrf_token=self.csrf_token, rerun_url=self.rerun_url))
        return JSONResponse(
            {"endpoints": list(ENDPOINTS), "console": list(CONSOLE_PAGES)}, headers=SECURITY_HEADERS
        )

    async def _state(self, request: Request) -> Response:
        state = await self._call(self._source.state)
        return _json(200, state.to_json())

    async def _metrics(self, request: Request) -> Response:
        source = self._source
        state = await self._call(source.state)
        # Each alarm by its servo, from a source that has them (the agent service does).
        alarms = await self._call(source.alarms) if isinstance(source, AlarmSource) else ()
        body = render_metrics(state, alarms).encode()
        # A render of a large fleet peaks at five to six times its body (every sample and line built first):
        # glibc keeps those freed pages, so the process's RSS stayed at its high-water mark between scrapes.
        # The trim runs once the answer is sent, after every render: about 1 ms for an 800-arm body that took
        # far longer to build, and the shared rate limit (30 s) skipped every other one of a 30 s scraper's.
        return Response(
            body,
            media_type=None,
            headers={**SECURITY_HEADERS, "content-type": PROMETHEUS_CONTENT_TYPE},
            background=BackgroundTask(heap.trim, force=True),
        )

    async def _healthz(self, request: Request) -> Response:
        report = await self._call(self._source.healthz)
        return _json(200 if report.healthy else 503, report.to_json())

    async def _stream(self, request: Request) -> Response:
        """The whole state at the stream rate, or with `?device=<id>` that one arm and the fleet's ids
        (stream_hub, `view:`); an empty id gives the ids alone, for a viewer that has not chosen yet."""
        device = request.query_params.get("device")
        if device is None:
            return self._subscribe(STATE)
        problem = device_id_problem(device) if device else None
        if problem is not None:
            return _error(400, "bad_device", detail=f"?device={device[:140]!r}: {problem}")
        return self._subscribe(VIEW_PREFIX + device)

    async def _alarms(self, request: Request) -> Response:
        source = self._source
        if not isinstance(source, AlarmSource):
            return _error(404, "not_found", path=request.url.path, endpoints=list(ENDPOINTS))
        include_normal = request.query_params.get("all", "0") not in ("", "0", "false")
        alarms = await self._call(lambda: source.alarms(include_normal=include_normal))
        device = request.query_params.get("device")
        if device is not None:
            alarms = tuple(a for a in alarms if a.device == device)
        return _json(200, AlarmList(alarms=alarms).to_json())

    async def _read_body(self, request: Request) -> Response | None:
        """Read a POST's body, which is not used, within the limits (so the connection stays in step); the
        refusal when it is too large or too slow."""
        body = await self._body(request)
        return body if isinstance(body, Response) else None

    async def _body(self, request: Request) -> bytes | Response:
        """A POST's body, read within the limits; the refusal when it is too large or too slow."""
        try:
            return await asyncio.wait_for(request.body(), self.settings.timeout_s)
        except BodyTooLarge as exc:
            return _error(413, "body_too_large", detail=str(exc))
        except TimeoutError:
            return _error(
                408,
                "request_timeout",
                detail=f"the request body did not arrive within {self.settings.timeout_s} s",
            )

    async def _forget(self, request: Request) -> Response:
        refused = await self._read_body(request)
        if refused is not None:
            return refused
        source = self._source
        if not isinstance(source, ArmSource):
            return _error(404, "not_found", detail="this source has no arms to forget")
        device = request.path_params["device"]
        try:
            forgotten = await self._call(lambda: source.forget_arm(device))
        except ArmNotFoundError:
            return _error(404, "arm_not_found", device=device, detail="GET /api/fleet lists every arm")
        except ArmNotForgettableError as exc:
            return _error(409, exc.code, device=device, detail=str(exc))
        except ForgetTimedOutError as exc:
            # Not known whether it is forgotten: the request still waits for the arm's mirror.
            return _error(504, "forget_timed_out", device=device, detail=str(exc))
        except WorkerError as exc:
            return _error(503, "worker_unavailable", device=device, detail=f"{exc}; try again once it runs")
        except NotSavedError as exc:
            # Forgotten in memory, but not kept: said as a failure, so nobody takes it for a lasting one.
            return _error(503, "not_saved", device=device, detail=str(exc))
        body = {
            "device": forgotten.device,
            "status": forgotten.status,
            "alarms_removed": forgotten.alarms_removed,
        }
        return JSONResponse(body, headers=SECURITY_HEADERS)

    async def _acknowledge(self, request: Request) -> Response:
        refused = await self._read_body(request)
        if refused is not None:
            return refused
        source = self._source
        if not isinstance(source, AlarmSource):
            return _error(404, "not_found", detail="this source has no alarms")
        alarm_id = alarm_id_of(request.scope)
        try:
            info = await self._call(lambda: source.acknowledge_alarm(alarm_id))
        except AlarmNotFound:
            return _error(404, "alarm_not_found", alarm_id=alarm_id, detail=ALARM_NOT_FOUND_DETAIL)
        except NothingToAcknowledge as exc:
            # Its state with it: NORMAL (cleared) and ACKNOWLEDGED are told apart on the page.
            return _error(409, "nothing_to_acknowledge", alarm_id=alarm_id, state=exc.state, detail=str(exc))
        except WorkerError as exc:
            # /alarms lists a restarting worker's alarms from its checkpoint; only the worker can change one.
            return _error(
                503,
                "worker_unavailable",
                alarm_id=alarm_id,
                detail=f"{exc}; acknowledge again once it runs (GET /state, agent.workers)",
            )
        except NotSavedError as exc:
            # Acknowledged in memory, but not kept: said as a failure, so nobody takes it for a lasting one.
            return _error(503, "not_saved", alarm_id=alarm_id, detail=str(exc))
        return _json(200, AlarmList(alarms=(info,)).to_json())

    async def _acknowledge_many(self, request: Request) -> Response:
        """POST /alarms/ack: every id of the body's list acknowledged as the single endpoint would, each id's
        outcome answered in one 200; a body that is not such a list is refused whole, nothing changed."""
        body = await self._body(request)
        if isinstance(body, Response):
            return body
        source = self._source
        if not isinstance(source, BulkAlarmSource):
            return _error(404, "not_found", detail="this source has no alarms")
        try:
            alarm_ids = bulk_alarm_ids(body)
        except BulkAckError as exc:
            return _error(exc.status, exc.error, detail=str(exc))
        try:
            results = await self._call(lambda: source.acknowledge_alarms(alarm_ids))
        except NotSavedError as exc:
            # Made in memory, but not kept: said as a failure, each id's outcome with it.
            made = cast(tuple[AckResult, ...], exc.result)
            return _error(503, "not_saved", detail=str(exc), **ack_results_json(made))
        return JSONResponse(ack_results_json(results), headers=SECURITY_HEADERS)

    # ------------------------------------------------------------------------------------------ the console

    def _html(self, body: bytes, status_code: int = 200) -> Response:
        return Response(
            body,
            status_code=status_code,
            media_type="text/html; charset=utf-8",
            headers={**SECURITY_HEADERS, "content-security-policy": PAGE_CSP},
        )

    def _page(self, page: str) -> Callable[[Request], Awaitable[Response]]:
        async def serve(request: Request) -> Response:
            return self._html(render_page(page, csrf_token=self.csrf_token, rerun_url=self.rerun_url))

        return serve

    async def _page_arm(self, request: Request) -> Response:
        device = request.path_params["device"]
        return self._html(
            render_page("arm", csrf_token=self.csrf_token, device=device, rerun_url=self.rerun_url)
        )

    async def _alarm_list(self) -> Sequence[AlarmInfo]:
        source = self._source
        if not isinstance(source, AlarmSource):
            return ()
        return await self._call(source.alarms)

    async def _api_fleet(self, request: Request) -> Response:
        rows, notices, listening, held = await self._call(functools.partial(fleet_parts, self._source))
        return _json(200, fleet_summary(rows, time.time(), notices, listening, held=held))

    async def _api_arm(self, request: Request) -> Response:
        device = request.path_params["device"]
        view = await self._call(lambda: arm_view_of(self._source, device))
        # An arm held by its refused calibration has no state but is known: its document says why it is held.
        if view.state is None and not view.calibration_refused:
            return _error(404, "device_not_found", device=device, detail="GET /api/fleet lists every device")
        return _json(200, arm_document(device, view))

    async def _stream_fleet(self, request: Request) -> Response:
        return self._subscribe(FLEET)

    async def _stream_arm(self, request: Request) -> Response:
        return self._subscribe(ARM_PREFIX + request.path_params["device"])

    def _subscribe(self, topic: str) -> Response:
        hub = self._hub
        if hub is None:
            return _error(503, "starting", detail="the server is starting; try again")
        return _EventStream(hub.subscribe(topic), hub.unsubscribe)

    async def _stream_events(self, request: Request) -> Response:
        hub = self._hub
        if hub is None:
            return _error(503, "starting", detail="the server is starting; try again")
        try:
            after = _int_param(request, "after", 0)
        except ValueError as exc:
            return _error(400, "bad_query", detail=str(exc))
        return _EventStream(await hub.subscribe_events(after), hub.unsubscribe)

    async def _query_events(self, request: Request, limit: int) -> tuple[Sequence[Event], bool] | Response:
        """The events the request selects, at most `limit` or its own `limit` (the newest), and whether the
        selection holds more (one more is read to know); or the error to answer."""
        source = self._source
        if not isinstance(source, EventSource):
            return _error(404, "not_found", detail="this source keeps no events")
        try:
            query = event_query(request, limit)
        except ValueError as exc:
            return _error(400, "bad_query", detail=str(exc))
        found = await self._call(lambda: source.events(dataclasses.replace(query, limit=query.limit + 1)))
        more = len(found) > query.limit
        return (found[1:] if more else found), more

    async def _api_events(self, request: Request) -> Response:
        # `last_id` is where a page's stream picks up. The newest id read before the query, so an event
        # stored between the two reads is in the answer or after the cursor; with it, a filter that matches
        # nothing does not send the page back to the start of every other arm's events.
        source = self._source
        newest = await self._call(lambda: newest_event_id(source)) if isinstance(source, EventSource) else 0
        answer = await self._query_events(request, limit=EVENTS_ANSWERED)
        if isinstance(answer, Response):
            return answer
        # `more`: the selection holds more than the answer (its newest are answered). Told, because a
        # selection of exactly the limit looks like a cut one otherwise (the Events page said "the newest
        # 1000" of a selection of 1,000).
        events, more = answer
        last = max(newest, events[-1].id if events else _int_param(request, "after", 0))
        head = b'{"last_id":' + str(last).encode() + b',"more":' + (b"true" if more else b"false")
        device = request.query_params.get("device", "").strip()
        if not events and device and await self._call(lambda: not self._any_event_of(device)):
            note = await self._call(lambda: self._no_event_note(device))
            head += b',"detail":' + json.dumps(note).encode()
        return _json(200, head + b',"events":' + encode_events(events) + b"}")

    def _no_event_note(self, device: str) -> str:
        """Why the agent holds no event of `device` (blocking): a known arm's aged out of the store (telling
        the operator to check the id would be untrue of it), else the id is likely a slip."""
        view = arm_view_of(self._source, device)
        if view.state is not None and not view.state.health.counters.received:
            # Listed in telemetry.devices, or kept for its alarms over a restart: tracked, never heard.
            return (
                f"the agent knows {device!r} (its Arm page) but has had no message of it since it started, "
                "so it holds no event of it yet"
            )
        if view.state is not None or view.calibration_refused:
            return (
                f"the agent knows {device!r} (its Arm page) but holds none of its events any more: they aged "
                "out of the newest [twin] events_capacity it keeps, pushed out by other events (raise it to "
                "keep more), or came before a restart with no [twin] events_file to keep them"
            )
        return (
            f"the agent holds no event of {device!r} at all: check the id against the Fleet page (a "
            "whole one, case-sensitive; device_part= finds part of one)"
        )

    def _any_event_of(self, device: str) -> bool:
        """Whether the source holds any event of `device` (a selection of its that is empty may just be
        narrow; one with none at all names an id the agent does not know: a slip of the id)."""
        source = self._source
        return isinstance(source, EventSource) and bool(source.events(EventQuery(device=device, limit=1)))

    async def _export_events_csv(self, request: Request) -> Response:
        answer = await self._query_events(request, limit=100_000)
        if isinstance(answer, Response):
            return answer
        events, _ = answer
        return Response(
            events_csv(events).encode("utf-8"),
            media_type="text/csv; charset=utf-8",
            headers={**SECURITY_HEADERS, "content-disposition": _attachment("csv")},
        )

    async def _export_events_json(self, request: Request) -> Response:
        answer = await self._query_events(request, limit=100_000)
        if isinstance(answer, Response):
            return answer
        events, _ = answer
        return Response(
            events_json(events),
            media_type=JSON_CONTENT_TYPE,
            headers={**SECURITY_HEADERS, "content-disposition": _attachment("json")},
        )

    # -------------------------------------------------------------------------------------------- sessions

    async def _session_list(self) -> list[SessionInfo]:
        return (await self._sessions_counted())[0]

    async def _sessions_counted(self) -> tuple[list[SessionInfo], float | None]:
        """The sessions with their alarm counts, and the time from which those counts are known."""
        catalog = self._sessions
        if catalog is None:
            return [], None
        now = time.monotonic()
        cached = self._sessions_cache
        if cached is not None and now - cached[0] < SESSIONS_REUSE_S:
            return cached[1], cached[2]
        gap = self.settings.session_gap_s
        listed = await self._call(lambda: catalog.sessions(gap))
        raised, since = await self._alarm_raises()
        wall = time.time()

        def count(s: SessionInfo) -> int | None:
            # Began before the raises are all held from: some of its own may be gone.
            if since is None or s.start < since:
                return None
            return sum(1 for device, t in raised if device == s.device and s.start <= t <= s.end + gap)

        out = [
            SessionInfo(
                device=s.device,
                start=s.start,
                end=s.end,
                messages=s.messages,
                status="active" if wall - s.end <= gap else "completed",
                alarms_raised=count(s),
            )
            for s in listed
        ]
        self._sessions_cache = (now, out, since)
        return out, since

    async def _alarm_raises(self) -> tuple[list[tuple[str, float]], float | None]:
        """Each alarm raise the agent's events hold (device, time), and the time from which those are all
        there were (None: not known, so no count is)."""
        source = self._source
        if not isinstance(source, EventSource) or not isinstance(source, AlarmHorizon):
            return [], None
        query = EventQuery(kinds=frozenset({EventKind.ALARM.value}), limit=EVENTS_READ_FOR_SESSIONS)

        def read() -> tuple[Sequence[Event], float | None]:
            # The events first: an alarm let go of after the read moves the time later, never earlier.
            return source.events(query), source.alarms_complete_from()

        alarms, since = await self._call(read)
        if since is not None and len(alarms) >= EVENTS_READ_FOR_SESSIONS:
            # The read may have left older ones out: not with today's bound on a store (the read takes as
            # many as the largest holds), but counting from them would claim raises never read.
            since = max(since, alarms[0].time)
        raises = [(e.device, e.time) for e in alarms if e.data.get("action") == "raised"]
        return raises, since

    async def _api_sessions(self, request: Request) -> Response:
        sessions, since = await self._sessions_counted()
        body = {
            "history": self._sessions is not None,
            # Of the read the list comes from; a catalog that cannot fail to read has no such attribute.
            "unreadable": getattr(self._sessions, "unreadable", None),
            "gap_s": self.settings.session_gap_s,
            "alarms_known_since": since,
            "kinds": list(SESSION_FILE_KINDS),
            "sessions": [
                {
                    "device": s.device,
                    "key": s.key,
                    "start": s.start,
                    "end": s.end,
                    "duration_s": round(s.end - s.start, 3),
                    "messages": s.messages,
                    "alarms_raised": s.alarms_raised,
                    "status": s.status,
                }
                for s in sessions
            ],
        }
        return JSONResponse(body, headers=SECURITY_HEADERS)

    async def _session_file(self, request: Request) -> Response:
        catalog = self._sessions
        if catalog is None:
            return _error(404, "no_history", detail="history is off: set [history] uri to keep sessions")
        device, start, kind = (request.path_params[k] for k in ("device", "start", "kind"))
        if kind not in SESSION_FILE_KINDS:
            return _error(404, "unknown_kind", kind=kind, kinds=list(SESSION_FILE_KINDS))
        # Not "session_not_found", which sends a person looking for a session that may well exist.
        if not (start.isascii() and start.isdigit()):
            return _error(
                400,
                "bad_session",
                device=device,
                start=start,
                detail=f"session {start!r} is not a session's key: its start in epoch milliseconds, a whole "
                "number such as 1796614097848 (GET /api/sessions gives each session's key)",
            )
        session = next((s for s in await self._session_list() if s.device == device and s.key == start), None)
        if session is None:
            return _error(
                404, "session_not_found", device=device, start=start, detail="GET /api/sessions lists them"
            )
        media_type, ext = SESSION_FILE_KINDS[kind]
        files = self._session_files
        directory = files.directory
        name = f"{_DEVICE_FILE.sub('_', device)}-{session.key}.{ext}"
        lock = self._file_locks.setdefault(name, asyncio.Lock())
        async with lock:
            path = directory / name
            # A completed session's file is made once; an active one grows, so it is made anew each time.
            if not path.is_file() or session.status == "active":
                try:
                    path = await self._call(lambda: catalog.session_file(session, kind, directory))
                except ValueError as exc:
                    return _error(409, "session_file_failed", detail=str(exc))
            files.used(path)
        for gone in files.trim():
            held = self._file_locks.get(gone)
            if held is not None and not held.locked():
                del self._file_locks[gone]
        return FileResponse(path, media_type=media_type, filename=name, headers=SECURITY_HEADERS)


# ----------------------------------------------------------------------------------------------- helpers


def _listen(host: str, port: int) -> socket.socket:
    """The listening socket, made now so a taken address is an error at construction, with the fix."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
        sock = socket.socket(family, kind, proto)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot listen on {host}:{port} ({exc.strerror or exc})") from exc
    try:
        # Port reuse so a restarted agent can bind at once while old sockets sit in TIME_WAIT.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(128)
    except OSError as exc:
        sock.close()
        raise OSError(
            exc.errno,
            f"cannot listen on {host}:{port} ({exc.strerror}); another agent may be running there: "
            "stop it or choose another address with --http HOST:PORT",
        ) from exc
    sock.setblocking(False)
    return sock


def alarm_id_of(scope: Scope) -> str:
    """The alarm id of POST /alarms/<id>/ack from the raw path: `device/joint/kind` as three segments, or as
    one percent-encoded segment (`arm-001%2Fwrist_roll%2Fover_temperature`); each segment is decoded once."""
    raw = bytes(scope.get("raw_path") or scope["path"].encode()).decode("latin-1").split("?", 1)[0]
    inner = raw.rstrip("/").removeprefix("/alarms/").removesuffix("/ack")
    return "/".join(unquote(part) for part in inner.split("/"))


class BulkAckError(ValueError):
    """A body POST /alarms/ack refuses whole: `status` and `error` its answer's, the message what to fix."""

    def __init__(self, status: int, error: str, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.error = error


_BULK_SHAPE = 'a JSON list of alarm ids as GET /alarms lists them, e.g. ["arm-001/elbow_flex/overload"]'


def bulk_alarm_ids(body: bytes) -> tuple[str, ...]:
    """The ids of a POST /alarms/ack body; BulkAckError naming what is wrong and the fix: not JSON, not a
    list, more than ACK_MANY_MAX ids, an id that is not a string, an id twice."""
    try:
        parsed = json.loads(body)
    except (ValueError, RecursionError):
        raise BulkAckError(400, "bad_json", f"the body is not JSON: send {_BULK_SHAPE}") from None
    if not isinstance(parsed, list):
        what = type(parsed).__name__
        raise BulkAckError(400, "not_a_list", f"the body is a JSON {what}: send {_BULK_SHAPE}")
    if len(parsed) > ACK_MANY_MAX:
        raise BulkAckError(
            413,
            "too_many_alarm_ids",
            f"{len(parsed)} alarm ids, at most {ACK_MANY_MAX} per request: send them in chunks of "
            f"{ACK_MANY_MAX} or fewer",
        )
    seen: set[str] = set()
    for i, item in enumerate(parsed):
        if not isinstance(item, str):
            raise BulkAckError(
                400,
                "bad_alarm_id",
                f"item {i} ({json.dumps(item)[:60]}) is not a string: send {_BULK_SHAPE}",
            )
        if item in seen:
            raise BulkAckError(
                400, "duplicate_alarm_id", f"item {i} ({item[:200]!r}) is listed twice: send each id once"
            )
        seen.add(item)
    return tuple(parsed)


def ack_results_json(results: Sequence[AckResult]) -> dict[str, object]:
    """The answer of POST /alarms/ack: each id's outcome, in the order asked, with the alarm's state after
    (None when there is no such alarm), and how many of each outcome."""
    counts = {str(outcome): 0 for outcome in AckOutcome}
    rows: list[dict[str, object]] = []
    for r in results:
        counts[str(r.outcome)] += 1
        row: dict[str, object] = {
            "alarm_id": r.alarm_id,
            "outcome": str(r.outcome),
            "state": r.state,
        }
        if r.detail:
            row["detail"] = r.detail
        rows.append(row)
    return {"results": rows, "counts": counts}


def _int_param(request: Request, name: str, default: int, *, least: int = 0) -> int:
    """A whole-number parameter, `default` when absent; ValueError (a 400 `bad_query`) for one that is not a
    whole number of at least `least`: ignored, `after=xyz` read every event again, and `limit=-1` all."""
    text = request.query_params.get(name, "").strip()
    if not text:
        return default
    if not text.isdigit() or int(text) < least:
        raise ValueError(f"{name} = {text!r} is not a whole number of at least {least}")
    return int(text)


def _float_param(request: Request, name: str) -> float | None:
    text = request.query_params.get(name, "").strip()
    if not text:
        return None
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{name} = {text!r} is not a time in epoch seconds") from None


def event_query(request: Request, limit: int) -> EventQuery:
    """An EventQuery from the query string: device (a whole id), device_part (part of one), level (minimum),
    kind (comma-separated), q (text), since, until (epoch seconds), after (an event id), limit."""
    params = request.query_params
    level = params.get("level", "").strip()
    kinds = frozenset(k.strip() for k in params.get("kind", "").split(",") if k.strip())
    since, until = _float_param(request, "since"), _float_param(request, "until")
    if since is not None and until is not None and until <= since:
        # Selects nothing by mistake (the range's ends swapped): said, not an empty list.
        raise ValueError(f"until ({until}) must be after since ({since})")
    return EventQuery(
        device=params.get("device", "").strip(),
        device_part=params.get("device_part", "").strip(),
        min_level=EventLevel.parse(level) if level else EventLevel.INFO,
        kinds=kinds,
        text=params.get("q", "").strip(),
        since=since,
        until=until,
        after_id=_int_param(request, "after", 0),
        limit=min(limit, _int_param(request, "limit", limit, least=1)),
    )
