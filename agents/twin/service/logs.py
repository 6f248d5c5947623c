"""JSON-lines logging for the agent: one object per line on stdout, which journald and CloudWatch keep as is.

Each line has `ts` (UTC, ISO 8601 with milliseconds), `level`, `logger`, `msg`, plus every field passed with
`extra={...}` and, for exceptions, `exc` (the formatted traceback). Nothing is buffered: systemd sees each
line as it happens, and a crash leaves the lines before it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import logging
import math
import sys
import threading
import time
import traceback
from collections import OrderedDict
from typing import Any, TextIO

_PR_SET_NAME = 15


def thread_stack(thread: threading.Thread | None) -> str:
    """Where `thread` is now, as a traceback prints it ("" when it does not run): where a stuck one waits."""
    frame = None if thread is None or thread.ident is None else sys._current_frames().get(thread.ident)
    return "" if frame is None else "".join(traceback.format_stack(frame))


def name_native_thread() -> None:
    """Give the calling thread's Python name to the OS thread too (Linux: 15 bytes), so `top -H`, /proc and
    `twin bench cost` can tell the agent's threads apart (CPython 3.11 leaves them all "python"). Does
    nothing where it cannot."""
    name = threading.current_thread().name.encode("ascii", "replace")[:15]
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(_PR_SET_NAME, ctypes.c_char_p(name), 0, 0, 0)
    except (OSError, AttributeError):
        return


# Attributes every LogRecord has; anything else on a record came from `extra=` and is emitted as a field.
_RECORD_ATTRS = frozenset(vars(logging.LogRecord("", 0, "", 0, "", None, None))) | {
    "message",
    "asctime",
    "taskName",
}


def _jsonable(value: Any) -> Any:
    if isinstance(value, str | int | float | bool) or value is None:
        return value
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [_jsonable(v) for v in value]
    return str(value)


class JsonLinesFormatter(logging.Formatter):
    """Formats a record as one JSON object on one line (newlines in messages are escaped by JSON)."""

    def format(self, record: logging.LogRecord) -> str:
        ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
        out: dict[str, Any] = {
            "ts": f"{ts}.{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        for key, value in vars(record).items():
            if key not in _RECORD_ATTRS and not key.startswith("_"):
                out[key] = _jsonable(value)
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, ensure_ascii=False, allow_nan=True)


class _FlushingHandler(logging.StreamHandler[TextIO]):
    """Looks up the stream at emit time so pytest's capture and a replaced sys.stdout both work."""

    def __init__(self, stream: TextIO | None = None) -> None:
        super().__init__(stream)
        self._explicit = stream is not None

    def emit(self, record: logging.LogRecord) -> None:
        if not self._explicit:
            self.stream = sys.stdout
        super().emit(record)


_HANDLER_MARK = "_twin_json_handler"


def setup_logging(level: str = "INFO", stream: TextIO | None = None) -> None:
    """Route every logger to JSON lines on stdout (or `stream`) at `level`; calling it again replaces it."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        if getattr(handler, _HANDLER_MARK, False):
            root.removeHandler(handler)
    handler = _FlushingHandler(stream)
    setattr(handler, _HANDLER_MARK, True)
    handler.setFormatter(JsonLinesFormatter())
    root.addHandler(handler)
    root.setLevel(level.upper())
    # Third-party chatter that uses logging (botocore) is held at WARNING so it does not drown the agent's
    # lines at DEBUG.
    for noisy in ("botocore", "boto3", "urllib3"):
        logging.getLogger(noisy).setLevel(max(logging.WARNING, root.level))


class RateLimitedLog:
    """Logs at most one line per key per interval, and at most `max_lines` per interval in all, and counts
    what it held back.

    A flood of malformed messages must not become a flood of log lines: the first rejection of a kind is
    logged at once, later ones are summarised as `suppressed` on the next line allowed for that key. Keys
    come from the network (device ids from topics), so a publisher inventing a new device id for every
    message would get a line each through a per-key limit alone: the overall budget holds those back too
    (their count is `suppressed_elsewhere` on the next line that goes out), and the per-key tables keep at
    most `max_keys` keys, the most recent.
    """

    def __init__(
        self,
        logger: logging.Logger,
        interval_s: float = 10.0,
        clock: Any = time.monotonic,
        *,
        max_lines: int = 50,
        max_keys: int = 1024,
    ) -> None:
        self._logger = logger
        self._interval = interval_s
        self._clock = clock
        self._max_lines = max_lines
        self._max_keys = max_keys
        self._last: OrderedDict[Any, float] = OrderedDict()
        self._suppressed: OrderedDict[Any, int] = OrderedDict()
        self._window_start = -math.inf
        self._window_lines = 0
        # Held back by the overall budget, or suppressed under a key that was since pushed out of the tables.
        self._elsewhere = 0

    def log(self, key: Any, level: int, msg: str, *args: Any, exc_info: bool = False, **fields: Any) -> bool:
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self._interval:
            self._count(self._suppressed, key)
            return False
        if now - self._window_start >= self._interval:
            self._window_start, self._window_lines = now, 0
        if self._window_lines >= self._max_lines:
            self._elsewhere += 1
            return False
        self._window_lines += 1
        self._last[key] = now
        self._last.move_to_end(key)
        if len(self._last) > self._max_keys:
            self._last.popitem(last=False)
        suppressed = self._suppressed.pop(key, 0)
        extra = {**fields, "suppressed": suppressed}
        if self._elsewhere:
            extra["suppressed_elsewhere"], self._elsewhere = self._elsewhere, 0
        self._logger.log(level, msg, *args, exc_info=exc_info, extra=extra)
        return True

    def _count(self, table: OrderedDict[Any, int], key: Any) -> None:
        table[key] = table.get(key, 0) + 1
        table.move_to_end(key)
        if len(table) > self._max_keys:
            _, count = table.popitem(last=False)
            self._elsewhere += count

    @property
    def keys(self) -> int:
        """Keys the limiter remembers (bounded by max_keys in each of its tables)."""
        return max(len(self._last), len(self._suppressed))
