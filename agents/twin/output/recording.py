"""The USD session recording as a sink: the agent's worker queues each applied sample, a thread of the sink's
own computes the body poses and writes them to the stage, so a slow disk or a long USD save never slows
mirroring (twin.output.sinks describes the contract).

The recorded pose is the applied (measured, clamped) pose: forward kinematics of `AppliedSample.joint_angles`
on the sink thread's own MuJoCo scratch data (`RobotModel.body_poses`).

Bounded three ways (`RecordingLimits`, the `[twin] record_*` settings). Each arm is recorded at most
`rate_hz` times a second (the rest are counted as skipped: a sample costs the sink's thread about 30
`json.loads` of an edge message, 0.3 ms at 10 us each, `twin bench usd`, so a large fleet at 10 Hz is more
than one thread records). A session rotates to a new file once its file reaches `max_bytes` or it is
`max_age_s` old: a USD stage lives in memory while it records, and a long one is rewritten at every save, so
an agent that runs for weeks must not keep one stage. And the session files in the directory are kept
within `budget_bytes`, the one being recorded counted at its largest (`max_bytes`): at each rotation the
oldest are deleted first, never the one being recorded.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from twin.core import heap
from twin.core.throttle import Throttle
from twin.output.edge_time import EdgeTime
from twin.output.recorder import SessionRecorder, file_size
from twin.output.sinks import AppliedSample, DeviceRateCap, QueuedSink, RejectedSample, SinkStats
from twin.robot.model import RobotModel

log = logging.getLogger(__name__)

RECORDING_SINK = "usd"
# A minute of 2,000 arms at 10 Hz would be 1.2 M samples; the recorder keeps at most 30 per arm per second
# anyway, so a deeper queue would only hold poses it drops. Newest wins when it overflows (counted).
MAX_PENDING_SAMPLES = 20_000
# The session files the budget counts (the agent names them session-<UTC time>-<pid>[-<n>].<format>).
SESSION_GLOB = "session-*.usd[ac]"
# After a failed save or open (a full disk), a new session is tried this often.
BROKEN_RETRY_S = 5.0
# A new session that keeps failing to open is told at once, then at most this often (with the count).
OPEN_ERROR_EVERY_S = 60.0
# EdgeSpacing: a change of a device's receive-minus-edge offset larger than this is an edge clock set forward
# past the arm's time line, or a stall that long: its samples are placed from the new offset at once. A reset
# backwards does not move it: the arm's time line goes on from its last sample (twin.output.edge_time).
JUMP_S = 5.0
# EdgeSpacing's offset is the least seen over the last one to two of these windows: a drifting edge clock
# is followed, and an old small delay does not hold for good.
OFFSET_WINDOW_S = 60.0
# EdgeSpacing's devices are dropped all at once past this many (a fleet whose ids churn), as the agent's
# own tables are bounded: each is placed afresh at its next sample.
MAX_PLACED_DEVICES = 20_000


@dataclass(slots=True)
class _Placement:
    offset: float  # the least receive time minus edge time of the windows below (seconds)
    window_min: float  # the least of the window begun at `window_start`
    window_start: float
    last: float  # the last time given
    edge: EdgeTime  # the arm's edge time line, which never runs backwards


class EdgeSpacing:
    """Each device's sample times for the recorder: its edge timestamps (on the arm's time line, which never
    runs backwards: twin.output.edge_time), shifted onto the receive clock by the least receive-minus-edge
    offset seen lately (the transit with the least delay, and the edge clock's offset), and no closer than
    `step_s` (one time code) to the previous one unless that would place it more than a time code past its
    receive time.

    Receive times bunch messages the edge sent 100 ms apart (a batch handed over at once, a burst after a
    stall), and the recorder keeps one sample per time code (1/30 s): the second of two received within one
    was dropped, 1 to 3 % of a demo's samples, and the stage replayed the network's jitter. The least offset
    is not one message's delay (a first message received late held an arm behind the others), follows a
    drifting edge clock within a window or two, and is taken afresh when it moves by JUMP_S (an edge clock
    set forward, a long stall). The floor of one time code keeps what arrives bunched anyway (after such a
    jump) from being dropped."""

    def __init__(self, step_s: float) -> None:
        self._step_s = step_s
        self._devices: dict[str, _Placement] = {}

    def time_of(self, device: str, received_s: float, edge_ms: int) -> float:
        arm = self._devices.get(device)
        if arm is None and len(self._devices) >= MAX_PLACED_DEVICES:
            self._devices.clear()
        line = arm.edge if arm is not None else EdgeTime()
        edge_s = line.place(edge_ms, received_s, device=device, output="usd recording") / 1000.0
        offset = received_s - edge_s
        if arm is None or abs(offset - arm.offset) > JUMP_S:
            last = arm.last if arm is not None else -math.inf
            arm = _Placement(offset, offset, received_s, last, line)
            self._devices[device] = arm
        elif received_s - arm.window_start >= OFFSET_WINDOW_S:
            # The window turns: the offset is the least of the one ending and the one beginning.
            arm.offset = min(arm.window_min, offset)
            arm.window_min, arm.window_start = offset, received_s
        else:
            arm.window_min = min(arm.window_min, offset)
            arm.offset = min(arm.offset, offset)
        # The floor is at most a time code past the receive time (a review): an edge faster than the time
        # codes, or a run of samples after a late first one, would otherwise run ahead without bound; those
        # that fall under it are the recorder's to drop.
        placed = max(edge_s + arm.offset, min(arm.last + self._step_s, received_s + self._step_s))
        arm.last = max(arm.last, placed)
        return placed


@dataclass(frozen=True)
class RecordingLimits:
    """How far a recording may grow (module doc); the defaults are the `[twin] record_*` settings'."""

    max_bytes: int = 256 * 2**20
    max_age_s: float = 3600.0
    budget_bytes: int = 4096 * 2**20
    rate_hz: float = 10.0

    def __post_init__(self) -> None:
        if self.max_bytes < 1 or self.budget_bytes < self.max_bytes:
            raise ValueError(
                f"recording limits: max_bytes {self.max_bytes} must be positive and at most the budget "
                f"{self.budget_bytes}"
            )
        if not (self.max_age_s > 0 and self.rate_hz > 0):
            raise ValueError(f"recording limits: max_age_s and rate_hz must be positive, got {self}")


@dataclass(frozen=True, slots=True)
class RecordingTotals:
    """The counters of every session this sink recorded, the current one included."""

    path: str
    samples_written: int = 0
    samples_dropped: int = 0
    flushes: int = 0
    flush_errors: int = 0
    rotations: int = 0
    files_deleted: int = 0


class _RecorderWorker:
    """The blocking half: runs on the sink's thread only."""

    def __init__(
        self,
        recorder: SessionRecorder,
        robot: RobotModel,
        *,
        limits: RecordingLimits,
        open_next: Callable[[int], SessionRecorder] | None,
        clock: Callable[[], float],
    ) -> None:
        self.recorder = recorder
        self._robot = robot
        self._limits = limits
        self._open_next = open_next
        self._clock = clock
        self._opened = clock()
        self._checked_flushes = 0
        self._retry_at = 0.0
        self._attempts = 0
        self._lock = threading.Lock()  # the totals, read by the agent's threads
        self._done = RecordingTotals(path="")
        self.rotations = 0
        self.files_deleted = 0
        # Samples that came while no session could take them (a failed save, a full disk): the output's
        # drops, so /metrics and the SinkDrops alarm see a recording the disk stopped. Sink thread only.
        self.unwritten = 0
        self.last_error = ""
        self._open_errors = Throttle(OPEN_ERROR_EVERY_S, clock=clock)
        # A hair over one time code: the recorder's rounding must not read the floor as less than one.
        self._spacing = EdgeSpacing(1.0001 / recorder.time_codes_per_second)

    def handle_applied(self, sample: AppliedSample) -> None:
        if self.recorder.broken:
            self.unwritten += 1
            if not self.last_error:
                self.last_error = f"session {self.recorder.path} set aside after a failed save (disk full?)"
            self.recorder.samples_dropped += 1
            self._rotate_if_due()
            return
        poses = self._robot.body_poses(sample.joint_angles)
        placed = self._spacing.time_of(sample.device_id, sample.received_mono_s, sample.timestamp_ms)
        self.recorder.record(sample.device_id, placed, poses, sample.telemetry.diagnostics)
        self._rotate_if_due()

    def handle_rejected(self, sample: RejectedSample) -> None:
        """A rejected message moved no twin: nothing to record."""

    def idle(self) -> None:
        self.recorder.flush_if_due()
        self._rotate_if_due()

    def close(self) -> None:
        self.recorder.close()

    def _rotate_if_due(self) -> None:
        """After a save (the file's size is known then), or once the session is too old: a new session. And
        after a failed save (a full disk), a new session as soon as one can be opened."""
        recorder = self.recorder
        if recorder.broken:
            now = self._clock()
            if now >= self._retry_at:
                self._retry_at = now + BROKEN_RETRY_S
                self._rotate(recorder, size=file_size(recorder.path), force=True)
            return
        saved = recorder.flushes != self._checked_flushes
        old = self._clock() - self._opened >= self._limits.max_age_s
        if not saved and not old:
            return
        self._checked_flushes = recorder.flushes
        size = file_size(recorder.path)
        if size < self._limits.max_bytes and not old:
            return
        self._rotate(recorder, size=size)

    def _rotate(self, recorder: SessionRecorder, *, size: int, force: bool = False) -> None:
        if self._open_next is None or (recorder.samples_written == 0 and not force):
            return  # nothing to rotate to, or an empty session (kept open, removed if it closes empty)
        recorder.close()
        # Every attempt gets a name of its own: a failed one may leave its file behind.
        self._attempts += 1
        try:
            successor = self._open_next(self._attempts)
        except Exception as exc:  # a full disk (pxr raises Tf.ErrorException): try again later
            recorder.broken = True  # closed, with no successor: the retry path takes it from here
            self._retry_at = self._clock() + BROKEN_RETRY_S
            self.last_error = f"the next session file could not be opened: {exc}"
            since = self._open_errors.due()
            if since is not None:
                log.error(
                    "recording: the next session file could not be opened (%s); trying again every %.0f s, "
                    "its samples dropped and counted meanwhile (%d failed attempt(s) since the last line)",
                    exc,
                    BROKEN_RETRY_S,
                    since,
                )
            return
        if self._open_errors.streak:
            log.warning(
                "recording: a session file is open again, after %d failed attempt(s); %d sample(s) in all "
                "were not recorded",
                self._open_errors.streak,
                self.unwritten,
            )
            self._open_errors.clear()
        with self._lock:
            self._done = _add(self._done, recorder)
            self.recorder = successor
            self.rotations += 1
        self._opened = self._clock()
        self._checked_flushes = 0
        log.info(
            "recording rotated",
            extra={"closed": str(recorder.path), "bytes": size, "next": str(successor.path)},
        )
        self._keep_within_budget(successor.path)
        # The closed session's stage (its layers, every sample authored) was freed: give its pages back, or
        # each rotation's peak stays in the RSS.
        heap.trim()

    def _keep_within_budget(self, current: Path) -> None:
        """Delete the oldest session files in the directory while they, and the session just begun at its
        largest (max_bytes), would take more than the budget."""
        files = []
        for path in current.parent.glob(SESSION_GLOB):
            if path == current:
                continue
            try:
                st = path.stat()
            except OSError:
                continue
            files.append((st.st_mtime, path, st.st_size))
        total = sum(size for _, _, size in files) + self._limits.max_bytes
        for _, path, size in sorted(files):
            if total <= self._limits.budget_bytes:
                break
            try:
                path.unlink()
            except OSError as exc:
                log.error("recording: %s could not be deleted to keep the disk budget: %s", path, exc)
                continue
            total -= size
            with self._lock:
                self.files_deleted += 1
            log.info("recording: %s deleted to keep the disk budget", path.name, extra={"bytes": size})

    def totals(self) -> RecordingTotals:
        with self._lock:
            totals = _add(self._done, self.recorder)
            return replace(totals, rotations=self.rotations, files_deleted=self.files_deleted)


def _add(totals: RecordingTotals, recorder: SessionRecorder) -> RecordingTotals:
    # Counters written by the sink's thread; int reads are atomic, and a figure one sample behind is fine.
    return RecordingTotals(
        # The newest session whose file is there: a report must not name one removed as empty at close.
        path=str(recorder.path) if recorder.kept else totals.path,
        samples_written=totals.samples_written + recorder.samples_written,
        samples_dropped=totals.samples_dropped + recorder.samples_dropped,
        flushes=totals.flushes + recorder.flushes,
        flush_errors=totals.flush_errors + recorder.flush_errors,
        rotations=totals.rotations,
        files_deleted=totals.files_deleted,
    )


class RecordingSink(QueuedSink):
    """A `SessionRecorder` behind a `QueuedSink`, rotating as `limits` say: `open_next(n)` opens the n-th
    next session (None: never rotate). `totals()` sums every session's counters; `path` is the current
    file."""

    def __init__(
        self,
        recorder: SessionRecorder,
        robot: RobotModel,
        *,
        max_pending: int = MAX_PENDING_SAMPLES,
        limits: RecordingLimits | None = None,
        open_next: Callable[[int], SessionRecorder] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.limits = limits or RecordingLimits()
        self._worker_half = _RecorderWorker(
            recorder, robot, limits=self.limits, open_next=open_next, clock=clock
        )
        super().__init__(RECORDING_SINK, self._worker_half, max_pending=max_pending)
        # A token bucket per device holding a second of the cap: on the receive clock, like the Rerun sink's.
        self._cap = DeviceRateCap(self.limits.rate_hz, burst=self.limits.rate_hz)
        self._skipped = 0
        self._rate_lock = threading.Lock()

    @property
    def recorder(self) -> SessionRecorder:
        """The session being recorded now."""
        return self._worker_half.recorder

    @property
    def path(self) -> Path:
        return self.recorder.path

    def totals(self) -> RecordingTotals:
        return self._worker_half.totals()

    def applied(self, sample: AppliedSample) -> None:
        if not self._cap.take(sample.device_id, sample.received_mono_s):
            with self._rate_lock:
                self._skipped += 1
            return
        super().applied(sample)

    def stats(self) -> SinkStats:
        with self._rate_lock:
            skipped = self._skipped
        base, worker = super().stats(), self._worker_half
        return replace(
            base,
            skipped=skipped,
            dropped=base.dropped + worker.unwritten,
            last_error=worker.last_error or base.last_error,
        )
