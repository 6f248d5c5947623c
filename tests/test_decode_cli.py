"""`twin decode`: the offline decoder, through the CLI entry point and the installed console script."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from twin.cli import main
from twin.robot import so101

EXAMPLE_CALIBRATION = (
    Path(__file__).resolve().parents[1] / "robots" / "so101" / "calibration" / "so101_follower_example.json"
)


def write_message(tmp_path: Path, positions: tuple[Any, ...], **per_joint: Any) -> Path:
    msg = {
        "device_id": "arm-007",
        "timestamp": 1706000000123,
        "joints": {
            n: {"position": p, **per_joint} for n, p in zip(so101.JOINT_NAMES, positions, strict=True)
        },
    }
    path = tmp_path / "payload.json"
    path.write_text(json.dumps(msg))
    return path


def run_decode(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, Any, str]:
    code = main(["decode", *argv])
    out, err = capsys.readouterr()
    return code, (json.loads(out) if out.strip() else None), err


def test_ticks_payload_auto_decides_from_one_message(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write_message(
        tmp_path, (2048, 1800, 2200, 2100, 2048, 1500), velocity=32778, load=1524, current=100
    )
    code, out, err = run_decode(capsys, str(path))
    assert (code, err) == (0, "")
    assert (out["device"], out["timestamp"], out["units"]) == ("arm-007", 1706000000123, "ticks")
    assert list(out["angles_rad"]) == list(so101.JOINT_NAMES)
    assert out["angles_rad"]["shoulder_lift"] == pytest.approx(
        -0.3789857804330544
    )  # (1800 - 2047) * 2pi/4095
    assert out["gripper_percent"] == pytest.approx(6.283716803026438)
    assert out["diagnostics"]["elbow_flex"] == {
        "velocity_steps_s": -10.0,  # 32778: bit 15 set, magnitude 10
        "velocity_rad_s": pytest.approx(-0.015339807878856412),
        "load_percent": -50.0,  # 1524: bit 10 set, magnitude 500 x 0.1 %
        "current_a": 0.65,  # 100 x 6.5 mA
    }


def test_calibration_file_changes_tick_angles(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_message(tmp_path, (2048, 1800, 2200, 2100, 2048, 1500))
    code, out, _ = run_decode(
        capsys, "--units", "ticks", "--calibration", str(EXAMPLE_CALIBRATION), str(path)
    )
    assert code == 0
    assert out["angles_rad"]["shoulder_pan"] == pytest.approx(
        0.018412264636423696
    )  # (2048 - 2036) * 2pi/4095
    assert out["gripper_percent"] == 0.0  # 1500 < range_min 2024: clamped closed


def test_degrees_payload_from_stdin(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    msg = {
        "device_id": "arm-001",
        "timestamp": 1706000000000,
        "joints": {
            n: {"position": p}
            for n, p in zip(so101.JOINT_NAMES, (2.01, -98.89, 97.27, 63.70, -3.44, 4.83), strict=True)
        },
    }
    stdin = io.TextIOWrapper(io.BytesIO(json.dumps(msg).encode()))
    monkeypatch.setattr(sys, "stdin", stdin)
    code, out, _ = run_decode(capsys, "-")
    assert code == 0
    assert out["units"] == "degrees"
    assert out["angles_rad"]["elbow_flex"] == pytest.approx(1.6976817634148842)  # 97.27 * pi / 180
    assert out["gripper_percent"] == pytest.approx(4.83)


def test_ambiguous_payload_needs_units(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_message(tmp_path, (0, 0, 0, 0, 0, 0))
    code, out, err = run_decode(capsys, str(path))
    assert (code, out) == (2, None)
    assert err.startswith("rejected: units_undecided:")
    assert "--units" in err
    code, out, _ = run_decode(capsys, "--units", "degrees", str(path))
    assert code == 0
    assert out["angles_rad"]["shoulder_pan"] == 0.0


def test_rejected_payload_exits_2_with_reason(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_message(tmp_path, (2.01, -98.89, 97.27, 63.70, -3.44, 4.83))
    code, out, err = run_decode(capsys, "--units", "ticks", str(path))
    assert (code, out) == (2, None)
    assert "rejected: wrong_type: position 2.01 of shoulder_pan is not a whole tick count" in err
    assert "set units=degrees" in err
    assert err.rstrip().endswith("(here: --units degrees)"), err  # this command's flag, not a setting


def test_unreadable_inputs_exit_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_decode(capsys, str(tmp_path / "missing.json"))
    assert code == 1 and "cannot read" in err
    bad_cal = tmp_path / "cal.json"
    bad_cal.write_text("{}")
    path = write_message(tmp_path, (2048, 1800, 2200, 2100, 2048, 1500))
    code, _, err = run_decode(capsys, "--calibration", str(bad_cal), str(path))
    assert code == 1 and "missing shoulder_pan" in err


def test_console_script_end_to_end(tmp_path: Path) -> None:
    twin = Path(sys.executable).with_name("twin")
    path = write_message(tmp_path, (2048, 1800, 2200, 2100, 2048, 1500))
    done = subprocess.run(
        [str(twin), "decode", str(path)], capture_output=True, text=True, timeout=60, check=False
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["units"] == "ticks"
    path.write_bytes(b"\xff\xfe not json")
    done = subprocess.run(
        [str(twin), "decode", str(path)], capture_output=True, text=True, timeout=60, check=False
    )
    assert done.returncode == 2
    assert done.stderr.startswith("rejected: not_utf8:")
