"""Telemetry history: every applied and rejected message appended to Delta Lake tables (delta-rs).

Two tables live under one base URI (a local directory or `s3://bucket/prefix`):
  <uri>/telemetry  one row per applied message: device, edge and receive time, units, and per joint the raw
                   readings exactly as sent plus the decoded position (docs/history.md lists the columns);
  <uri>/rejected   one row per rejected message: receive time, topic, device if known, reason, detail and
                   the payload's first bytes.
Both are partitioned by the UTC date of the receive time (not by device: a fleet would make thousands of
tiny partitions), sorted by device and time inside each file.

Threads and memory. The agent's worker hands samples to a `QueuedSink` (bounded queue, its own thread, see
twin.output.sinks). On that thread `HistoryWorker` only collects samples and turns each chunk of a few
thousand into an Arrow table: the raw readings come from parsing the chunk's payloads in Arrow's C++ JSON
reader, which does not hold the GIL, so the mirror's threads are barely touched. The Arrow tables go to
`HistoryWriter`, whose committer thread appends them to Delta every `commit_every_s` seconds or
`commit_every_rows` rows and runs compaction, checkpoints and vacuum on a schedule. Rows waiting for a
commit are bounded (`max_buffer_rows`): when storage is down or the disk is full the writer logs a clear
error, keeps retrying with backoff, and, if the outage outlasts the buffer, drops the oldest rows and counts
them. Nothing here raises into the twin.

Each commit carries a Delta app transaction (writer id, sequence number), so a commit whose outcome was lost
(a timeout after S3 accepted it) is recognised on retry instead of being written twice. Several writers may
append to one table: delta-rs commits with put-if-absent (a local rename, a conditional PUT on S3) and
retries an append that lost the race.
"""

from __future__ import annotations

import collections
import dataclasses
import datetime as dt
import errno
import importlib.util
import io
import json
import logging
import math
import operator
import os
import shlex
import socket
import sys
import threading
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.json as pa_json

from twin.core import heap
from twin.core.aws import region_or_env
from twin.core.locations import location_problem
from twin.core.throttle import Throttle
from twin.output.history_feed import REJECTED_PAYLOAD_MAX_BYTES, REJECTED_TABLE, TELEMETRY_TABLE
from twin.output.history_maintain import run_child
from twin.output.sinks import AppliedSample, QueuedSink, RejectedSample
from twin.robot import so101

log = logging.getLogger(__name__)

PARTITION_COLUMN = "date"
JOINTS: tuple[str, ...] = so101.JOINT_NAMES
# Per-joint fields of an edge message, stored exactly as sent (float64 holds every tick count exactly).
RAW_FIELDS: tuple[str, ...] = ("position", "velocity", "load", "temp", "current", "voltage")
MS_PER_DAY = 86_400_000


def raw_column(joint: str, name: str) -> str:
    return f"{joint}_{name}_raw"


def position_column(joint: str) -> str:
    return f"{joint}_position_rad"


def telemetry_schema() -> pa.Schema:
    fields = [
        pa.field(PARTITION_COLUMN, pa.date32(), nullable=False),
        pa.field("received_at", pa.timestamp("ms", tz="UTC"), nullable=False),
        pa.field("edge_time", pa.timestamp("ms", tz="UTC"), nullable=False),
        pa.field("device_id", pa.string(), nullable=False),
        pa.field("units", pa.string(), nullable=False),
    ]
    for joint in JOINTS:
        fields.append(pa.field(position_column(joint), pa.float64()))
        fields.extend(pa.field(raw_column(joint, name), pa.float64()) for name in RAW_FIELDS)
    return pa.schema(fields)


def rejected_schema() -> pa.Schema:
    return pa.schema(
        [
            pa.field(PARTITION_COLUMN, pa.date32(), nullable=False),
            pa.field("received_at", pa.timestamp("ms", tz="UTC"), nullable=False),
            pa.field("topic", pa.string(), nullable=False),
            pa.field("device_id", pa.string()),
            pa.field("reason", pa.string(), nullable=False),
            pa.field("detail", pa.string(), nullable=False),
            pa.field("payload", pa.binary(), nullable=False),
            pa.field("payload_bytes", pa.int64(), nullable=False),
        ]
    )


TELEMETRY_SCHEMA = telemetry_schema()
REJECTED_SCHEMA = rejected_schema()
SCHEMAS: dict[str, pa.Schema] = {TELEMETRY_TABLE: TELEMETRY_SCHEMA, REJECTED_TABLE: REJECTED_SCHEMA}

# What Arrow's JSON reader extracts from a payload; anything else in it (status, moving, padding) is ignored.
_JOINT_STRUCT = pa.struct([pa.field(name, pa.float64()) for name in RAW_FIELDS])
_PAYLOAD_SCHEMA = pa.schema([pa.field("joints", pa.struct([pa.field(j, _JOINT_STRUCT) for j in JOINTS]))])
_PARSE_OPTIONS = pa_json.ParseOptions(explicit_schema=_PAYLOAD_SCHEMA, unexpected_field_behavior="ignore")
_ANGLES = operator.itemgetter(*JOINTS)


class HistoryError(ValueError):
    """A history setting is invalid; the message names it and the fix."""


class HistoryLogError(HistoryError):
    """A local table's log holds an entry that is empty or not whole JSON; the message says which, and the
    fix."""


# Where the writer moves a table's newest log entry that is empty: beside the log, never deleted.
SET_ASIDE_DIR = "_delta_log_set_aside"
# The one line a log entry needs to be a commit with no action (a fix the error offers for an empty entry).
NO_ACTION_ENTRY = '{"commitInfo":{}}'


@dataclass(frozen=True)
class LogCheck:
    """A local table's log entries after its last checkpoint that it cannot read whole (a checkpoint holds
    everything before it): empty ones (zero bytes, blanks or NUL bytes) and ones that are not whole JSON."""

    empty: tuple[Path, ...] = ()
    broken: tuple[Path, ...] = ()
    newest: Path | None = None

    @property
    def trailing_empty(self) -> tuple[Path, ...]:
        """The empty entries that are the log's newest ones, a run with no whole entry after it, newest
        first: commits cut short, holding nothing. A power loss can leave several so (ext4 writes a file's
        blocks late; XFS can leave them all NUL bytes)."""
        if self.newest is None:
            return ()
        newest = int(self.newest.stem)
        run: list[Path] = []
        for entry in sorted(self.empty, reverse=True):
            if int(entry.stem) != newest - len(run):
                break
            run.append(entry)
        return tuple(run)

    @property
    def newest_empty_only(self) -> bool:
        """Whether the only damage is a trailing run of empty entries (`trailing_empty`)."""
        return bool(self.empty) and not self.broken and len(self.trailing_empty) == len(self.empty)

    def fix(self, location: str) -> str:
        """The damage, and what to do about it ("" when the log is whole)."""
        parts = []
        trailing = self.trailing_empty
        if trailing:
            names = ", ".join(str(entry) for entry in trailing)
            parts.append(
                f"its newest log entr{'y' if len(trailing) == 1 else 'ies'} {names} "
                f"{'is' if len(trailing) == 1 else 'are'} empty (a commit cut short by a crash, a power loss "
                f"or a full disk): move {'it' if len(trailing) == 1 else 'them, newest first,'} out of "
                f"_delta_log (the agent moves them to {SET_ASIDE_DIR} itself when it next opens the table), "
                "and the table reads as it was before that commit"
            )
        for entry in self.empty:
            if entry in trailing:
                continue
            parts.append(
                f"its log entry {entry} is empty (a commit cut short by a crash or a full disk) and "
                "later entries follow it: put back a whole copy from a backup, or, to go on without that "
                f"commit's rows, make it a commit with no action: echo {shlex.quote(NO_ACTION_ENTRY)} > "
                f"{shlex.quote(str(entry))}"
            )
        for entry in self.broken:
            parts.append(
                f"its log entry {entry} is not whole JSON: put back a whole copy from a backup"
                + (
                    ", or move it out of _delta_log (elsewhere, to keep it): the table then reads as it "
                    "was before that commit, without that commit's rows"
                    if entry == self.newest
                    else ""
                )
            )
        return f"the log of {location} is damaged: {'; '.join(parts)}" if parts else ""


def _checkpoint_version(log_dir: Path) -> int:
    """The version of the table's last checkpoint, -1 when it has none or its pointer does not read."""
    try:
        return int(json.loads((log_dir / "_last_checkpoint").read_text())["version"])
    except (OSError, ValueError, KeyError, TypeError):
        return -1


