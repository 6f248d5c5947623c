"""Reading telemetry history back (polars `scan_delta`): what is there, one device's window, plots, exports.

The table stores what the edge sent (raw readings) and the decoded joint positions; the decoded diagnostics
(velocity in rad/s, load in %, temperature in C, current in A, voltage in V) are exact functions of a raw
reading and the message's units, so they are computed here on read (`with_decoded`) instead of being stored
twice: storing them doubled a day's size (docs/history.md, "Schema"). tests/test_history.py checks that these
expressions give what `twin.core.telemetry` decodes from the same messages.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import json
import logging
import math
import os
import re
import shlex
import sys
import urllib.parse
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import polars as pl

from twin.core import telemetry as tm
from twin.core.topics import case_twin
from twin.output.history import (
    JOINTS,
    PARTITION_COLUMN,
    REJECTED_TABLE,
    TELEMETRY_TABLE,
    check_log,
    object_store_options,
    position_column,
    raw_column,
    table_uri,
)

log = logging.getLogger(__name__)

# A device's rows belong to one session while consecutive messages are at most this far apart: the console's
# default ([http] session_gap_s), so `twin history ls` and the Sessions page count the same sessions.
DEFAULT_SESSION_GAP_S = 30.0
# Any gap longer than this splits no history into sessions: larger ones (`--gap inf`) are taken as this.
MAX_SESSION_GAP_S = 100 * 365.25 * 86400.0
# A plot breaks its lines where messages lie further apart than this: the agent's default offline_after_s,
# after which a silent arm counts as gone, so a line never bridges a time the arm was offline.
PLOT_GAP_S = 10.0
# Plots draw at most this many points per line; longer windows are averaged into equal time buckets.
PLOT_MAX_POINTS = 4000
EXPORT_FORMATS = ("parquet", "csv")
# How many devices a hint for a device with no history names (`devices_hint`): a fleet's 2,000 would bury it.
HINT_DEVICES = 20

_RELATIVE = re.compile(r"^-?(\d+(?:\.\d+)?)\s*(s|m|h|d)$")
_UNIT_S = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}


class HistoryReadError(ValueError):
    """History cannot be read as asked; the message says what to change."""


class NoHistoryTableError(HistoryReadError):
    """No table at the location (nothing recorded there yet), where other read errors mean one is there and
    cannot be read."""


class HistoryArgumentError(HistoryReadError):
    """An argument that cannot select anything (an end before its start, a gap of 0): a bad argument (exit 2),
    where other read errors mean nothing to show or storage unreadable (exit 1)."""


class TimeFormatError(HistoryArgumentError):
    """A time given on the command line is none of the forms `parse_time` takes."""


def parse_time(text: str, *, now: dt.datetime | None = None) -> dt.datetime:
    """A point in time from the command line: ISO 8601 (no zone = UTC), epoch seconds, `now`, or `-2h` /
    `90m` (that long before now)."""
    try:
        return _parse_time(text, now)
    except (OverflowError, ValueError, OSError) as exc:
        if isinstance(exc, TimeFormatError):
            raise
        # Epoch seconds past year 9999, or a span before year 1: a traceback from datetime otherwise.
        raise TimeFormatError(
            f"time {text!r} is out of range ({exc}); give one between the years 1 and 9999"
        ) from None


def _parse_time(text: str, now: dt.datetime | None) -> dt.datetime:
    value = text.strip()
    now = now or dt.datetime.now(dt.UTC)
    if value.lower() == "now":
        return now
    match = _RELATIVE.match(value)
    if match:
        return now - dt.timedelta(seconds=float(match.group(1)) * _UNIT_S[match.group(2)])
    try:
        seconds = float(value)
    except ValueError:
        pass
    else:
        if seconds < 0 and math.isfinite(seconds):
            # Before 1970, no history's time: a span before now missing its unit, which selected everything.
            raise TimeFormatError(
                f"time {text!r} is epoch seconds before 1970, older than any history; for a span before now "
                f"give its unit: {value}m, {value}h or {value}d"
            )
        if math.isfinite(seconds):
            return dt.datetime.fromtimestamp(seconds, dt.UTC)
    try:
        parsed = dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        raise TimeFormatError(
            f"time {text!r} is not understood; use ISO 8601 (2026-11-21T14:00:00Z, no zone means UTC), "
            "epoch seconds, or a span before now such as -2h, 30m, 1d"
        ) from None
    return parsed.replace(tzinfo=dt.UTC) if parsed.tzinfo is None else parsed.astimezone(dt.UTC)


def with_decoded(frame: pl.LazyFrame) -> pl.LazyFrame:
    """Adds the decoded diagnostics next to the raw ones, by the decoder's rules (twin.core.telemetry)."""
    ticks = pl.col("units") == tm.Units.TICKS.value
    exprs = []
    for joint in JOINTS:
        velocity = pl.col(raw_column(joint, "velocity"))
        load = pl.col(raw_column(joint, "load"))
        # Raw ticks carry the velocity register's sign in bit 15 (decode_velocity); LeRobot floats are signed.
        steps = (
            pl.when(ticks & velocity.is_between(32768, 65535)).then(-(velocity - 32768)).otherwise(velocity)
        )
        # decode_load applies to both variants: old LeRobot passes the bit-10 sign through undecoded.
        load_units = pl.when(load.is_between(1024, 2047)).then(-(load - 1024)).otherwise(load)
        exprs += [
            (steps * tm.RAD_PER_STEP_S).alias(f"{joint}_velocity_rad_s"),
            (load_units / tm.LOAD_UNITS_PER_PERCENT).alias(f"{joint}_load_percent"),
            pl.col(raw_column(joint, "temp")).alias(f"{joint}_temperature_c"),
            (pl.col(raw_column(joint, "current")) * tm.CURRENT_MA_PER_UNIT / 1000.0).alias(
                f"{joint}_current_a"
            ),
            (pl.col(raw_column(joint, "voltage")) / tm.VOLTAGE_UNITS_PER_VOLT).alias(f"{joint}_voltage_v"),
        ]
    return frame.with_columns(exprs)


