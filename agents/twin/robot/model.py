"""Load and validate the MuJoCo model of the SO-101 the twin mirrors.

The twin writes joint angles by name, so a model is only usable when every name in `so101.JOINT_NAMES` is a
hinge joint. Validation happens once, at load, and a failure says exactly what is missing and how to point the
agent at another model (`[twin] model` in the agent config, `--model` on the command line). Position actuators
are only needed to drive the model in physics mode, so their absence is recorded rather than fatal here.
"""

from __future__ import annotations

import copy
import functools
import logging
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import mujoco
import numpy as np

from twin.robot import so101

log = logging.getLogger(__name__)

# Sites tried in order when no tcp site is configured: ours, then the upstream/menagerie name, so a user's
# Menagerie MJCF works without edits.
DEFAULT_TCP_SITES: tuple[str, ...] = (so101.TCP_SITE, "gripperframe")
# When no TCP site exists the gripper body's origin stands in for it (a few cm short of the fingertip).
FALLBACK_TCP_BODY = "gripper"

_FIX_HINT = (
    'Fix the MJCF, or point the agent at one that has them: `[twin] model = "/path/to/scene.xml"` in the '
    "agent config (empty = the bundled SO-101), or `--model` on the command line."
)


# Models compiled ahead of their first load, by resolved MJCF path. The workers' fork server compiles the
# bundled scene while it imports the rest of the mirror (twin.service.worker_preload); each worker forked
# from it takes its own copy-on-write copy here instead of compiling the meshes again (about 0.15 s).
_PRECOMPILED: dict[Path, mujoco.MjModel] = {}


def precompile(path: Path) -> None:
    """Compile `path` now, for the next `RobotModel.load` of it in this process (or in a process forked from
    it). A model that fails to compile is left out: that load compiles it again and reports the error."""
    path = path.resolve()
    try:
        _PRECOMPILED[path] = mujoco.MjModel.from_xml_path(str(path))
    except ValueError:
        _PRECOMPILED.pop(path, None)


class ModelError(ValueError):
    """The robot model cannot be used: the message lists what is wrong and how to fix it."""


def default_model_path() -> Path:
    """The bundled SO-101 scene (robot + floor + overview camera), shipped in the `twin_robots` package."""
    import twin_robots  # noqa: PLC0415 - only the loader needs the asset package

    return Path(twin_robots.__file__).resolve().parent / "so101" / "scene.xml"


def _name(model: mujoco.MjModel, obj: mujoco.mjtObj, index: int) -> str:
    return mujoco.mj_id2name(model, obj, index) or ""


def _is_position_servo(model: mujoco.MjModel, act: int) -> bool:
    # A <position> actuator is gain kp with an affine bias -kp*q (-kv*qdot); a <motor> or <velocity> on the
    # same joint would take the target angle as a torque or speed, which is wrong for physics mode.
    kp = float(model.actuator_gainprm[act, 0])
    return (
        model.actuator_gaintype[act] == mujoco.mjtGain.mjGAIN_FIXED
        and model.actuator_biastype[act] == mujoco.mjtBias.mjBIAS_AFFINE
        and kp > 0.0
        and bool(np.isclose(model.actuator_biasprm[act, 1], -kp))
    )


class JointTables(NamedTuple):
    """Per-joint tables in JOINT_NAMES order: qpos and dof addresses, lower and upper limits, the position
    actuator's id (-1 without one), and the model's reference pose clamped to the limits."""

    qpos: tuple[int, ...]
    dof: tuple[int, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]
    actuator: tuple[int, ...]
    rest: tuple[float, ...]


