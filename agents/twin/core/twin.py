"""The per-device twin of each arm, driven by decoded telemetry.

Two modes. Kinematic: each message sets the joint angles exactly (clamped to the joint ranges) and runs
forward kinematics; the twin is where the arm says it is. Physics: each message sets the position-actuator
targets and `step()` advances the simulation, so gravity, joint limits, servo strength and contacts shape the
motion.

Ordering is by the edge timestamp, per device: a message not newer than the last applied one is ignored and
counted, so MQTT duplicates and late deliveries never move the twin backwards. (The edge clock may jump: a
jump forward is followed, a jump backward is ignored until the clock catches up; health checks surface it.)

For the measured pose the twin also computes the model's joint torques by inverse dynamics with zero velocity
and acceleration: the torque each servo must exert to hold that pose against
gravity. It runs on a copy of the model with constraints disabled, because a resting pose that the model puts
a few mm into the floor would otherwise add a penetration force that measures the model's error, not the arm.
The service compares it with the servos' reported load (which drops when the arm rests on something).

Forward kinematics (the TCP position) and inverse dynamics are computed when someone reads them, not for
every message: a 10 Hz arm read by a 1 Hz scrape costs one computation a second instead of ten, and a fleet
mirrored at 20,000 messages a second spends its time on what is read. A snapshot carries the pose it was taken
at and computes both on first access, in the reading thread's own MuJoCo workspace (RobotModel.workspace is
per thread), at most once.

Threading: a DeviceTwin is owned by one thread, the service's worker, which alone calls `apply`, `step` and
the other methods. Other threads (HTTP, viewer, recorder) never touch it; the owner hands them `snapshot()`
results, which are immutable copies, cheap to make and safe to share.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from operator import sub
from typing import TYPE_CHECKING, NamedTuple, cast

import mujoco
import numpy as np

from twin.core.modes import TwinMode
from twin.robot.model import RobotModel

if TYPE_CHECKING:
    from twin.core.alarms import TorqueSource

log = logging.getLogger(__name__)


# How far (every joint, radians) a pose may be from the one whose holding torques the alarm engine reuses:
# 0.005 rad is about 3 encoder steps. Over it the bundled model's holding torques change by at most 0.0071 N m
# (3,000 random poses, every joint moved 0.005 rad), 0.44 % of the 7.4 V servo's 1.62 N m stall torque, where
# the model check's tolerance is 15 points (docs/servo-health.md).
HOLDING_POSE_RAD = 0.005


class _Figures:
    """TCP position and holding torques of one pose, computed at most once, in whichever thread asks first
    (a race computes the same values twice; either result is kept)."""

    __slots__ = ("_pose", "_robot", "_tcp", "_torques")

    def __init__(
        self,
        robot: RobotModel,
        pose: tuple[float, ...],
        tcp: tuple[float, float, float] | None = None,
        torques: dict[str, float] | None = None,
    ) -> None:
        self._robot = robot
        self._pose = pose
        self._tcp = tcp
        self._torques = torques

    @property
    def pose(self) -> tuple[float, ...]:
        return self._pose

    def _write(self, data: mujoco.MjData) -> None:
        # One indexed assignment (qpos addresses in joint_names order, as the pose is).
        data.qpos[self._robot.joint_indexes[0]] = self._pose

    @property
    def tcp(self) -> tuple[float, float, float]:
        tcp = self._tcp
        if tcp is None:
            robot = self._robot
            data = robot.workspace()[0]
            self._write(data)
            mujoco.mj_kinematics(robot.model, data)
            tcp = self._tcp = _tcp_of(robot, data)
        return tcp

    @property
    def torques(self) -> dict[str, float]:
        torques = self._torques
        if torques is None:
            # No velocity or acceleration: the gravity term (and springs), the holding torque.
            torques = self._torques = self._robot.inverse_dynamics(self._pose)
        return torques


def _near(a: tuple[float, ...], b: tuple[float, ...], tolerance: float) -> bool:
    # map() in C: the alarm engine asks this for every still arm's every message.
    return len(a) == len(b) and max(map(abs, map(sub, a, b)), default=0.0) <= tolerance


def _tcp_of(robot: RobotModel, data: mujoco.MjData) -> tuple[float, float, float]:
    if robot.tcp_site_id is not None:
        x, y, z = data.site_xpos[robot.tcp_site_id]
    else:
        x, y, z = data.xpos[robot.tcp_body_id]
    return (float(x), float(y), float(z))


class _HeldTorques:
    """A twin's holding torques of one pose, computed (or reused: DeviceTwin.holding_torques_when_read) when
    called."""

    __slots__ = ("_pose", "_twin")

    def __init__(self, twin: DeviceTwin, pose: tuple[float, ...]) -> None:
        self._twin = twin
        self._pose = pose

    def __call__(self) -> Mapping[str, float]:
        torques = self.kept()
        if torques is None:
            torques = self._twin.robot.inverse_dynamics(self._pose)
            self.keep(torques)
        return torques

    def kept(self) -> Mapping[str, float] | None:
        """The torques a call reuses: the twin's kept ones of a near pose, or those its snapshot of this pose
        already computed (kept from now on); None if they are to be computed."""
        twin, pose = self._twin, self._pose
        held = twin._holding
        if held is not None and _near(held[0], pose, HOLDING_POSE_RAD):
            return held[1]
        figures = twin._figures
        if figures is not None and figures.pose == pose and figures._torques is not None:
            twin._holding = (pose, figures._torques)
            return figures._torques
        return None

    def keep(self, torques: dict[str, float]) -> None:
        """Keep computed torques for the twin's next near pose, and give them to its snapshot of this pose,
        whose reader then gets them for free."""
        twin, pose = self._twin, self._pose
        figures = twin._figures
        if figures is not None and figures.pose == pose and figures._torques is None:
            figures._torques = torques
        twin._holding = (pose, torques)


def holding_torques_of(sources: Sequence[TorqueSource]) -> list[Mapping[str, float]]:
    """The holding torques of many `DeviceTwin.holding_torques_at` sources (each of another twin), as each
    would give them when called: what a call would reuse is reused (_HeldTorques.kept), the others computed
    together per model (RobotModel.holding_torques) and kept as the call would keep them. Any other source
    is called (or taken) as it is. For the alarm engine's model check of a batch (core.alarms)."""
    out: list[Mapping[str, float] | None] = []
    missing: dict[int, list[int]] = {}  # id(robot) -> positions in `sources` whose torques are computed
    robots: dict[int, RobotModel] = {}
    for n, source in enumerate(sources):
        if type(source) is not _HeldTorques:
            out.append(source() if callable(source) else source)
            continue
        kept = source.kept()
        out.append(kept)
        if kept is None:
            robot = source._twin.robot
            robots[id(robot)] = robot
            missing.setdefault(id(robot), []).append(n)
    for key, positions in missing.items():
        held_of = [cast(_HeldTorques, sources[n]) for n in positions]
        computed = robots[key].holding_torques([h._pose for h in held_of])
        for n, h, torques in zip(positions, held_of, computed, strict=True):
            h.keep(torques)
            out[n] = torques
    return cast(list[Mapping[str, float]], out)


