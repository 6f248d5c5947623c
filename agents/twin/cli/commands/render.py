"""`twin render`: write a PNG of the arm in a pose given as joint angles or as an edge telemetry payload.

Exit codes:
  0  PNG written (its path is printed)
  1  the model cannot be loaded or the image cannot be rendered
  2  bad input: command line, --pose JSON, calibration file, or a payload the decoder rejects
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

from twin.cli.output import Console

console = Console("render")


EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2

EPILOG = """examples:
  twin render --pose '{"shoulder_lift": -1.2, "elbow_flex": 1.1}' --out pose.png
  twin render --payload examples/payload-degrees.json --units degrees --out arm.png
  twin render --payload - --units ticks --out arm.png < examples/payload-ticks.json

exit codes: 0 written; 1 model or rendering failed; 2 bad pose, payload, units or calibration"""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "render",
        help="render the arm in a pose to a PNG (offscreen)",
        description=(
            "Render the SO-101 twin offscreen to a PNG, posed by --pose (joint angles in radians) or by an "
            "edge telemetry message (--payload). Without either, the zero pose."
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    source = parser.add_mutually_exclusive_group()
    source.add_argument(
        "--pose",
        metavar="JSON",
        help="joint angles in radians by joint name, e.g. '{\"elbow_flex\": 1.2}'; missing joints are 0",
    )
    source.add_argument(
        "--payload", metavar="FILE", help="an edge telemetry message (JSON) to decode; '-' reads stdin"
    )
    parser.add_argument(
        "--units",
        choices=("ticks", "degrees", "range100", "auto"),
        default="auto",
        help="units of the payload's positions (default auto: decided from this one message, if it can be)",
    )
    parser.add_argument("--calibration", metavar="FILE", help="LeRobot calibration JSON for the payload")
    parser.add_argument("--model", metavar="MJCF", help="robot model (default: the bundled SO-101 scene)")
    parser.add_argument("--out", metavar="PNG", default="twin-render.png", help="output file (%(default)s)")
    parser.add_argument("--width", type=int, default=640, help="image width in pixels (%(default)s)")
    parser.add_argument("--height", type=int, default=480, help="image height in pixels (%(default)s)")
    parser.add_argument(
        "--camera", default=None, help="model camera name, e.g. overview (default: a view framing the arm)"
    )
    parser.set_defaults(func=run)


def _pose_from_json(text: str, joint_names: tuple[str, ...]) -> dict[str, float]:
    """Parse --pose; raises ValueError naming the bad key or value."""
    try:
        doc: Any = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(
            f"--pose is not valid JSON ({exc}); pass an object like '{{\"elbow_flex\": 1.2}}'"
        ) from None
    if not isinstance(doc, dict):
        raise ValueError(f"--pose must be a JSON object of joint angles by name, got {type(doc).__name__}")
    unknown = sorted(set(doc) - set(joint_names))
    if unknown:
        raise ValueError(
            f"--pose has unknown joints {', '.join(unknown)}; joints are {', '.join(joint_names)}"
        )
    pose: dict[str, float] = {}
    for name, value in doc.items():
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise ValueError(f"--pose joint {name}: {value!r} is not a finite number of radians")
        pose[name] = float(value)
    return pose


def _pose_from_payload(args: argparse.Namespace) -> tuple[dict[str, float], str]:
    """Decode --payload; raises ValueError (bad file/calibration) or TelemetryRejected."""
    from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
    from twin.robot.calibration import load_calibration

    if args.payload == "-":
        payload: bytes = sys.stdin.buffer.read()
    else:
        try:
            payload = Path(args.payload).read_bytes()
        except OSError as exc:
            raise ValueError(f"cannot read --payload {args.payload}: {exc.strerror or exc}") from None
    calibration = load_calibration(args.calibration) if args.calibration else None
    # One message is all the evidence there is, so auto must decide from it (or reject it as undecidable).
    config = DecoderConfig(units=Units(args.units), calibration=calibration, auto_evidence_messages=1)
    telemetry = TelemetryDecoder(config).decode(payload)
    label = f"{telemetry.device_id}  t={telemetry.timestamp_ms} ms  units={telemetry.units}"
    return dict(telemetry.angles_rad), label


def run(args: argparse.Namespace) -> int:
    # MuJoCo binds its GL backend at first import; headless is the common case for this command.
    os.environ.setdefault("MUJOCO_GL", "egl")
    from twin.core.telemetry import TelemetryRejected
    from twin.output.render import RenderError, render_png
    from twin.robot.model import ModelError, RobotModel

    if args.width <= 0 or args.height <= 0:
        console.err(f"--width/--height must be positive, got {args.width}x{args.height}")
        return EXIT_BAD_INPUT
    try:
        robot = RobotModel.load(args.model)
    except ModelError as exc:
        console.err(str(exc))
        return EXIT_FAILED

    try:
        if args.payload is not None:
            angles, label = _pose_from_payload(args)
        elif args.pose is not None:
            angles, label = _pose_from_json(args.pose, robot.joint_names), "pose"
        else:
            angles, label = {}, "zero pose"
    except TelemetryRejected as exc:
        console.err(f"payload rejected ({exc.reason}): {exc}")
        return EXIT_BAD_INPUT
    except ValueError as exc:
        console.err(str(exc))
        return EXIT_BAD_INPUT

    try:
        out = render_png(
            robot, angles, args.out, width=args.width, height=args.height, camera=args.camera, text=label
        )
    except RenderError as exc:
        console.err(str(exc))
        return EXIT_FAILED
    console.out(str(out))
    return EXIT_OK
