"""The agent's state file: the servo alarms a person must still see after the agent restarts or the host
reboots (`[twin] state_file`, under the service's state directory on the host).

What it keeps: every alarm that is ACTIVE, ACKNOWLEDGED or LATCHED, with its state, when it last changed (wall
clock), how often it was raised and its message. An acknowledgement is a person's decision and a LATCHED
alarm is a condition nobody has seen yet: a restart must forget neither. NORMAL alarms are not kept (the next
message makes them again), nor counters, health or poses: those start again with the agent.

Written atomically (a temporary file in the same directory, flushed to disk, renamed over the old one, the
directory flushed), so a crash or a power cut mid-write leaves the previous file or the new one, never half of
one. Written when the kept alarms change (the agent checks every second), at the first check after it starts,
and when it stops. A file that cannot be read is reported and set aside; the agent starts without it rather
than not at all. Alarms of a kind this agent does not know (a newer agent's file, then a rollback) are not a
reason to set it aside: they are told, carried and written back as they were.

It also says whether the run that wrote it stopped: `stopped` is false from that first write until the stop's.
A file that still says false when an agent starts was left by a run that was killed, crashed or lost its host,
which nothing else tells the next run (the log just ends, without the `agent stopped` line): `load` logs a
warning naming that run and what such an end loses.

JSON, one object: {"version": 1, "written_at": <epoch s>, "pid": <the writer's pid>, "stopped": <bool>,
"alarms": [{...}, ...]}. A file without `stopped` (an older agent's) says nothing about how its run ended.

On the twin host a copy of the file is kept in the stack's bucket whenever it changes, and a host that
replaces this one starts with the newest host's copy (userdata/install-agent.sh, `adopt`): the alarms carry
over, and since the run that wrote it was another host's, the copy says nothing about how that run ended.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import logging
import math
import os
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from twin.core.alarms import AlarmKind, AlarmRecord, AlarmState
from twin.core.throttle import Throttle
from twin.output.sinks import SinkStats

log = logging.getLogger(__name__)

VERSION = 1
# The states a restart must not forget.
KEPT_STATES = frozenset({AlarmState.ACTIVE, AlarmState.ACKNOWLEDGED, AlarmState.LATCHED})


# The state file as an output in /state's `agent.sinks`: its failed writes reach SinkDrops and its alarm.
SINK_NAME = "state_file"
# A write that fails fails again at the next check, a second later: one log line per this many seconds.
ERROR_LOG_INTERVAL_S = 60.0


class StateFileError(ValueError):
    """The state file exists but is not one this agent wrote; the message says what is wrong."""


class NotSavedError(Exception):
    """A person's act (an acknowledgement, a forget) was made, but the state file could not be written
    before the answer: a restart before the next write that succeeds would undo it. `result` is the act's."""

    def __init__(self, message: str, result: object) -> None:
        super().__init__(message)
        self.result = result


@dataclass(frozen=True, slots=True)
class PreviousRun:
    """What the state file says of the run that wrote it: whether it made its stop's write (None: the file
    does not say, an older agent's) and when it last wrote (epoch s; None if not a number)."""

    stopped: bool | None
    written_at: float | None


