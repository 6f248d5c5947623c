"""Session recording: the twin's motion as a time-sampled USD stage that plays in usdview or Omniverse.

One stage per session. Each device gets `/World/<sanitised id>`, which references the arm's USD asset once;
every body prim of that reference gets time samples on its own translate/orient ops, authored so that the
composed world transform of the body at a time code equals MuJoCo's forward-kinematics world pose. The asset
nests bodies like the MJCF (base/shoulder/...), so a body's local transform is taken relative to its parent
body, including any static prims the asset places between the two. A body missing from the poses (a user MJCF
with other body names) keeps the asset's own local transform and moves with its parent.

With each pose the caller may pass the servos' decoded diagnostics: they become time-sampled custom
attributes on the device prim, `twin:servo:<joint>:<reading>` (velocityRadPerSecond, loadPercent,
temperatureCelsius, currentAmperes, voltageVolts; docs/servo-health.md), sampled at the same time codes as
the poses. A reading the edge did not send gets no sample, so it holds its last value in playback rather
than a made-up zero.

Time code = (t_seconds - origin) * time_codes_per_second, where origin is the first t_seconds recorded in the
session (kept in the layer's customLayerData as `twin:timeOriginSeconds`), so callers may pass any monotonic
clock. At most time_codes_per_second samples per device are kept: a sample less than one time code after
that device's previous one is dropped (and counted). The layer is saved every flush_interval_s of wall time,
driven by record() and flush_if_due(), so a crash loses at most that much. In the agent the recorder runs as
a sink on its own thread (twin.output.recording), never on the mirror's worker.
"""

from __future__ import annotations

import logging
import math
import os
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike
from pxr import Gf, Sdf, Tf, Usd, UsdGeom

from twin.core.telemetry import JointDiagnostics
from twin.robot import so101

log = logging.getLogger(__name__)

# The stage's time codes (and frames) per second unless a caller says otherwise.
TIME_CODES_PER_SECOND = 30.0
# A sample that lands a hair under one time code after the previous one (float rounding of t * fps) is kept.
_DROP_TOLERANCE = 1e-6
# usd-core saves a usdc layer that is already on disk in place, appending what is new: a save the disk cannot
# take tears the whole file, not just what it would add (a walk's 6 MB session became unreadable). So a save
# is made only with room for several times what the last one added, and at least this much.
MIN_FREE_FOR_SAVE_BYTES = 1 << 20
SAVE_ROOM_FACTOR = 4
_OP_SUFFIX = "twin"
_TIME_CODE_DIGITS = 6
_PRIM_NAME_BAD = re.compile(r"[^A-Za-z0-9_]")

BodyPoses = Mapping[str, tuple[ArrayLike, ArrayLike]]  # anything np.asarray takes: checked on arrival
_Vec = tuple[float, ...]
_Pose = tuple[_Vec, _Vec]  # a checked pose: position (3 floats, metres), unit quaternion (w, x, y, z)
# A rigid transform as floats: p -> rotate(quat, p) + pos (column vectors), quat (w, x, y, z) unit.
_Rigid = tuple[_Vec, _Vec]  # (quat, pos)
# JointDiagnostics field -> USD attribute name part (units in the name: a USD reader sees no docstring).
SERVO_READINGS: tuple[tuple[str, str], ...] = (
    ("velocity_rad_s", "velocityRadPerSecond"),
    ("load_percent", "loadPercent"),
    ("temperature_c", "temperatureCelsius"),
    ("current_a", "currentAmperes"),
    ("voltage_v", "voltageVolts"),
)


def servo_attribute_name(joint: str, reading: str) -> str:
    """The device prim's attribute for one servo reading, e.g. twin:servo:elbow_flex:temperatureCelsius."""
    return f"twin:servo:{joint}:{reading}"


def default_asset_path() -> Path:
    """The bundled SO-101 USD asset (robots/so101/usd/so101.usda, made by `make usd-asset`)."""
    return Path(str(resources.files("twin_robots") / "so101" / "usd" / "so101.usda"))


def sanitise_prim_name(device_id: str) -> str:
    """A valid USD prim name for a device id: invalid characters become '_', a leading digit gets a '_'."""
    name = _PRIM_NAME_BAD.sub("_", device_id) or "_"
    return f"_{name}" if name[0].isdigit() else name