class TwinSnapshot(NamedTuple):
    """One device's twin state at one moment, immutable: each read of the angle dicts builds a fresh one.

    The worker takes a snapshot of every device it changed after each batch, and most are never read, so it is
    a NamedTuple (built in a fraction of a frozen dataclass's time), the angles are kept as tuples
    (JOINT_NAMES order), and `joint_torques` and `tcp_position` are computed on first access (module doc)."""

    device_id: str
    timestamp_ms: int | None
    names: tuple[str, ...]
    angles: tuple[float, ...]
    target_values: tuple[float, ...]
    figures: _Figures
    mode: TwinMode = TwinMode.KINEMATIC
    applied: int = 0
    ignored_stale: int = 0
    clamped: int = 0

    @property
    def joint_angles(self) -> dict[str, float]:
        """Joint angles (radians) by name: measured in kinematic mode, simulated in physics mode."""
        return dict(zip(self.names, self.angles, strict=True))

    @property
    def targets(self) -> dict[str, float]:
        """The applied (clamped) angles by name; the actuator targets in physics mode."""
        return dict(zip(self.names, self.target_values, strict=True))

    @property
    def joint_torques(self) -> dict[str, float]:
        """Inverse-dynamics holding torque (N m) per joint of the measured pose (a fresh copy)."""
        return dict(self.figures.torques)

    @property
    def tcp_position(self) -> tuple[float, float, float]:
        return self.figures.tcp


