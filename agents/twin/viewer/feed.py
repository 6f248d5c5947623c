"""The viewer's link to the agent: reads the SSE `/stream` into a `FleetView`, falling back to polling
`/state` when the stream is unavailable, and retries forever while the agent is unreachable. Never touches
MuJoCo.
"""

from __future__ import annotations

import contextlib
import http.client
import logging
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterable, Iterator

from twin.viewer.config import ViewerConfig
from twin.viewer.fleet import LINK_POLLING, LINK_STREAM, LINK_UNREACHABLE, FleetView

log = logging.getLogger(__name__)

Clock = Callable[[], float]


def iter_sse_events(lines: Iterable[bytes]) -> Iterator[tuple[str, str]]:
    """(event name, data) of each Server-Sent Event in a line stream: the name "message" when the event
    gives none (the SSE default), multi-line data joined by newlines."""
    data: list[str] = []
    event = "message"
    for raw in lines:
        line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
        if not line:
            if data:
                yield event, "\n".join(data)
                data = []
            event = "message"
            continue
        if line.startswith(":"):
            continue  # comment / keep-alive
        field, _, value = line.partition(":")
        if field == "data":
            data.append(value.removeprefix(" "))
        elif field == "event":
            event = value.removeprefix(" ")


def iter_sse_data(lines: Iterable[bytes]) -> Iterator[str]:
    """The `data` payload of each Server-Sent Event in a line stream (multi-line data joined by newlines)."""
    for _, data in iter_sse_events(lines):
        yield data


def describe_error(exc: BaseException) -> str:
    """A short human reason for a connection problem (the overlay has one line for it)."""
    reason = getattr(exc, "reason", None)
    if isinstance(exc, urllib.error.HTTPError):
        return f"HTTP {exc.code} {exc.reason}"
    if isinstance(reason, BaseException):
        exc = reason
    elif isinstance(reason, str):
        return reason
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused"
    if isinstance(exc, TimeoutError):
        return "timed out"
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


class AgentFeed:
    """Background reader of the agent's live state into a FleetView; retries forever, never raises.

    With `wanted` (the device the window shows, None before one is chosen) it reads that one arm and the
    fleet's ids (`/stream?device=`), and reconnects when the choice changes: the agent then builds one arm's
    view per frame, not its whole state (docs/viewer.md). Without it, or from an agent that sends its whole
    state anyway, every device comes in every frame."""

    def __init__(
        self,
        config: ViewerConfig,
        fleet: FleetView,
        clock: Clock = time.monotonic,
        wanted: Callable[[], str | None] | None = None,
    ) -> None:
        self.config = config
        self.fleet = fleet
        self._clock = clock
        self._wanted = wanted
        self._base = config.agent_url.rstrip("/")
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._response: http.client.HTTPResponse | None = None

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="twin-view-feed", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        response = self._response
        if response is not None:
            with contextlib.suppress(Exception):
                response.close()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def _run(self) -> None:
        backoff = self.config.retry_s
        while not self._stop.is_set():
            try:
                self._read_stream()
                backoff = self.config.retry_s
                continue  # the agent closed the stream (restart?): reconnect at once
            except (OSError, http.client.HTTPException, ValueError) as exc:
                stream_error = describe_error(exc)
            if self._stop.is_set():
                break
            try:
                self._poll(stream_error)
                backoff = self.config.retry_s
            except (OSError, http.client.HTTPException, ValueError) as exc:
                self.fleet.set_link(LINK_UNREACHABLE, describe_error(exc))
                self._stop.wait(backoff)
                backoff = min(backoff * 2.0, self.config.max_retry_s)
        log.debug("agent feed stopped")

    def _open(self, path: str) -> http.client.HTTPResponse:
        request = urllib.request.Request(self._base + path, headers={"Accept": "text/event-stream"})
        return urllib.request.urlopen(request, timeout=self.config.read_timeout_s)

    def _read_stream(self) -> None:
        wanted = self._wanted
        asked = wanted() if wanted is not None else None
        path = "/stream" if wanted is None else "/stream?device=" + urllib.parse.quote(asked or "", safe="")
        response = self._open(path)
        self._response = response
        try:
            content_type = response.headers.get("Content-Type", "")
            if "text/event-stream" not in content_type:
                raise ValueError(f"/stream answered {content_type or 'no content type'}, not an SSE stream")
            try:
                for event, data in iter_sse_events(response):
                    if self._stop.is_set():
                        return
                    if event == "device":
                        self.fleet.update_view_json(data, self._clock())
                    else:
                        self.fleet.update_json(data, self._clock())
                    if self.fleet.link != LINK_STREAM:
                        self.fleet.set_link(LINK_STREAM)
                    if wanted is not None and wanted() != asked:
                        return  # another device chosen: ask for it (the caller reconnects at once)
            except AttributeError:
                # stop() closed the response under this read: http.client, in the middle of a chunked
                # body (the agent's stream is chunked), then reads from a file it has already dropped.
                if self._stop.is_set():
                    return
                raise
        finally:
            self._response = None
            response.close()

    def _poll(self, stream_error: str) -> None:
        """Poll /state until it is time to try the stream again; raises when the agent is unreachable."""
        deadline = self._clock() + self.config.stream_retry_s
        interval = 1.0 / self.config.poll_hz
        while not self._stop.is_set() and self._clock() < deadline:
            with self._open("/state") as response:
                document = response.read()
            self.fleet.update_json(document, self._clock())
            if self.fleet.link != LINK_POLLING:
                self.fleet.set_link(LINK_POLLING, f"stream: {stream_error}")
            self._stop.wait(interval)