class StateFile:
    """Reads and writes the state file at `path` (see the module doc)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.writes = 0
        self.write_errors = 0
        # Files `load` found unusable and set aside (their alarms were not restored).
        self.unusable = 0
        self.last_error = ""
        # The last write failed (and the file on disk is older than what the agent holds).
        self.failing = False
        self._error_lines = Throttle(ERROR_LOG_INTERVAL_S)
        # What the last write held, by what identifies a change (not the wall time, which a clock slewed
        # by NTP would move a little at every check), and whether it said the run had stopped.
        self._last: tuple[list[tuple[str, str, int, float]], int, bool] | None = None
        # The agent's supervisor and an acknowledgement's own write (AgentService) may both save: one at a
        # time, so `_last` always describes the file on disk.
        self._write_lock = threading.Lock()
        # The document `previous_run` read, kept for `load`: a large fleet's file is parsed once.
        self._document: dict[str, Any] | None = None
        # Alarms of kinds this agent does not know, as read (a newer agent's file, then a rollback): written
        # back with every write, so rolling forward again finds them as they were.
        self._carried: list[dict[str, Any]] = []

    def previous_run(self) -> PreviousRun | None:
        """How the run that wrote the file ended, read as the agent starts (before `load`); None without a
        file that parses (`load` then says what is wrong with it)."""
        try:
            document = _document_of(self.path.read_bytes())
        except (OSError, StateFileError):
            return None
        self._document = document
        stopped, written = document.get("stopped"), document.get("written_at")
        return PreviousRun(
            stopped=stopped if isinstance(stopped, bool) else None,
            written_at=float(written)
            if isinstance(written, int | float) and not isinstance(written, bool)
            else None,
        )

    # -- reading -------------------------------------------------------------------------------------------

    def load(self, now_mono: float, now_wall: float) -> list[AlarmRecord]:
        """The alarms the file keeps, with their times on this process's monotonic clock; [] when there is
        no file. A file that cannot be parsed is renamed `<name>.bad` and reported; [] then too. Temporary
        files that writes cut short by a kill left beside it are removed first."""
        self._remove_leftovers()
        document, self._document = self._document, None
        try:
            text = b"" if document is not None else self.path.read_bytes()
        except FileNotFoundError:
            # Absolute: a relative path started from another directory is a new, empty file there.
            log.info(
                "state file %s does not exist yet: no alarms are brought back; the first check writes it",
                self.path.absolute(),
                extra={"path": str(self.path.absolute())},
            )
            return []
        except OSError as exc:
            # Set aside as an invalid one is: left in place, the first check's write would replace it (a
            # rename needs only the directory's permission) and its acknowledgements with it.
            self._set_aside(f"cannot be read: {exc}")
            return []
        try:
            if document is None:
                document = _document_of(text)
            document, carried = _split_unknown_kinds(document)
            carried = _writable(carried, self.path)
            records = records_of(document, now_mono, now_wall)
        except StateFileError as exc:
            self._set_aside(f"is not valid: {exc}")
            return []
        log.info("state file read", extra={"path": str(self.path), "alarms": len(records)})
        with self._write_lock:
            self._carried = carried
        if carried:
            log.warning(
                "state file %s keeps %d alarm(s) of a kind this agent does not know (%s), written by a newer "
                "version of it: they are not shown or raised here, and are kept in the file for that version",
                self.path,
                len(carried),
                ", ".join(sorted({str(item.get("alarm_id", item["kind"])) for item in carried})),
                extra={"path": str(self.path), "unknown_alarms": len(carried)},
            )
        _report_unclean_stop(self.path, document)
        return records

    def _set_aside(self, problem: str) -> None:
        """Rename the file that `load` could not use to `<name>.bad`, so no write replaces it, and say so. One
        set aside before is not replaced: it may be the one that holds the acknowledgements (docs/deploy.md
        tells a person to move it back), and this one `<name>.bad.<n>` then."""
        try:
            bad = move_to_free_name(self.path, numbered(self.path.with_name(self.path.name + ".bad")))
        except OSError as exc:
            fix = f"it could not be moved aside ({exc}) and the first write replaces it: copy it away now"
        else:
            fix = (
                f"moved to {bad.name}; to bring its alarms back, stop the agent, correct that file (or copy "
                f"the host's saved one) and move it back to {self.path.name}"
            )
        # Its alarms, acknowledgements included, are not restored: a loss, counted as a dropped save so it
        # reaches /state's `agent.sinks`, SinkDrops and its alarm, not only this log line.
        self.unusable += 1
        self.last_error = f"state file {self.path} {problem}; started without the alarms it kept; {fix}"
        log.error("%s", self.last_error)

    def forget(self, device: str) -> None:
        """Drop the alarms of unknown kinds carried for `device` (an arm an operator forgot): the next write
        leaves them out, as it does the arm's own."""
        with self._write_lock:
            self._carried = [item for item in self._carried if item.get("device") != device]

    def _remove_leftovers(self) -> None:
        """A write killed between its temporary file's creation and the rename leaves that file (each as
        large as the state file), and nothing else ever removes it: crash after crash they would pile up.
        Called as the agent starts, before this process writes any."""
        removed = 0
        for leftover in self.path.parent.glob(f".{glob.escape(self.path.name)}.*{TEMPORARY_SUFFIX}"):
            with contextlib.suppress(OSError):
                leftover.unlink()
                removed += 1
        if removed:
            log.info(
                "state file: removed %d temporary file(s) left by writes a kill cut short",
                removed,
                extra={"path": str(self.path)},
            )

    # -- writing -------------------------------------------------------------------------------------------

    def save(
        self, records: Sequence[AlarmRecord], now_mono: float, now_wall: float, *, stopped: bool = False
    ) -> bool:
        """Write the kept alarms of `records` if they, or `stopped` (the agent's last write, as it stops),
        differ from the last write; True when written. The first call always writes: it marks the run as
        running (module doc). A failed write is logged and counted, never raised: the twin goes on without
        it."""
        with self._write_lock:
            return self._save(records, now_mono, now_wall, stopped)

    def _save(self, records: Sequence[AlarmRecord], now_mono: float, now_wall: float, stopped: bool) -> bool:
        kept = sorted((r for r in records if r.state in KEPT_STATES), key=lambda r: r.alarm_id)
        identity = (
            [(r.alarm_id, str(r.state), r.raised, round(r.since, 3)) for r in kept],
            len(self._carried),
            stopped,
        )
        if identity == self._last:
            return False
        entries = [entry(r, now_mono, now_wall) for r in kept] + self._carried
        document = {
            "version": VERSION,
            "written_at": now_wall,
            "pid": os.getpid(),
            "stopped": stopped,
            "alarms": entries,
        }
        try:
            write_atomically(self.path, json.dumps(document, indent=1, sort_keys=True) + "\n")
        except OSError as exc:
            self._failed(exc, now_mono, stopped=stopped)
            return False
        if self.failing:
            log.warning(
                "state file %s written again, after %d failed writes: the alarms it keeps are current",
                self.path,
                self.write_errors,
            )
        self.failing = False
        self._error_lines.clear()
        self._last = identity
        self.writes += 1
        return True

    def _failed(self, exc: OSError, now_mono: float, *, stopped: bool = False) -> None:
        """Count a failed write; log it at once, then at most once a minute (the next check tries again).
        The stop's own write is told whatever the minute: no check follows it, and without it the next start
        reads the file as left by a run that was killed."""
        self.write_errors += 1
        self.last_error = f"{exc.__class__.__name__}: {exc}"
        self.failing = True
        if stopped:
            log.error(
                "state file %s could not record this stop (%s): the next start will say this run did not "
                "stop, and bring back its alarms as of the file's last write; free space in (or fix the "
                "permissions of) %s before starting the agent again",
                self.path,
                exc,
                self.path.parent.absolute(),
                extra={"path": str(self.path)},
            )
            return
        since = self._error_lines.due(now=now_mono)
        if since is None:
            return
        again = f" ({since} failed writes since the last line)" if self._error_lines.told > 1 else ""
        log.error(
            "state file %s could not be written (%s)%s: acknowledgements and latched alarms since the last "
            "write would not survive a restart; free space in (or fix the permissions of) %s, and the next "
            "check, a second later, writes it",
            self.path,
            exc,
            again,
            self.path.parent.absolute(),
        )

    def stats(self) -> SinkStats:
        """The file as an output in /state's `agent.sinks`: each failed write is a dropped save, so it reaches
        the SinkDrops metric and its alarm, as does a file found unusable at the start (its alarms are lost to
        this run); `pending` is 1 while the file on disk is behind."""
        return SinkStats(
            name=SINK_NAME,
            delivered=self.writes,
            dropped=self.write_errors + self.unusable,
            errors=self.write_errors + self.unusable,
            pending=int(self.failing),
            last_error=self.last_error,
        )


