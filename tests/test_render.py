"""twin.output.render and `twin render`: offscreen PNGs that show the arm, in the pose asked for."""

from __future__ import annotations

import io
import itertools
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

# MuJoCo binds its GL backend at first import; headless here (the Makefile exports the same).
os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
import pytest
from PIL import Image
from twin.cli import main
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
from twin.output.render import (
    OFFSCREEN_SCENE_FLAGS,
    RenderError,
    framing_camera,
    offscreen_renderer,
    reach_poses,
    render_gif,
    render_png,
)
from twin.robot import so101
from twin.robot.calibration import load_calibration
from twin.robot.model import RobotModel, default_model_path

REST_DEG = (2.01, -98.89, 97.27, 63.70, -3.44, 0.0)
REST = {name: deg * so101.DEG for name, deg in zip(so101.JOINT_NAMES, REST_DEG, strict=True)}
W, H = 320, 240
# Rows under the overlay text band, for comparing renders whose labels differ.
BELOW_TEXT = slice(40, None)

DEGREES_PAYLOAD = {
    "device_id": "arm-001",
    "timestamp": 1706000000000,
    "joints": {
        "shoulder_pan": {"position": 2.01, "velocity": 0, "load": 12, "temp": 31, "current": 40},
        "shoulder_lift": {"position": -98.89, "velocity": 0, "load": 80, "temp": 33, "current": 90},
        "elbow_flex": {"position": 97.27, "velocity": 0, "load": 60, "temp": 32, "current": 70},
        "wrist_flex": {"position": 63.70, "velocity": 0, "load": 20, "temp": 31, "current": 30},
        "wrist_roll": {"position": -3.44, "velocity": 0, "load": 5, "temp": 30, "current": 10},
        "gripper": {"position": 4.83, "velocity": 0, "load": 3, "temp": 30, "current": 10},
    },
}
TICKS_PAYLOAD = {
    "device_id": "arm-002",
    "timestamp": 1706000000100,
    "joints": {
        name: {"position": pos, "velocity": 0, "load": 10, "temp": 30, "current": 80}
        for name, pos in zip(so101.JOINT_NAMES, (2048, 1800, 2200, 2100, 2048, 1500), strict=True)
    },
}


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


def pixels(path: Path) -> np.ndarray:
    with Image.open(path) as image:
        return np.asarray(image.convert("RGB"), dtype=np.int16)


def floor_only_scene(tmp_path: Path) -> Path:
    """The bundled scene with the arm swapped for an invisible stand-in chain: floor, sky and camera only."""
    chain = "".join(
        f'<body name="ghost{i}" pos="0 0 0.01"><joint name="{joint}" range="-3 3"/>'
        '<geom size="0.001" rgba="0 0 0 0" contype="0" conaffinity="0" mass="0.01"/>'
        for i, joint in enumerate(so101.JOINT_NAMES)
    ) + "</body>" * len(so101.JOINT_NAMES)
    (tmp_path / "ghost.xml").write_text(f"<mujoco><worldbody>{chain}</worldbody></mujoco>")
    scene = (
        default_model_path().read_text().replace('<include file="so101.xml"/>', '<include file="ghost.xml"/>')
    )
    assert 'include file="ghost.xml"' in scene
    path = tmp_path / "scene.xml"
    path.write_text(scene)
    return path


def test_png_has_the_size_asked_and_is_not_blank(robot: RobotModel, tmp_path: Path) -> None:
    out = render_png(robot, REST, tmp_path / "sub" / "rest.png", width=W, height=H)
    assert out == tmp_path / "sub" / "rest.png"
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with Image.open(out) as image:
        assert image.size == (W, H)
    img = pixels(out)
    assert img.std() > 10.0


# -- what offscreen pictures draw ----------------------------------------------------------------------------

SHADOW, REFLECTION = mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION


