"""Rerun sink: the fleet as a Rerun recording, saved to .rrd and/or served to a browser on loopback.

For each device it writes an entity tree under `arms/<device>/` (docs/web.md draws it):

    arms/<device>                          the arm's place in the fleet grid (static)
    arms/<device>/<body>                   the body's pose in the arm's base frame, per sample (edge_time)
    arms/<device>/<body>/visual/<geom>     the geom's triangles and colour, posed in the body (static)
    arms/<device>/joints/angle_deg         six joint angles, degrees (one series per joint)
    arms/<device>/servo/<quantity>         six servo readings per quantity, when the edge sends them
    arms/<device>/status                   a labelled point over an arm that is STALE, OFFLINE or FORGOTTEN
    arms/<device>/events                   the arm going STALE, OFFLINE and back ONLINE, servo status and
                                           rejected messages, as text

Everything temporal sits on the `edge_time` timeline (the edge's own timestamps, never running backwards per
arm: twin.output.edge_time). Forward kinematics runs in
the sink's thread (`RobotModel.body_pose_array`). Cost is what decides the shape of the code: building a Rerun
archetype in Python costs far more than the sample it carries, so samples are buffered per device and sent as
Arrow columns, one record batch per device every `flush_s` (docs/web.md has the figures). The blocking part
runs behind `QueuedSink`, whose thread takes samples HANDOFF_S at a time; a per-device rate cap in front of it
bounds the stream, and Rerun's server memory limit bounds what the served stream keeps for late viewers. The
mirror never waits on any of it.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import operator
import os
import socket
import subprocess
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb
import rerun_bindings
from rerun.chunk import Chunk

from twin.core import heap
from twin.core.lifetime import die_with_parent
from twin.core.telemetry import JointDiagnostics
from twin.core.throttle import Throttle
from twin.output.edge_time import EdgeTime
from twin.output.rerun_settings import RerunSettings
from twin.output.sinks import (
    AppliedSample,
    DeviceRateCap,
    QueuedSink,
    RejectedSample,
    SinkStats,
    StatusChange,
)
from twin.robot import so101
from twin.robot.model import RobotModel
from twin.robot.visuals import VisualGeom, fit_face_budget, visual_geoms

log = logging.getLogger(__name__)

APPLICATION_ID = "so101-twin"
ROOT = "arms"
TIMELINE = "edge_time"
LOOPBACK = "127.0.0.1"
# Servo readings logged per joint, in the units JointDiagnostics carries: (field, entity name, plot title).
SERVO_SERIES: tuple[tuple[str, str, str], ...] = (
    ("temperature_c", "temperature_c", "temperature (C)"),
    ("load_percent", "load_percent", "load (%)"),
    ("current_a", "current_a", "current (A)"),
    ("velocity_rad_s", "velocity_rad_s", "velocity (rad/s)"),
    ("voltage_v", "voltage_v", "voltage (V)"),
)
# Feetech STS3215 status register (address 65), bits 0..5 (docs/telemetry.md, "Diagnostics").
SERVO_STATUS_BITS: tuple[str, ...] = (
    "voltage",
    "angle sensor",
    "temperature",
    "current",
    "angle",
    "overload",
)
# One colour per joint, the same in every plot (matplotlib's tab10, which reads well on dark and light).
JOINT_COLOURS: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
)
FLEET_COLUMNS = 10
# A device buffers at most this many samples before it is flushed whatever its age.
MAX_BATCH_ROWS = 256
# Rejections are logged as text at most this often per device; the rest are counted in the next line.
REJECT_TEXT_EVERY_S = 1.0
MAX_REJECT_KEYS = 4096
WEB_VIEWER_START_S = 15.0
PLOT_WINDOW_S = 30.0
# The sink's thread takes what is queued at most this often (QueuedSink's hand-off), so it wakes about 20
# times a second instead of once per sample: each wake-up passes the GIL between the mirror's threads and the
# sink's, which at 100 arms x 10 Hz cost more CPU than the samples' own work (docs/web.md has the figures).
# It adds nothing visible to a stream sent every flush_s.
HANDOFF_S = 0.05
# The arms' static parts (meshes, grid places) are logged a slice of arms at a time, when an arm first
# appears and again into each new .rrd after a rotation: all at once, 200 arms' meshes held the sink's thread
# for 3-6 s (a py-spy profile, docs/performance.md "Soak") while 2,000 samples a second arrived for a queue of
# 10,000, and the fleet's start and every rotation dropped samples. A slice lasts about STATICS_SLICE_S (one
# arm at least), and the next waits until the slices have had STATICS_DUTY of the thread: 200 arms' 3-6 s
# of statics spread over 12-24 s, while samples keep flowing.
STATICS_SLICE_S = 0.02
STATICS_DUTY = 0.25

_V3 = pa.list_(pa.field("item", pa.float32(), nullable=False), 3)
_Q4 = pa.list_(pa.field("item", pa.float32(), nullable=False), 4)
_SCALARS = pa.list_(pa.field("item", pa.float64(), nullable=False))
_NS = pa.timestamp("ns")
_XYZW = [4, 5, 6, 3]  # columns of a (x y z qw qx qy qz) pose row that make Rerun's (qx qy qz qw)
_NO_READINGS: tuple[None, ...] = (None,) * len(SERVO_SERIES)
# An arm's status line's level in the events view: silence is a warning, as on the console's Events page.
_STATUS_LEVELS = {"STALE": rr.TextLogLevel.WARN, "OFFLINE": rr.TextLogLevel.WARN}
# And the point labelled with it over the arm (in its base frame, above its reach): amber, red, and grey
# over an arm the agent forgot, whose meshes stay drawn with its last pose (the label says it is not live).
_STATUS_COLOURS = {"STALE": (255, 176, 0), "OFFLINE": (220, 40, 40), "FORGOTTEN": (140, 140, 140)}
# Forgotten ids whose FORGOTTEN label a new arm of that id clears (it takes its entity path): the newest
# ones, so ids churning for weeks keep the sink's memory bounded (older ones: `_ForgottenLabels.floor`).
FORGOTTEN_KEPT = 10_000
# A dropped label time further ahead than this of the forget that drops it (the later of its label time and
# the agent's wall clock then) does not move the floor: a clock is set wrong (an edge at 2099 put every later
# arm's first Clear and labels there, far from the rest of the fleet on the timeline). NTP keeps a sound
# clock within milliseconds; a label time is its arm's last sample plus the silence the agent saw, so only a
# clock this far ahead gets past it. The forget's own label time is in the reference so that an agent whose
# clock is behind (a board before NTP syncs) does not take every sound edge for one ahead. Such times are
# logged, at most once a minute (and counted: `RerunWorker.floor_ahead_ignored`).
FLOOR_AHEAD_TOLERANCE_S = 60.0
FLOOR_AHEAD_TELL_EVERY_S = 60.0
STATUS_LABEL_AT = (0.0, 0.0, 0.55)


class RerunSinkError(OSError):
    """The Rerun sink cannot start (a port is taken, the viewer binary is missing, ...); says what to do."""


def _field_meta(entity: str, descriptor: rr.ComponentDescriptor) -> dict[bytes, bytes]:
    # The Arrow metadata Rerun reads to place a column (rerun.chunk.Chunk.from_record_batch).
    return {
        b"rerun:kind": b"data",
        b"rerun:entity_path": entity.encode(),
        b"rerun:archetype": (descriptor.archetype or "").encode(),
        b"rerun:component": descriptor.component.encode(),
        b"rerun:component_type": (descriptor.component_type or "").encode(),
    }


def entity_of(device: str) -> str:
    """The entity path of a device's tree (device ids may hold characters entity paths escape)."""
    return f"/{ROOT}/{rr.escape_entity_path_part(device)}"