class DeviceTwin:
    """The MuJoCo twin of one arm. Owned by one thread; see the module docstring."""

    def __init__(self, robot: RobotModel, device_id: str, mode: TwinMode = TwinMode.KINEMATIC) -> None:
        self.robot = robot
        self.device_id = device_id
        self.mode = TwinMode(mode)
        if self.mode is TwinMode.PHYSICS:
            robot.require_actuators()
        model = robot.model
        # Physics needs a state of its own that persists between steps. A kinematic twin is fully described
        # by its joint angles: it computes through the owning thread's shared workspace and keeps only the
        # figures it publishes, so a fleet of thousands costs kilobytes per arm, not two MjData each.
        self._own_data = mujoco.MjData(model) if self.mode is TwinMode.PHYSICS else None
        # Flat per-joint tables, JOINT_NAMES order: the hot path indexes lists instead of hashing names. They
        # are the model's, shared by every twin of it: a fleet's first messages each create a twin.
        self._names = robot.joint_names
        self._qadr, self._dadr, self._lo, self._hi, self._act, rest = robot.joint_tables
        self._targets = list(rest)
        self._tcp: tuple[float, float, float] | None = None  # physics: of the simulated state
        self._figures: _Figures | None = None  # of the current targets, once computed
        # The last pose whose holding torques the alarm engine asked for, and those torques.
        self._holding: tuple[tuple[float, ...], dict[str, float]] | None = None
        self._sim_debt = 0.0
        self.last_timestamp_ms: int | None = None
        self.applied = 0
        self.ignored_stale = 0
        self.clamped = 0
        if self._own_data is not None:
            self._write_pose(self._own_data, self._targets)
            self._write_ctrl(self._own_data, self._targets)
            mujoco.mj_forward(model, self._own_data)
            self._tcp = _tcp_of(robot, self._own_data)

    @property
    def data(self) -> mujoco.MjData:
        """A MuJoCo state holding this twin's pose (positions computed), e.g. for rendering.

        Physics mode: the twin's own simulation state. Kinematic mode: the owning thread's shared workspace,
        loaded with this twin's angles; it stays this twin's only until another twin of the same model on
        the same thread computes, so use it right away.
        """
        if self._own_data is not None:
            return self._own_data
        return self._kinematics()

    def _kinematics(self) -> mujoco.MjData:
        data = self.robot.workspace()[0]
        self._write_pose(data, self._targets)
        mujoco.mj_kinematics(self.robot.model, data)
        return data

    def _current_figures(self) -> _Figures:
        figures = self._figures
        if figures is None:
            figures = self._figures = _Figures(self.robot, tuple(self._targets), tcp=self._tcp)
        return figures

    # -- hot path -------------------------------------------------------------------------------------------

    def apply(self, angles_rad: Mapping[str, float], timestamp_ms: int) -> bool:
        """Apply one message's joint angles (radians, by joint name); False if it is not newer than the last.

        Joints missing from `angles_rad` keep their previous target; names the model lacks are ignored.
        Angles outside a joint's range are clamped to it and counted in `clamped`. A non-finite angle raises
        ValueError before anything changes (the decoder rejects those, so this only guards direct callers).
        """
        last = self.last_timestamp_ms
        if last is not None and timestamp_ms <= last:
            self.ignored_stale += 1
            return False
        targets = self._targets.copy()
        clamped = 0
        get = angles_rad.get
        for i, name in enumerate(self._names):
            value = get(name)
            if value is None:
                continue
            value = float(value)
            if value - value != 0.0:  # NaN or +-inf: clamping would hide a decoder bug
                raise ValueError(f"joint {name}: angle {value!r} is not finite; decode telemetry first")
            lo = self._lo[i]
            hi = self._hi[i]
            if value < lo:
                value = lo
                clamped += 1
            elif value > hi:
                value = hi
                clamped += 1
            targets[i] = value
        own = self._own_data
        if own is not None or targets != self._targets:
            # Computed when read; an arm holding still keeps the figures of its pose.
            self._figures = None
        self._targets = targets
        self.clamped += clamped
        if own is not None:
            if last is None:
                # Start the simulation at the first measured pose instead of swinging there from qpos0.
                self._write_pose(own, targets)
                own.qvel[:] = 0.0
                mujoco.mj_forward(self.robot.model, own)
                self._tcp = _tcp_of(self.robot, own)
            self._write_ctrl(own, targets)
        self.last_timestamp_ms = timestamp_ms
        self.applied += 1
        return True

    def _write_pose(self, data: mujoco.MjData, values: list[float]) -> None:
        qpos = data.qpos
        for adr, value in zip(self._qadr, values, strict=True):
            qpos[adr] = value

    def _write_ctrl(self, data: mujoco.MjData, values: list[float]) -> None:
        ctrl = data.ctrl
        for act, value in zip(self._act, values, strict=True):
            ctrl[act] = value

    # -- simulation -----------------------------------------------------------------------------------------

    def step(self, seconds: float) -> None:
        """Physics mode: advance the simulation by `seconds` toward the targets; kinematic mode: no-op.

        Time is advanced in whole model timesteps; the remainder carries over to the next call, so calling
        this with wall-clock intervals keeps simulated time in step with real time.
        """
        data = self._own_data  # set exactly in physics mode
        if self.mode is not TwinMode.PHYSICS or data is None:
            return
        if not seconds > 0.0:
            return
        model = self.robot.model
        dt = model.opt.timestep
        self._sim_debt += seconds
        # The epsilon absorbs float error so step(0.01) with dt 0.005 runs exactly two steps.
        steps = math.floor(self._sim_debt / dt + 1e-9)
        if steps <= 0:
            return
        self._sim_debt = max(0.0, self._sim_debt - steps * dt)
        for _ in range(steps):
            mujoco.mj_step(model, data)
        # mj_step leaves positions from before its final integration; refresh them for readers and renderers.
        mujoco.mj_kinematics(model, data)
        self._tcp = _tcp_of(self.robot, data)
        self._figures = None

    # -- state ----------------------------------------------------------------------------------------------

    @property
    def joint_angles(self) -> dict[str, float]:
        """Current joint angles (radians) by name: measured in kinematic mode, simulated in physics mode."""
        if self._own_data is None:
            return dict(zip(self._names, self._targets, strict=True))  # kinematic: exactly what was applied
        qpos = self._own_data.qpos
        return {n: float(qpos[a]) for n, a in zip(self._names, self._qadr, strict=True)}

    @property
    def targets(self) -> dict[str, float]:
        """The last applied (clamped) angles by name; the actuator targets in physics mode."""
        return dict(zip(self._names, self._targets, strict=True))

    @property
    def target_values(self) -> tuple[float, ...]:
        """`targets`' values in the model's joint order (`robot.joint_names`), without building a dict."""
        return tuple(self._targets)

    @property
    def joint_torques(self) -> dict[str, float]:
        """Inverse-dynamics holding torque (N m) per joint for the last measured pose."""
        return dict(self._current_figures().torques)

    def holding_torques_when_read(self) -> Callable[[], Mapping[str, float]]:
        """The holding torques of the current pose as a function that computes them on its first call: for
        callers that may not need them, the alarm engine's model check.

        A still arm's pose wanders by an encoder step or two between messages; over HOLDING_POSE_RAD its
        holding torques change by far less than the model check's tolerance, so the torques last computed for
        a pose that close are reused instead of running inverse dynamics (about 30 us) for every message of
        every still arm. `joint_torques` and snapshots always have the exact pose's."""
        return _HeldTorques(self, tuple(self._targets))

    def holding_torques_at(self, pose: tuple[float, ...]) -> Callable[[], Mapping[str, float]]:
        """`holding_torques_when_read` for `pose`, the current one (`target_values`) that the caller already
        holds: one small object per message, the figures made only if the torques are asked for."""
        return _HeldTorques(self, pose)

    @property
    def tcp_position(self) -> np.ndarray:
        """World position (m) of the tool-centre point (the TCP site, or the fallback body origin)."""
        return np.array(self._current_figures().tcp)

    def body_poses(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """World position (3,) and orientation quaternion (w, x, y, z) (4,) per body, copies.

        Bodies are so101.BODY_NAMES in order; a user model lacking some of those names returns those it has.
        """
        data = self.data
        xpos = data.xpos
        xquat = data.xquat
        return {name: (xpos[bid].copy(), xquat[bid].copy()) for name, bid in self.robot.body_ids.items()}

    def snapshot(self) -> TwinSnapshot:
        """An immutable copy of this twin's state to hand to other threads (call it on the owning thread).

        Cheap: no MuJoCo call; the TCP and torques are computed by whoever reads them first."""
        targets = tuple(self._targets)
        own = self._own_data
        angles = targets if own is None else tuple(float(own.qpos[a]) for a in self._qadr)
        return TwinSnapshot(
            self.device_id,
            self.last_timestamp_ms,
            self._names,
            angles,
            targets,
            self._current_figures(),
            self.mode,
            self.applied,
            self.ignored_stale,
            self.clamped,
        )
