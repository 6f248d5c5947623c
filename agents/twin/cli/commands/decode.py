"""`twin decode`: decode one telemetry payload offline and print what the twin would see.

Useful to check an edge's units and a calibration file before pointing the agent at the fleet. With
`--units auto` (the default) a single payload must decide on its own (auto evidence of 1 message): an
ambiguous payload (whole, non-negative, small positions) exits 2 with units_undecided; pass --units then.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from twin.cli.output import Console

EXIT_REJECTED = 2
console = Console("decode")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "decode",
        help="decode one telemetry payload (file or stdin) and print joint angles as JSON",
        description=(
            "Validate and decode one edge telemetry message exactly as the agent does, and print the device, "
            "timestamp, resolved units, joint angles in radians, gripper percent and decoded diagnostics as "
            "JSON. A rejected payload exits 2 with the reason on stderr. With --units auto a single payload "
            "must decide the units by itself; an ambiguous one (e.g. all positions 0) needs --units."
        ),
    )
    parser.add_argument("payload", metavar="PAYLOAD.json|-", help="file holding one message, or - for stdin")
    parser.add_argument(
        "--units",
        choices=["ticks", "degrees", "range100", "auto"],
        default="auto",
        help="units of `position` (default auto: decided from this one payload when it can be)",
    )
    parser.add_argument(
        "--calibration", metavar="FILE", type=Path, help="LeRobot calibration JSON of the follower arm"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import msgspec  # lazy with the decoder: keeps `twin --help` light

    from twin.core.telemetry import DecoderConfig, TelemetryDecoder, TelemetryRejected, Units
    from twin.robot.calibration import load_calibration  # lazy: keeps `twin --help` light

    try:
        calibration = load_calibration(args.calibration) if args.calibration else None
    except ValueError as exc:
        console.err(str(exc))
        return 1
    try:
        raw = sys.stdin.buffer.read() if args.payload == "-" else Path(args.payload).read_bytes()
    except OSError as exc:
        console.err(f"cannot read {args.payload}: {exc.strerror or exc}")
        return 1
    # One payload is all the evidence there will be, so auto must decide from it alone.
    decoder = TelemetryDecoder(
        DecoderConfig(units=Units(args.units), calibration=calibration, auto_evidence_messages=1)
    )
    try:
        telemetry = decoder.decode(raw)
    except TelemetryRejected as exc:
        hint = " (pass --units ticks|degrees|range100)" if exc.reason == "units_undecided" else ""
        # The agent's words name its setting; here the same choice is this command's flag.
        said = re.search(r"set units=(\w+)", str(exc))
        if said and not hint:
            hint = f" (here: --units {said.group(1)})"
        # A line of its own, no command prefix: scripts match on "rejected: <reason>:" (docs/telemetry.md).
        sys.stderr.write(f"rejected: {exc.reason}: {exc}{hint}\n")
        return EXIT_REJECTED
    out = {
        "device": telemetry.device_id,
        "timestamp": telemetry.timestamp_ms,
        "units": telemetry.units.value,
        "angles_rad": telemetry.angles_rad,
        "gripper_percent": telemetry.gripper_percent,
        "diagnostics": {
            name: {k: v for k, v in msgspec.structs.asdict(diag).items() if v is not None}
            for name, diag in telemetry.diagnostics.items()
        },
    }
    console.out(json.dumps(out, indent=2))
    return 0