def _first_version(log_dir: Path) -> int:
    """Where the check starts: after the checkpoint `_last_checkpoint` names, when that one is there. A
    stale pointer (a checkpoint since cleaned up with the entries after it), one that does not read, or a
    version out of range names no entry: the log is then listed once, and the check starts after its newest
    checkpoint, or at its oldest entry when that is later (or there is no checkpoint)."""
    pointer = _checkpoint_version(log_dir)
    if (log_dir / f"{pointer + 1:020d}.json").exists():
        return pointer + 1
    if pointer >= 0 and any(
        (log_dir / f"{pointer:020d}{suffix}").exists() for suffix in (".json", ".checkpoint.parquet")
    ):
        return pointer + 1  # the pointer is right: no commit followed its checkpoint
    checkpoint, first = -1, None
    try:
        with os.scandir(log_dir) as names:
            for item in names:
                name = item.name
                if len(name) < 25 or not name[:20].isdigit():
                    continue
                if name[20:] == ".json":
                    first = name if first is None or name < first else first
                elif name[20:].startswith(".checkpoint."):
                    checkpoint = max(checkpoint, int(name[:20]))
    except OSError:
        return 0
    return max(checkpoint + 1, 0 if first is None else int(first[:20]))


# A log entry this long or shorter is read by a check that only looks for empty entries (parse=False); a
# commit cut short leaves zero bytes, or NUL bytes as long as it was meant to be (XFS after a power loss).
_SMALL_ENTRY = 4096


def _blank(data: bytes) -> bool:
    return not data.strip(b" \t\r\n\0")


def _entry_damage(entry: Path, *, parse: bool) -> str:
    """What is wrong with one log entry: "empty", "broken" or "" (FileNotFoundError when it is gone)."""
    size = entry.stat().st_size
    if size == 0:
        return "empty"
    if not parse and size > _SMALL_ENTRY:
        with entry.open("rb") as fh:  # a whole entry starts with "{"; only a NUL one needs reading on
            if not _blank(fh.read(64)):
                return ""
    data = entry.read_bytes()
    if _blank(data):
        return "empty"
    if parse:
        try:
            for line in data.splitlines():
                if line.strip():
                    json.loads(line)
        except ValueError:  # a bad byte is a UnicodeDecodeError, a ValueError too
            return "broken"
    return ""


def check_log(location: str, *, parse: bool = True) -> LogCheck:
    """The entries of a local table's log that do not read whole (`LogCheck`); with parse=False only the
    empty ones (a stat each, and a read of small ones, for a reader asked every few seconds). Only the
    entries after the last checkpoint are looked at, from its version up until one is missing: a log kept
    30 days holds hundreds of thousands. An S3 table is not checked: a PUT is whole or absent, so a crash
    leaves no entry cut short there."""
    local = location.removeprefix("file://")
    if "://" in local:
        return LogCheck()
    log_dir = Path(local) / "_delta_log"
    version = _first_version(log_dir)
    empty: list[Path] = []
    broken: list[Path] = []
    newest = None
    while True:
        entry = log_dir / f"{version:020d}.json"
        try:
            damage = _entry_damage(entry, parse=parse)
        except FileNotFoundError:
            break  # the newest entry was the one before
        except OSError:  # unreadable: named as not whole, and the walk stops (each later one would fail too)
            broken.append(entry)
            newest = entry
            break
        if damage == "empty":
            empty.append(entry)
        elif damage == "broken":
            broken.append(entry)
        newest = entry
        version += 1
    return LogCheck(tuple(empty), tuple(broken), newest)


def require_history_libraries() -> None:
    """Raise HistoryError naming the extra to install when the Delta Lake writer is absent: history is an
    optional part of the distribution (pyproject.toml's `history` extra), and the agent must say so when it
    starts, not fail at its first commit."""
    if importlib.util.find_spec("deltalake") is None:
        raise HistoryError(
            "history is on but deltalake is not installed: install the history extra "
            "(pip install 'so101-twin[history]'), or set [history] enabled = false"
        )


@dataclass(frozen=True)
class HistorySettings:
    """Where and how history is written ([history] in the agent config; docs/history.md)."""

    uri: str
    # A commit every N seconds or M rows, whichever comes first.
    commit_every_s: float = 10.0
    commit_every_rows: int = 50_000
    # Rows waiting for a commit (during an outage too) are bounded; beyond this the oldest are dropped.
    max_buffer_rows: int = 200_000
    # The sink's queue in front of the chunker: 3 s of a 1,000-arm fleet at 10 Hz, ~2 KB a queued sample.
    queue_max: int = 30_000
    chunk_rows: int = 4096
    chunk_max_age_s: float = 1.0
    # Compaction, checkpoint and vacuum run this often (0 = never, e.g. when another writer maintains).
    maintain_every_s: float = 3600.0
    # Files replaced by compaction stay this long for readers still using an older version.
    vacuum_retention_hours: float = 24.0
    # Each maintenance run deletes the days before the last keep_days whole UTC days, never one of the newest
    # keep_days + 1 days that hold rows (0 = keep everything: an upgrade must not remove anyone's rows); the
    # vacuum then frees their files.
    keep_days: int = 0
    target_file_mb: int = 128
    retry_min_s: float = 1.0
    retry_max_s: float = 60.0
    # A rejected message is kept up to this many bytes (its full size is stored too).
    rejected_payload_max_bytes: int = REJECTED_PAYLOAD_MAX_BYTES
    # Extra object-store options for delta-rs (endpoint, credentials, timeouts); AWS_* env vars also apply.
    storage_options: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        require_history_libraries()
        if not self.uri or not self.uri.strip():
            raise HistoryError(
                'history uri is empty: give a directory ("out/history") or "s3://bucket/history"'
            )
        # The rule `[history] uri` and `--history` are held to: s3a:// passed here (the writer's object
        # store reads it) while the settings refused it, so a location was good or bad by where it was given.
        problem = location_problem(self.uri)
        if problem:
            raise HistoryError(
                f'history uri {self.uri!r} {problem}; give a directory ("out/history") or '
                '"s3://bucket/history"'
            )
        for name in ("commit_every_s", "chunk_max_age_s", "retry_min_s", "retry_max_s"):
            if not getattr(self, name) > 0:
                raise HistoryError(f"history {name} = {getattr(self, name)!r} must be greater than 0")
        if self.retry_max_s < self.retry_min_s:
            raise HistoryError(
                f"history retry_max_s = {self.retry_max_s} is below retry_min_s = {self.retry_min_s}"
            )
        for name in ("commit_every_rows", "queue_max", "chunk_rows", "target_file_mb"):
            if getattr(self, name) < 1:
                raise HistoryError(f"history {name} = {getattr(self, name)!r} must be at least 1")
        if self.max_buffer_rows < self.commit_every_rows:
            raise HistoryError(
                f"history max_buffer_rows = {self.max_buffer_rows} must be at least commit_every_rows = "
                f"{self.commit_every_rows}, or no commit could ever fill"
            )
        if self.maintain_every_s < 0 or self.vacuum_retention_hours < 0:
            raise HistoryError("history maintain_every_s and vacuum_retention_hours must not be negative")
        if self.rejected_payload_max_bytes < 0:
            raise HistoryError("history rejected_payload_max_bytes must not be negative")
        if isinstance(self.keep_days, bool) or not isinstance(self.keep_days, int) or self.keep_days < 0:
            raise HistoryError(
                f"history keep_days = {self.keep_days!r} must be a whole number of days, at least 0 "
                "(0 keeps everything)"
            )

    @property
    def is_s3(self) -> bool:
        return self.uri.startswith("s3://")

    def table_uri(self, table: str) -> str:
        return table_uri(self.uri, table)

    def object_store_options(self) -> dict[str, str]:
        return object_store_options(self.uri, self.storage_options)


def table_uri(base: str, table: str) -> str:
    """The URI of one history table under the base URI (a local path stays a path)."""
    if "://" in base:
        return f"{base.rstrip('/')}/{table}"
    return str(Path(base) / table)


def object_store_options(uri: str, extra: Mapping[str, str] | None = None) -> dict[str, str]:
    """delta-rs storage options: bounded timeouts on S3 so an outage surfaces as an error in seconds, not
    after object_store's default of ten retries over three minutes; `extra` wins."""
    options: dict[str, str] = {}
    if uri.startswith("s3://"):
        options.update(
            {"timeout": "30s", "connect_timeout": "5s", "max_retries": "3", "retry_timeout": "20s"}
        )
    options.update({str(k): str(v) for k, v in (extra or {}).items()})
    return options


# --- rows ------------------------------------------------------------------------------------------------


