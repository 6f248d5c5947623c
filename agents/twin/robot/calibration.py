"""LeRobot motor calibration files: load and validate them for the telemetry decoder.

LeRobot writes one JSON object per arm, keyed by motor name, each entry holding the integer fields
`id, drive_mode, homing_offset, range_min, range_max` (huggingface/lerobot
src/lerobot/motors/motors_bus.py, MotorCalibration). For a follower it lives under
`~/.cache/huggingface/lerobot/calibration/robots/so_follower/<id>.json` (`so101_follower/` before
LeRobot 0.4.3).

The homing offset is applied inside the servo (Present_Position already has it subtracted), so the decoder
never uses it; it is loaded only so a file round-trips and a bad value is caught.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

from twin.robot import so101

_FIELDS = ("id", "drive_mode", "homing_offset", "range_min", "range_max")
# Homing_Offset is sign-magnitude with the sign in bit 11, so its magnitude is at most 2047.
_HOMING_LIMIT = 2047
# A file of six motors is about 1 KB; anything far larger is not a calibration (and is not read whole).
MAX_FILE_BYTES = 64 * 1024
# Where LeRobot keeps a leader arm's calibration (calibration/teleoperators/so_leader/<id>.json, beside the
# follower's robots/so_follower/): the same six motor names, so only its place tells it apart.
LEADER_DIRECTORIES = frozenset({"teleoperators", "so_leader", "so100_leader", "so101_leader"})
# LeRobot keeps each robot type's under calibration/robots/<type>/; another follower (koch_follower) names its
# motors as the SO-101's, ids 1 to 6, so its file parses too and would decode the arm at its angles.
SO_FOLLOWER_DIRECTORY = re.compile(r"(bi_)?so(\d+)?_follower")
FOLLOWER_FILE = "~/.cache/huggingface/lerobot/calibration/robots/so_follower/<id>.json"


@dataclass(frozen=True, slots=True)
class MotorCalibration:
    """One motor's entry of a LeRobot calibration file."""

    id: int
    drive_mode: int
    homing_offset: int
    range_min: int
    range_max: int

    @property
    def mid(self) -> float:
        """Middle of the calibrated range: LeRobot's DEGREES zero."""
        return (self.range_min + self.range_max) / 2


# eq=False: Mapping already compares by content.
@dataclass(frozen=True, eq=False)
class Calibration(Mapping[str, MotorCalibration]):
    """A validated calibration for the six SO-101 motors, keyed by joint name (so101.JOINT_NAMES)."""

    motors: Mapping[str, MotorCalibration]
    source: str = "<memory>"

    def __post_init__(self) -> None:
        validated = _validate_motors(self.motors, self.source)
        object.__setattr__(self, "motors", MappingProxyType(validated))

    def __getitem__(self, name: str) -> MotorCalibration:
        return self.motors[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self.motors)

    def __len__(self) -> int:
        return len(self.motors)

    @classmethod
    def from_dict(cls, data: object, source: str = "<memory>") -> Calibration:
        """Build from the parsed JSON of a LeRobot calibration file (ValueError on any problem)."""
        if not isinstance(data, dict):
            raise ValueError(
                f"{source}: a LeRobot calibration file is a JSON object keyed by motor name, "
                f"got {type(data).__name__}"
            )
        if _OLD_LAYOUT.intersection(data) and not isinstance(next(iter(data.values()), None), dict):
            keys = ", ".join(sorted(_OLD_LAYOUT))
            raise ValueError(
                f"{source} is in LeRobot's old calibration layout (lists under {keys}), from before LeRobot "
                "keyed its files by motor name: calibrate the arm again with a current LeRobot "
                "(lerobot-calibrate), which writes robots/so_follower/<id>.json"
            )
        # A key that names no motor (a note, a tool's metadata), or six motors: the names are checked first,
        # and that key is named as unknown. Checked entry by entry, it read as "motor 'meta' lacks id", which
        # sent the user to calibrate again.
        if not set(data).issubset(so101.JOINT_NAMES) or set(so101.JOINT_NAMES).issubset(data):
            _check_motor_names(set(data), source)
        motors: dict[str, MotorCalibration] = {}
        for name, entry in data.items():
            if not isinstance(entry, dict):
                raise ValueError(
                    f"{source}: entry {name!r} must be an object with fields {', '.join(_FIELDS)}"
                )
            missing = [f for f in _FIELDS if f not in entry]
            if missing:
                raise ValueError(
                    f"{source}: motor {name!r} lacks {', '.join(missing)}; re-run LeRobot's calibration "
                    "(lerobot-calibrate) to write a complete file"
                )
            values: dict[str, int] = {}
            for field in _FIELDS:
                value = entry[field]
                # bool is an int subclass in Python; a true/false here is a broken file, not a 1/0.
                if type(value) is not int:
                    raise ValueError(
                        f"{source}: motor {name!r} field {field} must be a JSON integer, got {value!r}"
                    )
                values[field] = value
            motors[name] = MotorCalibration(**values)
        return cls(motors, source)

    def to_dict(self) -> dict[str, dict[str, int]]:
        """The LeRobot file layout (for writing an example or a test fixture)."""
        return {name: {f: getattr(m, f) for f in _FIELDS} for name, m in self.motors.items()}