def status_text(statuses: Mapping[str, int]) -> str:
    """Servo status registers -> a sentence naming each joint's error bits ("" when all are clear)."""
    parts = []
    for joint, value in statuses.items():
        bits = [name for i, name in enumerate(SERVO_STATUS_BITS) if value >> i & 1]
        if bits:
            parts.append(f"{joint}: {', '.join(bits)} error")
    return "; ".join(parts)


@dataclass
class _Arm:
    """One device's place in the recording and its samples not yet sent (columns, grown as needed)."""

    device: str
    entity: str
    index: int
    bodies: int
    n: int = 0
    times_ns: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    poses: np.ndarray = field(default_factory=lambda: np.empty((0, 0, 7)))  # x y z qw qx qy qz
    angles_rad: np.ndarray = field(default_factory=lambda: np.empty((0, len(so101.JOINT_NAMES))))
    servo: np.ndarray = field(
        default_factory=lambda: np.empty((0, len(so101.JOINT_NAMES), len(SERVO_SERIES)))
    )
    first_pending: float = 0.0
    # The arm's place on edge_time, which never runs backwards (twin.output.edge_time).
    edge: EdgeTime = field(default_factory=EdgeTime)
    status: str = ""
    status_key: tuple[int | None, ...] = ()
    # The arm's status as its label over it shows it (handle_status), and the label's time: ONLINE is none.
    shown: str = "ONLINE"
    shown_ms: int = 0
    # The time of the last Clear of that label: a later label goes after it, or the Clear hides it at the live
    # end. A new arm's first one may be past its own clock (`_ForgottenLabels.floor`, from other arms).
    cleared_ms: int = 0
    servo_styled: set[str] = field(default_factory=set)
    schemas: dict[tuple[str, ...], pa.Schema] = field(default_factory=dict)

    def next_row(self) -> int:
        """Index of the row to fill, growing the buffers (x2, up to MAX_BATCH_ROWS) when they are full."""
        row = self.n
        if row >= len(self.times_ns):
            cap = min(max(16, 2 * len(self.times_ns)), MAX_BATCH_ROWS)
            self.times_ns = np.resize(self.times_ns, cap)
            self.poses = np.resize(self.poses, (cap, self.bodies, 7))
            self.angles_rad = np.resize(self.angles_rad, (cap, self.angles_rad.shape[1]))
            self.servo = np.resize(self.servo, (cap, *self.servo.shape[1:]))
        self.n += 1
        return row


class _ForgottenLabels:
    """The FORGOTTEN labels a new arm of an id may inherit, as it takes the forgotten arm's entity path: the
    label times of the newest FORGOTTEN_KEPT ids, and past them a floor, the latest label time dropped (once
    set, any new arm may have inherited a label, so each clears it after that: a clear with no label to clear
    costs one small row). A dropped time too far ahead of both the agent's clock and the label time of the
    forget that drops it leaves the floor where it is (FLOOR_AHEAD_TOLERANCE_S)."""

    def __init__(self) -> None:
        self.times: dict[str, int] = {}  # a forgotten id: its label's time, oldest first
        self.floor: int | None = None
        self.ahead_ignored = 0
        self._ahead_lines = Throttle(FLOOR_AHEAD_TELL_EVERY_S)

    def keep(self, device: str, at_ms: int, wall_s: float) -> None:
        """`device` forgotten, labelled at `at_ms` (its line) when the agent's wall clock read `wall_s`."""
        self.times.pop(device, None)
        self.times[device] = at_ms
        if len(self.times) > FORGOTTEN_KEPT:
            self._drop_oldest(max(wall_s, at_ms / 1000))

    def inherited(self, device: str) -> int | None:
        """The time of the label a new arm of `device` may inherit (None: none), forgetting the id's own."""
        return self.times.pop(device, self.floor)

    def _drop_oldest(self, now_s: float) -> None:
        """Into the floor unless too far ahead of `now_s`, the later of the agent's clock and the label time
        at the forget that drops it (so sound edges outvote an agent clock behind): the floor puts every later
        arm after it. An id left out so keeps its label if an arm of it comes back with its clock set right:
        one arm, not the fleet."""
        device = next(iter(self.times))
        dropped = self.times.pop(device)
        ahead_s = dropped / 1000 - now_s
        if ahead_s <= FLOOR_AHEAD_TOLERANCE_S:
            self.floor = max(self.floor or dropped, dropped)
            return
        self.ahead_ignored += 1
        since = self._ahead_lines.due()
        if since is not None:
            log.warning(
                "rerun: the FORGOTTEN label of %s is %.0f s ahead of the agent's clock and of the arm "
                "forgotten after it: the edge's clock, or the agent's own, is set wrong. Its time does not "
                "move later arms' labels, and an arm of that id that comes back keeps the label%s. Fix: keep "
                "the edge's clock set by NTP, or, if the agent's clock is the one behind, its host's "
                "(chronyc tracking)",
                device,
                ahead_s,
                f" ({since - 1} more such since the last line)" if since > 1 else "",
            )


class _Tee:
    """The sink's streams as one: every call goes to each (the file's and the served one)."""

    def __init__(self, streams: list[rr.RecordingStream]) -> None:
        self.streams = streams

    def log(self, entity: str, *archetypes: object, static: bool = False) -> None:
        for rec in self.streams:
            rec.log(entity, *archetypes, static=static)  # type: ignore[arg-type]

    def set_time(self, timeline: str, *, timestamp: float | np.datetime64) -> None:
        for rec in self.streams:
            rec.set_time(timeline, timestamp=timestamp)

    def send_chunks(self, chunk: Chunk | list[Chunk]) -> None:
        for rec in self.streams:
            rr.send_chunks(chunk, recording=rec)

    def send_blueprint(self, blueprint: rrb.Blueprint, **options: bool) -> None:
        for rec in self.streams:
            rec.send_blueprint(blueprint, **options)

    def flush(self, timeout_sec: float) -> None:
        for rec in self.streams:
            rec.flush(timeout_sec=timeout_sec)

    def disconnect(self) -> None:
        for rec in self.streams:
            rec.disconnect()