def _date32(ms: np.ndarray) -> pa.Array:
    return pa.array((ms // MS_PER_DAY).astype(np.int32), pa.int32()).cast(pa.date32())


def _timestamps(ms: np.ndarray) -> pa.Array:
    return pa.array(ms, pa.int64()).cast(pa.timestamp("ms", tz="UTC"))


def _one_line(payload: bytes) -> bytes:
    # Valid JSON can hold a raw newline only as whitespace (never inside a string), so a space is equivalent
    # and keeps one message per line for the line-delimited reader.
    if b"\n" in payload or b"\r" in payload:
        return payload.replace(b"\n", b" ").replace(b"\r", b" ")
    return payload or b"{}"


def _raw_columns_arrow(payloads: Sequence[bytes]) -> dict[str, pa.Array]:
    blob = b"\n".join(_one_line(p) for p in payloads)
    # One block for the whole chunk: the reader then keeps the rows in input order.
    options = pa_json.ReadOptions(block_size=max(1 << 20, len(blob) + 1), use_threads=False)
    parsed = pa_json.read_json(io.BytesIO(blob), read_options=options, parse_options=_PARSE_OPTIONS)
    if parsed.num_rows != len(payloads):
        raise ValueError(f"parsed {parsed.num_rows} rows from {len(payloads)} payloads")
    joints = parsed.column("joints").combine_chunks()
    out: dict[str, pa.Array] = {}
    # StructArray.flatten() carries a null parent (a payload without "joints") down to every field.
    for joint, entry in zip(JOINTS, joints.flatten(), strict=True):
        for name, values in zip(RAW_FIELDS, entry.flatten(), strict=True):
            out[raw_column(joint, name)] = values
    return out


def _raw_columns_python(payloads: Sequence[bytes]) -> dict[str, pa.Array]:
    """The slow path for a chunk Arrow's reader refused (e.g. duplicate keys): the stdlib parser, which is
    what the decoder used, so the values are the ones the twin saw."""
    columns: dict[str, list[float | None]] = {raw_column(j, n): [] for j in JOINTS for n in RAW_FIELDS}
    for payload in payloads:
        try:
            joints = json.loads(payload).get("joints", {}) if payload else {}
        except (ValueError, AttributeError):
            joints = {}
        for joint in JOINTS:
            entry = joints.get(joint) if isinstance(joints, dict) else None
            for name in RAW_FIELDS:
                value = entry.get(name) if isinstance(entry, dict) else None
                number = value if isinstance(value, int | float) and not isinstance(value, bool) else None
                columns[raw_column(joint, name)].append(None if number is None else float(number))
    return {name: pa.array(values, pa.float64()) for name, values in columns.items()}


def telemetry_table(samples: Sequence[AppliedSample]) -> tuple[pa.Table, bool]:
    """Arrow rows for applied samples (TELEMETRY_SCHEMA); the flag says the slow parse path was needed."""
    return telemetry_table_of(
        device_ids=[s.device_id for s in samples],
        received_wall_s=[s.received_wall_s for s in samples],
        edge_ms=[s.telemetry.timestamp_ms for s in samples],
        units=[s.telemetry.units.value for s in samples],
        angles=[a for s in samples for a in _ANGLES(s.telemetry.angles_rad)],
        payloads=[s.payload for s in samples],
    )


def telemetry_table_of(
    *,
    device_ids: Sequence[str],
    received_wall_s: Sequence[float],
    edge_ms: Sequence[int],
    units: Sequence[str],
    angles: Sequence[float],
    payloads: Sequence[bytes],
) -> tuple[pa.Table, bool]:
    """`telemetry_table` from columns (the history writer process gets them so): `angles` holds each row's
    decoded angles in JOINTS order, one row after the other."""
    n = len(device_ids)
    received_ms = np.rint(np.asarray(received_wall_s, dtype=np.float64) * 1000.0).astype(np.int64)
    edge = np.asarray(edge_ms, dtype=np.int64)
    decoded = np.asarray(angles, dtype=np.float64).reshape(n, len(JOINTS))
    slow = False
    try:
        raw = _raw_columns_arrow(payloads)
    except (pa.ArrowInvalid, ValueError):
        raw = _raw_columns_python(payloads)
        slow = True
    columns: dict[str, Any] = {
        PARTITION_COLUMN: _date32(received_ms),
        "received_at": _timestamps(received_ms),
        "edge_time": _timestamps(edge),
        "device_id": pa.array(device_ids, pa.string()),
        "units": pa.array(units, pa.string()),
    }
    for i, joint in enumerate(JOINTS):
        columns[position_column(joint)] = pa.array(decoded[:, i], pa.float64())
        for name in RAW_FIELDS:
            columns[raw_column(joint, name)] = raw[raw_column(joint, name)]
    return pa.table(columns, schema=TELEMETRY_SCHEMA), slow


def rejected_table(samples: Sequence[RejectedSample], payload_max_bytes: int) -> pa.Table:
    return rejected_table_of([rejected_row(s, payload_max_bytes) for s in samples])


# One rejected message as the rejected table keeps it: receive wall time, topic, device (None when the topic
# names none), reason, detail, the payload's first bytes, and its whole length.
RejectedRow = tuple[float, str, str | None, str, str, bytes, int]


def rejected_row(sample: RejectedSample, payload_max_bytes: int) -> RejectedRow:
    payload = sample.payload
    return (
        sample.received_wall_s,
        sample.topic,
        sample.device_id,
        sample.reason,
        sample.detail,
        bytes(payload[:payload_max_bytes]),
        sample.size,  # the whole message's, though the sample may carry only its first bytes
    )


def rejected_table_of(rows: Sequence[RejectedRow]) -> pa.Table:
    """`rejected_table` from RejectedRows (the history writer process gets them so)."""
    received_ms = np.rint(np.fromiter((r[0] for r in rows), np.float64, len(rows)) * 1000.0).astype(np.int64)
    return pa.table(
        {
            PARTITION_COLUMN: _date32(received_ms),
            "received_at": _timestamps(received_ms),
            "topic": pa.array([r[1] for r in rows], pa.string()),
            "device_id": pa.array([r[2] for r in rows], pa.string()),
            "reason": pa.array([r[3] for r in rows], pa.string()),
            "detail": pa.array([r[4] for r in rows], pa.string()),
            "payload": pa.array([r[5] for r in rows], pa.binary()),
            "payload_bytes": pa.array([r[6] for r in rows], pa.int64()),
        },
        schema=REJECTED_SCHEMA,
    )


# --- the committer -------------------------------------------------------------------------------------


@dataclass
class TableStats:
    rows_committed: int = 0
    commits: int = 0
    commit_failures: int = 0
    rows_dropped: int = 0
    rows_buffered: int = 0
    duplicate_commits_skipped: int = 0
    # Times the writer opened the table (the first append, after a failure or maintenance, every
    # REOPEN_EVERY_COMMITS commits).
    opens: int = 0
    last_commit_version: int | None = None
    last_error: str = ""
    # Newest log entries found empty (a commit cut short by a crash) and moved to SET_ASIDE_DIR.
    log_entries_set_aside: int = 0
    # The writer's storage_ok is all its tables' (a table that keeps failing holds the commits-failing gauge
    # at 1 while another's commits work: its alarm needs 5 minutes of it in a row).
    last_commit_ok: bool = True


@dataclass
class WriterStats:
    tables: dict[str, TableStats] = field(default_factory=dict)
    maintenance_runs: int = 0
    maintenance_failures: int = 0
    maintenance_conflicts: int = 0
    # Windows in which another writer held the maintenance lease.
    maintenance_skipped: int = 0
    # Rows maintenance deleted for being older than keep_days (their files go at a later vacuum).
    rows_expired: int = 0
    slow_parses: int = 0
    conversion_failures: int = 0
    rows_lost_in_conversion: int = 0
    # Whether every table's last commit worked; None until the first commit attempt: a writer started again
    # has not yet seen its storage, which claiming OK would hide for as long as no row came to write.
    storage_ok: bool | None = None
    last_error: str = ""
    # How long ago the oldest row not yet written arrived (0 when every row is written): history's lag behind
    # the twin, which grows for as long as commits fail, rows dropped or not (CloudWatch alarms on it).
    lag_s: float = 0.0


def _no_backoff_waits() -> dict[str, float]:
    """When each table may commit next, none held back by a backoff (the start, a flush, the close)."""
    return dict.fromkeys(SCHEMAS, 0.0)


@dataclass
class _Pending:
    table: pa.Table
    since: float  # monotonic time the rows arrived
    # Set once a commit of exactly these rows was attempted: a retry reuses it, so if the first attempt did
    # land (its answer lost), the table's app-transaction version shows it and the rows are not written twice.
    seq: int | None = None


def _has_committed(dtable: Any, writer_id: str, seq: int) -> bool:
    """Whether the open table holds writer `writer_id`'s commit `seq` (its app transaction's version)."""
    done = dtable.transaction_version(writer_id)
    return done is not None and done >= seq


def _writer_properties(level: int) -> Any:
    from deltalake import ColumnProperties, WriterProperties  # noqa: PLC0415 - heavy, only when writing

    # Timestamps step by ~100 ms: delta encoding stores them in about a byte a row. Positions follow smooth
    # motion, which plain floats let zstd match; the diagnostics take few distinct values (dictionary).
    columns = {
        name: ColumnProperties(encoding="DELTA_BINARY_PACKED", dictionary_enabled=False)
        for name in ("received_at", "edge_time")
    }
    for joint in JOINTS:
        columns[raw_column(joint, "position")] = ColumnProperties(
            encoding="BYTE_STREAM_SPLIT", dictionary_enabled=False
        )
        columns[position_column(joint)] = ColumnProperties(encoding="PLAIN", dictionary_enabled=False)
    return WriterProperties(compression="ZSTD", compression_level=level, column_properties=columns)


# zstd 3 for the frequent small commits (cheap), a stronger level when compaction rewrites them once.
COMMIT_ZSTD_LEVEL = 3
COMPACT_ZSTD_LEVEL = 12
# A DeltaTable object's state holds every data file's metadata and grows with each commit it is updated
# with; a long-lived one kept the writer's RSS growing between compactions (docs/performance.md, "Soak").
# Opening the table anew starts from the current state (one checkpoint read plus the JSON commits after it).
REOPEN_EVERY_COMMITS = 50
# A maintenance process still running after this long is stopped and counted as failed.
MAINTENANCE_TIMEOUT_S = 1800.0
# The maintenance process: a module-level entry point run by a fresh interpreter (see _maintain).
MAINTENANCE_MODULE = "twin.output.history_maintain"
TABLE_CONFIGURATION = {
    # A checkpoint every 100 commits keeps opening the table to one Parquet read plus a few JSON files.
    "delta.checkpointInterval": "100",
    "delta.logRetentionDuration": "interval 30 days",
    # Each agent run leaves one app-transaction id; forget them after a week.
    "delta.setTransactionRetentionDuration": "interval 7 days",
}


def _make_local_directory(settings: HistorySettings) -> None:
    """A local history uri's directory, made now: a writer that cannot write there fails at its start, with
    the fix, rather than at its first commit. An S3 uri has nothing to make."""
    if settings.is_s3:
        return
    path = settings.uri.removeprefix("file://")
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HistoryError(
            f"history uri {settings.uri!r} cannot be created ({exc}); give a writable directory"
        ) from exc


class HistoryWriter:
    """Appends Arrow tables to the history tables from a committer thread of its own.

    `add()` never blocks on storage: it queues the rows (bounded) and returns. `flush()` asks for a commit
    now and waits for it; `close()` commits what is left (bounded by its timeout) and stops the thread.
    """

    # Whether the last commit failed on a full disk: the next one checks the free space first.
    _disk_was_full = False

    def __init__(
        self,
        settings: HistorySettings,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        writer_id: str | None = None,
        maintain_in_child: bool = True,
        reopen_every: int = REOPEN_EVERY_COMMITS,
    ) -> None:
        if reopen_every < 1:
            raise ValueError(f"reopen_every must be at least 1, got {reopen_every}")
        self.settings = settings
        self._maintain_in_child = maintain_in_child
        self._reopen_every = reopen_every
        # What runs maintenance (module doc of twin.output.history_maintain); tests swap in a failing one.
        self.maintenance_command: list[str] = [sys.executable, "-m", MAINTENANCE_MODULE]
        self._clock = clock
        self._wall = wall_clock
        self.writer_id = writer_id or (
            f"so101-twin-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        )
        self._options = settings.object_store_options()
        self._cond = threading.Condition(threading.Lock())
        self._pending: dict[str, collections.deque[_Pending]] = {t: collections.deque() for t in SCHEMAS}
        # Rejected rows carry payload bytes: a tenth of the row budget keeps a flood of them small.
        self._limits = {
            TELEMETRY_TABLE: settings.max_buffer_rows,
            REJECTED_TABLE: max(1, settings.max_buffer_rows // 10),
        }
        self._inflight_rows = dict.fromkeys(SCHEMAS, 0)
        # When the oldest row not yet written arrived (None: every row is written). Dropped rows do not move
        # it: while commits fail, the lag keeps growing however many rows the bound drops.
        self._unwritten_since: float | None = None
        self._seq = 0
        self._stats = WriterStats(tables={t: TableStats() for t in SCHEMAS})
        self._flush_requested = False
        self._flushes_done = 0
        self._closing = False
        self._close_deadline = 0.0
        self._retry_at = _no_backoff_waits()
        self._backoff = dict.fromkeys(SCHEMAS, settings.retry_min_s)
        self._next_maintenance = self._maintenance_after(clock())
        self._tables: dict[str, Any] = {}
        self._appends_since_open = dict.fromkeys(SCHEMAS, 0)
        # Set by a finished maintenance run; the committer reopens its tables before its next append.
        self._tables_stale = False
        self._maintenance_thread: threading.Thread | None = None
        # One line per backoff step at most once every 10 s: an outage must be visible, not a flood.
        self._error_lines = Throttle(10.0, clock=clock)
        # Called on the committer thread after each commit is counted, outside the writer's lock: the history
        # writer process writes its shared counters there, so a crash right after a commit finds it counted.
        self.on_commit: Callable[[], object] | None = None
        # Called on the committer thread just before each append, with (table, seq, rows, the table's rows
        # committed so far): the writer process records the commit it is in, so that if it dies before
        # counting it, the next writer can ask the table whether it landed.
        self.before_append: Callable[[str, int, int, int], object] | None = None
        self._thread = threading.Thread(target=self._run, name="history-commit", daemon=True)
        self._started = False
        _make_local_directory(settings)

    # -- producer side (the sink thread) ---------------------------------------------------------------

    def start(self) -> HistoryWriter:
        if not self._started:
            self._started = True
            self._thread.start()
        return self

    def add(self, table: str, rows: pa.Table) -> None:
        """Queue rows for `table` (TELEMETRY_TABLE or REJECTED_TABLE); drops the oldest beyond the bound."""
        if rows.num_rows == 0:
            return
        with self._cond:
            queue = self._pending[table]
            stats = self._stats.tables[table]
            now = self._clock()
            queue.append(_Pending(rows, now))
            if self._unwritten_since is None:
                self._unwritten_since = now
            stats.rows_buffered += rows.num_rows
            dropped = self._trim(table)
            self._cond.notify()
        if dropped:
            log.error(
                "history: %d %s rows dropped: the write buffer is full (max_buffer_rows = %d) because "
                "commits to %s keep failing (%s); fix the storage or raise max_buffer_rows",
                dropped,
                table,
                self._limits[table],
                self.settings.uri,
                self._stats.last_error or "no error yet",
                extra={"history_dropped_rows": dropped, "table": table},
            )

    def _trim(self, table: str) -> int:
        """Drop the oldest queued rows while queued plus in-flight rows exceed the bound (lock held)."""
        queue = self._pending[table]
        stats = self._stats.tables[table]
        dropped = 0
        while queue and stats.rows_buffered + self._inflight_rows[table] > self._limits[table]:
            oldest = queue.popleft()
            stats.rows_buffered -= oldest.table.num_rows
            dropped += oldest.table.num_rows
        stats.rows_dropped += dropped
        return dropped

    def flush(self, timeout: float = 30.0) -> bool:
        """Commit everything queued now; True when a commit round finished without error in time."""
        with self._cond:
            target = self._flushes_done + 1
            self._flush_requested = True
            self._retry_at = _no_backoff_waits()
            self._cond.notify()
            deadline = time.monotonic() + timeout
            while self._flushes_done < target:
                left = deadline - time.monotonic()
                if left <= 0 or not self._thread.is_alive():
                    return False
                self._cond.wait(left)
            return self._stats.storage_ok is not False  # no attempt yet: nothing was queued, nothing failed

    def close(self, timeout: float = 30.0) -> None:
        """Commit what is queued (retrying until `timeout`), then stop. Rows still unwritten are logged."""
        with self._cond:
            self._closing = True
            self._close_deadline = time.monotonic() + timeout
            self._retry_at = _no_backoff_waits()
            self._cond.notify()
        if self._started:
            self._thread.join(timeout + 5.0)
        maintenance = self._maintenance_thread
        if maintenance is not None:
            # A running maintenance process sees `_closing` within a poll and is stopped (run_child).
            maintenance.join(timeout + 10.0)
        left = self.buffered_rows()
        if left:
            log.error(
                "history: %d rows were not written to %s before shutdown (%s)",
                left,
                self.settings.uri,
                self._stats.last_error or "the committer did not finish in time",
                extra={"history_unwritten_rows": left},
            )

    def buffered_rows(self) -> int:
        with self._cond:
            buffered = sum(s.rows_buffered for s in self._stats.tables.values())
            return buffered + sum(self._inflight_rows.values())

    def stats(self) -> WriterStats:
        with self._cond:
            return dataclasses.replace(
                self._stats,
                tables={k: dataclasses.replace(v) for k, v in self._stats.tables.items()},
                lag_s=self._lag(self._clock()),
            )

    def _lag(self, now: float) -> float:
        """Seconds since the oldest row not yet written arrived (lock held)."""
        return 0.0 if self._unwritten_since is None else max(0.0, now - self._unwritten_since)

    def count_conversion(self, *, slow: bool = False, lost_rows: int = 0, error: str = "") -> None:
        with self._cond:
            self._stats.slow_parses += int(slow)
            if lost_rows:
                self._stats.conversion_failures += 1
                self._stats.rows_lost_in_conversion += lost_rows
                self._stats.last_error = error

    # -- the committer thread ------------------------------------------------------------------------

    def _due(self, now: float) -> bool:
        if self._closing or self._flush_requested:
            return True
        for table, queue in self._pending.items():
            # Each table backs off on its own: one whose commits fail must not slow the other's working ones
            # until its buffer fills and drops rows that its storage would take.
            if not queue or now < self._retry_at[table]:
                continue
            if self._stats.tables[table].rows_buffered >= self.settings.commit_every_rows:
                return True
            if now - queue[0].since >= self.settings.commit_every_s:
                return True
        return False

    def _wait_s(self, now: float) -> float:
        waits = [self._next_maintenance - now]
        for table, queue in self._pending.items():
            if queue:
                due = max(queue[0].since + self.settings.commit_every_s, self._retry_at[table])
                waits.append(due - now)
        return min(max(0.01, min(waits)), 1.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                while True:
                    now = self._clock()
                    if self._due(now) or now >= self._next_maintenance:
                        break
                    self._cond.wait(self._wait_s(now))
                closing = self._closing
                flush = self._flush_requested
                self._flush_requested = False
                batches: dict[str, list[_Pending]] = {}
                for table, queue in self._pending.items():
                    if queue and (closing or flush or now >= self._retry_at[table]):
                        batches[table] = list(queue)
                        queue.clear()
                        rows = sum(p.table.num_rows for p in batches[table])
                        self._stats.tables[table].rows_buffered -= rows
                        self._inflight_rows[table] += rows
            ok = True
            for table, items in batches.items():
                ok = self._commit_round(table, items) and ok
            if ok and sum(p.table.num_rows for items in batches.values() for p in items) >= (
                self.settings.commit_every_rows
            ):
                # A burst (a backlog after an outage, a full buffer): its Arrow tables are freed now.
                heap.trim()
            with self._cond:
                if batches and ok:
                    # Written up to here: the lag starts again from what arrived meanwhile.
                    waiting = [q[0].since for q in self._pending.values() if q]
                    self._unwritten_since = min(waiting) if waiting else None
                if flush or closing:
                    self._flushes_done += 1
                    self._cond.notify_all()
                left = sum(s.rows_buffered for s in self._stats.tables.values())
                if closing and (left == 0 or time.monotonic() >= self._close_deadline):
                    return
                if closing and not ok:
                    # Storage is down at shutdown: retry until the close deadline, a second apart.
                    self._cond.wait(min(1.0, max(0.0, self._close_deadline - time.monotonic())))
                    if time.monotonic() >= self._close_deadline:
                        return
            if self._clock() >= self._next_maintenance and not closing:
                self._start_maintenance()

    def _commit_round(self, table: str, items: list[_Pending]) -> bool:
        """Commit a batch attempted before (alone, with its sequence number), then everything else at once."""
        first = items[0].seq
        retried = [p for p in items if first is not None and p.seq == first]
        groups = [g for g in (retried, items[len(retried) :]) if g]
        for i, group in enumerate(groups):
            if not self._commit(table, group, later=[p for g in groups[i + 1 :] for p in g]):
                return False
        return True

    def _commit(self, table: str, group: list[_Pending], *, later: list[_Pending]) -> bool:
        rows = group[0].table if len(group) == 1 else pa.concat_tables([p.table for p in group])
        n = rows.num_rows
        seq = group[0].seq
        if seq is None:
            self._seq += 1
            seq = self._seq
        announce = self.before_append
        if announce is not None:
            with self._cond:
                committed = self._stats.tables[table].rows_committed
            announce(table, seq, n, committed)
        try:
            version = self._append(table, rows, seq)
        except Exception as exc:
            # The items keep their own identity (the bound trims them one by one) and share the sequence.
            self._failed(table, [dataclasses.replace(p, seq=seq) for p in group], later, exc)
            return False
        self._disk_was_full = False
        with self._cond:
            stats = self._stats.tables[table]
            self._inflight_rows[table] -= n
            stats.rows_committed += n
            stats.commits += 1
            if version is None:
                stats.duplicate_commits_skipped += 1
            else:
                stats.last_commit_version = version
            stats.last_commit_ok = True
            all_ok = all(t.last_commit_ok for t in self._stats.tables.values())
            if all_ok:
                if self._stats.storage_ok is False:
                    log.warning("history: writing to %s works again", self.settings.uri)
                self._error_lines.clear()
            self._backoff[table] = self.settings.retry_min_s
            self._stats.storage_ok = all_ok
        hook = self.on_commit
        if hook is not None:
            try:
                hook()
            except Exception:  # the commit stands; whoever reads the figures later reads them then
                log.exception("history: the commit hook failed")
        return True

    def _append(self, table: str, rows: pa.Table, seq: int) -> int | None:
        """One Delta append carrying (writer_id, seq); returns the new version, or None if `seq` was already
        committed by an earlier attempt whose answer was lost."""
        from deltalake import CommitProperties, Transaction, write_deltalake  # noqa: PLC0415

        dtable = self._table(table)
        dtable.update_incremental()
        if _has_committed(dtable, self.writer_id, seq):
            return None
        if table == TELEMETRY_TABLE:
            rows = rows.sort_by([("device_id", "ascending"), ("received_at", "ascending")])
        else:
            rows = rows.sort_by([("received_at", "ascending")])
        if self._disk_was_full and not self.settings.is_s3:
            _require_free_space(self.settings.uri)
        write_deltalake(
            dtable,
            rows,
            mode="append",
            # Columns a newer agent adds are merged in; an append with the table's own schema adds no
            # metadata action, so concurrent appends from several writers never conflict on it.
            schema_mode="merge",
            writer_properties=_writer_properties(COMMIT_ZSTD_LEVEL),
            target_file_size=self.settings.target_file_mb << 20,
            commit_properties=CommitProperties(
                app_transactions=[Transaction(self.writer_id, seq)], max_commit_retries=50
            ),
        )
        return int(dtable.version())

    def _table(self, table: str) -> Any:
        """The open table, opened anew every `reopen_every` appends (REOPEN_EVERY_COMMITS says why) and after
        a maintenance run (its checkpoint makes the new state small)."""
        with self._cond:
            stale, self._tables_stale = self._tables_stale, False
        if stale:
            self._appends_since_open = dict.fromkeys(SCHEMAS, self._reopen_every)
        dtable = self._tables.get(table)
        if dtable is not None and self._appends_since_open[table] < self._reopen_every:
            self._appends_since_open[table] += 1
            return dtable
        reopening = self._tables.pop(table, None) is not None
        del dtable  # the old state must be gone before the trim below can give its pages back
        dtable = self._open_or_create(table, self.settings.table_uri(table))
        self._tables[table] = dtable
        self._appends_since_open[table] = 1
        with self._cond:
            self._stats.tables[table].opens += 1
        if reopening:
            heap.trim()
        return dtable

    def landed(self, table: str, writer_id: str, seq: int) -> bool:
        """Whether `table` holds the commit `seq` of writer `writer_id` (its app transaction): how a writer
        started after one that died learns whether the commit that one was in landed."""
        from deltalake import DeltaTable  # noqa: PLC0415
        from deltalake.exceptions import TableNotFoundError  # noqa: PLC0415

        try:
            dtable = DeltaTable(self.settings.table_uri(table), storage_options=self._options)
        except TableNotFoundError:
            return False
        return _has_committed(dtable, writer_id, seq)

    def _open_or_create(self, table: str, uri: str) -> Any:
        """The table at `uri`, created first if missing. Created on its own (not by the first append) so two
        writers starting together race only on the empty creation commit, which the loser just re-reads."""
        from deltalake import CommitProperties, DeltaTable  # noqa: PLC0415
        from deltalake.exceptions import TableNotFoundError  # noqa: PLC0415

        self._mend_log(table, uri)
        try:
            return DeltaTable(uri, storage_options=self._options)
        except TableNotFoundError:
            pass
        try:
            DeltaTable.create(
                uri,
                schema=SCHEMAS[table],
                mode="ignore",
                partition_by=[PARTITION_COLUMN],
                configuration=TABLE_CONFIGURATION,
                storage_options=self._options,
                # No retry: a writer that loses the race for version 0 must fail here, not commit the same
                # schema again as version 1 (delta-rs retries a conflicting create at the next version).
                commit_properties=CommitProperties(max_commit_retries=0),
            )
        except Exception:
            log.info("history: %s was created concurrently by another writer", uri, exc_info=True)
        return DeltaTable(uri, storage_options=self._options)

    def _mend_log(self, table: str, uri: str) -> None:
        """Before a local table is opened to append to: the newest log entries left empty (commits cut short
        by a crash, a power loss or a full disk) are moved to SET_ASIDE_DIR, newest first, kept and counted,
        and the table reads as it was before those commits; delta-rs took one for a commit with no action
        and appended after it, and every read left that commit's rows out without a word. Any other damage
        refuses the append (HistoryLogError names it and the fix): the rows wait in the buffer, and each
        retry looks again."""
        check = check_log(uri)
        if check.newest_empty_only:
            for entry in check.trailing_empty:  # newest first: the log stays a run with no gap
                moved = _set_aside(entry)
                if moved is None:
                    break
                with self._cond:
                    self._stats.tables[table].log_entries_set_aside += 1
                log.error(
                    "history: the newest log entry of %s was empty (a commit cut short by a crash, a power "
                    "loss or a full disk): moved it to %s, and the table reads as it was before that commit; "
                    "that commit's rows, if its data file was written, stay unread in the table's folder",
                    uri,
                    moved,
                    extra={"table": table, "log_entry_set_aside": str(moved)},
                )
            check = check_log(uri)
        problem = check.fix(uri)
        if problem:
            raise HistoryLogError(problem)

    def _failed(self, table: str, failed: list[_Pending], later: list[_Pending], exc: BaseException) -> None:
        message = _describe_storage_error(self.settings.uri, exc)
        self._disk_was_full = _is_disk_full(exc)
        # The table handle may describe a state the failed commit left half-known; reload it next time.
        self._tables.pop(table, None)
        now = self._clock()
        n = sum(p.table.num_rows for p in (*failed, *later))
        with self._cond:
            stats = self._stats.tables[table]
            stats.commit_failures += 1
            stats.last_error = message
            self._stats.last_error = message
            stats.last_commit_ok = False
            self._stats.storage_ok = False
            self._inflight_rows[table] -= n
            # Back to the front of the queue, oldest first, still within the bound.
            queue = self._pending[table]
            for item in reversed([*failed, *later]):
                queue.appendleft(item)
            stats.rows_buffered += n
            dropped = self._trim(table)
            self._retry_at[table] = now + self._backoff[table]
            # A stop retries a second apart until its deadline, whatever the backoff had reached: the line
            # said "retrying in 60 s" while the stop retried each second.
            retry_in = 1.0 if self._closing else self._backoff[table]
            # The stop's last attempt: `_run` returns at the deadline, before another second is up.
            last = self._closing and time.monotonic() + retry_in >= self._close_deadline
            then = f"retrying in {retry_in:.0f} s"
            if last:
                then = "not retried: the stop gives up on them at its deadline"
            self._backoff[table] = min(self._backoff[table] * 2.0, self.settings.retry_max_s)
            buffered = stats.rows_buffered
            failures = stats.commit_failures
        # A drop is a loss, told whatever the interval; so is the stop's last attempt, whose rows it loses.
        if self._error_lines.due(force=bool(dropped) or last, now=now) is not None:
            log.error(
                "history: %s; %d %s rows kept in memory (bound %d), %s",
                message,
                buffered,
                table,
                self._limits[table],
                then,
                extra={"table": table, "commit_failures": failures, "history_dropped_rows": dropped},
            )

    def _take_lease(self, table: str) -> bool:
        """Only one writer may maintain a table per window: delta-rs 1.6 lets two concurrent compactions of
        the same files both commit (their removes carry dataChange=false), which duplicates every row they
        touched. The lease is a put-if-absent object per table and window, like a Delta commit itself."""
        window = int(self._wall() // max(self.settings.maintain_every_s, 60.0))
        key = f"_maintenance/{table}-{window}.lease"
        body = json.dumps({"writer": self.writer_id, "window": window}).encode()
        if not self.settings.is_s3:
            base = Path(self.settings.uri.removeprefix("file://")) / "_maintenance"
            base.mkdir(parents=True, exist_ok=True)
            try:
                fd = os.open(base / key.rsplit("/", 1)[1], os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                return False
            with os.fdopen(fd, "wb") as fh:
                fh.write(body)
            for old in base.glob(f"{table}-*.lease"):
                stem = old.stem.rsplit("-", 1)[-1]
                if stem.isdigit() and int(stem) < window - 2:
                    old.unlink(missing_ok=True)
            return True
        bucket, _, prefix = self.settings.uri.split("://", 1)[1].partition("/")
        client = _s3_client(self._options)
        try:
            client.put_object(
                Bucket=bucket, Key=f"{prefix.strip('/')}/{key}".lstrip("/"), Body=body, IfNoneMatch="*"
            )
        except Exception as exc:
            code = getattr(exc, "response", {}).get("Error", {}).get("Code", "")
            if code in ("PreconditionFailed", "ConditionalRequestConflict"):
                return False
            raise
        return True

    def _maintenance_after(self, now: float) -> float:
        """When maintenance is next due after `now` (never with maintain_every_s = 0)."""
        every = self.settings.maintain_every_s
        return now + every if every > 0 else float("inf")

    def _start_maintenance(self) -> None:
        """Start the due maintenance on a thread of its own and return: the committer goes on committing
        while it runs. A run still going when the next one is due makes that one wait an interval.

        Appends and a compaction of the same partition commit side by side: the compaction removes only files
        it read and adds their rows again (dataChange=false), an append only adds new files, and delta-rs
        commits whichever comes second on top of the first (`tests/test_history.py` checks every row is
        there once). Rewriting the day took longer as the day grew (49 s after 50 minutes at 200 arms,
        docs/performance.md "Soak"); had the committer waited, the rows arriving meanwhile would have piled
        up as one ever larger backlog and, past `max_buffer_rows`, been dropped.
        """
        self._next_maintenance = self._maintenance_after(self._clock())
        running = self._maintenance_thread
        if running is not None and running.is_alive():
            log.warning(
                "history: maintenance is still running after maintain_every_s = %.0f s; the next run waits "
                "an interval",
                self.settings.maintain_every_s,
            )
            return
        self._maintenance_thread = threading.Thread(
            target=self._maintain, kwargs={"interruptible": True}, name="history-maintain", daemon=True
        )
        self._maintenance_thread.start()

    def _maintain(self, today: dt.date | None = None, *, interruptible: bool = False) -> None:
        """Compact today's and yesterday's partitions, checkpoint, vacuum replaced files, trim the log.

        It runs in a process of its own (`maintenance_command`) unless the writer was made with
        maintain_in_child=False: compaction reads and rewrites the day's files, and the hundreds of MB that
        takes stayed in this process's RSS after it (glibc keeps freed arenas); a process that exits gives
        them all back. The committer's own runs are started by `_start_maintenance` and do not hold it up.
        `interruptible`: stop the process if the writer is closed meanwhile (the committer's own runs).
        """
        started = time.monotonic()
        today = today or dt.datetime.fromtimestamp(self._wall(), dt.UTC).date()
        if self._maintain_in_child:
            self._maintain_in_process_of_its_own(today, interruptible)
        else:
            self.maintain_here(today)
        with self._cond:
            self._tables_stale = True
        took = time.monotonic() - started
        log.info("history: maintenance took %.1f s", took, extra={"maintenance_s": round(took, 3)})
        heap.trim()

    def maintain_here(self, today: dt.date) -> None:
        """Maintenance on the caller's thread, in this process (what the maintenance process runs)."""
        from deltalake.exceptions import CommitFailedError  # noqa: PLC0415

        days = [today - dt.timedelta(days=1), today]
        for table in SCHEMAS:
            dtable = self._leased_table(table)
            if dtable is None:
                continue
            try:
                self._expire(table, dtable, today)
                self._maintain_table(table, dtable, days)
                with self._cond:
                    self._stats.maintenance_runs += 1
            except CommitFailedError as exc:
                # Another writer changed the same files first (its compaction, say): nothing is lost, the
                # next run tries again.
                with self._cond:
                    self._stats.maintenance_conflicts += 1
                log.warning(
                    "history: maintenance of %s lost a commit race (%s); retried next time", table, exc
                )
            except Exception as exc:
                self._maintenance_failed(table, exc)

    def _leased_table(self, table: str) -> Any:
        """The table to maintain, or None: another writer holds the lease (counted as skipped), the table does
        not exist yet, or opening it failed (counted and logged)."""
        from deltalake import DeltaTable  # noqa: PLC0415

        try:
            if not self._take_lease(table):
                with self._cond:
                    self._stats.maintenance_skipped += 1
                return None
            # A checkpoint over a log entry left empty would make it part of the table for good.
            problem = check_log(self.settings.table_uri(table)).fix(self.settings.table_uri(table))
            if problem:
                raise HistoryLogError(problem)
        except Exception as exc:
            self._maintenance_failed(table, exc)
            return None
        try:
            return DeltaTable(self.settings.table_uri(table), storage_options=self._options)
        except Exception as exc:
            if type(exc).__name__ != "TableNotFoundError":
                self._maintenance_failed(table, exc)
            return None

    def _expire(self, table: str, dtable: Any, today: dt.date) -> None:
        """Delete the rows of the days before the last keep_days whole UTC days (today, partial, is kept as
        well), but never one of the newest keep_days + 1 days that hold rows (`_expiry_cut` says why). The
        predicate is on the partition column alone, so delta-rs removes whole files without reading them;
        they stay on storage, for readers of older versions, until the vacuum after vacuum_retention_hours
        frees them."""
        if self.settings.keep_days <= 0:
            return
        days = _partition_days(dtable)
        cut = _expiry_cut(table, days, today, self.settings.keep_days, key=self.settings.table_uri(table))
        old = [day for day in days if day < cut]
        if not old:  # no day old enough: no delete to run, nothing to log
            return
        metrics = dtable.delete(f"{PARTITION_COLUMN} < '{cut}'")
        # delta-rs leaves the count out when it could only know it by reading the files.
        counted = metrics.get("num_deleted_rows")
        rows = int(counted or 0)
        with self._cond:
            self._stats.rows_expired += rows
        log.info(
            "history: deleted %s rows of %s older than keep_days = %d (%s)",
            "the" if counted is None else rows,
            table,
            self.settings.keep_days,
            ", ".join(old) if len(old) <= 10 else f"{old[0]} to {old[-1]}, {len(old)} days",
            extra={
                "rows_expired": rows,
                "days_expired": len(old),
                "files_removed": metrics.get("num_removed_files"),
            },
        )

    def _maintain_table(self, table: str, dtable: Any, days: list[dt.date]) -> None:
        existing = set(_partition_days(dtable))
        for day in days:
            if day.isoformat() not in existing:
                continue
            metrics = dtable.optimize.compact(
                partition_filters=[(PARTITION_COLUMN, "=", day.isoformat())],
                target_size=self.settings.target_file_mb << 20,
                writer_properties=_writer_properties(COMPACT_ZSTD_LEVEL),
            )
            log.info(
                "history: compacted %s/%s",
                table,
                day.isoformat(),
                extra={
                    "files_added": metrics.get("numFilesAdded"),
                    "files_removed": metrics.get("numFilesRemoved"),
                },
            )
        dtable.create_checkpoint()
        dtable.vacuum(
            # Whole hours, rounded up: a retention shorter than asked (0.5 h truncated was 0) would take
            # files from under a reader still on an older version.
            retention_hours=math.ceil(self.settings.vacuum_retention_hours),
            enforce_retention_duration=False,
            dry_run=False,
        )
        dtable.cleanup_metadata()

    def maintain_now(self, today: dt.date | None = None) -> None:
        """Run maintenance now, waiting for it, for `today` (UTC) and the day before; call it on a writer
        whose committer is closed or has maintenance off (`maintain_every_s = 0`)."""
        self._maintain(today)

    def maintenance_request(self, today: dt.date) -> dict[str, Any]:
        """What the maintenance process needs to maintain as this writer would (plain JSON values).

        `wall` is this writer's clock as it asks: the process takes its lease for that window, not for the
        one its own clock reads once it has started, so a run asked for just before a window's end is
        still leased in the window it was due in (and a test's clock reaches the process)."""
        settings = dataclasses.asdict(self.settings)
        settings["storage_options"] = dict(self.settings.storage_options)
        return {
            "settings": settings,
            "writer_id": self.writer_id,
            "today": today.isoformat(),
            "wall": self._wall(),
            "clock_warned": {table: list(jump) for table, jump in _CLOCK_WARNED.items()},
        }

    def maintenance_result(self) -> dict[str, Any]:
        """This writer's maintenance counters (what the maintenance process answers)."""
        with self._cond:
            stats = self._stats
            return {
                "maintenance_runs": stats.maintenance_runs,
                "maintenance_failures": stats.maintenance_failures,
                "maintenance_conflicts": stats.maintenance_conflicts,
                "maintenance_skipped": stats.maintenance_skipped,
                "rows_expired": stats.rows_expired,
                "last_error": stats.last_error,
                "clock_warned": {table: list(jump) for table, jump in _CLOCK_WARNED.items()},
            }

    def _maintain_in_process_of_its_own(self, today: dt.date, interruptible: bool) -> None:
        try:
            result = run_child(
                self.maintenance_command,
                self.maintenance_request(today),
                timeout_s=MAINTENANCE_TIMEOUT_S,
                stop=(lambda: self._closing) if interruptible else None,
            )
        except Exception as exc:
            self._maintenance_process_failed(f"{type(exc).__name__}: {exc}")
            return
        if result is None:
            log.warning("history: maintenance was stopped by the shutdown; it runs again at the next start")
            return
        with self._cond:
            stats = self._stats
            for name in ("maintenance_runs", "maintenance_failures", "maintenance_conflicts"):
                setattr(stats, name, getattr(stats, name) + int(result.get(name, 0)))
            stats.maintenance_skipped += int(result.get("maintenance_skipped", 0))
            stats.rows_expired += int(result.get("rows_expired", 0))
            if result.get("maintenance_failures") and result.get("last_error"):
                stats.last_error = str(result["last_error"])
        remember_clock_warnings(result.get("clock_warned", {}))

    def _maintenance_process_failed(self, message: str) -> None:
        with self._cond:
            self._stats.maintenance_failures += 1
            self._stats.last_error = f"history maintenance process failed: {message}"
        log.error(
            "history: the maintenance process failed (%s); retried at the next interval",
            message,
            extra={"maintenance_failures": self._stats.maintenance_failures},
        )

    def _maintenance_failed(self, table: str, exc: BaseException) -> None:
        message = _describe_storage_error(self.settings.uri, exc)
        with self._cond:
            self._stats.maintenance_failures += 1
            self._stats.last_error = message
        log.error("history: maintenance of %s failed: %s; retried at the next interval", table, message)


def _partition_days(dtable: Any) -> list[str]:
    """The days (ISO, sorted) a table holds rows on. A partition without a value (null) is no day: as the
    string "None" it sorted after every date and took one of the newest days keep_days always keeps."""
    values = (p.get(PARTITION_COLUMN) for p in dtable.partitions())
    return sorted({str(v) for v in values if v is not None and v != ""})


# The jump (the last day held back, the next day with rows) said at WARNING by this agent, for each table:
# the same jump is said again at INFO, as an arm used weekly with a short keep_days would see the same
# warning at every maintenance, but a new one (the clock stepped to 2099 since) at WARNING. One entry a
# table, so it stays as small as the tables are few. The maintenance process, new at each run, is handed it
# and hands it back (`remember_clock_warnings`).
_CLOCK_WARNED: dict[str, tuple[str, str]] = {}


def remember_clock_warnings(warned: Mapping[str, Sequence[str]]) -> None:
    """Take the jumps a maintenance process (or the writer that started it) already warned about."""
    for table, jump in warned.items():
        if len(jump) == 2:
            _CLOCK_WARNED[str(table)] = (str(jump[0]), str(jump[1]))


def _expiry_cut(table: str, days: Sequence[str], today: dt.date, keep_days: int, *, key: str = "") -> str:
    """The first day (ISO) keep_days keeps of `table` (its name, as every log line says it), whose days with
    rows are `days` (sorted); `key` (its location, default its name) is what a warning is remembered by, as
    two writers' tables of one name are not one table.

    The wall clock alone is not trusted: one stepped far forward (a bad NTP answer at first boot, the year
    2099) put every day before its cut, and the first maintenance deleted the whole history. So the newest
    keep_days + 1 days that hold rows are kept whatever the clock says; older days go as rows of later days
    come in, as fast as the agent really writes them. A day held back that the clock alone would delete is
    said: at WARNING when the rows jump forward by more than the whole window after it (a clock stepped
    forward, or no rows that long), once for each such jump of a table while the agent runs, else at INFO
    (an arm not used every day)."""
    by_clock = (today - dt.timedelta(days=keep_days)).isoformat()
    newest = days[-(keep_days + 1) :]
    cut = min(by_clock, newest[0]) if newest else by_clock
    held = [day for day in days if cut <= day < by_clock]
    if held:
        after = next((day for day in days if day > held[-1]), today.isoformat())
        jump = (dt.date.fromisoformat(after) - dt.date.fromisoformat(held[-1])).days
        key = key or table
        warn = jump > keep_days and _CLOCK_WARNED.get(key) != (held[-1], after)
        if warn:
            _CLOCK_WARNED[key] = (held[-1], after)
        log.log(
            logging.WARNING if warn else logging.INFO,
            "history: keep_days = %d kept %d day(s) of %s that the clock (today %s) puts before its cut "
            "(%s to %s): the table holds rows on fewer than %d later days%s; they go once it does",
            keep_days,
            len(held),
            table,
            today.isoformat(),
            held[0],
            held[-1],
            keep_days + 1,
            f", and its rows jump {jump} days forward after {held[-1]}: the clock stepped (check it with "
            f"timedatectl), or the table had no rows for {jump} days"
            if jump > keep_days
            else "",
            extra={"days_held": len(held), "table": table},
        )
    return cut


def _s3_client(options: Mapping[str, str]) -> Any:
    """A boto3 S3 client for the same endpoint and credentials delta-rs uses (options, else the AWS chain)."""
    import boto3  # noqa: PLC0415 - only S3 history needs it

    kwargs: dict[str, Any] = {}
    for key, arg in (
        ("AWS_ENDPOINT_URL", "endpoint_url"),
        ("AWS_REGION", "region_name"),
        ("AWS_ACCESS_KEY_ID", "aws_access_key_id"),
        ("AWS_SECRET_ACCESS_KEY", "aws_secret_access_key"),
        ("AWS_SESSION_TOKEN", "aws_session_token"),
    ):
        value = options.get(key) or options.get(key.lower())
        if value:
            kwargs[arg] = value
    # delta-rs reads AWS_REGION itself; boto3 does not (twin.core.aws).
    kwargs.setdefault("region_name", region_or_env())
    return boto3.client("s3", **kwargs)


# What os.link raises where the filesystem has no hard links (vfat, exFAT, CIFS, some FUSE): EPERM on vfat
# and exFAT, ENOTSUP/EOPNOTSUPP on CIFS and FUSE, ENOSYS or EXDEV on some FUSE filesystems.
_NO_HARD_LINKS = frozenset({errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS, errno.EXDEV})


def _link(source: Path, target: Path) -> bool:
    """os.link; False, having linked nothing, where the filesystem has no hard links."""
    try:
        os.link(source, target)
    except OSError as exc:
        if exc.errno in _NO_HARD_LINKS:
            return False
        raise
    return True


def _set_aside(entry: Path) -> Path | None:
    """Move a table's newest log entry to SET_ASIDE_DIR beside its log; None, with the entry put back, when
    another writer committed after it meanwhile: it is then no longer the newest. Each step is a hard link
    and an unlink, never a rename: a rename replaces what it lands on, and a put back landed on the new
    entry of that number another writer had committed meanwhile, with its rows. Still a check and then an
    act: safe with one writer per local table (docs/history.md). Where the filesystem has no hard links,
    each step is a check that the name is free and then a rename (`_set_aside_by_rename`)."""
    folder = entry.parent.parent / SET_ASIDE_DIR
    folder.mkdir(exist_ok=True)
    n = 0
    while True:
        target = folder / (entry.name if n == 0 else f"{entry.name}.{n}")
        try:
            if not _link(entry, target):
                return _set_aside_by_rename(entry, folder)
            break
        except FileExistsError:  # one set aside before, under this name: kept too
            n += 1
    os.unlink(entry)
    if (entry.parent / f"{int(entry.stem) + 1:020d}.json").exists():
        try:
            linked = _link(target, entry)
        except FileExistsError:  # another writer committed this version anew: its entry stays, ours aside
            return target
        if not linked:
            return _put_back_by_rename(entry, target)
        os.unlink(target)
        return None
    return target


def _set_aside_by_rename(entry: Path, folder: Path) -> Path | None:
    """`_set_aside` where hard links are refused: a rename replaces what it lands on, so each name is checked
    free first, which leaves a moment in which another writer's new entry can be replaced."""
    log.warning(
        "history: the filesystem has no hard links: the log entry %s is moved aside by rename, which "
        "could replace an entry another writer commits at that moment (keep one writer per table)",
        entry,
        extra={"event": "history_set_aside_rename", "entry": str(entry)},
    )
    n = 0
    target = folder / entry.name
    while target.exists():  # one set aside before, under this name: kept too
        n += 1
        target = folder / f"{entry.name}.{n}"
    os.rename(entry, target)
    if (entry.parent / f"{int(entry.stem) + 1:020d}.json").exists():
        return _put_back_by_rename(entry, target)
    return target


def _put_back_by_rename(entry: Path, target: Path) -> Path | None:
    if entry.exists():  # another writer committed this version anew: its entry stays, ours aside
        return target
    os.rename(target, entry)
    return None


# Below this much free space a local commit that follows one failed on a full disk fails before deltalake is
# called: on a full disk deltalake's object store panicked on a worker thread at each attempt, a Rust panic
# on stderr ("Already shut down", and with RUST_BACKTRACE set its backtrace) beside the writer's own line,
# once a minute for as long as the disk stayed full. Only then: statvfs's figures are not trusted at each
# commit (a FUSE or network filesystem can report zeros, and root may write into the blocks kept for it).
MIN_FREE_BYTES = 1 << 20


def _is_disk_full(exc: BaseException) -> bool:
    """What `_describe_storage_error` calls a full disk (a file past the filesystem's size limit too)."""
    text = str(exc).lower()
    return (
        getattr(exc, "errno", None) in (errno.ENOSPC, errno.EFBIG)
        or "no space left" in text
        or "enospc" in text
        or "file too large" in text
    )


def _require_free_space(uri: str) -> None:
    """Raise ENOSPC when the local history's filesystem has less than MIN_FREE_BYTES free; nothing when
    statvfs does not tell (zero blocks or block size, as FUSE and network filesystems can say)."""
    try:
        st = os.statvfs(uri.removeprefix("file://"))
    except OSError:
        return  # the commit itself says what is wrong with the path
    if not st.f_blocks or not st.f_frsize:
        return
    # Root may write into the blocks the filesystem keeps for it (5 % on ext4), so those count for root.
    free = (st.f_bfree if os.geteuid() == 0 else st.f_bavail) * st.f_frsize
    if free < MIN_FREE_BYTES:
        raise OSError(
            errno.ENOSPC,
            f"No space left on device: {free} bytes free, below the {MIN_FREE_BYTES} a commit is tried with",
        )


def _describe_storage_error(uri: str, exc: BaseException) -> str:
    if isinstance(exc, HistoryLogError):  # names the entry and the fix itself
        return f"cannot write history to {uri}: {exc}"
    text = " ".join(str(exc).split())
    if len(text) > 400:
        text = text[:397] + "..."
    lowered = text.lower()
    if "no space left" in lowered or "enospc" in lowered or "file too large" in lowered:
        hint = (
            "the disk is full: free space or point [history] uri at a larger volume (a Rust panic on stderr, "
            "'Already shut down', is deltalake's for this same failure, not a crash)"
        )
    elif "permission denied" in lowered or "accessdenied" in lowered or "forbidden" in lowered:
        hint = "access denied: check the directory's permissions or the role's s3:PutObject on the prefix"
    elif "nosuchbucket" in lowered:
        hint = "the bucket does not exist: check [history] uri"
    elif any(w in lowered for w in ("connect", "timed out", "dns", "error sending request", "unreachable")):
        hint = "storage is unreachable: check the network or the S3 endpoint"
    else:
        hint = "see the error above"
    return f"cannot write history to {uri} ({type(exc).__name__}: {text}); {hint}"


# --- the sink ------------------------------------------------------------------------------------------


class HistoryWorker:
    """The `SinkWorker` of the history sink: chunks samples into Arrow tables for the `HistoryWriter`."""

    def __init__(self, writer: HistoryWriter, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.writer = writer
        self._settings = writer.settings
        self._clock = clock
        self._applied: list[AppliedSample] = []
        self._rejected: list[RejectedSample] = []
        self._applied_since = 0.0
        self._rejected_since = 0.0
        # How long close() lets the writer retry its last commit; the sink sets it from its own close budget.
        self.close_timeout_s = 25.0

    def handle_applied(self, sample: AppliedSample) -> None:
        if not self._applied:
            self._applied_since = self._clock()
        self._applied.append(sample)
        if len(self._applied) >= self._settings.chunk_rows or (
            self._clock() - self._applied_since >= self._settings.chunk_max_age_s
        ):
            self._convert_applied()

    def handle_rejected(self, sample: RejectedSample) -> None:
        if not self._rejected:
            self._rejected_since = self._clock()
        self._rejected.append(sample)
        if len(self._rejected) >= self._settings.chunk_rows or (
            self._clock() - self._rejected_since >= self._settings.chunk_max_age_s
        ):
            self._convert_rejected()

    def idle(self) -> None:
        now = self._clock()
        if self._applied and now - self._applied_since >= self._settings.chunk_max_age_s:
            self._convert_applied()
        if self._rejected and now - self._rejected_since >= self._settings.chunk_max_age_s:
            self._convert_rejected()

    def flush(self, timeout: float = 30.0) -> bool:
        """Convert what is collected and commit it now (called on the sink's thread, or when it is idle)."""
        self._convert_applied()
        self._convert_rejected()
        return self.writer.flush(timeout)

    def close(self) -> None:
        self._convert_applied()
        self._convert_rejected()
        # Shorter than the sink's own wait (HistorySink.close), so a dead store is reported by the writer
        # (with the count of rows it could not write) before the sink gives up on it.
        self.writer.close(timeout=self.close_timeout_s)

    def _convert_applied(self) -> None:
        samples, self._applied = self._applied, []
        if not samples:
            return
        try:
            rows, slow = telemetry_table(samples)
        except Exception as exc:
            self.writer.count_conversion(lost_rows=len(samples), error=f"{type(exc).__name__}: {exc}")
            raise
        if slow:
            self.writer.count_conversion(slow=True)
            log.warning("history: a chunk of %d payloads needed the slow JSON path", len(samples))
        self.writer.add(TELEMETRY_TABLE, rows)

    def _convert_rejected(self) -> None:
        samples, self._rejected = self._rejected, []
        if not samples:
            return
        try:
            rows = rejected_table(samples, self._settings.rejected_payload_max_bytes)
        except Exception as exc:
            self.writer.count_conversion(lost_rows=len(samples), error=f"{type(exc).__name__}: {exc}")
            raise
        self.writer.add(REJECTED_TABLE, rows)


class HistorySink(QueuedSink):
    """The history sink the agent adds next to its other sinks. /state shows its queue (`stats()`, as for
    every sink) and its writer (`writer.stats()`: commits, rows, storage health)."""

    def __init__(self, settings: HistorySettings, *, writer_id: str | None = None) -> None:
        self.writer = HistoryWriter(settings, writer_id=writer_id).start()
        self.worker = HistoryWorker(self.writer)
        # Rows wait for a commit anyway: handing them over 50 ms at a time costs the mirror nothing.
        super().__init__("history", self.worker, max_pending=settings.queue_max, idle_s=0.25, hand_off_s=0.05)

    def close(self, timeout: float = 30.0) -> None:
        # The queue drains first; the worker's close commits the rest, retrying for all but the last few
        # seconds of `timeout` (the writer bounds its own wait and reports the rows it could not write).
        self.worker.close_timeout_s = max(1.0, timeout - 8.0)
        super().close(timeout)