def test_offscreen_renderers_draw_the_shadow_but_no_reflection_and_keep_the_rest(robot: RobotModel) -> None:
    # On llvmpipe the floor's reflection costs about a fifth of a 640x480 frame with the shadow (about
    # 125 -> 102 ms CPU, docs/robot-model.md) for a faint mirror image, so it is off. The key light's shadow
    # costs more but stays: it shows how high the gripper is above the floor. Both are decisions: both pinned.
    assert dict(OFFSCREEN_SCENE_FLAGS) == {REFLECTION: False}
    defaults = mujoco.MjvScene().flags
    with offscreen_renderer(robot.model, W, H) as renderer:
        flags = renderer.scene.flags.copy()
    assert flags[SHADOW] and not flags[REFLECTION]
    # Everything else (the shadow, skybox, haze, face culling ...) stays as MuJoCo draws it.
    others = [i for i in range(len(defaults)) if i != REFLECTION]
    assert np.array_equal(flags[others], defaults[others])


def test_png_and_gif_are_rendered_with_the_offscreen_flags(
    robot: RobotModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    drawn: list[np.ndarray] = []
    render = mujoco.Renderer.render

    def spy(self: mujoco.Renderer, **kwargs: object) -> np.ndarray:
        drawn.append(self.scene.flags.copy())
        return render(self, **kwargs)

    monkeypatch.setattr(mujoco.Renderer, "render", spy)
    render_png(robot, REST, tmp_path / "rest.png", width=W, height=H)
    render_gif(robot, [{}, REST], tmp_path / "arm.gif", width=160, height=120)
    assert len(drawn) == 3
    assert all(flags[SHADOW] and not flags[REFLECTION] for flags in drawn)


def test_the_flags_take_effect(robot: RobotModel, tmp_path: Path) -> None:
    # The same view drawn with MuJoCo's defaults also has the arm's mirror image on the floor; drawn without
    # the shadow it loses the arm's shadow on the floor and on itself.
    camera = framing_camera(robot, [REST], aspect=W / H)
    picture = pixels(render_png(robot, REST, tmp_path / "rest.png", width=W, height=H, camera=camera))
    data = mujoco.MjData(robot.model)
    for name, value in REST.items():
        lo, hi = robot.joint_ranges[name]  # as render_png does: REST's elbow is just past its range
        data.qpos[robot.qpos_addr[name]] = min(max(value, lo), hi)
    mujoco.mj_forward(robot.model, data)
    with mujoco.Renderer(robot.model, height=H, width=W) as renderer:
        renderer.update_scene(data, camera=camera)
        full = renderer.render().astype(np.int16)
        for flag, enabled in OFFSCREEN_SCENE_FLAGS.items():
            renderer.scene.flags[flag] = enabled
        renderer.update_scene(data, camera=camera)
        lean = renderer.render().astype(np.int16)
        renderer.scene.flags[SHADOW] = False
        renderer.update_scene(data, camera=camera)
        shadowless = renderer.render().astype(np.int16)
    # Nothing but the flags differs from a plain renderer's picture; the mirror image they remove and the
    # shadow they keep are each a visible part of it (measured 2.3 % and 2.8 % of the pixels).
    assert np.array_equal(picture, lean)
    assert (np.abs(picture - full).sum(axis=2) > 60).mean() > 0.015
    assert (np.abs(picture - shadowless).sum(axis=2) > 60).mean() > 0.015


def arm_pixels(robot: RobotModel, pose: dict[str, float], camera, tmp_path: Path) -> np.ndarray:
    """Where the arm is in a render: the pixels that change when the arm is swapped for an invisible one."""
    arm = pixels(render_png(robot, pose, tmp_path / "arm.png", width=W, height=H, camera=camera))
    empty_scene = RobotModel.load(floor_only_scene(tmp_path))
    empty = pixels(render_png(empty_scene, {}, tmp_path / "empty.png", width=W, height=H, camera=camera))
    # Pictures draw the key light's shadow but no floor reflection (OFFSCREEN_SCENE_FLAGS): the arm and its
    # shadow change, no mirror image.
    return np.abs(arm - empty).sum(axis=2) > 60


def test_the_arm_is_visible_against_the_background(robot: RobotModel, tmp_path: Path) -> None:
    changed = arm_pixels(robot, {}, "overview", tmp_path)
    # The arm and its shadow cover a real part of the overview (measured 3.3 %), not a speck, in the frame.
    assert 0.02 < changed.mean() < 0.6
    rows, cols = np.nonzero(changed)
    assert rows.min() > 0 and cols.min() > 0 and rows.max() < H - 1 and cols.max() < W - 1


@pytest.mark.slow
@pytest.mark.parametrize("pose", [{}, REST], ids=["zero", "rest"])
def test_the_default_view_frames_the_arm_in_the_scene(
    robot: RobotModel, tmp_path: Path, pose: dict[str, float]
) -> None:
    camera = framing_camera(robot, [pose], aspect=W / H)
    changed = arm_pixels(robot, pose, camera, tmp_path)
    rows, cols = np.nonzero(changed)
    # Several times the overview's share (3.3 % there; measured 40 % and 32 % here), clear of every edge with
    # the shadow counted: the key light stands high on the camera's side of the arm, so the shadow falls
    # behind the arm, away from the bottom edge (lowest changed row measured 222 and 227 of 240).
    assert changed.mean() > 0.15
    assert rows.min() > 2 and cols.min() > 2 and rows.max() < H - 3 and cols.max() < W - 3
    # No camera given means exactly this framing.
    default = pixels(render_png(robot, pose, tmp_path / "default.png", width=W, height=H))
    assert np.array_equal(default, pixels(tmp_path / "arm.png"))


@pytest.mark.slow
def test_one_framing_for_several_poses_holds_them_all(tmp_path: Path) -> None:
    bare = RobotModel.load(default_model_path().with_name("so101.xml"))
    both = framing_camera(bare, [{}, RAISED], aspect=W / H)
    for name, pose in (("zero", {}), ("raised", RAISED)):
        img = pixels(render_png(bare, pose, tmp_path / f"{name}.png", width=W, height=H, camera=both))
        rows, cols = np.nonzero(img.sum(axis=2) > 30)
        assert rows.min() > 2 and cols.min() > 2 and rows.max() < H - 3 and cols.max() < W - 3, name
    with pytest.raises(RenderError, match="no poses"):
        framing_camera(bare, [])


@pytest.mark.slow
def test_different_poses_give_different_images(robot: RobotModel, tmp_path: Path) -> None:
    zero = pixels(render_png(robot, {}, tmp_path / "zero.png", width=W, height=H))
    rest = pixels(render_png(robot, REST, tmp_path / "rest.png", width=W, height=H))
    again = pixels(render_png(robot, {}, tmp_path / "zero2.png", width=W, height=H))
    assert (np.abs(zero - rest).sum(axis=2) > 60).mean() > 0.02
    assert np.array_equal(zero, again)  # deterministic: same pose, same pixels


RAISED = {"shoulder_pan": 1.5, "shoulder_lift": -0.3, "elbow_flex": -1.5, "gripper": 1.2}


@pytest.mark.parametrize("pose", [{}, REST, RAISED], ids=["zero", "rest", "raised"])
def test_the_default_view_fits_the_arm_into_the_image(tmp_path: Path, pose: dict[str, float]) -> None:
    bare = RobotModel.load(default_model_path().with_name("so101.xml"))  # no floor, no sky, no camera
    assert bare.camera_names == ()
    img = pixels(render_png(bare, pose, tmp_path / "bare.png", width=W, height=H))
    arm = img.sum(axis=2) > 30  # the background of a model without a skybox is black
    rows, cols = np.nonzero(arm)
    top, bottom, left, right = rows.min(), H - 1 - rows.max(), cols.min(), W - 1 - cols.max()
    # Whole, with a margin on every side ...
    assert min(top, bottom, left, right) > 2
    # ... as large as the image allows: the long side fills ~90 % (8 % margin), centred within a few pixels.
    width, height = (cols.max() - cols.min()) / W, (rows.max() - rows.min()) / H
    assert max(width, height) > 0.85, (width, height)
    if width > height:
        assert abs(left - right) <= 4
    else:
        assert abs(top - bottom) <= 4


@pytest.mark.slow
def test_the_reach_framing_holds_every_reach_pose_in_a_wide_window(tmp_path: Path) -> None:
    # `twin view` starts from this camera: stretched over the pan range, upright or folded, the arm shows.
    bare = RobotModel.load(default_model_path().with_name("so101.xml"))
    poses = reach_poses(bare)
    assert len(poses) == 5
    camera = framing_camera(bare, poses, aspect=16 / 9)
    for i, pose in enumerate(poses):
        img = pixels(render_png(bare, pose, tmp_path / f"{i}.png", width=320, height=180, camera=camera))
        rows, cols = np.nonzero(img.sum(axis=2) > 30)
        assert rows.min() > 1 and cols.min() > 1 and rows.max() < 178 and cols.max() < 318, pose


@pytest.mark.slow
def test_gif_holds_every_frame_with_the_arm_in_view(tmp_path: Path) -> None:
    bare = RobotModel.load(default_model_path().with_name("so101.xml"))
    poses = [{}, REST, RAISED, {"shoulder_pan": -1.5, "wrist_roll": 2.0}]
    out = render_gif(bare, poses, tmp_path / "anim" / "arm.gif", width=160, height=120)
    with Image.open(out) as gif:
        assert gif.size == (160, 120)
        assert gif.n_frames == len(poses)
        frames = []
        for i in range(gif.n_frames):
            gif.seek(i)
            frames.append(np.asarray(gif.convert("RGB"), dtype=np.int16))
    for i, frame in enumerate(frames):
        rows, cols = np.nonzero(frame.sum(axis=2) > 30)
        assert rows.min() > 1 and cols.min() > 1 and rows.max() < 118 and cols.max() < 158, i
    assert all((np.abs(a - b).sum(axis=2) > 60).mean() > 0.01 for a, b in itertools.pairwise(frames))
    with pytest.raises(RenderError, match="no frames"):
        render_gif(bare, [], tmp_path / "none.gif")


@pytest.mark.slow
def test_text_overlay_is_drawn(robot: RobotModel, tmp_path: Path) -> None:
    plain = pixels(render_png(robot, {}, tmp_path / "plain.png", width=W, height=H))
    text = pixels(render_png(robot, {}, tmp_path / "text.png", width=W, height=H, text="arm-001"))
    diff = np.abs(plain - text).sum(axis=2) > 0
    assert diff[:40, :150].mean() > 0.05
    assert not diff[BELOW_TEXT].any()


def test_larger_than_the_model_buffer_and_named_cameras(robot: RobotModel, tmp_path: Path) -> None:
    wide = robot.model.vis.global_.offwidth + 64
    with Image.open(render_png(robot, {}, tmp_path / "wide.png", width=wide, height=60)) as image:
        assert image.size == (wide, 60)
    with pytest.raises(RenderError, match=r"camera 'nope' .*cameras: overview"):
        render_png(robot, {}, tmp_path / "x.png", camera="nope")
    with pytest.raises(RenderError, match="not positive"):
        render_png(robot, {}, tmp_path / "x.png", width=0)


# -- the command ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_cli_pose(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "pose.png"
    pose = {"shoulder_lift": -1.2, "elbow_flex": 1.1}
    rc = main(
        ["render", "--pose", json.dumps(pose), "--out", str(out), "--width", str(W), "--height", str(H)]
    )
    assert rc == 0
    assert capsys.readouterr().out.strip() == str(out)
    robot = RobotModel.load()
    expected = pixels(render_png(robot, pose, tmp_path / "lib.png", width=W, height=H))
    assert np.array_equal(pixels(out)[BELOW_TEXT], expected[BELOW_TEXT])


@pytest.mark.slow
def test_cli_payload_renders_the_decoded_pose(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    payload = tmp_path / "message.json"
    payload.write_text(json.dumps(DEGREES_PAYLOAD))
    out = tmp_path / "payload.png"
    rc = main(
        [
            "render",
            "--payload",
            str(payload),
            "--units",
            "degrees",
            "--out",
            str(out),
            "--width",
            str(W),
            "--height",
            str(H),
        ]
    )
    assert rc == 0, capsys.readouterr().err
    decoded = TelemetryDecoder(DecoderConfig(units=Units.DEGREES)).decode(payload.read_bytes())
    expected = pixels(
        render_png(RobotModel.load(), decoded.angles_rad, tmp_path / "lib.png", width=W, height=H)
    )
    assert np.array_equal(pixels(out)[BELOW_TEXT], expected[BELOW_TEXT])
    # auto decides from this one message (fractional, negative positions: degrees): the same image.
    auto = tmp_path / "auto.png"
    assert (
        main(["render", "--payload", str(payload), "--out", str(auto), "--width", str(W), "--height", str(H)])
        == 0
    )
    assert np.array_equal(pixels(auto)[BELOW_TEXT], expected[BELOW_TEXT])


def test_cli_payload_from_stdin_in_ticks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    stdin = io.TextIOWrapper(io.BytesIO(json.dumps(TICKS_PAYLOAD).encode()))
    monkeypatch.setattr(sys, "stdin", stdin)
    out = tmp_path / "ticks.png"
    rc = main(
        [
            "render",
            "--payload",
            "-",
            "--units",
            "ticks",
            "--out",
            str(out),
            "--width",
            str(W),
            "--height",
            str(H),
        ]
    )
    assert rc == 0, capsys.readouterr().err
    with Image.open(out) as image:
        assert image.size == (W, H)


@pytest.mark.parametrize(
    ("payload", "units", "reason"),
    [
        (b"{not json", "degrees", "not_json"),
        (json.dumps(DEGREES_PAYLOAD).encode(), "ticks", "wrong_type"),
        (json.dumps({**DEGREES_PAYLOAD, "joints": {}}).encode(), "degrees", "missing_joint"),
    ],
)
def test_cli_rejected_payload_exits_2_with_the_reason(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], payload: bytes, units: str, reason: str
) -> None:
    path = tmp_path / "bad.json"
    path.write_bytes(payload)
    out = tmp_path / "bad.png"
    assert main(["render", "--payload", str(path), "--units", units, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"payload rejected ({reason})" in err
    assert not out.exists()


@pytest.mark.parametrize(
    ("pose", "message"),
    [
        ('{"elbow": 1}', "unknown joints elbow"),
        ("[1, 2]", "JSON object"),
        ('{"elbow_flex": "1"}', "not a finite number"),
        ("{oops", "not valid JSON"),
    ],
)
def test_cli_bad_pose_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], pose: str, message: str
) -> None:
    assert main(["render", "--pose", pose, "--out", str(tmp_path / "x.png")]) == 2
    assert message in capsys.readouterr().err


def test_cli_missing_model_exits_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["render", "--model", str(tmp_path / "none.xml"), "--out", str(tmp_path / "x.png")]) == 1
    assert "[twin] model" in capsys.readouterr().err