# The keys of LeRobot's calibration files before they were keyed by motor name: one list per field.
_OLD_LAYOUT = frozenset({"homing_offset", "drive_mode", "start_pos", "end_pos", "calib_mode", "motor_names"})


def _check_motor_names(names: set[str], source: str) -> None:
    """ValueError unless `names` are exactly the SO-101 follower's motors."""
    missing = [n for n in so101.JOINT_NAMES if n not in names]
    extra = sorted(names.difference(so101.JOINT_NAMES))
    if missing or extra:
        parts = []
        if missing:
            parts.append(f"missing {', '.join(missing)}")
        if extra:
            parts.append(f"unknown {', '.join(extra)}")
        raise ValueError(
            f"{source}: not an SO-101 follower calibration ({'; '.join(parts)}); expected exactly the motors "
            f"{', '.join(so101.JOINT_NAMES)} (LeRobot robots/so_follower/<id>.json)"
        )


def _validate_motors(motors: Mapping[str, MotorCalibration], source: str) -> dict[str, MotorCalibration]:
    _check_motor_names(set(motors), source)
    ordered: dict[str, MotorCalibration] = {}
    for name in so101.JOINT_NAMES:
        m = motors[name]
        if not isinstance(m, MotorCalibration):
            raise ValueError(f"{source}: motor {name!r} must be a MotorCalibration, got {type(m).__name__}")
        if m.id != so101.MOTOR_IDS[name]:
            # LeRobot's SO-101 follower sets its motors to these ids; the alarms name a servo by it.
            raise ValueError(
                f"{source}: motor {name!r} has id {m.id}, where an SO-101 follower's {name} is motor "
                f"{so101.MOTOR_IDS[name]} (LeRobot's so101_follower, set by lerobot-setup-motors); is it "
                "this arm's file, and unedited?"
            )
        if m.drive_mode not in (0, 1):
            raise ValueError(f"{source}: motor {name!r} drive_mode must be 0 or 1, got {m.drive_mode}")
        if not 0 <= m.range_min < m.range_max <= so101.TICK_MAX:
            raise ValueError(
                f"{source}: motor {name!r} needs 0 <= range_min < range_max <= {so101.TICK_MAX}, got "
                f"range_min={m.range_min} range_max={m.range_max}; re-run the calibration and move the joint "
                "through its whole range when asked"
            )
        if abs(m.homing_offset) > _HOMING_LIMIT:
            raise ValueError(
                f"{source}: motor {name!r} homing_offset {m.homing_offset} is outside the servo's "
                f"+-{_HOMING_LIMIT} (LeRobot writes it to the servo, which holds no more); re-run the "
                "calibration with the joint at the middle of its range when asked, or restore the file "
                "LeRobot wrote if this one was edited"
            )
        ordered[name] = m
    return ordered


