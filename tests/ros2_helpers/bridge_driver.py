"""Drive the ROS 2 sink against the real rclpy listener; runs inside the loopback-only namespace.

Starts `rclpy_listener.py` with .venv-ros2's Python, waits until it has subscribed, then feeds the sink one
AppliedSample per arm at 10 Hz (edge-simulator payloads through the real decoder) until the listener has
written its report or the time is up. Writes {"sent": {device: [sample...]}, "listener": <report>,
"stats": ...} to --out.
"""

from __future__ import annotations

import argparse
import json
import random
import sys
import time
from pathlib import Path

from listener_process import start_listener
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
from twin.edge.simulator import make_payload
from twin.output.ros2 import Ros2Bridge, Ros2Settings, resolve_topic
from twin.output.sinks import AppliedSample, QueuedSink
from twin.robot import so101


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--ros-python", required=True)
    parser.add_argument("--listener", required=True)
    parser.add_argument("--devices", required=True)
    parser.add_argument("--settings", required=True, help="Ros2Settings keyword arguments as JSON")
    parser.add_argument("--count", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=40.0)
    parser.add_argument(
        "--reset-after", type=int, default=0, help="from each arm's N-th sample on, its edge clock is reset"
    )
    parser.add_argument("--reset-back-ms", type=int, default=30_000, help="how far back the reset sets it")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()

    devices = args.devices.split(",")
    kwargs = json.loads(args.settings)
    for key in ("joint_names", "peers"):
        if key in kwargs:
            kwargs[key] = tuple(kwargs[key])
    settings = Ros2Settings(enabled=True, **kwargs)
    topics = sorted({resolve_topic(settings.topic, d) for d in devices})
    report = Path(args.out).with_suffix(".listener.json")
    options = ["--count", str(args.count), "--timeout", str(args.seconds - 5)]
    listener = start_listener(args.ros_python, args.listener, topics, report, options)
    if listener is None:
        return 1

    bridge = Ros2Bridge(settings)
    sink = QueuedSink("ros2", bridge)
    sent = feed(sink, bridge, devices, listener, args)
    listener.wait(15)
    sink.close()
    stats = sink.stats()
    result = {
        "sent": sent,
        "listener": json.loads(report.read_text()) if report.exists() else None,
        "stats": {"delivered": stats.delivered, "errors": stats.errors, "last_error": stats.last_error},
        "bridge": {
            "domain_id": bridge.domain_id,
            "arms": bridge.counters.arms,
            "published": bridge.counters.published,
            "refused": bridge.counters.refused,
            "refused_devices": sorted(bridge.counters.refused_devices),
        },
    }
    Path(args.out).write_text(json.dumps(result))
    return 0


def matched(bridge: Ros2Bridge, device: str) -> bool:
    """Whether the arm's writer has matched the listener's reader: samples written before it are lost
    (volatile durability), however long discovery took."""
    arm = bridge._arms.get(device)
    return arm is not None and arm.writer.get_publication_matched_status().current_count > 0


def feed(sink: QueuedSink, bridge: Ros2Bridge, devices: list[str], listener, args) -> dict[str, list[dict]]:
    """One sample per arm at 10 Hz until the listener is done. Receive times are the sample's index times
    100 ms, not the clock's: a test can then tell a step on the time line exactly, however loaded the host.
    With --reset-after, an arm's edge clock is set back from its N-th sample after its writer matched."""
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    rng = random.Random(7)
    sent: dict[str, list[dict]] = {d: [] for d in devices}
    matched_at: dict[str, int] = {}
    # What the mirror applies after an edge clock reset (docs/agent.md): samples older than the arm's last.
    back_ms = args.reset_back_ms if args.reset_after else 0
    started = time.monotonic()
    deadline = started + args.seconds
    while listener.poll() is None and time.monotonic() < deadline:
        for index, device in enumerate(devices):
            if device not in matched_at and matched(bridge, device):
                matched_at[device] = len(sent[device])
            # Each arm its own phase of the motion, so one arm's message can never pass for another's.
            payload = make_payload(device, time.monotonic() - started + 1.7 * index, "ticks", rng)
            reset = bool(back_ms) and len(sent[device]) >= matched_at.get(device, 1 << 30) + args.reset_after
            if reset:
                payload["timestamp"] -= back_ms
            telemetry = decoder.decode(json.dumps(payload).encode(), topic_device=device)
            angles = {j: telemetry.angles_rad[j] for j in so101.JOINT_NAMES}
            received_mono_s = 0.1 * len(sent[device])
            sink.applied(AppliedSample(device, time.time(), received_mono_s, telemetry, angles))
            sent[device].append(
                {
                    "timestamp_ms": telemetry.timestamp_ms,
                    "reset": reset,
                    "position": [angles[j] for j in so101.JOINT_NAMES],
                    "velocity": [telemetry.diagnostics[j].velocity_rad_s for j in so101.JOINT_NAMES],
                }
            )
        time.sleep(0.1)
    return sent


if __name__ == "__main__":
    sys.exit(main())