@dataclass(frozen=True)
class _BodyLink:
    """Where a body sits in the asset. Transforms are float (quat, pos) pairs, see _Rigid."""

    name: str
    rel_path: str  # below the asset's default prim, e.g. "Geometry/base/shoulder"
    parent_body: str | None
    offset: _Rigid  # this body's parent prim in the parent body's frame (or the device root's)
    asset_local: _Rigid  # the body's own local transform in the asset, used when its pose is missing


@dataclass
class _DeviceTrack:
    # The attributes' paths in the session layer, where their time samples are written (see _author).
    prim_path: str
    translate_attrs: dict[str, Sdf.Path]
    orient_attrs: dict[str, Sdf.Path]
    last_quat: dict[str, _Vec] = field(default_factory=dict)  # the orient last written, (w, x, y, z)
    servo_attrs: dict[tuple[str, str], Sdf.Path] = field(default_factory=dict)
    last_time_code: float = -math.inf
    samples: int = 0
    warned_missing: bool = False


class SessionRecorder:
    """Writes one session's twin motion to a USD stage (see the module docstring for the layout)."""

    def __init__(
        self,
        path: Path,
        *,
        asset_path: Path | None = None,
        flush_interval_s: float = 2.0,
        time_codes_per_second: float = TIME_CODES_PER_SECOND,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (math.isfinite(time_codes_per_second) and time_codes_per_second > 0):
            raise ValueError(f"time_codes_per_second must be positive, got {time_codes_per_second!r}")
        if not (math.isfinite(flush_interval_s) and flush_interval_s > 0):
            raise ValueError(f"flush_interval_s must be positive seconds, got {flush_interval_s!r}")
        self.path = Path(path).resolve()
        if self.path.exists():
            raise FileExistsError(
                f"session file {self.path} already exists; recordings are never overwritten, pick a new name"
            )
        self.asset_path = Path(asset_path).resolve() if asset_path is not None else default_asset_path()
        if not self.asset_path.is_file():
            raise FileNotFoundError(
                f"USD asset {self.asset_path} not found; run `make usd-asset` or pass asset_path"
            )
        self.flush_interval_s = float(flush_interval_s)
        self.time_codes_per_second = float(time_codes_per_second)

        asset = Usd.Stage.Open(str(self.asset_path))
        if asset is None or not asset.GetDefaultPrim():
            raise ValueError(f"USD asset {self.asset_path} has no default prim to reference; set defaultPrim")
        self._links = _inspect_asset(asset, self.asset_path)
        meters_per_unit = UsdGeom.GetStageMetersPerUnit(asset)
        # Poses arrive in metres; the asset's unit decides what a translate value means.
        self._units_per_metre = 1.0 / meters_per_unit

        self._stage = self._create_stage(asset, meters_per_unit)
        self._layer: Sdf.Layer = self._stage.GetRootLayer()
        self._asset_ref = _relative_asset_path(self.asset_path, self.path.parent)

        self._devices: dict[str, _DeviceTrack] = {}
        self._prim_names: set[str] = set()
        self._time_origin_s: float | None = None
        self._min_time_code = math.inf
        self._max_time_code = -math.inf
        self._closed = False
        # A save failed: usd-core (26.11) crashes the process when a usdc layer whose save failed (a full
        # disk) is written to again, so nothing more is written to this session (RecordingSink starts a new
        # one once it can).
        self.broken = False
        self.samples_written = 0  # these five: the agent's metrics
        self.samples_dropped = 0
        self.samples_rejected = 0
        self.flushes = 0
        self.flush_errors = 0
        # What the last save added to the file: the next one needs room for a few times as much.
        self._last_growth = 0
        self._first_save()
        # Wall-time flushes are measured on this clock (injectable, so tests need not sleep).
        self._clock = clock
        self._last_flush = clock()
        log.info("recording session to %s (asset %s)", self.path, self._asset_ref)

    @classmethod
    def not_begun(cls, path: str | Path) -> SessionRecorder:
        """A session whose file could not be begun (a full disk as a worker starts), set aside from the
        start: every sample is dropped and counted, and RecordingSink opens a real session once the disk
        has room, as after a failed save. Without it a worker could not start, nor start again after a
        crash, while the disk was full, and its arms stopped being mirrored for a recording."""
        self = cls.__new__(cls)
        self.path = Path(path).resolve()
        # Read by the sink as it places samples (recording.EdgeSpacing): a set-aside first session stopped
        # the agent's start on a full disk without it.
        self.time_codes_per_second = TIME_CODES_PER_SECOND
        self._devices = {}
        self._closed = True  # nothing to save or close: record() drops, close() does nothing
        self.broken = True
        self.samples_written = self.samples_dropped = self.samples_rejected = 0
        self.flushes = self.flush_errors = 0
        return self

    def _first_save(self) -> None:
        """The new session's first save; a file that cannot be saved (a full disk) is removed, not left
        behind empty (a walk found one such 0-byte file per attempt, 24 a minute, while the disk was full)."""
        try:
            saved = self._layer.Save()
        except Tf.ErrorException:
            saved = False
        if not saved:
            raise self._not_begun()

    def _not_begun(self) -> OSError:
        """A session whose file could not be written at its start: the file is removed, not left behind empty
        or torn, and the error says what to check."""
        self.path.unlink(missing_ok=True)
        return OSError(f"session {self.path} could not be saved; check disk space and permissions")

    def _room_to_save(self) -> bool:
        """Whether the disk has room for the next save (MIN_FREE_FOR_SAVE_BYTES); if not, said, and the
        session set aside."""
        try:
            st = os.statvfs(self.path.parent)
        except OSError:
            return True  # not knowable: the save itself will tell
        free = st.f_bavail * st.f_frsize
        needed = max(MIN_FREE_FOR_SAVE_BYTES, SAVE_ROOM_FACTOR * self._last_growth)
        if free >= needed:
            return True
        self.flush_errors += 1
        self.broken = True
        log.error(
            "session %s not saved: %d bytes free on its disk, %d needed (a save cut short would tear the "
            "whole file). Its file holds what it had at its last save; the samples since are dropped, and "
            "the recording goes on in a new session once the disk has room. Free space in %s",
            self.path,
            free,
            needed,
            self.path.parent,
        )
        return False

    def _create_stage(self, asset: Usd.Stage, meters_per_unit: float) -> Usd.Stage:
        """The session stage: the asset's up axis and units, a /World default prim, time codes per second."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            stage = Usd.Stage.CreateNew(str(self.path))
        except Tf.ErrorException as exc:  # CreateNew writes the file at once: a full disk fails here
            raise self._not_begun() from exc
        if stage is None:
            raise OSError(f"cannot create USD stage {self.path}; check the folder is writable")
        UsdGeom.SetStageUpAxis(stage, UsdGeom.GetStageUpAxis(asset))
        UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
        stage.SetTimeCodesPerSecond(self.time_codes_per_second)
        stage.SetFramesPerSecond(self.time_codes_per_second)
        stage.SetStartTimeCode(0)
        stage.SetEndTimeCode(0)
        world = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(world.GetPrim())
        return stage

    @property
    def time_origin_s(self) -> float | None:
        """The t_seconds that maps to time code 0 (the first sample recorded); None before any sample."""
        return self._time_origin_s

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def kept(self) -> bool:
        """Whether the session's file is on disk: not for a session closed with no sample (close() removes
        its file), nor one set aside before its file was begun (not_begun)."""
        return self.samples_written > 0 or not self._closed

    @property
    def devices(self) -> dict[str, str]:
        """Device id -> prim path of every device recorded so far."""
        return {device_id: track.prim_path for device_id, track in self._devices.items()}

    def time_code(self, t_seconds: float) -> float:
        """The stage time code of a record() time (the first sample fixes the origin)."""
        if self._time_origin_s is None:
            raise RuntimeError("no sample recorded yet, so the time origin is not fixed")
        # Rounded so float noise (9.000000000000002) does not clutter the text layer.
        return round((t_seconds - self._time_origin_s) * self.time_codes_per_second, _TIME_CODE_DIGITS)

    def record(
        self,
        device_id: str,
        t_seconds: float,
        body_poses: BodyPoses,
        diagnostics: Mapping[str, JointDiagnostics] | None = None,
    ) -> bool:
        """Time-sample one device's body world poses (and servo diagnostics, if given); True if written,
        False if dropped or rejected.

        Bad input (no known body, non-finite or malformed pose, non-finite time) is logged and counted in
        samples_rejected, never raised, so a recording problem cannot take the twin service down.
        """
        if self._closed or self.broken:
            self.samples_dropped += 1
            if not self.broken:
                log.warning("record(%r) after %s was closed; sample dropped", device_id, self.path.name)
            return False
        try:
            if not math.isfinite(t_seconds):
                raise ValueError(f"t_seconds must be finite, got {t_seconds!r}")
            poses = _validate_poses(body_poses)
        except (TypeError, ValueError) as exc:
            self.samples_rejected += 1
            log.warning("session %s: sample for %r rejected: %s", self.path.name, device_id, exc)
            return False

        if self._time_origin_s is None:
            self._time_origin_s = float(t_seconds)
            self._layer.customLayerData = {
                **self._layer.customLayerData,
                "twin:timeOriginSeconds": float(t_seconds),
            }
        tc = self.time_code(t_seconds)
        track = self._devices.get(device_id) or self._add_device(device_id)
        if tc < track.last_time_code + 1.0 - _DROP_TOLERANCE:
            self.samples_dropped += 1
            return False
        if len(poses) < len(self._links) and not track.warned_missing:
            track.warned_missing = True
            missing = [link.name for link in self._links if link.name not in poses]
            log.warning("device %r: no poses for bodies %s; they keep the asset's pose", device_id, missing)

        readings = self._servo_readings(track, diagnostics) if diagnostics else ()
        self._author(track, poses, readings, tc)
        track.last_time_code = tc
        track.samples += 1
        self.samples_written += 1
        self._min_time_code = min(self._min_time_code, tc)
        self._max_time_code = max(self._max_time_code, tc)
        self.flush_if_due()
        return True

    def _author(
        self,
        track: _DeviceTrack,
        poses: dict[str, _Pose],
        readings: Sequence[tuple[Sdf.Path, float]],
        tc: float,
    ) -> None:
        """Time-sample every body's local transform so its composed world transform equals its pose, and the
        servo readings.

        The samples go straight into the session layer (`Sdf.Layer.SetTimeSample`), in one change block: the
        layer is the stage's edit target, so this is what `Usd.Attribute.Set` writes, without its per-call
        value resolution and notices (about 16 us a value, against 5 here; a sample has 14 pose values and up
        to 30 servo readings, and the recording is one thread under the interpreter lock with the mirror).
        The pose math is float quaternions (_compose etc.), not Gf matrices: composing and inverting 4x4
        Gf.Matrix4d per body was about 40 % of a sample; the layer still gets the attributes' Gf types."""
        worlds: dict[str, _Rigid] = {}
        layer = self._layer
        s = self._units_per_metre
        with Sdf.ChangeBlock():
            for link in self._links:  # base to tip, so a parent's world is known before its children
                parent = link.offset
                if link.parent_body is not None:
                    parent = _compose(worlds[link.parent_body], parent)
                pose = poses.get(link.name)
                if pose is None:
                    quat, pos = link.asset_local
                    worlds[link.name] = _compose(parent, link.asset_local)
                else:
                    world = worlds[link.name] = (pose[1], (pose[0][0] * s, pose[0][1] * s, pose[0][2] * s))
                    quat, pos = _relative(parent, world)
                    quat = _gf_sign(quat)
                quat = _continue_hemisphere(track.last_quat.get(link.name), quat)
                track.last_quat[link.name] = quat
                layer.SetTimeSample(track.translate_attrs[link.name], tc, Gf.Vec3d(pos[0], pos[1], pos[2]))
                layer.SetTimeSample(
                    track.orient_attrs[link.name], tc, Gf.Quatd(quat[0], quat[1], quat[2], quat[3])
                )
            for path, value in readings:
                layer.SetTimeSample(path, tc, value)

    def flush_if_due(self) -> None:
        """Save when `flush_interval_s` has passed since the last save (record() and an idle sink call it)."""
        if not self._closed and not self.broken and self._clock() - self._last_flush >= self.flush_interval_s:
            self.flush()

    def flush(self) -> None:
        """Save the stage so far (time range included). A failed save is logged and counted, not raised."""
        if self._closed:
            return
        if self.samples_written:
            self._stage.SetStartTimeCode(min(0.0, self._min_time_code))
            self._stage.SetEndTimeCode(self._max_time_code)
        self._last_flush = self._clock()
        if not self._room_to_save():
            return
        before = file_size(self.path)
        try:
            saved = self._layer.Save()
        except Exception:  # pxr raises Tf.ErrorException; a full disk must not stop the twin
            log.exception("saving session %s failed", self.path)
            saved = False
        if saved:
            self.flushes += 1
            self._last_growth = max(0, file_size(self.path) - before)
        else:
            self.flush_errors += 1
            self.broken = True
            log.error(
                "session %s could not be saved; check disk space and permissions. Nothing more is written to "
                "it, and its file may be unreadable (a save cut short tears a usdc file); the recording goes "
                "on in a new session once one can be saved",
                self.path,
            )

    def close(self) -> None:
        """Final save (none for a session whose save failed); later calls do nothing. A session that recorded
        no sample is removed instead: each worker of an agent opens one at start, and one given no arm left
        an empty file beside the others at every run."""
        if self._closed:
            return
        if self.samples_written == 0:
            self._closed = True
            self._remove_empty()
            return
        if not self.broken:
            self.flush()
        self._closed = True
        log.info(
            "session %s closed: %d samples written, %d dropped, %d rejected, %d devices",
            self.path,
            self.samples_written,
            self.samples_dropped,
            self.samples_rejected,
            len(self._devices),
        )

    def _remove_empty(self) -> None:
        try:
            self.path.unlink(missing_ok=True)
        except OSError as exc:
            log.warning("session %s recorded no sample; its file could not be removed: %s", self.path, exc)
            return
        log.info(
            "session %s closed with no sample recorded (%d dropped, %d rejected): its file is removed",
            self.path,
            self.samples_dropped,
            self.samples_rejected,
        )

    def __enter__(self) -> SessionRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _servo_readings(
        self, track: _DeviceTrack, diagnostics: Mapping[str, JointDiagnostics]
    ) -> list[tuple[Sdf.Path, float]]:
        """(attribute path, value) of each finite reading sent, creating a reading's attribute the first time
        it comes (outside the change block that writes the samples: the stage must see the new spec)."""
        readings: list[tuple[Sdf.Path, float]] = []
        prim = None
        for joint, diag in diagnostics.items():
            if joint not in so101.JOINT_NAMES:
                continue
            for field_name, reading in SERVO_READINGS:
                value = getattr(diag, field_name)
                if value is None or not math.isfinite(value):
                    continue
                path = track.servo_attrs.get((joint, reading))
                if path is None:
                    prim = prim or self._stage.GetPrimAtPath(track.prim_path)
                    attr = prim.CreateAttribute(
                        servo_attribute_name(joint, reading), Sdf.ValueTypeNames.Double, custom=True
                    )
                    path = track.servo_attrs[(joint, reading)] = attr.GetPath()
                readings.append((path, float(value)))
        return readings

    def _add_device(self, device_id: str) -> _DeviceTrack:
        name = sanitise_prim_name(device_id)
        unique, n = name, 1
        while unique in self._prim_names:  # "arm-1" and "arm_1" must not share a prim
            n += 1
            unique = f"{name}_{n}"
        self._prim_names.add(unique)
        prim = UsdGeom.Xform.Define(self._stage, f"/World/{unique}").GetPrim()
        prim.GetReferences().AddReference(self._asset_ref)
        prim.SetCustomDataByKey("twin:deviceId", device_id)
        track = _DeviceTrack(prim_path=str(prim.GetPath()), translate_attrs={}, orient_attrs={})
        for link in self._links:
            body = self._stage.GetPrimAtPath(prim.GetPath().AppendPath(Sdf.Path(link.rel_path)))
            if not body:
                raise RuntimeError(f"body prim {link.rel_path} missing after referencing {self._asset_ref}")
            xformable = UsdGeom.Xformable(body)
            translate = xformable.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble, _OP_SUFFIX)
            orient = xformable.AddOrientOp(UsdGeom.XformOp.PrecisionDouble, _OP_SUFFIX)
            # Replaces the asset's static ops on this body: the samples carry its whole local transform.
            xformable.SetXformOpOrder([translate, orient])
            track.translate_attrs[link.name] = translate.GetAttr().GetPath()
            track.orient_attrs[link.name] = orient.GetAttr().GetPath()
        self._devices[device_id] = track
        # DEBUG: the mirror logs a new device once; every rotation registers each arm again (a 200-arm soak
        # logged 200 lines a rotation at INFO).
        log.debug("session %s: device %r recorded at %s", self.path.name, device_id, track.prim_path)
        return track


