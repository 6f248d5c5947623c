"""`twin edge-sim`: publish SO-101 edge telemetry (mock motion) with optional faults; the servo readings are
the edge mock mode's noise or, with `--servos physical`, what servos following the motion report."""

from __future__ import annotations

import argparse
import json
import logging
from typing import Any

from twin.cli.output import Console, stop_on_signals
from twin.core.topics import DEFAULT_TOPIC_PREFIX

console = Console("edge-sim")


def _probability(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{value} is not a probability between 0 and 1")
    return value


def _positive(text: str) -> float:
    value = float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{value} must be positive")
    return value


def _device_id(text: str) -> str:
    """An id the stack mirrors (the rule `twin calibration` keeps): another would publish to a topic that
    no deployed agent subscribes to, or that IoT Core's policy refuses."""
    from twin.service.calibrations import check_device

    try:
        check_device(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"{exc}; pass --device such an id (as the arm's edge publishes)"
        ) from None
    return text


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "edge-sim",
        help="publish simulated SO-101 edge telemetry (ticks or LeRobot degrees) with optional faults",
        description=(
            "Publishes what the SO-101 edge component publishes, driven by its mock-mode motion, to a local "
            "broker or AWS IoT Core. Faults are per-message probabilities. Stops after --seconds, or on "
            "Ctrl-C / SIGTERM, then prints how many messages went out per fault kind."
        ),
    )
    _add_fleet_arguments(parser)
    _add_broker_arguments(parser)
    _add_message_faults(parser.add_argument_group("faults"))
    parser.add_argument("--seed", type=int, help="random seed for reproducible runs")
    parser.add_argument("--json", action="store_true", help="print the final counts as JSON")
    parser.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    parser.set_defaults(func=run)


def _add_fleet_arguments(parser: argparse.ArgumentParser) -> None:
    """What is simulated: payload format, which arms, how fast, for how long."""
    parser.add_argument(
        "--variant", choices=("ticks", "degrees"), default="ticks", help="payload format (default ticks)"
    )
    who = parser.add_mutually_exclusive_group()
    who.add_argument("--devices", type=int, metavar="N", help="simulate arm-001..arm-00N (default 1)")
    who.add_argument(
        "--device",
        action="append",
        type=_device_id,
        metavar="ID",
        help="device id: 1..64 letters, digits, '-', '_' or '.' (repeatable)",
    )
    parser.add_argument(
        "--rate", type=_positive, default=10.0, metavar="HZ", help="messages/s per device (default 10)"
    )
    parser.add_argument("--seconds", type=_positive, metavar="S", help="run time (default: until stopped)")


def _add_broker_arguments(parser: argparse.ArgumentParser) -> None:
    """Where it publishes: the broker and the topic and client id prefixes."""
    parser.add_argument(
        "--broker",
        default="mqtt://127.0.0.1:1883",
        metavar="URL",
        help='mqtt://host:port, mqtts://host:port, or "iot" for AWS IoT Core (default %(default)s)',
    )
    parser.add_argument(
        "--region", default="", help="iot: AWS region (default: AWS_REGION, else the AWS config)"
    )
    parser.add_argument("--endpoint", default="", help="iot: data endpoint (default: iot:DescribeEndpoint)")
    parser.add_argument(
        "--ca-file", default="", help="mqtts: PEM CA bundle that signed the broker certificate"
    )
    parser.add_argument(
        "--client-id-prefix", default="so101-edge-sim-", help="client id prefix (default %(default)s)"
    )
    parser.add_argument(
        "--topic-prefix", default=DEFAULT_TOPIC_PREFIX, help="topic prefix (default %(default)s)"
    )


def _add_message_faults(faults: Any) -> None:
    """Per-message faults (probabilities), then the servo faults of `_add_servo_faults`."""
    faults.add_argument("--drop", type=_probability, default=0.0, metavar="P", help="drop a message")
    faults.add_argument("--duplicate", type=_probability, default=0.0, metavar="P", help="send twice")
    faults.add_argument(
        "--reorder", type=_probability, default=0.0, metavar="P", help="swap with the device's next message"
    )
    faults.add_argument(
        "--malformed",
        type=_probability,
        default=0.0,
        metavar="P",
        help="send a broken message instead (not JSON, missing joint, NaN, > 128 KB, wrong types, ...)",
    )
    faults.add_argument(
        "--clock-skew-ms",
        type=int,
        default=0,
        metavar="MS",
        help="add to timestamps; spread over devices, the last one gets the full MS",
    )
    _add_servo_faults(faults)