class SaveRotation:
    """When the saved .rrd rotates, and the disk budget of the saved files.

    The live file is always `save` (what `rerun <save>` opens); at a rotation it is renamed
    `<stem>-<UTC start time>-<n>.rrd` beside it, and the oldest of those are deleted while they, with
    the live file at its largest, would take more than `save_budget_mb`. Each file holds the arms' static
    parts, so it opens on its own (the first one also the layout); `rerun` opens several at once as one
    recording (they share its id).

    A file rotates at `save_max_mb`, or at twice its static parts (`opened_with`) if that is more: a fleet
    whose meshes alone fill `save_max_mb` would otherwise start every new file already due, and rewrite
    every arm's meshes once a second instead of logging samples."""

    CHECK_EVERY_S = 1.0

    def __init__(
        self, save: Path, settings: RerunSettings, *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.save = save
        self.max_bytes = int(settings.save_max_mb * 2**20)
        self.max_age_s = settings.save_max_age_s
        self.budget_bytes = int(settings.save_budget_mb * 2**20)
        self._opened = clock()
        self._opened_wall = time.time()
        self._next_check = 0.0
        self.rotations = 0
        self.deleted = 0
        # Bytes of the live file's static parts (0 until the first rotation measures them), and the size
        # it rotates at.
        self.static_bytes = 0
        self.limit_bytes = self.max_bytes
        # The save_max_mb the last warning advised: the static parts of two files differ by some bytes (the
        # samples logged between slices), so a warning for each new limit would repeat the same advice.
        self._advised_mb = 0

    def opened_with(self, static_bytes: int) -> None:
        """The new live file holds `static_bytes` of static parts: rotate it at twice that if
        `save_max_mb` is less, and say so, with the setting that would restore the limit."""
        self.static_bytes = static_bytes
        limit = max(self.max_bytes, 2 * static_bytes)
        advice_mb = math.ceil(limit / 2**20)
        if limit > self.max_bytes and advice_mb > self._advised_mb:
            self._advised_mb = advice_mb
            log.warning(
                "rerun: the arms' static parts take %.1f MB of each .rrd, more than half of "
                "rerun.save_max_mb = %g; files rotate at %.1f MB instead. Raise rerun.save_max_mb to at "
                "least %.0f (and save_budget_mb with it) to keep to the setting",
                static_bytes / 2**20,
                self.max_bytes / 2**20,
                limit / 2**20,
                advice_mb,
            )
        if limit != self.limit_bytes:
            self.limit_bytes = limit
            self._keep_within_budget()

    def due(self, now: float) -> bool:
        if now < self._next_check:
            return False
        self._next_check = now + self.CHECK_EVERY_S
        if now - self._opened >= self.max_age_s:
            return True
        try:
            return self.save.stat().st_size >= self.limit_bytes
        except OSError:
            return False

    def rotated(self, now: float) -> None:
        """The live file is closed: rename it, keep the budget."""
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(self._opened_wall))
        target = self.save.with_name(f"{self.save.stem}-{stamp}-{self.rotations + 1}{self.save.suffix}")
        try:
            os.replace(self.save, target)
        except OSError as exc:
            log.error("rerun: %s could not be renamed to %s: %s", self.save, target.name, exc)
        self.rotations += 1
        self._opened, self._opened_wall = now, time.time()
        self._keep_within_budget()
        log.info("rerun: recording rotated", extra={"closed": target.name, "rotations": self.rotations})

    def _keep_within_budget(self) -> None:
        """Delete the oldest rotated files while they, and the live file at its largest, exceed the budget."""
        files = []
        for path in self.save.parent.glob(f"{self.save.stem}-*{self.save.suffix}"):
            try:
                st = path.stat()
            except OSError:
                continue
            files.append((st.st_mtime, path, st.st_size))
        total = sum(size for _, _, size in files) + self.limit_bytes
        for _, path, size in sorted(files):
            if total <= self.budget_bytes:
                break
            try:
                path.unlink()
            except OSError as exc:
                log.error("rerun: %s could not be deleted to keep the disk budget: %s", path, exc)
                continue
            total -= size
            self.deleted += 1