def file_size(path: Path) -> int:
    """A session file's size in bytes; 0 when it cannot be read (gone, or its disk unreadable)."""
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _validate_poses(body_poses: BodyPoses) -> dict[str, _Pose]:
    """Each known body's (pos, unit quat wxyz) as floats. Plain floats and `math`, not numpy: numpy's call
    overhead on 3- and 4-vectors (np.linalg.norm is about 5 us) made this check a fifth of a sample's cost."""
    if not isinstance(body_poses, Mapping):
        raise TypeError(f"body poses must map body name to (pos, quat), got {type(body_poses).__name__}")
    poses: dict[str, _Pose] = {}
    for name in so101.BODY_NAMES:
        if name not in body_poses:
            continue
        try:
            pos_in, quat_in = body_poses[name]
            pos = _floats(pos_in, 3)
            quat = _floats(quat_in, 4)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"pose of {name!r} must be (pos (3,), quat wxyz (4,)): {exc}") from None
        norm = math.hypot(*quat)
        if not (all(map(math.isfinite, pos)) and math.isfinite(norm) and norm > 0.5):
            raise ValueError(f"pose of {name!r} is not finite or its quaternion is not unit: {pos}, {quat}")
        poses[name] = (pos, (quat[0] / norm, quat[1] / norm, quat[2] / norm, quat[3] / norm))
    if not poses:
        raise ValueError(
            f"no known body in poses {sorted(body_poses)}; pass DeviceTwin.body_poses() "
            f"(bodies named as so101.BODY_NAMES)"
        )
    return poses