def _add_servo_faults(faults: Any) -> None:
    """What the simulated servos report: the load sign bit, timed servo faults, model-consistent loads."""
    faults.add_argument(
        "--load-sign", action="store_true", help="set the load sign bit (bit 10) on about half the loads"
    )
    faults.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="KIND:JOINT[:START_S[:DURATION_S]]",
        help=(
            "servo fault on one joint, repeatable: heat (temperature ramps to 68 C and back), overload "
            "(stall at 90 %% load, 2.9 A; after 2 s the servo's overload status bit), contact (pose "
            "holds, load jumps by 45 points); start and duration in seconds since the run began (default 5 "
            "and 20), e.g. heat:elbow_flex:5:30"
        ),
    )
    faults.add_argument(
        "--model-loads",
        action="store_true",
        help=(
            "send the load each servo reports holding the pose (the bundled model's inverse dynamics, 7.4 V "
            "servos on 5 V) instead of the edge mock's random 0.5..5 %%, so the agent's model check has a "
            "true baseline"
        ),
    )
    _add_physical_servos(faults)


def _add_physical_servos(group: Any) -> None:
    """`--servos physical` and its settings (twin.edge.servo_physics, docs/servo-health.md)."""
    group.add_argument(
        "--servos",
        choices=("mock", "physical"),
        default="mock",
        help=(
            "mock (default): the edge mock mode's random velocity, load, temperature and current, as the "
            "real edge sends; physical: what servos following the motion report: load from the model's "
            "gravity and motion torques, current from the load, temperature from a thermal model of it"
        ),
    )
    group.add_argument(
        "--payload",
        type=float,
        default=0.0,
        metavar="KG",
        help="physical: a mass held at the gripper tip, in kg (default 0)",
    )
    group.add_argument(
        "--ambient",
        type=float,
        default=25.0,
        metavar="C",
        help="physical: the room's temperature, where the servos start and cool to (default %(default)s C)",
    )
    group.add_argument(
        "--thermal-speedup",
        action="append",
        default=[],
        metavar="JOINT:FACTOR",
        help=(
            "physical: run this servo's thermal model FACTOR times faster than the clock (a servo heats in "
            "minutes; shoulder_lift:80 shows it in seconds), repeatable"
        ),
    )


def _config(args: argparse.Namespace) -> Any:
    """The simulator's settings from the flags; ValueError (BrokerConfigError included) names a bad one."""
    from twin.edge.servo_faults import parse_fault
    from twin.edge.servo_physics import PhysicalServoConfig, parse_speedup
    from twin.edge.simulator import EdgeSimConfig, FaultConfig, device_ids
    from twin.transport.broker import BrokerConfig

    devices = list(args.device) if args.device else device_ids(args.devices or 1)
    if args.servos == "mock" and (args.payload or args.thermal_speedup):
        raise ValueError("--payload and --thermal-speedup are settings of --servos physical; add it")
    physical = PhysicalServoConfig(
        ambient_c=args.ambient,
        payload_kg=args.payload,
        speedup=dict(parse_speedup(text) for text in args.thermal_speedup),
    )
    return EdgeSimConfig(
        broker=BrokerConfig(
            url=args.broker,
            region=args.region,
            endpoint=args.endpoint,
            ca_file=args.ca_file,
            client_id_prefix=args.client_id_prefix,
        ),
        devices=devices,
        variant=args.variant,
        rate_hz=args.rate,
        seconds=args.seconds,
        topic_prefix=args.topic_prefix,
        faults=FaultConfig(
            drop=args.drop,
            duplicate=args.duplicate,
            reorder=args.reorder,
            malformed=args.malformed,
            clock_skew_ms=args.clock_skew_ms,
        ),
        seed=args.seed,
        load_sign=args.load_sign,
        servo_faults=tuple(parse_fault(text) for text in args.fault),
        model_loads=args.model_loads,
        servos=args.servos,
        physical=physical,
    )


def run(args: argparse.Namespace) -> int:
    # awscrt and the simulator load only when the command runs, so `twin --help` stays fast.
    from twin.edge.simulator import EdgeSimulator
    from twin.transport.broker import BrokerConfigError

    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        config = _config(args)
    except ValueError as exc:
        console.err(str(exc))
        return 2

    with stop_on_signals() as stop:
        try:
            report = EdgeSimulator(config).run(stop)
        except (ConnectionError, BrokerConfigError) as exc:
            console.err(str(exc))
            return 1

    if args.json:
        console.out(json.dumps(report.as_dict(), indent=2))
    else:
        console.out(
            f"ticks {report.ticks}, generated {report.generated}, published {report.published} "
            f"(failed {report.publish_failures}), dropped {report.dropped}, duplicated {report.duplicated}, "
            f"reordered {report.reordered}, malformed {report.malformed_total}, "
            f"skipped ticks {report.skipped_ticks}, {report.elapsed_s:.1f} s"
        )
        for kind, count in report.malformed.items():
            if count:
                console.out(f"  malformed {kind}: {count}")
    return 0