@dataclass
class Session:
    start: dt.datetime
    end: dt.datetime
    rows: int

    @property
    def seconds(self) -> float:
        return (self.end - self.start).total_seconds()

    def as_dict(self) -> dict[str, Any]:
        return {
            "start": iso_utc(self.start),
            "end": iso_utc(self.end),
            "seconds": round(self.seconds, 3),
            "rows": self.rows,
            "rate_hz": round(self.rows / self.seconds, 2) if self.seconds > 0 else None,
        }


@dataclass
class DeviceSummary:
    device_id: str
    rows: int
    first: dt.datetime
    last: dt.datetime
    units: list[str]
    sessions: list[Session] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {
            "device_id": self.device_id,
            "rows": self.rows,
            "first": iso_utc(self.first),
            "last": iso_utc(self.last),
            "units": self.units,
            "sessions": [s.as_dict() for s in self.sessions],
        }


def _time_span(times: pl.Series) -> tuple[dt.datetime, dt.datetime]:
    """The first and last time of a non-empty Datetime column (the history's received_at)."""
    first, last = times.min(), times.max()
    if not isinstance(first, dt.datetime) or not isinstance(last, dt.datetime):
        raise TypeError(f"column {times.name} holds {times.dtype}, not times")
    return first, last


def iso_utc(value: dt.datetime) -> str:
    """A time as the history and replay commands print it: UTC, milliseconds, `Z`."""
    return value.astimezone(dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


# deltalake colours the arrows of its error chain for a terminal: escape codes in a log or a message.
_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _unreadable(location: str, exc: Exception) -> str:
    """Why a table could not be opened; for missing AWS credentials, also how to give this machine some, and
    for a bucket that does not exist, where its name comes from."""
    text = _ANSI.sub("", str(exc))
    if "NoSuchBucket" in text:
        # deltalake's own text is five lines of a failed HTTP GET and S3's XML answer.
        bucket = urllib.parse.urlsplit(location).netloc
        return (
            f"cannot read history at {location}: there is no bucket {bucket!r} (S3: NoSuchBucket); give "
            "--history the stack's HistoryUri output, as docs/getting-started.md prints it"
        )
    if "no credentials found" in text.lower():
        # deltalake's own text is the chain of every provider it tried, twenty lines that name no fix.
        return (
            f"cannot read history at {location}: no AWS credentials found: run `aws configure` or "
            "`aws sso login`, set AWS_PROFILE, or export AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY "
            f"(deltalake: {text})"
        )
    damaged = _damaged_log(location, text)
    if damaged:
        return damaged
    return f"cannot read history at {location}: {text}"


def _damaged_log(location: str, text: str) -> str:
    """For a local table whose log does not open on an entry that is not JSON (a disk's damage, a copy cut
    short): the entries and the fix. deltalake's own text names neither, and ends in a backtrace of
    `<unknown>` frames. "" when that is not the failure, or the walk finds no such entry."""
    if "://" in location or "json error" not in text.lower():
        return ""
    entries = sorted(Path(location, "_delta_log").glob("*.json"))
    bad = []
    for entry in entries:
        try:
            for line in entry.read_text().splitlines():
                if line.strip():
                    json.loads(line)
        except (OSError, ValueError):  # a bad byte is a UnicodeDecodeError, a ValueError too
            bad.append(entry)
    if not bad:
        return ""
    newest = bad == entries[-1:]
    fix = (
        "move it out of _delta_log (elsewhere, to keep it): the table then reads as it was before that "
        "commit, without that commit's rows"
        if newest
        else "put back a whole copy from a backup: the entries after it need it (only a log's newest entry "
        "can be moved out, which reads the table as it was before that commit)"
    )
    first = text.splitlines()[0] if text else ""
    return (
        f"cannot read history at {location}: its log entry {', '.join(map(str, bad[:5]))} is not whole "
        f"JSON ({first}); {fix}"
    )


# polars names an I/O error's cause only in its text ("No space left on device (os error 28)").
_OS_ERROR = re.compile(r"\(os error (\d+)\)")


def _os_errno(exc: BaseException) -> int | None:
    """The errno of an OSError, also of one polars raised with it in the text only."""
    if isinstance(exc, OSError) and exc.errno is not None:
        return exc.errno
    match = _OS_ERROR.search(str(exc))
    return int(match.group(1)) if match else None


# How many damaged files a message names (then "and more").
NAMED_FILES = 5
# The deep walk's findings by table, version and its files' sizes and times: the console's Sessions page
# asks again every 10 s while a table stays damaged, and a deep walk reads every page of every file
# (seconds on a large table). A file put back whole under the same name changes its time.
_DEEP_FOUND: dict[tuple[str, int, int], list[str]] = {}
_DEEP_FOUND_MAX = 8


def _damaged_files(location: str, *, deep: bool = False) -> list[str] | None:
    """The data files of a local table that are missing or not whole Parquet (a footer that does not read,
    or with `deep` any of its pages): what to move out of it. None for a remote table, which is not walked
    (a GET per file). The deep walk stops past the files a message names, and is done once per version."""
    if "://" in location:
        return None
    from deltalake import DeltaTable  # noqa: PLC0415

    table = DeltaTable(location)
    if not deep:
        return _walk(table.file_uris(), deep=False)
    uris = table.file_uris()
    key = (str(Path(location).resolve()), table.version(), hash(tuple(_stamp(uri) for uri in uris)))
    found = _DEEP_FOUND.get(key)
    if found is None:
        found = _walk(uris, deep=True)
        if len(_DEEP_FOUND) >= _DEEP_FOUND_MAX:
            _DEEP_FOUND.clear()
        _DEEP_FOUND[key] = found
    return list(found)


def _local_path(uri: str) -> str:
    # deltalake gives a local file as a URI path: a space in it is `%20`, which no file is named.
    return urllib.parse.unquote(uri.removeprefix("file://"))


def _stamp(uri: str) -> tuple[int, int]:
    try:
        st = os.stat(_local_path(uri))
    except OSError:
        return (-1, -1)
    return (st.st_mtime_ns, st.st_size)


def _walk(uris: list[str], *, deep: bool) -> list[str]:
    import pyarrow as pa  # noqa: PLC0415
    import pyarrow.parquet as pq  # noqa: PLC0415

    bad: list[str] = []
    for uri in uris:
        if deep and len(bad) > NAMED_FILES:
            break  # enough to name, and to say there are more
        path = _local_path(uri)
        try:
            if deep:
                parquet = pq.ParquetFile(path)
                for group in range(parquet.num_row_groups):
                    parquet.read_row_group(group)
            else:
                pq.read_metadata(path)
        except (OSError, ValueError, pa.ArrowException):
            bad.append(path)
    return bad


# What a URL's path keeps as it is (RFC 3986's sub-delims, `:` and `@`): deltalake escapes the rest.
_URL_PATH_SAFE = "/!$&'()*+,:;=@~"


def _escaped(location: str) -> str:
    """The characters of a local path that a file URI escapes (a space is `%20`), quoted; "" if none."""
    if "://" in location:
        return ""
    path = str(Path(location).resolve())
    return " ".join(sorted({repr(c) for c in path if urllib.parse.quote(c, safe=_URL_PATH_SAFE) != c}))


def _unreadable_data(location: str, exc: BaseException) -> str:
    """Why the rows of a table whose log opened could not be read, and what to do."""
    first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    try:
        bad = _damaged_files(location)
        if bad == [] and _os_errno(exc) != errno.ENOENT:
            # Every footer reads, yet a page did not (damage inside a file): read them whole, once, as this
            # error's hint. It said "every data file its log names reads whole now" of a corrupt file.
            bad = _damaged_files(location, deep=True)
    except Exception:  # the walk is a hint; the message stands without it
        bad = None
    escaped = _escaped(location)
    if bad == [] and escaped:
        # polars opens each file at the escaped path deltalake gives it (`a%20b`): it reads no such table.
        return (
            f"cannot read history at {location}: polars reads no table whose path holds a space or another "
            f"character a URI escapes ({escaped}), and found none of its files ({first}): move "
            "the history to a path without one (a symbolic link does not help: polars resolves it)"
        )
    if bad == [] and _os_errno(exc) == errno.ENOENT:
        # Every file of the table's version now reads: the one that went away was replaced meanwhile.
        return (
            f"cannot read history at {location}: a file went away during the read ({first}), and every data "
            "file of the table reads whole now: its maintenance compacted and vacuumed it meanwhile (see "
            "[history] vacuum_retention_hours); run the command again"
        )
    if bad == []:
        return f"cannot read history at {location}: {first} (every data file its log names reads whole now)"
    named = f": {', '.join(bad[:NAMED_FILES])}{' and more' if len(bad) > NAMED_FILES else ''}" if bad else ""
    return (
        f"cannot read history at {location}: a data file its log names is missing or damaged{named} "
        f"({first}). Move a damaged file out of the table, then drop the missing ones from its log: "
        f"{shlex.quote(sys.executable)} -c "
        # Quoted whole: a `'`, `"` or `$` in the path would break the line or be expanded by the shell.
        f"{shlex.quote(f'from deltalake import DeltaTable; print(DeltaTable({location!r}).repair())')} "
        "(their rows are lost unless a copy of the file is put back instead)"
    )


def _a_data_file_failed(exc: BaseException) -> bool:
    """Whether an error of a read is a data file's: gone or unreadable (ENOENT, EIO), not Parquet (polars
    says so in its text), or a Rust panic (what a file cut short gives). Anything else (a missing column,
    a strict cast, expired credentials, an export's full disk) is no file's, and the repair advice wrong."""
    if isinstance(exc, pl.exceptions.PanicException):
        return True
    code = _os_errno(exc)
    if code is not None:
        return code in (errno.ENOENT, errno.EIO)
    text = str(exc).lower()
    return any(word in text for word in ("parquet", "footer", "out of specification"))


@contextlib.contextmanager
def reading(location: str) -> Iterator[None]:
    """Turns what polars raises when a data file the table's log names is missing or damaged (a file removed
    by hand, a copy cut short: a FileNotFoundError, a ComputeError or a Rust panic, deep in `collect`) into
    a HistoryReadError naming the table, the files and what to do, instead of a traceback."""
    try:
        yield
    except (OSError, pl.exceptions.PolarsError, pl.exceptions.PanicException) as exc:
        if _storage_refused(location, exc):
            raise HistoryReadError(
                f"cannot read history at {location}: the storage refused it ({str(exc)[:300]}); refresh "
                "the AWS credentials in use (`aws sts get-caller-identity` names them), then run it again"
            ) from exc
        if not _a_data_file_failed(exc):
            raise
        raise HistoryReadError(_unreadable_data(location, exc)) from exc


def _storage_refused(location: str, exc: BaseException) -> bool:
    """Whether a read of an object store (`location` a URI) failed on its refusal (expired or missing
    credentials, access denied), which polars raises as a ComputeError in the middle of a read."""
    return (
        "://" in location
        and isinstance(exc, pl.exceptions.ComputeError)
        and _REFUSED.search(str(exc)) is not None
    )


# What an object store's refusal says (S3's error codes, HTTP 403), as whole words: a file named part-00403
# is no refusal.
_REFUSED = re.compile(
    r"ExpiredToken|InvalidAccessKeyId|AccessDenied|\bcredentials?\b|\b403\b|Forbidden", re.IGNORECASE
)


def _one_level_off(uri: str, table: str) -> str:
    """For a local --history one level off the directory that holds the tables (the table itself, as
    `pl.scan_delta("<uri>/telemetry")` names it, the demo's out/demo, or the default out/history after only
    `make demo` ran): where the history is."""
    if "://" in uri:
        return ""
    base = Path(uri)
    if (base / "_delta_log").is_dir():
        return f"; {uri} is a table itself: give the directory that holds it, --history {base.parent}"
    below = sorted(str(p.parent.parent) for p in base.glob(f"*/{table}/_delta_log"))
    if below:
        return f"; history lies one level down: --history {' or '.join(below[:3])}"
    # The default out/history after `make demo`, whose history is out/demo/history.
    beside = sorted(str(p.parent.parent) for p in base.parent.glob(f"*/{base.name}/{table}/_delta_log"))
    return f"; there is history at --history {' or '.join(beside[:3])}" if beside else ""


class HistoryReader:
    """Reads the history tables under one base URI (a directory or s3://bucket/prefix)."""

    def __init__(self, uri: str, storage_options: Mapping[str, str] | None = None) -> None:
        self.uri = uri
        self._options = object_store_options(uri, storage_options)

    def _scan(self, table: str) -> pl.LazyFrame:
        from deltalake import DeltaTable  # noqa: PLC0415
        from deltalake.exceptions import TableNotFoundError  # noqa: PLC0415

        location = table_uri(self.uri, table)
        try:
            # Opened here so a missing table is a clear error now rather than a traceback at collect().
            dtable = DeltaTable(location, storage_options=self._options or None)
        except TableNotFoundError as exc:
            raise NoHistoryTableError(
                f"no history table at {location}: nothing was recorded there yet (check --history / "
                f"[history] uri, and that the agent ran with history on){_one_level_off(self.uri, table)}"
            ) from exc
        except Exception as exc:
            raise HistoryReadError(_unreadable(location, exc)) from exc
        del dtable
        # deltalake reads an empty log entry as a commit with no action: that commit's rows were left out of
        # every read without a word.
        empty = check_log(location, parse=False).fix(location)
        if empty:
            raise HistoryReadError(f"cannot read history: {empty}")
        return pl.scan_delta(location, storage_options=self._polars_options() or None)

    def _polars_options(self) -> dict[str, str]:
        # polars parses retry settings itself and refuses object_store's string forms for them.
        return {k: v for k, v in self._options.items() if k not in ("max_retries", "retry_timeout")}

    def scan(self) -> pl.LazyFrame:
        return self._scan(TELEMETRY_TABLE)

    def collect(self, frame: pl.LazyFrame, table: str = TELEMETRY_TABLE) -> pl.DataFrame:
        """`frame.collect()`, a missing or damaged data file of `table` said as a HistoryReadError."""
        with reading(table_uri(self.uri, table)):
            return frame.collect()

    def scan_rejected(self) -> pl.LazyFrame:
        return self._scan(REJECTED_TABLE)

    def window(
        self,
        device: str | None = None,
        since: dt.datetime | None = None,
        until: dt.datetime | None = None,
        *,
        decoded: bool = True,
    ) -> pl.LazyFrame:
        """One device's (or every device's) rows in [since, until), oldest first. The date filter lets
        delta-rs skip whole partitions; the device and time filters reach the Parquet statistics."""
        frame = _selected(self.scan(), device, since, until)
        frame = frame.sort(["device_id", "received_at"] if device is None else ["received_at"])
        return with_decoded(frame) if decoded else frame

    def known_devices(self) -> list[str]:
        """Every device the telemetry table holds rows of (to name them when a device has none)."""
        frame = self.collect(self.scan().select(pl.col("device_id").unique().sort()))
        return [str(d) for d in frame["device_id"]]

    def span(self, device: str | None = None) -> tuple[dt.datetime, dt.datetime] | None:
        """The first and last receive time of `device`'s rows (the table's when None); None without rows."""
        received = pl.col("received_at")
        frame = self.collect(
            self.window(device, None, None, decoded=False).select(
                received.min().alias("first"), received.max().alias("last")
            )
        )
        first, last = frame["first"][0], frame["last"][0]
        if not isinstance(first, dt.datetime) or not isinstance(last, dt.datetime):
            return None
        return first, last

    def summary(
        self,
        *,
        device: str | None = None,
        since: dt.datetime | None = None,
        until: dt.datetime | None = None,
        gap_s: float = DEFAULT_SESSION_GAP_S,
    ) -> list[DeviceSummary]:
        """Devices with their time ranges and sessions (runs without a gap longer than `gap_s`)."""
        if not gap_s > 0:
            raise HistoryArgumentError(f"--gap {gap_s:g} must be greater than 0 seconds")
        frame = self.window(device, since, until, decoded=False).select(["device_id", "received_at", "units"])
        # `--gap inf` (never split) is a fair ask; past a century it means the same, and timedelta overflows.
        gap = dt.timedelta(seconds=min(gap_s, MAX_SESSION_GAP_S))
        runs = self.collect(
            frame.with_columns(
                (pl.col("received_at").diff().over("device_id") > gap).fill_null(True).alias("_new")
            )
            .with_columns(pl.col("_new").cast(pl.Int64).cum_sum().over("device_id").alias("_session"))
            .group_by(["device_id", "_session"])
            .agg(
                pl.col("received_at").min().alias("start"),
                pl.col("received_at").max().alias("end"),
                pl.len().alias("rows"),
                pl.col("units").unique().alias("units"),
            )
            .sort(["device_id", "start"])
        )
        out: dict[str, DeviceSummary] = {}
        for row in runs.iter_rows(named=True):
            summary = out.get(row["device_id"])
            if summary is None:
                summary = out[row["device_id"]] = DeviceSummary(
                    row["device_id"], 0, row["start"], row["end"], []
                )
            summary.rows += row["rows"]
            summary.first = min(summary.first, row["start"])
            summary.last = max(summary.last, row["end"])
            summary.units = sorted(set(summary.units) | set(row["units"]))
            summary.sessions.append(Session(row["start"], row["end"], row["rows"]))
        return list(out.values())

    def rejected_counts(
        self,
        *,
        device: str | None = None,
        since: dt.datetime | None = None,
        until: dt.datetime | None = None,
    ) -> dict[str, int]:
        """Rejected messages by reason, of the same selection as `summary` (a walk found the whole table's
        counts under a one-device, one-hour listing)."""
        try:
            frame = self.scan_rejected()
        except HistoryReadError:
            return {}
        frame = _selected(frame, device, since, until)
        counts = self.collect(frame.group_by("reason").agg(pl.len().alias("n")), REJECTED_TABLE)
        return {r["reason"]: r["n"] for r in counts.iter_rows(named=True)}


def _selected(
    frame: pl.LazyFrame, device: str | None, since: dt.datetime | None, until: dt.datetime | None
) -> pl.LazyFrame:
    """`frame`'s rows of `device` (None: all) received in [since, until); an end not after its start selects
    nothing by mistake, so it is refused (as `twin replay` refuses it)."""
    if since is not None and until is not None and until <= since:
        raise HistoryArgumentError(
            f"--until ({iso_utc(until)}) must be after --since ({iso_utc(since)}); nothing lies between them"
        )
    if device is not None:
        frame = frame.filter(pl.col("device_id") == device)
    if since is not None:
        frame = frame.filter(
            (pl.col(PARTITION_COLUMN) >= since.astimezone(dt.UTC).date()) & (pl.col("received_at") >= since)
        )
    if until is not None:
        frame = frame.filter(
            (pl.col(PARTITION_COLUMN) <= until.astimezone(dt.UTC).date()) & (pl.col("received_at") < until)
        )
    return frame


# --- export ------------------------------------------------------------------------------------------------


def export(
    reader: HistoryReader,
    out: Path,
    fmt: str,
    *,
    device: str | None = None,
    since: dt.datetime | None = None,
    until: dt.datetime | None = None,
    decoded: bool = True,
) -> int:
    """Write the selected rows to one Parquet or CSV file (streamed); returns the row count. Written beside
    `out` and renamed over it once whole: an interrupted or failed export leaves `out` as it was, never a
    file that looks complete and is not. No row: nothing written (HistoryReadError)."""
    if fmt not in EXPORT_FORMATS:
        raise HistoryArgumentError(f"--format {fmt!r} is not one of {', '.join(EXPORT_FORMATS)}")
    _not_a_directory(out, fmt)
    frame = reader.window(device, since, until, decoded=decoded)
    with written_whole(out) as partial:
        with reading(table_uri(reader.uri, TELEMETRY_TABLE)):
            if fmt == "parquet":
                frame.sink_parquet(partial, compression="zstd")
            else:
                frame.sink_csv(partial)
        if fmt == "parquet":
            rows = pl.scan_parquet(partial).select(pl.len()).collect().item()
        else:
            rows = pl.scan_csv(partial).select(pl.len()).collect().item()
        if not rows:
            hint = empty_hint(reader, device)
            raise HistoryReadError(
                f"no rows in this selection, so nothing was written (see `twin history ls`{hint})"
            )
    return int(rows)


@contextlib.contextmanager
def written_whole(out: Path) -> Iterator[Path]:
    """Where to write `out`: a hidden file beside it (so the rename is atomic), renamed over it once the block
    ends without an error, so an interrupted or failed write leaves `out` as it was, never a cut file that
    looks whole. A write's own failure naming no file (a full disk, as polars and PIL raise it) or naming
    that hidden one is raised again with `out` as its file, so `twin` says which path and the fix
    (twin.cli.main.path_error_message)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(f".{out.name}.partial-{os.getpid()}")
    try:
        yield partial
        os.replace(partial, out)
    except (OSError, pl.exceptions.PolarsError) as exc:
        # sink_parquet's full disk is a ComputeError, its errno in its text only.
        code = _os_errno(exc)
        named = getattr(exc, "filename", None)
        # Only a write's own failures: a read's (too many open files, a data file refused) is no --out's.
        ours = str(named) == str(partial) if named is not None else code in _WRITE_ERRNOS
        if code is None or not ours:
            raise
        raise OSError(code, os.strerror(code), str(out)) from exc
    finally:
        partial.unlink(missing_ok=True)


# What writing a file fails on whatever is read: the disk full, over quota, the file too big, read-only.
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS})


def _not_a_directory(out: Path, extension: str) -> None:
    """`--out` names a file to write (plot's and export's), not a folder to write into."""
    if out.is_dir():
        raise HistoryArgumentError(
            f"--out {out} is a directory; give a file name, e.g. {out / f'history.{extension}'}"
        )


def empty_hint(reader: HistoryReader, device: str | None) -> str:
    """Why a selection holds no row: a device with none at all (`devices_hint`), else the time its rows (or
    the table's) span, so a window that missed them, or a clock taken for UTC, shows at once."""
    hint = devices_hint(reader, device)
    if hint:
        return hint
    span = reader.span(device)
    if span is None:
        return _EMPTY_TABLE
    whose = f"{device}'s rows" if device else "its rows"
    return f"; {whose} span {iso_utc(span[0])} .. {iso_utc(span[1])}"


# A table whose rows were all deleted: "devices with history are none" read like a mistyped --device.
_EMPTY_TABLE = "; the table holds no row of any device now (keep_days, or a delete, removed them)"


def devices_hint(reader: HistoryReader, device: str | None) -> str:
    """For a device with no row at all: the one whose id differs in case alone, else the devices there are (a
    mistyped id reads like an empty hour), the first HINT_DEVICES of a large fleet and a count of the rest."""
    if device is None:
        return ""
    known = reader.known_devices()
    if device in known:
        return ""
    if not known:
        return _EMPTY_TABLE
    twin = case_twin(device, known)
    if twin is not None:
        return f"; no row of {device!r} at all: device ids are case-sensitive, and {twin!r} has history"
    named = ", ".join(known[:HINT_DEVICES])
    more = f" and {len(known) - HINT_DEVICES} more" if len(known) > HINT_DEVICES else ""
    return f"; no row of {device!r} at all: devices with history are {named}{more}"


# --- plot --------------------------------------------------------------------------------------------------


def _downsample(frame: pl.DataFrame, max_points: int) -> tuple[pl.DataFrame, float | None]:
    if frame.height <= max_points:
        return frame, None
    first, last = _time_span(frame["received_at"])
    span = (last - first).total_seconds()
    bucket_s = max(0.1, span / max_points)
    every = f"{max(1, round(bucket_s * 1000))}ms"
    numeric = [c for c, t in frame.schema.items() if t.is_numeric()]
    sampled = (
        frame.sort("received_at")
        .group_by_dynamic("received_at", every=every)
        .agg([pl.col(c).mean() for c in numeric])
    )
    return sampled, bucket_s


# The plot's panels: a label and the column suffix after each joint's name.
_PANELS = (
    ("joint angle (deg)", ""),
    ("temperature (C)", "_temperature_c"),
    ("load (%)", "_load_percent"),
    ("current (A)", "_current_a"),
)


def _segments(sampled: pl.DataFrame, gap_s: float) -> list[pl.DataFrame]:
    """The rows split where consecutive samples lie more than `gap_s` apart (a pause, a restart), so lines
    break across gaps instead of bridging them."""
    breaks = sampled["received_at"].diff().dt.total_seconds().fill_null(0.0) > gap_s
    marked = sampled.with_columns(breaks.cast(pl.Int64).cum_sum().alias("_segment"))
    return marked.partition_by("_segment", maintain_order=True)


def _draw_panel(
    ax: Any, parts: list[pl.DataFrame], columns: list[str], colors: list[str], sampled: pl.DataFrame
) -> None:
    """One line per joint column (one colour per joint), drawn segment by segment; absent columns skipped."""
    for i, (joint, column) in enumerate(zip(JOINTS, columns, strict=True)):
        if column not in sampled.columns or sampled[column].null_count() == sampled.height:
            continue
        for k, part in enumerate(parts):
            ax.plot(
                part["received_at"].to_list(),
                part[column].to_list(),
                color=colors[i % len(colors)],
                linewidth=0.8,
                label=joint if k == 0 else None,
            )
    ax.grid(True, alpha=0.3)


def plot(
    reader: HistoryReader,
    device: str,
    out: Path,
    *,
    since: dt.datetime | None = None,
    until: dt.datetime | None = None,
    gap_s: float = PLOT_GAP_S,
    max_points: int = PLOT_MAX_POINTS,
) -> dict[str, Any]:
    """Joint angles, temperature, load and current of one device on a shared time axis, as a PNG."""
    import matplotlib  # noqa: PLC0415 - heavy; only this command draws

    matplotlib.use("Agg")
    import matplotlib.dates as mdates  # noqa: PLC0415
    import matplotlib.pyplot as plt  # noqa: PLC0415

    _not_a_directory(out, "png")
    frame = reader.collect(reader.window(device, since, until))
    if frame.height == 0:
        window = (
            f" between {iso_utc(since) if since else 'the start'} and {iso_utc(until) if until else 'now'}"
        )
        # As ls and export say it: a case twin, or the first of a fleet's devices, not all 2,000 of them.
        hint = empty_hint(reader, device)
        raise HistoryReadError(f"no history rows for device {device!r}{window}{hint} (see `twin history ls`)")
    rows = frame.height
    frame = frame.with_columns([(pl.col(position_column(j)) * (180.0 / math.pi)).alias(j) for j in JOINTS])
    sampled, bucket_s = _downsample(frame, max_points)
    parts = _segments(sampled, max(gap_s, 3.0 * (bucket_s or 0.0)))
    fig, axes = plt.subplots(len(_PANELS), 1, sharex=True, figsize=(12, 10), dpi=100)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, (label, suffix) in zip(axes, _PANELS, strict=True):
        _draw_panel(ax, parts, [f"{joint}{suffix}" for joint in JOINTS], colors, sampled)
        ax.set_ylabel(label)
    handles, labels = axes[0].get_legend_handles_labels()
    unique = dict(zip(labels, handles, strict=False))
    fig.legend(
        unique.values(), unique.keys(), loc="upper center", bbox_to_anchor=(0.5, 0.965), ncol=len(JOINTS)
    )
    first, last = _time_span(frame["received_at"])
    note = f", mean per {bucket_s:.1f} s" if bucket_s else ""
    locator = mdates.AutoDateLocator()
    axes[-1].xaxis.set_major_locator(locator)
    axes[-1].xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))
    axes[-1].set_xlabel("received at (UTC)")
    fig.suptitle(f"{device}: {rows} messages, {iso_utc(first)} .. {iso_utc(last)}{note}", y=0.99, fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    try:
        with written_whole(out) as partial:  # a full disk left a cut PNG where the old one was (--force)
            fig.savefig(partial, format="png")  # format given: without it, `--out x` wrote x.png
    finally:
        plt.close(fig)
    return {
        "device_id": device,
        "rows": rows,
        "first": iso_utc(first),
        "last": iso_utc(last),
        "path": str(out),
    }