def _relative_asset_path(asset: Path, session_dir: Path) -> str:
    try:
        rel = Path(os.path.relpath(asset, session_dir)).as_posix()
    except ValueError:  # another drive on Windows: only an absolute path can work
        return asset.as_posix()
    # "./" anchors the path to the session layer instead of the resolver's search path.
    return rel if rel.startswith("../") else f"./{rel}"


def _inspect_asset(asset: Usd.Stage, asset_path: Path) -> list[_BodyLink]:
    """Find every so101 body prim below the default prim and its static offset from its parent body."""
    root = asset.GetDefaultPrim()
    found: dict[str, Usd.Prim] = {}
    xformable = Tf.Type.Find(UsdGeom.Xformable)
    for prim in Usd.PrimRange(root):
        if prim.GetName() in so101.BODY_NAMES and prim.IsA(xformable):
            if prim.GetName() in found:
                raise ValueError(f"USD asset {asset_path} has two prims named {prim.GetName()!r}")
            found[prim.GetName()] = prim
    if root.GetName() in found and found[root.GetName()] == root:
        raise ValueError(
            f"USD asset {asset_path}: the default prim is body {root.GetName()!r}; the recorder needs "
            "the bodies below a root prim it can reference"
        )
    missing = [name for name in so101.BODY_NAMES if name not in found]
    if missing:
        raise ValueError(
            f"USD asset {asset_path} lacks Xformable body prims {missing}; regenerate it from an MJCF "
            "with the body names in so101.BODY_NAMES (`make usd-asset`)"
        )
    body_prims = set(found.values())
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    links = []
    for name in so101.BODY_NAMES:  # base to tip: parents come before children
        prim = found[name]
        parent_body = prim.GetParent()
        while parent_body and parent_body not in body_prims and parent_body != root:
            parent_body = parent_body.GetParent()
        if parent_body in body_prims:
            offset, _ = cache.ComputeRelativeTransform(prim.GetParent(), parent_body)
            parent_name: str | None = parent_body.GetName()
        else:
            offset = cache.GetLocalToWorldTransform(prim.GetParent())
            parent_name = None
        asset_local, _ = cache.GetLocalTransformation(prim)
        for what, matrix in (("its parent body", offset), ("itself", asset_local)):
            if not _is_rigid(matrix):
                raise ValueError(
                    f"USD asset {asset_path}: the transform between {name!r} and {what} has scale or shear; "
                    "the recorder can only re-pose bodies joined by rigid transforms"
                )
        links.append(
            _BodyLink(
                name=name,
                rel_path=str(prim.GetPath().MakeRelativePath(root.GetPath())),
                parent_body=parent_name,
                offset=_rigid(offset),
                asset_local=_rigid(asset_local),
            )
        )
    return links