@dataclass(eq=False)
class RobotModel:
    """A validated MuJoCo model of the arm plus the index tables the twin needs (read-only after load).

    One RobotModel can be shared by many DeviceTwins and threads: nothing here changes after `load` except
    the per-thread scratch data of `workspace()`.
    """

    model: mujoco.MjModel
    path: Path
    joint_names: tuple[str, ...]
    joint_ids: dict[str, int]
    qpos_addr: dict[str, int]
    dof_addr: dict[str, int]
    joint_ranges: dict[str, tuple[float, float]]
    # Joint name -> id of the position actuator driving it; joints without one are in `missing_actuators`.
    actuator_ids: dict[str, int]
    missing_actuators: tuple[str, ...]
    # Bodies of so101.BODY_NAMES present in this model, in that order (a user model may lack some).
    body_ids: dict[str, int]
    tcp_site: str | None
    tcp_site_id: int | None
    tcp_body_id: int
    # A copy of `model` with constraints disabled, for holding torques by inverse dynamics
    # (see twin.core.twin).
    inverse_model: mujoco.MjModel
    camera_names: tuple[str, ...] = field(default=())
    _local: threading.local = field(default_factory=threading.local, repr=False)

    @classmethod
    def load(
        cls, path: str | Path | None = None, *, tcp_site: str | Sequence[str] | None = None
    ) -> RobotModel:
        """Load an MJCF (None = the bundled SO-101 scene) and validate it; raises ModelError.

        `tcp_site` names the tool-centre-point site (or candidates, first match wins); None tries
        "tcp" then "gripperframe". Without any, the gripper body origin stands in and a warning is logged.
        """
        mjcf = Path(path).expanduser() if path not in (None, "") else default_model_path()
        if not mjcf.is_file():
            raise ModelError(
                f"robot model not found: {mjcf} does not exist or is not a file. "
                "Set `[twin] model` in the agent config (or --model) to an existing MJCF file, "
                "or leave it empty to use the bundled SO-101."
            )
        # Taken once: a second load in the same process compiles the file as it is then.
        model = _PRECOMPILED.pop(mjcf.resolve(), None)
        try:
            if model is None:
                model = mujoco.MjModel.from_xml_path(str(mjcf))
        except ValueError as exc:  # mujoco reports XML, include and compile errors as ValueError
            raise ModelError(
                f"robot model {mjcf} could not be loaded by MuJoCo: {str(exc).strip()}. "
                "Fix the file, or set `[twin] model` in the agent config (or --model) to a valid MJCF."
            ) from exc
        return cls.from_model(model, mjcf, tcp_site=tcp_site)

    @classmethod
    def from_model(
        cls, model: mujoco.MjModel, path: str | Path, *, tcp_site: str | Sequence[str] | None = None
    ) -> RobotModel:
        """Validate an already compiled model (e.g. built from a string in a test); raises ModelError."""
        mjcf = Path(path)
        joint_ids = _joint_ids(model, mjcf)
        actuator_ids = _position_actuators(model, joint_ids)
        site_name, site_id, tcp_body = _tcp(model, mjcf, joint_ids, tcp_site)
        # A resting pose the model places a few mm into the floor (or exactly at a limit) would otherwise add
        # an arbitrary soft-constraint force from the penetration depth; holding torque = gravity (+ springs).
        inverse_model = copy.deepcopy(model)
        inverse_model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
        body_ids = {
            name: bid
            for name in so101.BODY_NAMES
            if (bid := mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)) >= 0
        }
        return cls(
            model=model,
            path=mjcf,
            joint_names=so101.JOINT_NAMES,
            joint_ids=joint_ids,
            qpos_addr={n: int(model.jnt_qposadr[j]) for n, j in joint_ids.items()},
            dof_addr={n: int(model.jnt_dofadr[j]) for n, j in joint_ids.items()},
            joint_ranges=_joint_ranges(model, mjcf, joint_ids),
            actuator_ids=actuator_ids,
            missing_actuators=tuple(n for n in so101.JOINT_NAMES if n not in actuator_ids),
            body_ids=body_ids,
            tcp_site=site_name,
            tcp_site_id=site_id,
            tcp_body_id=tcp_body,
            inverse_model=inverse_model,
            camera_names=tuple(_name(model, mujoco.mjtObj.mjOBJ_CAMERA, c) for c in range(model.ncam)),
        )

    @functools.cached_property
    def joint_tables(self) -> JointTables:
        """The per-joint index tables a twin reads per message, each in `joint_names` order; built on first
        use and kept with the model."""
        names = self.joint_names
        lo = tuple(self.joint_ranges[n][0] for n in names)
        hi = tuple(self.joint_ranges[n][1] for n in names)
        qadr = tuple(self.qpos_addr[n] for n in names)
        return JointTables(
            qpos=qadr,
            dof=tuple(self.dof_addr[n] for n in names),
            lo=lo,
            hi=hi,
            actuator=tuple(self.actuator_ids.get(n, -1) for n in names),
            rest=tuple(
                min(max(float(self.model.qpos0[a]), low), high)
                for a, low, high in zip(qadr, lo, hi, strict=True)
            ),
        )

    @functools.cached_property
    def joint_indexes(self) -> tuple[slice | list[int], slice | list[int]]:
        """The joints' qpos and dof addresses (`joint_tables` order) as numpy indexes, for writing a pose into
        MjData and reading its joints back: a slice where they are consecutive, as in the bundled model, since
        a slice reads and writes a row of six in about a third less time than a list of addresses does."""
        tables = self.joint_tables
        return _index(tables.qpos), _index(tables.dof)

    def workspace(self) -> tuple[mujoco.MjData, mujoco.MjData]:
        """This thread's scratch MjData for `model` and for `inverse_model`, made on first use.

        Kinematic twins keep only their joint angles and derived figures; they compute through this shared
        pair instead of owning two MjData each (about 0.9 MB and a few milliseconds to allocate per arm),
        which is what lets one agent hold a fleet of thousands. Per thread, because twins owned by different
        threads (the service worker, a render in the main thread) must not share scratch state.
        """
        local = self._local
        pair = getattr(local, "pair", None)
        if pair is None:
            pair = (mujoco.MjData(self.model), mujoco.MjData(self.inverse_model))
            local.pair = pair
        return pair

    def inverse_dynamics(
        self,
        pose: Sequence[float],
        velocity: Sequence[float] | None = None,
        acceleration: Sequence[float] | None = None,
        *,
        passive: bool = True,
    ) -> dict[str, float]:
        """The torque (N·m, by joint name) each joint needs to move with `acceleration` at `pose` and
        `velocity` (rad, rad/s, rad/s², `joint_names` order; None = zero), by inverse dynamics on
        `inverse_model` in this thread's workspace: gravity, inertia (with the rotors' armature), Coriolis and
        centrifugal terms, and, with `passive`, the joints' springs and damping.

        With neither velocity nor acceleration this is the holding torque the twin's model check compares
        with the servos' load (twin.core.twin); the edge simulator's physical servos add the motion."""
        scratch = self.workspace()[1]
        qadr, dofs = self.joint_indexes
        scratch.qpos[qadr] = pose
        # Written every call: the scratch is shared, and mj_inverse reads whatever the last caller left.
        scratch.qvel[dofs] = 0.0 if velocity is None else velocity
        scratch.qacc[dofs] = 0.0 if acceleration is None else acceleration
        mujoco.mj_inverse(self.inverse_model, scratch)
        forces = scratch.qfrc_inverse
        if not passive:
            # mj_inverse subtracts the passive forces (qfrc_inverse = M qacc + bias - passive); add them back.
            forces = forces + scratch.qfrc_passive
        return dict(zip(self.joint_names, forces[dofs].tolist(), strict=True))

    def holding_torques(self, poses: Sequence[Sequence[float]]) -> list[dict[str, float]]:
        """`inverse_dynamics(pose)` of each pose (no velocity, no acceleration, with the passive forces), in
        one loop over this thread's workspace: the same values, without a call's setting up per pose (for a
        batch of a fleet's messages, about half the time per pose)."""
        if not poses:
            return []
        scratch = self.workspace()[1]
        qadr, dofs = self.joint_indexes
        # Written for every batch: the scratch is shared, and mj_inverse reads whatever the last caller left.
        scratch.qvel[dofs] = 0.0
        scratch.qacc[dofs] = 0.0
        qpos, forces, names, model = scratch.qpos, scratch.qfrc_inverse, self.joint_names, self.inverse_model
        inverse = mujoco.mj_inverse
        out = []
        for pose in poses:
            qpos[qadr] = pose
            inverse(model, scratch)
            out.append(dict(zip(names, forces[dofs].tolist(), strict=True)))
        return out

    def _kinematics(self, angles_rad: Mapping[str, float]) -> mujoco.MjData:
        # This thread's workspace posed at `angles_rad` (other joints at the reference pose), kinematics done.
        data = self.workspace()[0]
        data.qpos[:] = self.model.qpos0
        for name, value in angles_rad.items():
            adr = self.qpos_addr.get(name)
            if adr is not None:
                data.qpos[adr] = value
        mujoco.mj_kinematics(self.model, data)
        return data

    def body_poses(self, angles_rad: Mapping[str, float]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """World position (3,) and quaternion (w, x, y, z) (4,) of each body for joint angles (radians, by
        name), by forward kinematics on this thread's workspace. Joints missing from `angles_rad` sit at the
        model's reference pose; angles are used as given (clamp first if they may leave the joint ranges)."""
        data = self._kinematics(angles_rad)
        return {name: (data.xpos[bid].copy(), data.xquat[bid].copy()) for name, bid in self.body_ids.items()}

    def body_pose_array(self, angles_rad: Mapping[str, float]) -> np.ndarray:
        """`body_poses` as one (bodies, 7) array in `body_ids` order: position x y z, then the quaternion
        w x y z. For sinks that pose every sample of a fleet: one copy out of MuJoCo instead of a dict of
        fourteen small arrays, which costs several times the kinematics itself."""
        data = self._kinematics(angles_rad)
        rows = self.__dict__.get("_pose_rows")
        if rows is None:
            # A slice when the bodies are consecutive (they are in every SO-101 model): fancy indexing is
            # most of this function's cost otherwise.
            ids = np.fromiter(self.body_ids.values(), dtype=np.intp)
            consecutive = ids.size > 0 and np.array_equal(ids, np.arange(ids[0], ids[0] + ids.size))
            rows = slice(int(ids[0]), int(ids[0]) + ids.size) if consecutive else ids
            self.__dict__["_pose_rows"] = rows
        out = np.empty((len(self.body_ids), 7))
        out[:, :3] = data.xpos[rows]
        out[:, 3:] = data.xquat[rows]
        return out

    def require_actuators(self) -> None:
        """Raise ModelError unless every joint has a position actuator (physics mode drives them)."""
        if self.missing_actuators:
            raise ModelError(
                f"robot model {self.path} cannot run in physics mode: no <position> actuator drives "
                f"{', '.join(self.missing_actuators)}. Add one <position joint=...> actuator per joint, use "
                '`[twin] mode = "kinematic"`, or set `[twin] model` to an MJCF with position actuators.'
            )


def _index(addresses: tuple[int, ...]) -> slice | list[int]:
    """`addresses` as a numpy index: the slice that selects them if they are consecutive and ascending."""
    first = addresses[0] if addresses else 0
    if addresses == tuple(range(first, first + len(addresses))):
        return slice(first, first + len(addresses))
    return list(addresses)


def _joint_ids(model: mujoco.MjModel, mjcf: Path) -> dict[str, int]:
    """Joint name -> id for every SO-101 joint; ModelError listing what is missing or not a hinge."""
    names = so101.JOINT_NAMES
    missing: list[str] = []
    wrong_type: list[str] = []
    joint_ids: dict[str, int] = {}
    for name in names:
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            missing.append(name)
        elif model.jnt_type[jid] != mujoco.mjtJoint.mjJNT_HINGE:
            kind = mujoco.mjtJoint(model.jnt_type[jid]).name.removeprefix("mjJNT_").lower()
            wrong_type.append(f"{name} (is {kind})")
        else:
            joint_ids[name] = jid
    if missing or wrong_type:
        found = [_name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(model.njnt)]
        problems = []
        if missing:
            problems.append(f"missing joints: {', '.join(missing)}")
        if wrong_type:
            problems.append(f"not hinge joints: {', '.join(wrong_type)}")
        raise ModelError(
            f"robot model {mjcf} cannot mirror the SO-101: {'; '.join(problems)}. "
            f"The twin needs hinge joints named {', '.join(names)} (the edge telemetry's names); "
            f"the model has: {', '.join(n or '<unnamed>' for n in found) or 'no joints'}. {_FIX_HINT}"
        )
    return joint_ids


def _joint_ranges(
    model: mujoco.MjModel, mjcf: Path, joint_ids: dict[str, int]
) -> dict[str, tuple[float, float]]:
    joint_ranges: dict[str, tuple[float, float]] = {}
    for name, jid in joint_ids.items():
        if model.jnt_limited[jid]:
            lo, hi = (float(v) for v in model.jnt_range[jid])
            joint_ranges[name] = (lo, hi)
        else:
            # An unlimited joint would accept any telemetry; clamp to the real arm's travel instead.
            joint_ranges[name] = so101.JOINT_RANGES_RAD[name]
            log.info(
                "joint %s has no range in %s; clamping to the SO-101 range %s", name, mjcf, joint_ranges[name]
            )
    return joint_ranges


def _position_actuators(model: mujoco.MjModel, joint_ids: dict[str, int]) -> dict[str, int]:
    """Joint name -> the first position actuator driving it (physics mode needs one per joint)."""
    actuator_ids: dict[str, int] = {}
    for act in range(model.nu):
        if model.actuator_trntype[act] != mujoco.mjtTrn.mjTRN_JOINT:
            continue
        target = int(model.actuator_trnid[act, 0])
        for name, jid in joint_ids.items():
            if jid == target and name not in actuator_ids and _is_position_servo(model, act):
                actuator_ids[name] = act
    return actuator_ids


def _tcp(
    model: mujoco.MjModel, mjcf: Path, joint_ids: dict[str, int], tcp_site: str | Sequence[str] | None
) -> tuple[str | None, int | None, int]:
    """(site name, site id) of the first TCP site found (None, None without one), and the fallback body."""
    candidates = (tcp_site,) if isinstance(tcp_site, str) else tuple(tcp_site or DEFAULT_TCP_SITES)
    site_name: str | None = None
    site_id: int | None = None
    for candidate in candidates:
        sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, candidate)
        if sid >= 0:
            site_name, site_id = candidate, sid
            break
    tcp_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, FALLBACK_TCP_BODY)
    if tcp_body < 0:
        # Last resort for a model with other body names: the body the gripper joint moves.
        tcp_body = int(model.jnt_bodyid[joint_ids[so101.GRIPPER]])
    if site_id is None:
        log.warning(
            "robot model %s has no TCP site (tried %s); using the origin of body %r as the TCP. "
            "Add a site at the gripper tip or configure its name.",
            mjcf,
            ", ".join(candidates),
            _name(model, mujoco.mjtObj.mjOBJ_BODY, tcp_body),
        )
    return site_name, site_id, tcp_body