@pytest.mark.slow
def test_console_script_end_to_end(tmp_path: Path) -> None:
    twin_bin = shutil.which("twin", path=str(Path(sys.executable).parent))
    assert twin_bin, "the `twin` console script is not installed in this venv"
    out = tmp_path / "cli.png"
    result = subprocess.run(
        [
            twin_bin,
            "render",
            "--pose",
            '{"shoulder_pan": 0.5}',
            "--out",
            str(out),
            "--width",
            "200",
            "--height",
            "150",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "MUJOCO_GL": "egl"},
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == str(out)
    with Image.open(out) as image:
        assert image.size == (200, 150)


@pytest.mark.slow
def test_cli_payload_with_a_calibration_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Off-centre calibrated ranges move the mid point: the decoded pose differs from the uncalibrated one.
    calibration = tmp_path / "follower.json"
    calibration.write_text(
        json.dumps(
            {
                name: {"id": i + 1, "drive_mode": 0, "homing_offset": 0, "range_min": 900, "range_max": 2900}
                for i, name in enumerate(so101.JOINT_NAMES)
            }
        )
    )
    payload = tmp_path / "ticks.json"
    payload.write_text(json.dumps(TICKS_PAYLOAD))
    out = tmp_path / "calibrated.png"
    args = ["render", "--payload", str(payload), "--units", "ticks", "--width", str(W), "--height", str(H)]
    assert main([*args, "--calibration", str(calibration), "--out", str(out)]) == 0, capsys.readouterr().err
    config = DecoderConfig(units=Units.TICKS, calibration=load_calibration(calibration))
    decoded = TelemetryDecoder(config).decode(payload.read_bytes())
    expected = pixels(
        render_png(RobotModel.load(), decoded.angles_rad, tmp_path / "lib.png", width=W, height=H)
    )
    assert np.array_equal(pixels(out)[BELOW_TEXT], expected[BELOW_TEXT])
    plain = tmp_path / "uncalibrated.png"
    assert main([*args, "--out", str(plain)]) == 0
    assert not np.array_equal(pixels(plain)[BELOW_TEXT], expected[BELOW_TEXT])

    broken = tmp_path / "broken.json"
    broken.write_text("{")
    assert main([*args, "--calibration", str(broken), "--out", str(tmp_path / "x.png")]) == 2
    assert "not valid JSON" in capsys.readouterr().err