def _is_rigid(matrix: Gf.Matrix4d) -> bool:
    m = np.array(matrix)
    rotation = m[:3, :3]
    # Row-vector matrices keep the projective column (last column) at (0, 0, 0, 1). A mirror (det -1) is
    # orthonormal too but has no quaternion.
    return bool(
        np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
        and np.allclose(m[:3, 3], 0)
        and np.linalg.det(rotation) > 0
    )


def _rigid(matrix: Gf.Matrix4d) -> _Rigid:
    """A rigid Gf row-vector matrix as (quat, pos): the same rotation, the quaternion sign Gf extracts."""
    q = matrix.ExtractRotationQuat().GetNormalized()
    imaginary = np.array(q.GetImaginary(), dtype=float).tolist()
    pos = np.array(matrix.ExtractTranslation(), dtype=float).tolist()
    return (float(q.GetReal()), *imaginary), tuple(pos)


# Float quaternion math for _author. Plain floats, not numpy: for 3- and 4-vectors numpy's per-call overhead
# is larger than the arithmetic (docs/performance.md, "USD recording, per sample").


def _qmul(a: _Vec, b: _Vec) -> _Vec:
    """Hamilton product a * b (rotate by b, then by a)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _rotate(q: _Vec, v: _Vec) -> _Vec:
    """v rotated by unit quaternion q: v + w t + u x t, with u = (x, y, z) and t = 2 u x v."""
    w, x, y, z = q
    vx, vy, vz = v
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (vx + w * tx + y * tz - z * ty, vy + w * ty + z * tx - x * tz, vz + w * tz + x * ty - y * tx)


def _compose(outer: _Rigid, inner: _Rigid) -> _Rigid:
    """The transform that applies inner, then outer (Gf row-vector: inner * outer)."""
    oq, op = outer
    iq, ip = inner
    p = _rotate(oq, ip)
    return _qmul(oq, iq), (p[0] + op[0], p[1] + op[1], p[2] + op[2])


def _relative(parent: _Rigid, world: _Rigid) -> _Rigid:
    """local such that _compose(parent, local) == world (Gf: world * parent.GetInverse())."""
    pq, pp = parent
    wq, wp = world
    inv = (pq[0], -pq[1], -pq[2], -pq[3])
    q = _qmul(inv, wq)
    norm = math.hypot(*q)  # unit up to rounding; Gf normalised its extracted quaternion too
    return (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm), _rotate(
        inv, (wp[0] - pp[0], wp[1] - pp[1], wp[2] - pp[2])
    )


def _gf_sign(q: _Vec) -> _Vec:
    """q or -q, whichever Gf.Matrix4d.ExtractRotationQuat returns for q's rotation, so a body's first sample
    has the sign the Gf code gave it: w positive when w^2 exceeds every x^2, y^2, z^2, else the largest of
    those (the later one on a tie; Gf compares the matrix diagonal, whose entry i is 2 (w^2 + x_i^2) - 1).
    On an exact tie Gf's choice is float rounding, so there the sign may differ; the rotation is the same."""
    w, x, y, z = q
    xx, yy, zz = x * x, y * y, z * z
    if xx > yy:
        big, lead = (xx, x) if xx > zz else (zz, z)
    else:
        big, lead = (yy, y) if yy > zz else (zz, z)
    if w * w > big:
        lead = w
    return q if lead >= 0.0 else (-w, -x, -y, -z)


def _continue_hemisphere(previous: _Vec | None, q: _Vec) -> _Vec:
    """q, or -q (the same rotation) when it is in the other hemisphere from the previous sample's, so orient
    interpolation between the two takes the short arc."""
    if previous is not None and (
        previous[0] * q[0] + previous[1] * q[1] + previous[2] * q[2] + previous[3] * q[3] < 0.0
    ):
        return (-q[0], -q[1], -q[2], -q[3])
    return q


def _floats(value: ArrayLike, size: int) -> _Vec:
    """`value` as `size` floats; ValueError or TypeError if it is not that many numbers."""
    if isinstance(value, np.ndarray) and value.dtype == np.float64 and value.shape == (size,):
        return tuple(value.tolist())  # FK's own arrays, every sample: no conversion through np.asarray
    return tuple(np.asarray(value, dtype=float).reshape(size).tolist())