def leader_problem(path: str | Path) -> str | None:
    """What is wrong when `path` is where LeRobot keeps a leader arm's calibration, or another robot type's
    than an SO follower, to follow the path in a message (the caller adds what to do with the follower's
    file); None when it is not there."""
    parts = Path(path).expanduser().parts
    leader = LEADER_DIRECTORIES.intersection(parts)
    if not leader:
        # LeRobot's layout only (robots/<type>/<id>.json): a folder of the user's own ("left_follower") is
        # theirs to name.
        folder = parts[-2] if len(parts) >= 3 and parts[-3] == "robots" else ""
        if folder.endswith("_follower") and not SO_FOLLOWER_DIRECTORY.fullmatch(folder.lower()):
            return (
                f"is a {folder} robot's calibration (LeRobot keeps each robot type's under its own folder): "
                f"this twin is of an SO-101 follower arm, whose file is {FOLLOWER_FILE}"
            )
        return None
    # A leader's file parses like the follower's, and would decode the follower at wrong angles.
    return (
        f"is a leader arm's calibration (LeRobot keeps those under {sorted(leader)[0]}/): the edge reads the "
        f"follower arm, whose file is {FOLLOWER_FILE}"
    )


def load_calibration(path: str | Path) -> Calibration:
    """Read a LeRobot follower arm's calibration JSON file; ValueError names the problem and the fix."""
    p = Path(path).expanduser()
    problem = leader_problem(p)
    if problem:
        raise ValueError(f"calibration file {p} {problem}; use that one")
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise ValueError(
            f"calibration file {p} does not exist; LeRobot keeps follower calibrations under "
            "~/.cache/huggingface/lerobot/calibration/robots/so_follower/<id>.json"
        ) from None
    except OSError as exc:
        raise ValueError(f"calibration file {p} cannot be read: {exc}") from None
    return parse_calibration(data, f"calibration file {p}")


def parse_calibration(data: bytes | str, source: str) -> Calibration:
    """A LeRobot calibration from the bytes of its file (from disk, S3 or an upload); `source` names where it
    came from in every error. ValueError names the problem and the fix."""
    if len(data) > MAX_FILE_BYTES:
        raise ValueError(
            f"{source} is {len(data)} bytes; a LeRobot calibration of six motors is about 1 KB (at most "
            f"{MAX_FILE_BYTES}): is it the right file?"
        )
    if isinstance(data, bytes) and data[:2] in (b"\xff\xfe", b"\xfe\xff"):
        # What Windows PowerShell 5's `>` and Out-File write; Python's decode error would name no fix.
        raise ValueError(
            f"{source} is UTF-16 text (as Windows PowerShell's > and Out-File write it), not UTF-8: save it "
            "as UTF-8 (Out-File -Encoding utf8, or copy the file itself rather than its printed text)"
        )
    try:
        # utf-8-sig: a file saved on Windows may start with a byte order mark, which says only "UTF-8".
        text = data if isinstance(data, str) else data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{source} is not UTF-8 text: {exc}") from None
    try:
        parsed = json.loads(text)
    except ValueError as exc:
        raise ValueError(f"{source} is not valid JSON: {exc}") from None
    except RecursionError:
        # A few KB of nested brackets: uncaught, it stopped `twin run` from starting and each push and poll.
        raise ValueError(
            f"{source} nests its JSON too deeply to be a LeRobot calibration (one object of six motors): "
            "is it the right file?"
        ) from None
    return Calibration.from_dict(parsed, source)


def example_path() -> Path:
    """The example follower calibration shipped with the model (robots/so101/calibration): plausible values
    for trying the twin with the edge simulator, measured on no arm."""
    import twin_robots  # noqa: PLC0415 - only this check needs the asset package

    folder = Path(twin_robots.__file__).resolve().parent / "so101" / "calibration"
    return folder / "so101_follower_example.json"


def is_example(calibration: Calibration) -> bool:
    """Whether `calibration` holds the example's values (however the file is laid out): a real arm given it
    would be shown off by the difference between the example's ranges and its own."""
    try:
        example = load_calibration(example_path())
    except (OSError, ValueError):
        return False
    return dict(example) == dict(calibration)