def _report_unclean_stop(path: Path, document: dict[str, Any]) -> None:
    """Warn when the file was left by a run that never made its stop's write (module doc)."""
    if document.get("stopped") is False:
        pid = document.get("pid")
        written_at = document.get("written_at")
        log.warning(
            "the agent's previous run (pid %s) did not stop: killed, crashed or its host went down (or its "
            "stop could not be written here, a full or read-only disk, which its log's last lines say). Its "
            "alarms are back as of its last check (it checked every second; this file last changed at %s); "
            "its counters start again, and the messages it still held, or that arrived while no agent ran, "
            "are lost without a count. Its workers' `worker stopped` lines say what they could not write, "
            "and its history writer logs any rows it could not commit. Look for why it ended (journalctl, "
            "the kernel's OOM log)",
            pid,
            _utc(written_at),
            extra={"path": str(path), "previous_pid": pid, "state_written_at": written_at},
        )


def _utc(epoch_s: object) -> str:
    """`epoch_s` as an ISO UTC time, whatever the file holds (this only words a warning)."""
    try:
        return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(float(epoch_s)))  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError, OSError):
        return "an unknown time"


def entry(record: AlarmRecord, now_mono: float, now_wall: float) -> dict[str, Any]:
    """One alarm as the file keeps it: the change time on the wall clock (a reboot resets monotonic time)."""
    return {
        "alarm_id": record.alarm_id,
        "device": record.device,
        "joint": record.joint,
        "kind": str(record.kind),
        "state": str(record.state),
        "changed_at": now_wall - (now_mono - record.since),
        "raised": record.raised,
        "value": record.value,
        "message": record.message,
    }


