"""The console's sessions, from the telemetry history: the list, and each session's files made on demand.

A session is one device's continuous telemetry: consecutive messages no more than the gap apart (the
console's `[http] session_gap_s`, 30 s by default), as `twin history ls` splits them. Its files:

- `csv`, `parquet`: its rows, stored and decoded columns (`twin history export`);
- `png`: joint angles, temperature, load and current (`twin history plot`);
- `rrd`: a Rerun recording rebuilt from the rows, as the Rerun sink would have written it live (docs/web.md);
- `usd`: a USD session rebuilt the same way, as the agent's recorder writes it (docs/robot-model.md).

The rebuilt files come from the stored readings: each row becomes the edge message it was (twin replay's
`payload_for`), decoded again by the agent's own decoder, so the angles are those the agent showed. The
service layer cannot import this (the history reader sits in the tools, above it): `twin run` hands a
`HistorySessions` to the agent, which gives it to its HTTP server.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import re
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from twin.core.telemetry import DecoderConfig, TelemetryDecoder, TelemetryRejected, Units
from twin.output.sinks import AppliedSample
from twin.service.config import AgentConfig
from twin.service.console import SESSION_FILE_KINDS, SessionInfo

if TYPE_CHECKING:
    from twin.ops.history import HistoryReader
    from twin.robot.model import RobotModel

log = logging.getLogger(__name__)

# The distinct errors the Sessions page's reads were told of, at most (then the set starts again).
MAX_WARNED = 64
# What differs from one read's error to the next's: numbers, hexadecimal ids.
_VARYING = re.compile(r"[0-9a-f]{6,}|\d+")


class HistorySessions:
    """A `twin.service.console.SessionCatalog` over the history at `uri`."""

    def __init__(self, uri: str, storage_options: dict[str, str] | None = None, model: str = "") -> None:
        self.uri = uri
        self._options = storage_options or {}
        self._model = model
        # Each console refresh reads the history again: a damaged table is told once per distinct error.
        self._warned: set[str] = set()
        # Why the last read listed nothing though a table is there (None: it read, or there is none yet): the
        # page said "no session yet" of a damaged history, as if it held nothing.
        self.unreadable: str | None = None

    def _reader(self) -> HistoryReader:
        from twin.ops.history import HistoryReader  # noqa: PLC0415 - polars and deltalake load here

        return HistoryReader(self.uri, self._options)

    def sessions(self, gap_s: float) -> list[SessionInfo]:
        from twin.ops.history import HistoryReadError, NoHistoryTableError  # noqa: PLC0415

        # Set once, at the end: a request between a reset and a failing read's reason (another tab's) read
        # None, and its page said "no session yet" of a damaged table.
        try:
            summaries = self._reader().summary(gap_s=gap_s)
        except NoHistoryTableError as exc:
            log.debug("no sessions yet: %s", exc)
            self.unreadable = None
            return []
        except HistoryReadError as exc:
            self.unreadable = str(exc)
            # A table that is there and cannot be read (a damaged file) must not pass for an empty one. Told
            # by what comes before its first parenthesis: after it come request ids, file names and the Rust
            # task of a panic, another each time. Bounded: a run of distinct errors starts the set again.
            head = _VARYING.sub("#", str(exc).split("(", 1)[0])
            said = f"{type(exc).__name__}: {head}"
            level = logging.DEBUG if said in self._warned else logging.WARNING
            if len(self._warned) >= MAX_WARNED:
                self._warned.clear()
            self._warned.add(said)
            log.log(level, "history: the console lists no sessions: %s", exc)
            return []
        self.unreadable = None
        out = [
            SessionInfo(device=d.device_id, start=s.start.timestamp(), end=s.end.timestamp(), messages=s.rows)
            for d in summaries
            for s in d.sessions
        ]
        return sorted(out, key=lambda s: (-s.start, s.device))

    def session_file(self, session: SessionInfo, kind: str, directory: Path) -> Path:
        from twin.ops.history import HistoryReadError, export, plot  # noqa: PLC0415

        if kind not in SESSION_FILE_KINDS:
            raise ValueError(
                f"no session file of kind {kind!r}; the kinds are {', '.join(SESSION_FILE_KINDS)}"
            )
        since, until = _window(session)
        name = "".join(c if c.isalnum() or c in "-_." else "_" for c in session.device)
        path = directory / f"{name}-{session.key}.{SESSION_FILE_KINDS[kind][1]}"
        tmp = path.with_name(path.name + ".part")
        tmp.unlink(missing_ok=True)
        reader = self._reader()
        try:
            if kind in ("csv", "parquet"):
                export(reader, tmp, kind, device=session.device, since=since, until=until)
            elif kind == "png":
                plot(reader, session.device, tmp.with_suffix(".png"), since=since, until=until)
                tmp.with_suffix(".png").replace(tmp)
            elif kind == "rrd":
                self._rebuild_rrd(reader, session, tmp, since, until)
            else:
                self._rebuild_usd(reader, session, path, since, until)
                return path
            tmp.replace(path)
        except BaseException as exc:
            # What a failed export wrote goes with it (the session-files bound does not count `.part`
            # files, and they stayed until the agent stopped).
            for part in (tmp, tmp.with_suffix(".png")):
                with contextlib.suppress(OSError):
                    part.unlink(missing_ok=True)
            if isinstance(exc, HistoryReadError):
                raise ValueError(str(exc)) from exc
            raise
        return path

    # ----------------------------------------------------------------------------------------- rebuilding

    def _samples(
        self, reader: HistoryReader, session: SessionInfo, since: dt.datetime, until: dt.datetime
    ) -> Iterator[AppliedSample]:
        """The session's rows as the samples the agent handed its sinks, decoded again."""
        from twin.ops.replay import payload_for, recorded_rows  # noqa: PLC0415

        decoders: dict[str, TelemetryDecoder] = {}
        for row in recorded_rows(reader, session.device, since, until):
            units = str(row["units"])
            decoder = decoders.get(units)
            if decoder is None:
                decoder = decoders[units] = TelemetryDecoder(DecoderConfig(units=Units(units)))
            edge_ms = int(row["edge_time"].timestamp() * 1000)
            received = row["received_at"].timestamp()
            try:
                telemetry = decoder.decode(
                    payload_for(row, session.device, edge_ms), topic_device=session.device
                )
            except TelemetryRejected as exc:
                log.debug("history row not decodable: %s", exc)
                continue
            yield AppliedSample(
                device_id=session.device,
                received_wall_s=received,
                received_mono_s=received,
                telemetry=telemetry,
                joint_angles=telemetry.angles_rad,
            )

    def _robot(self) -> RobotModel:
        from twin.robot.model import RobotModel  # noqa: PLC0415 - MuJoCo loads here

        return RobotModel.load(self._model or None)

    def _rebuild_rrd(
        self, reader: HistoryReader, session: SessionInfo, out: Path, since: dt.datetime, until: dt.datetime
    ) -> None:
        from twin.output.rerun_settings import RerunSettings  # noqa: PLC0415
        from twin.output.rerun_sink import RerunWorker  # noqa: PLC0415 - rerun loads here

        settings = RerunSettings(save=str(out), mesh_detailed_arms=1, focus_device=session.device)
        worker = RerunWorker(self._robot(), settings)
        try:
            for sample in self._samples(reader, session, since, until):
                worker.handle_applied(sample)
        finally:
            worker.close()

    def _rebuild_usd(
        self, reader: HistoryReader, session: SessionInfo, out: Path, since: dt.datetime, until: dt.datetime
    ) -> None:
        from pxr import Tf, Usd  # noqa: PLC0415 - usd-core loads here

        from twin.output.recorder import SessionRecorder  # noqa: PLC0415

        out.unlink(missing_ok=True)  # a recorder never overwrites; an active session's file is made anew
        recorded = out.with_name(f".{out.name}.recorded{out.suffix}")
        recorded.unlink(missing_ok=True)
        robot = self._robot()
        recorder = SessionRecorder(recorded, flush_interval_s=3600.0)
        try:
            for sample in self._samples(reader, session, since, until):
                recorder.record(
                    sample.device_id,
                    sample.received_mono_s,
                    robot.body_poses(sample.joint_angles),
                    sample.telemetry.diagnostics,
                )
        finally:
            recorder.close()
        # A download goes to another machine: the recorder references the robot's asset by a path relative to
        # its file, which resolves only beside this checkout (a walk's copy opened with no arm). Flattened,
        # the file holds the arm itself, about 1 MB more. Exported beside it and renamed: an export the disk
        # cuts short leaves its part of a file, which at `out` the console would serve as the session's.
        flat = out.with_name(f".{out.name}.flat{out.suffix}")
        problem = f"the session's USD file could not be written in {out.parent}; free space there"
        try:
            try:
                written = Usd.Stage.Open(str(recorded)).Flatten().Export(str(flat))
            except Tf.ErrorException as exc:
                # USD's message is a few lines of its own source locations; the OS error is in them.
                raise ValueError(f"{problem} ({' '.join(str(exc).split())[:400]})") from exc
            if not written:
                raise ValueError(problem)
            flat.replace(out)
        finally:
            recorded.unlink(missing_ok=True)
            flat.unlink(missing_ok=True)


def _window(session: SessionInfo) -> tuple[dt.datetime, dt.datetime]:
    """[since, until) around the session's rows (history keeps milliseconds; the ends here are floats)."""
    since = dt.datetime.fromtimestamp(session.start - 0.0005, dt.UTC)
    until = dt.datetime.fromtimestamp(session.end + 0.001, dt.UTC)
    return since, until


def history_sessions(config: AgentConfig) -> HistorySessions | None:
    """The sessions of the agent's own history, or None when history is off (or its extra is missing: the
    Sessions page then says so)."""
    h = config.history
    if not h.enabled:
        return None
    try:
        import polars  # noqa: F401, PLC0415 - only to know whether the reader can run
    except ImportError:
        log.warning("the console's Sessions page needs the history extra (polars); it stays empty")
        return None
    return HistorySessions(h.uri.strip(), {"AWS_REGION": h.region} if h.region else {}, config.twin.model)
