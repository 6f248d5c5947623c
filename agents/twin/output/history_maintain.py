"""History maintenance in a short-lived process of its own: `python -m twin.output.history_maintain`.

The history writer (twin.output.history.HistoryWriter._maintain says why) starts it, writes one JSON request
to its stdin (the writer's settings, its id for the maintenance lease, the UTC day) and waits. The process
compacts, checkpoints and vacuums as the writer would have on its own thread, then exits, which returns
every page the compaction took to the system. Its stdout is JSON lines: its log records (the writer logs
them again, so they reach the agent's log as if written there) and, last, `{"result": {...}}` with the
maintenance counters the writer adds to its own. A process that exits otherwise (a crash, a kill, a
timeout) is one maintenance failure in the writer's figures.

A plain subprocess, not multiprocessing: a fresh interpreter imports nothing of its parent's __main__, so
whatever script embeds the writer, nothing of it runs again here.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

log = logging.getLogger(__name__)

# Attributes every LogRecord has; anything else on a record is an `extra` field worth forwarding.
_STANDARD = frozenset(logging.makeLogRecord({}).__dict__) | {"message", "asctime"}
_POLL_S = 0.5


class _Forward(logging.Handler):
    """Writes each record as one JSON line to stdout for the writer to log again."""

    def emit(self, record: logging.LogRecord) -> None:
        extra = {
            k: v
            for k, v in record.__dict__.items()
            if k not in _STANDARD and isinstance(v, str | int | float | bool | type(None))
        }
        line = {"log": {"name": record.name, "level": record.levelno, "msg": record.getMessage()}}
        # Which process wrote it: the record is logged again by the writer, under the writer's pid.
        line["log"]["extra"] = {**extra, "maintenance_pid": os.getpid()}
        sys.stdout.write(json.dumps(line) + "\n")
        sys.stdout.flush()


def main() -> int:
    from twin.output.history import HistorySettings, HistoryWriter, remember_clock_warnings  # noqa: PLC0415

    # The writer process ignores SIGTERM (its last commit must not be cut short) and exec keeps that: take
    # the default back, so the writer can stop this process at shutdown.
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    root = logging.getLogger()
    root.handlers[:] = [_Forward()]
    root.setLevel(logging.INFO)
    request = json.loads(sys.stdin.read())
    asked_at = float(request.get("wall", time.time()))
    remember_clock_warnings(request.get("clock_warned", {}))
    writer = HistoryWriter(
        HistorySettings(**request["settings"]), writer_id=request["writer_id"], wall_clock=lambda: asked_at
    )
    writer.maintain_here(dt.date.fromisoformat(request["today"]))
    sys.stdout.write(json.dumps({"result": writer.maintenance_result()}) + "\n")
    return 0


def _relog(line: str) -> dict[str, Any] | None:
    """Log a forwarded record again here; return the result if `line` is the result."""
    try:
        message = json.loads(line)
    except ValueError:
        log.warning("history maintenance process: %s", line.strip()[:400])
        return None
    if "result" in message:
        result: dict[str, Any] = message["result"]
        return result
    record = message.get("log", {})
    logging.getLogger(str(record.get("name", __name__))).log(
        int(record.get("level", logging.INFO)), "%s", record.get("msg", ""), extra=record.get("extra") or {}
    )
    return None


def run_child(
    command: Sequence[str],
    request: dict[str, Any],
    *,
    timeout_s: float,
    stop: Callable[[], bool] | None = None,
) -> dict[str, Any] | None:
    """Run the maintenance process and return its result; None when `stop()` turned true and it was stopped.
    Raises RuntimeError when it failed (exit code, no result) or ran over `timeout_s` (it is killed)."""
    child = subprocess.Popen(list(command), stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    deadline = time.monotonic() + timeout_s
    data: str | None = json.dumps(request)
    while True:
        try:
            out, _ = child.communicate(data, timeout=_POLL_S)
            break
        except subprocess.TimeoutExpired:
            data = None  # written already: communicate() must not be given it again
            if stop is not None and stop():
                _end(child)
                return None
            if time.monotonic() >= deadline:
                _end(child)
                raise RuntimeError(f"still running after {timeout_s:.0f} s; stopped") from None
    result = None
    for line in out.splitlines():
        if line.strip():
            result = _relog(line) or result
    if child.returncode != 0 or result is None:
        raise RuntimeError(f"exit code {child.returncode} without a result")
    return result


def _end(child: subprocess.Popen[str]) -> None:
    child.terminate()
    try:
        child.communicate(timeout=5.0)
    except subprocess.TimeoutExpired:
        child.kill()
        child.communicate()


if __name__ == "__main__":
    sys.exit(main())