class RerunWorker:
    """The blocking half of the sink (a `SinkWorker`): runs on the sink's own thread only, except the
    constructor, which opens the file, the gRPC server and the web viewer so that a taken port or a bad path
    fails the caller's start-up, not a background thread."""

    def __init__(self, robot: RobotModel, settings: RerunSettings) -> None:
        self.robot = robot
        self.settings = settings
        # One recording, in up to two streams: the file's, rotated (SaveRotation), and the served one, which
        # lives as long as the sink so a viewer's connection and the server's memory survive a rotation.
        self._recording_id = uuid.uuid4()
        self.grpc_url: str | None = None
        self.viewer_url: str | None = None
        self.save_path: Path | None = Path(settings.save) if settings.save else None
        self._web: subprocess.Popen[bytes] | None = None
        self._file: rr.RecordingStream | None = None
        self._served: rr.RecordingStream | None = None
        if self.save_path is not None:
            self._file = self._file_stream(self.save_path)
        if settings.serve:
            grpc_port = bindable_port(settings.grpc_port, "rerun.grpc_port", "--grpc-port")
            self._served = self._stream(
                rr.GrpcServerSink(LOOPBACK, grpc_port, server_memory_limit=settings.memory_limit.strip())
            )
            self.grpc_url = f"rerun+http://{LOOPBACK}:{grpc_port}/proxy"
        self._rec = _Tee([s for s in (self._file, self._served) if s is not None])
        self._rotation = SaveRotation(self.save_path, settings) if self.save_path is not None else None
        # Arms whose static parts are still to be logged (STATICS_SLICE_S): True for every stream (a new arm),
        # False for the new file only (after a rotation). While a new file takes them, `_statics_bytes` sums
        # what they took of it. When the next slice may start, and the slice (a test sets 0: one arm a slice).
        self._statics: deque[tuple[_Arm, bool]] = deque()
        self._measuring = False
        self._statics_bytes = 0
        self._statics_resume = -math.inf
        self.statics_slice_s = STATICS_SLICE_S
        if settings.serve:
            try:
                web_port = bindable_port(settings.web_port, "rerun.web_port", "--web-port")
                self._web = start_web_viewer(self.grpc_url or "", web_port)
            except Exception:
                self._rec.disconnect()
                raise
            self.viewer_url = viewer_url(web_port, self.grpc_url or "")
        self._arms: dict[str, _Arm] = {}  # the arms drawn, less those the agent forgot (handle_status)
        self._placed = 0  # the arms given a place in the fleet grid so far
        self._forgotten = _ForgottenLabels()  # the FORGOTTEN labels a new arm of an id may inherit
        self._focus: str | None = None
        self._focus_index: int | None = None  # the focus arm's grid place, kept for its id's return
        # Triangles per arm of the detailed and the far copy (see _log_arm).
        self.mesh_faces: dict[bool, int] = {}
        # Built now, on the caller's thread before any telemetry flows: thinning detailed meshes takes a
        # second or two of the GIL, which the mirror's worker must not wait for when the first arm appears.
        self._meshes = self._visuals()
        self._bodies = tuple(robot.body_ids)
        # Bodies welded to the world never move: their pose is logged once, not per sample.
        self._moving = tuple(b for b in self._bodies if int(robot.model.body_weldid[robot.body_ids[b]]) != 0)
        self._moving_idx = np.array([self._bodies.index(b) for b in self._moving], dtype=np.int64)
        self._next_sweep = 0.0
        # Per device (None: no device could be read): last rejection text time, rejections unwritten since.
        self._rejects: dict[str | None, tuple[float, int]] = {}
        self.samples_logged = 0
        self.batches_sent = 0

    def _file_stream(self, path: Path) -> rr.RecordingStream:
        """The stream into the file at `path`. rr.FileSink fails a file it cannot create with a RuntimeError
        (a traceback, for `twin run`): opening it here first raises the OSError, with the path, that start-up
        says how to fix."""
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open("ab"):
            pass
        return self._stream(rr.FileSink(str(path)))

    def _stream(self, sink: rr.FileSink | rr.GrpcServerSink, *, layout: bool = True) -> rr.RecordingStream:
        """A stream of this sink's one recording into `sink`, with the recording's name and root axes, and the
        default layout unless `layout` is false."""
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=self._recording_id)
        # Only edge_time: the SDK's own log_time/log_tick timelines would put every sample on a second clock.
        rec.set_log_time_enabled(False)
        rec.set_log_tick_enabled(False)
        if layout:
            rec.set_sinks(sink, default_blueprint=self._blueprint(None))
        else:
            rec.set_sinks(sink)
        rec.send_recording_name("so101-twin fleet")
        # MuJoCo's world is z-up; Rerun's 3D views follow what the root says.
        rec.log(f"/{ROOT}", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        return rec

    @property
    def rotations(self) -> int:
        return self._rotation.rotations if self._rotation is not None else 0

    @property
    def floor_ahead_ignored(self) -> int:
        """Dropped FORGOTTEN label times too far ahead to move the floor (FLOOR_AHEAD_TOLERANCE_S): logged,
        not in /state, where a sink has the generic SinkStats only."""
        return self._forgotten.ahead_ignored

    @property
    def files_deleted(self) -> int:
        return self._rotation.deleted if self._rotation is not None else 0

    def _rotate_if_due(self, now: float) -> None:
        """A new .rrd once the current one is too large or too old (SaveRotation); the arms' static parts
        follow into it a slice at a time (_log_statics), after which it stands on its own."""
        rotation, old = self._rotation, self._file
        # Not before the file holds every arm's static parts, or a rotated file would not open on its own.
        if rotation is None or old is None or self._statics or not rotation.due(now):
            return
        for arm in self._arms.values():
            if arm.n:
                self._flush(arm)
        # Nothing but `old` may hold the file's stream now, or it outlives the sweep below.
        self._file = None
        self._rec = _Tee([s for s in (self._served,) if s is not None])
        old.flush(timeout_sec=30.0)
        old.disconnect()  # writes the file's footer
        del old
        # A dropped stream keeps its batcher and writer threads until the SDK sweeps the orphans (two threads
        # per rotation, for as long as the agent runs, otherwise).
        rerun_bindings.flush_and_cleanup_orphaned_recordings()
        rotation.rotated(now)
        # The old stream's buffers and threads are gone: give their pages back (twin.core.heap).
        heap.trim()
        assert self.save_path is not None
        # No layout in the new file: every blueprint the SDK (0.41) builds keeps a stream of its own, with two
        # threads, for as long as the process runs, which a rotation every few minutes would pile up. A later
        # file opens with Rerun's own layout; opened with the first one, it takes the first one's.
        self._file = new = self._stream(rr.FileSink(str(self.save_path)), layout=False)
        self._rec = _Tee([s for s in (new, self._served) if s is not None])
        for arm in self._arms.values():
            arm.servo_styled.clear()  # logged again with the next batch
            arm.status, arm.status_key = "", ()
            # A quiet arm sends no sample to log it again with: its label goes into the new file now.
            if arm.shown != "ONLINE":
                self._label(arm, _Tee([new]))
        # Static data holds for every time, so an arm's may follow its first samples in the file
        # (STATICS_SLICE_S).
        self._statics.extend((arm, False) for arm in self._arms.values())
        self._measuring, self._statics_bytes = True, 0
        self._statics_resume = -math.inf
        self._log_statics(now)

    def _log_statics(self, now: float) -> None:
        """Log the static parts of the next pending arms, for about one slice, if the last slice's pause is
        over. After a rotation the slices are measured, and once all are in, the new file's static parts
        decide where it rotates."""
        pending = self._statics
        if not pending or now < self._statics_resume:
            return
        new = self._file if self._measuring else None
        only_new = _Tee([new]) if new is not None else None
        start = time.monotonic()
        # Measured around the slice, written out, so samples logged between slices are not counted as static.
        before = self._flushed_size(new) if new is not None else None
        while True:
            arm, everywhere = pending.popleft()
            self._log_arm(arm, None if everywhere else only_new)
            if not pending or time.monotonic() - start >= self.statics_slice_s:
                break
        if new is not None:
            after = self._flushed_size(new)
            if before is not None and after is not None:
                self._statics_bytes += after - before
        end = time.monotonic()
        self._statics_resume = end + (end - start) * (1.0 / STATICS_DUTY - 1.0)
        if not pending and self._measuring:
            self._measuring = False
            if self._rotation is not None:
                self._rotation.opened_with(self._statics_bytes)

    def _flushed_size(self, rec: rr.RecordingStream) -> int | None:
        """The saved file's size once `rec` has written out what it holds (None, logged, if unreadable)."""
        assert self.save_path is not None
        rec.flush(timeout_sec=30.0)
        try:
            return self.save_path.stat().st_size
        except OSError as exc:
            log.error("rerun: %s could not be measured after a rotation: %s", self.save_path, exc)
            return None

    # --- SinkWorker ---------------------------------------------------------------------------------------

    def handle_applied(self, sample: AppliedSample) -> None:
        arm = self._arms.get(sample.device_id) or self._arm(sample.device_id)
        now = time.monotonic()
        if arm.n == 0:
            arm.first_pending = now
        row = arm.next_row()
        edge_ms = arm.edge.place(
            sample.timestamp_ms, sample.received_mono_s, device=sample.device_id, output="rerun"
        )
        arm.times_ns[row] = edge_ms * 1_000_000
        angles = sample.joint_angles
        arm.poses[row] = self.robot.body_pose_array(angles)
        arm.angles_rad[row] = [angles.get(j, math.nan) for j in so101.JOINT_NAMES]
        diagnostics = sample.telemetry.diagnostics
        # One (joints, quantities) block; a reading the edge did not send is None, which becomes NaN.
        arm.servo[row] = [_servo_row(d) for d in map(diagnostics.get, so101.JOINT_NAMES)]
        if arm.shown == "FORGOTTEN":
            self._unlabel(arm, edge_ms)  # a new arm of a forgotten id: the label was its predecessor's
        self._status(arm, sample)
        if sample.alarm_events:
            self._alarms(arm, sample)
        self.samples_logged += 1
        if arm.n >= MAX_BATCH_ROWS or now - arm.first_pending >= self._flush_s():
            self._flush(arm)
        if now >= self._next_sweep:
            self._sweep(now)
            self._rotate_if_due(now)
        if self._statics:
            self._log_statics(now)

    def handle_rejected(self, sample: RejectedSample) -> None:
        device = sample.device_id
        entity = f"{entity_of(device)}/events" if device is not None else f"/{ROOT}/events"
        now = time.monotonic()
        last, unlogged = self._rejects.get(device, (-math.inf, 0))
        if now - last < REJECT_TEXT_EVERY_S:
            self._rejects[device] = (last, unlogged + 1)
            return
        if len(self._rejects) >= MAX_REJECT_KEYS:
            # Made-up device ids must not grow this table without bound.
            self._rejects.clear()
        self._rejects[device] = (now, 0)
        more = f" (+{unlogged} more since the last line)" if unlogged else ""
        # A rejected message may have no usable edge timestamp; the agent's receive time stands in.
        self._rec.set_time(TIMELINE, timestamp=sample.received_wall_s)
        text = f"rejected ({sample.reason}): {sample.detail}{more}"
        self._rec.log(entity, rr.TextLog(text, level=rr.TextLogLevel.WARN))

    def handle_status(self, change: StatusChange) -> None:
        """The arm's status as a line of its events, on its own line after its last sample (where a viewer at
        the live end sees it: the pose there is the last one the arm sent)."""
        arm = self._arms.get(change.device_id)
        if arm is None:
            return  # nothing of it is shown (its samples were all skipped or dropped)
        if change.forgotten:
            self._forget(arm, change)
            return
        at_ms = arm.edge.after_last(change.at_mono_s)
        self._rec.set_time(TIMELINE, timestamp=np.datetime64(at_ms, "ms"))
        level = _STATUS_LEVELS.get(change.status, rr.TextLogLevel.INFO)
        text = f"arm {change.status} (was {change.previous})"
        if change.status in _STATUS_COLOURS:
            text += ": its pose is the last one it sent"
            # After the arm's last label and Clear, which a far floor may have put past its own clock.
            arm.shown_ms = max(at_ms, arm.shown_ms + 1, arm.cleared_ms + 1)
            arm.shown = change.status
            self._label(arm)
        elif arm.shown != "ONLINE":
            self._unlabel(arm, at_ms)
        self._rec.log(f"{arm.entity}/events", rr.TextLog(text, level=level))

    def _forget(self, arm: _Arm, change: StatusChange) -> None:
        """The agent forgot the arm: its samples still buffered go, a grey FORGOTTEN label goes over its
        meshes (which stay drawn with its last pose) and a line says so, and its record is dropped (an arm of
        that name that publishes again is a new one, in a new place unless it is the focus id, which takes its
        old place back, and clears the label), so the records stay within the arms tracked at once however
        many come and go."""
        if arm.n:
            self._flush(arm)
        at_ms = max(arm.edge.after_last(change.at_mono_s), arm.shown_ms + 1, arm.cleared_ms + 1)
        arm.shown, arm.shown_ms = "FORGOTTEN", at_ms
        self._label(arm)
        self._rec.set_time(TIMELINE, timestamp=np.datetime64(at_ms, "ms"))
        text = f"arm forgotten by the agent (was {change.previous})"
        self._rec.log(f"{arm.entity}/events", rr.TextLog(text, level=rr.TextLogLevel.INFO))
        del self._arms[arm.device]
        self._forgotten.keep(arm.device, at_ms, change.at_wall_s)
        # The focus stays on the forgotten arm (labelled FORGOTTEN, so the view is truthful): handing it on
        # would send a blueprint, and each keeps a stream and two threads for as long as the process runs
        # (SDK 0.41), so arms churning for weeks would pile them up. An arm of that id takes the place back.

    def _label(self, arm: _Arm, rec: _Tee | None = None) -> None:
        """The arm's status over it in the fleet view (the events view shows the focus arm's lines only), into
        `rec` (all the sink's streams by default)."""
        rec = rec or self._rec
        rec.set_time(TIMELINE, timestamp=np.datetime64(arm.shown_ms, "ms"))
        label = rr.Points3D(
            [STATUS_LABEL_AT],
            radii=0.02,
            colors=[_STATUS_COLOURS[arm.shown]],
            labels=[arm.shown],
            show_labels=True,
        )
        rec.log(f"{arm.entity}/status", label)

    def _unlabel(self, arm: _Arm, at_ms: int) -> None:
        """The mirror reads the arm ONLINE again: the label over its live pose goes, with the change, not
        with its first sample back: a STALE arm that sends one sample and falls quiet again stays STALE to the
        mirror (and on the console), which sends no change. Never behind the label: a sample delivered late
        (a backlog after an outage) may have been measured before its time."""
        arm.cleared_ms = max(at_ms, arm.shown_ms + 1)
        self._rec.set_time(TIMELINE, timestamp=np.datetime64(arm.cleared_ms, "ms"))
        self._rec.log(f"{arm.entity}/status", rr.Clear(recursive=False))
        arm.shown = "ONLINE"

    def idle(self) -> None:
        now = time.monotonic()
        self._sweep(now)
        self._rotate_if_due(now)
        self._log_statics(now)

    def close(self) -> None:
        try:
            # The file stands on its own only with every arm's static parts, whatever the pace.
            only_file = _Tee([self._file]) if self._file is not None else None
            while self._statics:
                arm, everywhere = self._statics.popleft()
                self._log_arm(arm, None if everywhere else only_file)
            for arm in self._arms.values():
                if arm.n:
                    self._flush(arm)
            self._rec.flush(timeout_sec=30.0)
        finally:
            # Closing the sinks writes the .rrd footer and stops the gRPC server.
            self._rec.disconnect()
            self.stop_web_viewer()
        log.info(
            "rerun sink closed",
            extra={
                "samples": self.samples_logged,
                "batches": self.batches_sent,
                "rrd": str(self.save_path) if self.save_path else None,
            },
        )

    def stop_web_viewer(self) -> None:
        web, self._web = self._web, None
        if web is not None:
            stop_process(web)

    # --- devices -------------------------------------------------------------------------------------------

    def _arm(self, device: str) -> _Arm:
        arm = self._arms.get(device)
        if arm is not None:
            return arm
        # A forgotten arm's place is not taken again: its meshes stay there, labelled FORGOTTEN, in the
        # recording (static), until an arm of its id takes its entity path, and moves them to its new place.
        # The focus arm's id returning takes its old place back, where the layout's camera looks (the layout
        # is sent once: see _forget).
        back = self._focus_index if device == self._focus else None
        index = self._placed if back is None else back
        arm = _Arm(device=device, entity=entity_of(device), index=index, bodies=len(self._bodies))
        forgot_ms = self._forgotten.inherited(device)
        if forgot_ms is not None:
            arm.shown, arm.shown_ms = "FORGOTTEN", forgot_ms  # cleared at its first sample (handle_applied)
        if back is None:
            self._placed += 1
        self._arms[device] = arm
        self._statics.append((arm, True))  # logged by _log_statics, a slice at a time
        focus = self.settings.focus_device
        if self._focus is None and (not focus or focus == device):
            self._focus, self._focus_index = device, arm.index
            self._rec.send_blueprint(self._blueprint(device), make_active=True, make_default=True)
        return arm

    def _log_arm(self, arm: _Arm, rec: _Tee | None = None) -> None:
        """The static part of a device: its grid place, fixed bodies, meshes and plot styles (into `rec`,
        by default every stream)."""
        rec = rec or self._rec
        rec.log(arm.entity, rr.Transform3D(translation=self._grid_position(arm.index)), static=True)
        reference = self.robot.body_poses({})
        for name in self._bodies:
            if name not in self._moving:
                pos, quat = reference[name]
                rec.log(
                    f"{arm.entity}/{name}",
                    rr.Transform3D(translation=pos, quaternion=rr.Quaternion(xyzw=[*quat[1:], quat[0]])),
                    static=True,
                )
        # The arms the layout opens on (the grid's first row and the focus arm) are drawn in detail; the
        # rest, further from the camera, get the coarser copy: the static meshes are encoded, written and
        # kept by the stream once per arm, so their size is most of what a large fleet costs to log.
        settings = self.settings
        focus = settings.focus_device
        detailed = arm.index < settings.mesh_detailed_arms or (
            arm.device == focus if focus else arm.index == 0
        )
        for path, transform, mesh in self._meshes[detailed]:
            rec.log(f"{arm.entity}/{path}", transform, mesh, static=True)
        rec.log(f"{arm.entity}/joints/angle_deg", _series_style(), static=True)

    def _visuals(self) -> dict[bool, list[tuple[str, rr.Transform3D, rr.Mesh3D]]]:
        """(path under the arm, pose in the body, mesh) of each visual geom, detailed (True) and far (False),
        each built once for every arm that uses it: Rerun archetypes are costly to build in Python."""
        geoms = visual_geoms(self.robot.model, self.robot.body_ids)
        near, _ = fit_face_budget(geoms, self.settings.mesh_faces_per_arm)
        self.mesh_faces[True] = sum(g.face_count for g in near)
        meshes = {True: _posed_meshes(near)}
        if self.mesh_faces[True] <= self.settings.mesh_faces_far:
            far = near  # already small enough: the far arms share the detailed copy
            meshes[False] = meshes[True]
        else:
            # Thinned from the detailed copy, not from the model: the same clustering at a coarser cell, on
            # a tenth of the official meshes' triangles.
            far, _ = fit_face_budget(near, self.settings.mesh_faces_far)
            meshes[False] = _posed_meshes(far)
        self.mesh_faces[False] = sum(g.face_count for g in far)
        log.info(
            "rerun sink: %d visual geoms; %d triangles per detailed arm, %d per far arm",
            len(near),
            self.mesh_faces[True],
            self.mesh_faces[False],
        )
        return meshes

    def _status(self, arm: _Arm, sample: AppliedSample) -> None:
        diagnostics = sample.telemetry.diagnostics
        # Per sample, only a comparison: the registers almost never change between messages.
        key = tuple(d.status for d in diagnostics.values())
        if key == arm.status_key:
            return
        arm.status_key = key
        text = status_text({j: d.status for j, d in diagnostics.items() if d.status is not None})
        if text == arm.status:
            return
        cleared = not text
        message = "all servos report no error" if cleared else text
        arm.status = text
        self._rec.set_time(TIMELINE, timestamp=np.datetime64(arm.edge.last_ms, "ms"))
        level = rr.TextLogLevel.INFO if cleared else rr.TextLogLevel.WARN
        self._rec.log(f"{arm.entity}/events", rr.TextLog(f"servo status: {message}", level=level))

    def _alarms(self, arm: _Arm, sample: AppliedSample) -> None:
        # Raised and cleared servo alarms (docs/servo-health.md) as the alarm engine words them.
        self._rec.set_time(TIMELINE, timestamp=np.datetime64(arm.edge.last_ms, "ms"))
        for event in sample.alarm_events:
            if event.action == "raised":
                level = rr.TextLogLevel.ERROR if event.severity == "critical" else rr.TextLogLevel.WARN
            else:
                level = rr.TextLogLevel.INFO
            text = f"servo alarm {event.action}: {event.message}"
            self._rec.log(f"{arm.entity}/events", rr.TextLog(text, level=level))

    # --- sending -------------------------------------------------------------------------------------------

    def _flush_s(self) -> float:
        """How long a device's samples wait: flush_s, or longer when the fleet would otherwise send more
        than max_batches_per_s batches (the sending cost is per batch, the stream's delay is per device)."""
        return max(self.settings.flush_s, len(self._arms) / self.settings.max_batches_per_s)

    def _sweep(self, now: float) -> None:
        wait = self._flush_s()
        self._next_sweep = now + min(wait / 4.0, 0.25)
        for arm in self._arms.values():
            if arm.n and now - arm.first_pending >= wait:
                self._flush(arm)

    def _flush(self, arm: _Arm) -> None:
        """Send a device's buffered samples as one Arrow record batch (one Rerun chunk per entity)."""
        k = arm.n
        servo = arm.servo[:k]
        # Rows where a quantity has no joint's reading send nothing for it (a null row, not six NaNs).
        present = ~np.isnan(servo).all(axis=1)  # (k, quantities)
        servo_names = tuple(SERVO_SERIES[q][1] for q in range(len(SERVO_SERIES)) if present[:, q].any())
        schema = arm.schemas.get(servo_names)
        if schema is None:
            schema = arm.schemas[servo_names] = self._schema(arm, servo_names)
        # Checked per batch, not per new schema: a rotation clears servo_styled, and the new file needs the
        # styles again for quantities whose schema is long known.
        for name in servo_names:
            if name not in arm.servo_styled:
                arm.servo_styled.add(name)
                self._rec.log(f"{arm.entity}/servo/{name}", _series_style(), static=True)
        poses = arm.poses[:k][:, self._moving_idx, :]  # (k, moving bodies, 7)
        # Body-major float32 copies, so each body's column is one contiguous slice. Every array handed to
        # Rerun owns its memory: Arrow wraps numpy buffers without copying, Rerun encodes later on its own
        # threads, and the arm's buffers are refilled by the next samples.
        translations = np.ascontiguousarray(poses[:, :, :3].transpose(1, 0, 2), dtype=np.float32)
        # MuJoCo quaternions are (w, x, y, z); Rerun's are (x, y, z, w).
        quaternions = np.ascontiguousarray(poses[:, :, _XYZW].transpose(1, 0, 2), dtype=np.float32)
        arrays: list[pa.Array] = [pa.array(arm.times_ns[:k].copy(), type=_NS)]
        for b in range(len(self._moving)):
            arrays.append(pa.FixedSizeListArray.from_arrays(pa.array(translations[b].ravel()), type=_V3))
            arrays.append(pa.FixedSizeListArray.from_arrays(pa.array(quaternions[b].ravel()), type=_Q4))
        arrays.append(_six_per_row(np.degrees(arm.angles_rad[:k]), None))
        for q, (_attr, name, _title) in enumerate(SERVO_SERIES):
            if name in servo_names:
                arrays.append(_six_per_row(servo[:, :, q], present[:, q]))
        arm.n = 0
        self._rec.send_chunks(Chunk.from_record_batch(pa.RecordBatch.from_arrays(arrays, schema=schema)))
        self.batches_sent += 1

    def _schema(self, arm: _Arm, servo_names: Sequence[str]) -> pa.Schema:
        translation = rr.Transform3D.descriptor_translation()
        quaternion = rr.Transform3D.descriptor_quaternion()
        scalars = rr.Scalars.descriptor_scalars()
        fields = [
            pa.field(
                TIMELINE,
                _NS,
                nullable=False,
                metadata={b"rerun:kind": b"index", b"rerun:index_name": TIMELINE.encode()},
            )
        ]
        for body in self._moving:
            entity = f"{arm.entity}/{body}"
            fields.append(pa.field(f"{entity}:translation", _V3, metadata=_field_meta(entity, translation)))
            fields.append(pa.field(f"{entity}:quaternion", _Q4, metadata=_field_meta(entity, quaternion)))
        entity = f"{arm.entity}/joints/angle_deg"
        fields.append(pa.field(f"{entity}:scalars", _SCALARS, metadata=_field_meta(entity, scalars)))
        for name in servo_names:
            entity = f"{arm.entity}/servo/{name}"
            fields.append(pa.field(f"{entity}:scalars", _SCALARS, metadata=_field_meta(entity, scalars)))
        return pa.schema(fields)

    # --- layout --------------------------------------------------------------------------------------------

    def _grid_position(self, index: int) -> np.ndarray:
        """Where arm number `index` stands: rows of FLEET_COLUMNS side by side along +y, further rows behind
        along -x. Each arm reaches towards +x, so neighbours stand beside it, not in its reach, and from the
        front three-quarter view the fleet recedes behind the first arm."""
        row, col = divmod(index, FLEET_COLUMNS)
        spacing = self.settings.fleet_spacing_m
        return np.array([-row * spacing, col * spacing, 0.0])

    def _blueprint(self, device: str | None) -> rrb.Blueprint:
        """The fleet in 3D; beside it the focus arm's joint angles, servo plots and events."""
        fleet = rrb.Spatial3DView(name="Fleet", origin=f"/{ROOT}", contents=[f"/{ROOT}/**"])
        if device is None:
            return rrb.Blueprint(fleet, collapse_panels=True)
        arm = self._arms[device]
        base = self._grid_position(arm.index)
        # The same three-quarter view as the MuJoCo overview camera (robots/so101/scene.xml), on this arm.
        target = base + np.array([0.15, 0.0, 0.12])
        eye = base + np.array([0.8, -0.8, 0.5])
        fleet = rrb.Spatial3DView(
            name="Fleet",
            origin=f"/{ROOT}",
            contents=[f"/{ROOT}/**"],
            eye_controls=rrb.EyeControls3D(position=eye, look_target=target, eye_up=[0.0, 0.0, 1.0]),
        )
        # Plots show the last PLOT_WINDOW_S before the time cursor: a live view that draws every sample
        # since start slows down the longer the agent runs (zooming out in the viewer shows the rest).
        window = rrb.VisibleTimeRange(
            TIMELINE,
            start=rrb.TimeRangeBoundary.cursor_relative(seconds=-PLOT_WINDOW_S),
            end=rrb.TimeRangeBoundary.cursor_relative(),
        )
        plots = [
            rrb.TimeSeriesView(
                name=f"{device} {title}", origin=f"{arm.entity}/servo/{name}", time_ranges=window
            )
            for _attr, name, title in SERVO_SERIES
        ]
        side = rrb.Vertical(
            rrb.TimeSeriesView(
                name=f"{device} joint angles (deg)", origin=f"{arm.entity}/joints", time_ranges=window
            ),
            rrb.Tabs(*plots, name=f"{device} servos"),
            rrb.TextLogView(name=f"{device} events", origin=f"{arm.entity}/events"),
            row_shares=[3, 3, 1],
        )
        return rrb.Blueprint(
            rrb.Horizontal(fleet, side, column_shares=[3, 2]),
            rrb.BlueprintPanel(state="collapsed"),
            rrb.SelectionPanel(state="collapsed"),
            rrb.TimePanel(state="collapsed"),
        )


class RerunSink:
    """The Rerun sink the agent adds (a `TwinSink`): a per-device rate cap in front of a `QueuedSink`, whose
    thread takes HANDOFF_S worth of samples at a time."""

    name = "rerun"

    def __init__(self, robot: RobotModel, settings: RerunSettings) -> None:
        settings.validate()
        self.settings = settings
        self.worker = RerunWorker(robot, settings)
        self._queue = QueuedSink(
            self.name,
            self.worker,
            max_pending=settings.max_pending,
            idle_s=settings.flush_s / 2.0,
            hand_off_s=HANDOFF_S,
        )
        # A token bucket per device holding burst_s seconds of the cap: a backlog released at once (network
        # jitter, or the agent's own MQTT thread stalled for seconds on a loaded host) costs an arm under
        # the cap nothing, while a flood is held to the cap once the burst is spent.
        self._cap = DeviceRateCap(
            settings.max_rate_hz,
            burst=settings.max_rate_hz * settings.burst_s,
            fleet_rate_hz=settings.max_fleet_rate_hz,
        )
        self._skipped = 0
        self._lock = threading.Lock()

    @property
    def viewer_url(self) -> str | None:
        """The web viewer page, already pointed at the stream (None unless serving)."""
        return self.worker.viewer_url

    @property
    def grpc_url(self) -> str | None:
        """The stream for a native viewer: `rerun --connect <url>` (None unless serving)."""
        return self.worker.grpc_url

    @property
    def save_path(self) -> Path | None:
        return self.worker.save_path

    def applied(self, sample: AppliedSample) -> None:
        if not self._cap.take(sample.device_id, sample.received_mono_s):
            with self._lock:
                self._skipped += 1
            return
        self._queue.applied(sample)

    def rejected(self, sample: RejectedSample) -> None:
        self._queue.rejected(sample)

    def status(self, change: StatusChange) -> None:
        # Not rate-capped: a change is rare, and the one a viewer must not miss.
        self._queue.status(change)

    def stats(self) -> SinkStats:
        with self._lock:
            skipped = self._skipped
        return replace(self._queue.stats(), skipped=skipped)

    def close(self, timeout: float = 10.0) -> None:
        self._queue.close(timeout)
        # If the queue's thread did not get to it, the web viewer is still ours to stop.
        self.worker.stop_web_viewer()


# --- helpers -------------------------------------------------------------------------------------------


@functools.cache
def _series_style() -> rr.SeriesLines:
    # Built once: the same names and colours go on every arm's plots.
    return rr.SeriesLines(names=list(so101.JOINT_NAMES), colors=list(JOINT_COLOURS))


def _posed_meshes(geoms: Sequence[VisualGeom]) -> list[tuple[str, rr.Transform3D, rr.Mesh3D]]:
    return [
        (
            f"{g.body}/visual/{rr.escape_entity_path_part(g.name)}",
            rr.Transform3D(translation=g.pos, quaternion=rr.Quaternion(xyzw=[*g.quat[1:], g.quat[0]])),
            rr.Mesh3D(
                vertex_positions=g.vertices,
                triangle_indices=g.faces,
                vertex_normals=g.normals,
                albedo_factor=[round(255 * min(max(c, 0.0), 1.0)) for c in g.rgba],
            ),
        )
        for g in geoms
    ]


_SERVO_READINGS = operator.attrgetter(*(attr for attr, _name, _title in SERVO_SERIES))


def _servo_row(d: JointDiagnostics | None) -> tuple[float | None, ...]:
    return _NO_READINGS if d is None else _SERVO_READINGS(d)


def _six_per_row(values: np.ndarray, present: np.ndarray | None) -> pa.Array:
    """A (rows, joints) array as a list<float64> column; rows where `present` is False are null."""
    rows, width = values.shape
    offsets = pa.array(np.arange(0, rows * width + 1, width, dtype=np.int32))
    flat = pa.array(np.array(values, dtype=np.float64).ravel())  # a copy: see _flush
    mask = None if present is None or present.all() else pa.array(~present)
    return pa.ListArray.from_arrays(offsets, flat, type=_SCALARS, mask=mask)


def bindable_port(port: int, key: str, flag: str | None = None) -> int:
    """The loopback port to listen on (0 picks a free one); raises RerunSinkError when it is taken, naming
    the config `key` and the command-line `flag` that set it."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((LOOPBACK, port))
        except OSError as exc:
            zero = f"{key} = 0, or {flag} 0," if flag else f"{key} = 0"
            raise RerunSinkError(
                f"{key} = {port}: {LOOPBACK}:{port} is in use ({exc.strerror}); stop what holds it or choose "
                f"another port ({zero} picks a free one)"
            ) from exc
        return int(probe.getsockname()[1])


def viewer_binary() -> Path:
    """The `rerun` binary that ships in the rerun-sdk wheel (the viewer and its web server)."""
    import rerun_cli  # noqa: PLC0415 - ships with rerun-sdk; only needed when serving

    path = Path(rerun_cli.__file__).resolve().parent / "rerun"
    if not path.is_file():
        raise RerunSinkError(f"the Rerun viewer binary is missing ({path}); reinstall rerun-sdk (make setup)")
    return path


def viewer_url(web_port: int, grpc_url: str) -> str:
    """The web viewer page, pointed at a stream."""
    return f"http://{LOOPBACK}:{web_port}/?url={quote(grpc_url, safe='')}"


def start_web_viewer(source: str, web_port: int, *, grpc_port: int | None = None) -> subprocess.Popen[bytes]:
    """Rerun's web viewer (HTML + Wasm) on 127.0.0.1:`web_port`, for `source`: a stream URL, or a .rrd
    file that the process then also serves as a stream on 127.0.0.1:`grpc_port`.

    `rr.serve_web_viewer` takes no bind address and listens on every interface; the `rerun` binary that ships
    in the wheel takes `--bind`, so it serves the page (given a stream URL it hosts no gRPC server of its
    own). Returns once the page answers; raises RerunSinkError when the process exits or stays silent."""
    cmd = [str(viewer_binary()), "--serve-web", "--bind", LOOPBACK, "--web-viewer-port", str(web_port)]
    if grpc_port is not None:
        cmd += ["--port", str(grpc_port)]
    proc = subprocess.Popen(
        [*cmd, source],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        # If the agent is killed outright the viewer goes too, so no orphan holds the port (the sink is
        # built on the agent's main thread).
        preexec_fn=die_with_parent(),  # noqa: PLW1509 - only prctl, async-signal-safe enough
    )
    deadline = time.monotonic() + WEB_VIEWER_START_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            err = proc.stderr.read().decode(errors="replace")[-600:] if proc.stderr else ""
            raise RerunSinkError(
                f"the Rerun web viewer exited at start (code {proc.returncode}): {err.strip()}"
            )
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
            probe.settimeout(0.2)
            if probe.connect_ex((LOOPBACK, web_port)) == 0:
                if proc.stderr is not None:
                    # Nobody reads its log from here on; a full pipe must not stall it.
                    threading.Thread(target=_drain, args=(proc.stderr,), daemon=True).start()
                return proc
        time.sleep(0.1)
    stop_process(proc)
    raise RerunSinkError(
        f"the Rerun web viewer did not listen on {LOOPBACK}:{web_port} within {WEB_VIEWER_START_S:.0f} s"
    )


def stop_process(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM, then SIGKILL after 5 s; waits for it."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)


def _drain(stream: Iterable[bytes]) -> None:
    with contextlib.suppress(Exception):
        for line in stream:
            log.debug("rerun web viewer: %s", line.decode(errors="replace").rstrip())
