"""The USD session recording as a sink: the agent's worker queues each applied sample, a thread of the sink's
own computes the body poses and writes them to the stage, so a slow disk or a long USD save never slows
mirroring (twin.output.sinks describes the contract).

The recorded pose is the applied (measured, clamped) pose: forward kinematics of `AppliedSample.joint_angles`
on the sink thread's own MuJoCo scratch data (`RobotModel.body_poses`).
"""

from __future__ import annotations

import logging
from pathlib import Path

from twin.output.recorder import SessionRecorder
from twin.output.sinks import AppliedSample, QueuedSink, RejectedSample
from twin.robot.model import RobotModel

log = logging.getLogger(__name__)

RECORDING_SINK = "usd"
# A minute of 2,000 arms at 10 Hz would be 1.2 M samples; the recorder keeps at most 30 per arm per second
# anyway, so a deeper queue would only hold poses it drops. Newest wins when it overflows (counted).
MAX_PENDING_SAMPLES = 20_000


class _RecorderWorker:
    """The blocking half: runs on the sink's thread only."""

    def __init__(self, recorder: SessionRecorder, robot: RobotModel) -> None:
        self._recorder = recorder
        self._robot = robot

    def handle_applied(self, sample: AppliedSample) -> None:
        poses = self._robot.body_poses(sample.joint_angles)
        self._recorder.record(sample.device_id, sample.received_mono_s, poses, sample.telemetry.diagnostics)

    def handle_rejected(self, sample: RejectedSample) -> None:
        """A rejected message moved no twin: nothing to record."""

    def idle(self) -> None:
        self._recorder.flush_if_due()

    def close(self) -> None:
        self._recorder.close()


class RecordingSink(QueuedSink):
    """A `SessionRecorder` behind a `QueuedSink`; `recorder` exposes the file and its counters."""

    def __init__(
        self, recorder: SessionRecorder, robot: RobotModel, *, max_pending: int = MAX_PENDING_SAMPLES
    ):
        super().__init__(RECORDING_SINK, _RecorderWorker(recorder, robot), max_pending=max_pending)
        self.recorder = recorder

    @property
    def path(self) -> Path:
        return self.recorder.path