def parse(text: str, now_mono: float, now_wall: float) -> list[AlarmRecord]:
    """The records of a state file's text; StateFileError naming the first thing wrong."""
    return records_of(_document_of(text), now_mono, now_wall)


def _document_of(text: str | bytes) -> dict[str, Any]:
    """A state file's text as its document, read once (a 600-arm fleet's file is megabytes); StateFileError
    when it is not JSON or not this version's."""
    try:
        # Bytes as read: a file a failing disk left as garbage is then not JSON (UnicodeDecodeError is a
        # ValueError), where decoding it first raised past the callers and stopped the agent's start.
        document = json.loads(text)
    except ValueError as exc:
        raise StateFileError(f"not JSON: {exc}") from None
    except RecursionError:
        # Uncaught, it passed the start's checks: "cannot start: maximum recursion depth exceeded".
        raise StateFileError("not JSON: nested too deeply") from None
    if not isinstance(document, dict) or document.get("version") != VERSION:
        raise StateFileError(f"not a version-{VERSION} state file")
    return document


# An alarm entry is an object of scalars: a newer agent's may add some nesting, not hundreds of levels.
MAX_CARRIED_DEPTH = 32


def _split_unknown_kinds(document: dict[str, Any]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The document without its alarms of kinds this agent does not know, and those alarms. An agent rolled
    back to a version without a kind would otherwise refuse the whole file, and with it every acknowledgement
    and latched alarm of the kinds it does know."""
    alarms = document.get("alarms")
    if not isinstance(alarms, list):
        return document, []  # records_of says what is wrong
    known_kinds = {kind.value for kind in AlarmKind}
    known: list[Any] = []
    unknown: list[dict[str, Any]] = []
    for item in alarms:
        kind = item.get("kind") if isinstance(item, dict) else None
        (unknown if isinstance(kind, str) and kind not in known_kinds else known).append(item)
    return {**document, "alarms": known}, unknown


def _writable(carried: list[dict[str, Any]], path: Path) -> list[dict[str, Any]]:
    """The carried alarms that can be written back. One nested near the parser's limit loaded, and every save
    after raised RecursionError in json.dumps: no agent writes one so deep, so it alone is dropped, said,
    and the file's other alarms (acknowledgements) are kept."""
    kept: list[dict[str, Any]] = []
    dropped: list[str] = []
    for item in carried:
        if _depth(item) <= MAX_CARRIED_DEPTH:
            kept.append(item)
        else:
            dropped.append(str(item.get("alarm_id", item["kind"]))[:80])
    if dropped:
        log.warning(
            "state file %s: dropped %d alarm(s) of an unknown kind nested more than %d levels deep, which no "
            "agent writes (%s); the file's other alarms are kept",
            path,
            len(dropped),
            MAX_CARRIED_DEPTH,
            ", ".join(repr(d) for d in dropped),
        )
    return kept


def _depth(value: Any) -> int:
    """How deeply `value` (parsed JSON) nests lists and objects, without recursion."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        item, depth = stack.pop()
        deepest = max(deepest, depth)
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else ()
        stack.extend((child, depth + 1) for child in children if isinstance(child, dict | list))
    return deepest


def records_of(document: dict[str, Any], now_mono: float, now_wall: float) -> list[AlarmRecord]:
    """The records of a state file's document (`_document_of`); StateFileError naming the first thing
    wrong."""
    alarms = document.get("alarms")
    if not isinstance(alarms, list):
        raise StateFileError("'alarms' is not a list")
    out = []
    for i, item in enumerate(alarms):
        try:
            state = AlarmState(item["state"])
            changed_at = float(item["changed_at"])
            value = item.get("value")
            record = AlarmRecord(
                device=str(item["device"]),
                joint=str(item["joint"]),
                kind=AlarmKind(item["kind"]),
                state=state,
                # Back on this process's monotonic clock; a change "in the future" (a clock stepped back)
                # is taken as now.
                since=now_mono - max(0.0, now_wall - changed_at),
                # The condition of an ACTIVE or ACKNOWLEDGED alarm is taken as still present: it clears by
                # the usual rule once readings show it gone.
                present=state is not AlarmState.LATCHED,
                raised=int(item.get("raised", 1)),
                value=float(value) if isinstance(value, int | float) and math.isfinite(value) else None,
                message=str(item.get("message", "")),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise StateFileError(f"alarm {i}: {exc!r}") from None
        if state not in KEPT_STATES:
            raise StateFileError(f"alarm {i} is {state}, which the file never keeps")
        out.append(record)
    return out


def adopt(text: str | bytes) -> tuple[str, int]:
    """Another host's state file as this host's first one, and how many alarms it keeps: the same alarms,
    without `stopped` (that run was not this host's, and it may still be running while its replacement
    boots, so it ended neither cleanly nor not). StateFileError when the text is not a valid state file: a
    bad copy is not put in place."""
    document = _document_of(text)
    records = records_of(document, time.monotonic(), time.time())
    document.pop("stopped", None)
    return json.dumps(document, indent=1, sort_keys=True) + "\n", len(records)


def adopt_file(source: str, target: str) -> int:
    """`adopt` from file to file (install-agent.sh runs it), written atomically; the number of alarms."""
    adopted, alarms = adopt(Path(source).read_bytes())
    write_atomically(Path(target), adopted)
    return alarms


def numbered(path: Path, count: int | None = None) -> Iterator[Path]:
    """`path`, then `<path>.1`, `<path>.2` ... (`count` names in all, or without end): the names tried for a
    copy that must not replace one already there (a state file set aside, a calibration rescued)."""
    n = 0
    while count is None or n < count:
        yield path if n == 0 else path.with_name(f"{path.name}.{n}")
        n += 1


def move_to_free_name(path: Path, names: Iterable[Path]) -> Path:
    """Rename `path` to the first of `names` that no file holds, and return it. A hard link is made first,
    which fails when the name is taken, then `path` is removed: a test for a free name and a rename after it
    would let another process's file, made between the two, be replaced. A filesystem without hard links
    takes the test and the rename. OSError when the directory cannot be looked in or written."""
    for name in names:
        try:
            # The link itself when `path` is one, as a rename moves it (Python 3.14 follows it by default).
            os.link(path, name, follow_symlinks=False)
        except FileExistsError:
            continue
        except OSError as exc:
            if exc.errno not in _NO_HARD_LINKS:
                raise
            if name.exists() or name.is_symlink():
                continue
            os.replace(path, name)
            return name
        try:
            os.unlink(path)
        except OSError:
            # Left with two names (a sticky directory lets a link be made but not the file removed): the
            # new one goes, or each start would add one.
            with contextlib.suppress(OSError):
                os.unlink(name)
            raise
        return name
    raise FileExistsError(f"every name for {path} is taken")


# What a filesystem without hard links (vfat, some network shares) answers a link with.
_NO_HARD_LINKS = frozenset({errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EMLINK, errno.ENOSYS})


# write_atomically's temporary files are `.<name>.<random>.tmp`, beside the file they become.
TEMPORARY_SUFFIX = ".tmp"


def is_temporary(name: str) -> bool:
    """Whether a file name is one of write_atomically's temporary files."""
    return name.startswith(".") and name.endswith(TEMPORARY_SUFFIX)


def write_atomically(path: Path, text: str | bytes) -> None:
    """Replace `path` with `text` (str as UTF-8) so that a crash at any point leaves the old file or the new
    one; a write that fails leaves no temporary file behind."""
    data = text.encode() if isinstance(text, str) else text
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TEMPORARY_SUFFIX, dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            # mkstemp's file is 0600: renamed as it is, a calibration pushed by root would be one the agent's
            # own user can no longer read. The file keeps the mode it had, and a new one gets the umask's.
            # A filesystem that refuses modes (vfat, some network shares) still takes the write: the mode
            # is a courtesy to other readers, the content is what must not be lost.
            with contextlib.suppress(OSError):
                os.fchmod(fh.fileno(), _mode_for(path))
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    # The rename itself is durable only once the directory is.
    dir_fd = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def _mode_for(path: Path) -> int:
    """The permission bits `path` has, or a new file's under this process's umask (read from /proc: setting
    and restoring it with os.umask would race with other threads' files)."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        pass
    umask = 0o022
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                umask = int(line.split()[1], 8)
    return 0o666 & ~umask
