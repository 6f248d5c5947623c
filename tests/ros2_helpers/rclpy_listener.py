"""A real ROS 2 subscriber (rclpy from the Jazzy PyPI wheels, run with .venv-ros2's Python, never .venv's).

Subscribes to `sensor_msgs/JointState` on each topic with ROS 2's default QoS, prints one line "ready" once
subscribed, and writes a JSON report when every topic has `--count` messages (and, with `--idle S`, no new
message came for S seconds after that: the publisher has stopped) or `--timeout` passes: the messages as
rclpy decoded them, and each topic's publishers as ROS 2 discovered them (type, type hash, QoS). Exit 0
either way; the test judges the report.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--topics", required=True, help="comma-separated ROS topics")
    parser.add_argument("--count", type=int, default=5)
    parser.add_argument("--timeout", type=float, default=30.0)
    parser.add_argument(
        "--idle", type=float, default=0.0, help="then wait until S seconds pass without a message"
    )
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    topics = [t for t in args.topics.split(",") if t]

    rclpy.init()
    node = Node("so101_twin_test_listener")
    received: dict[str, list[dict]] = {t: [] for t in topics}
    last = [time.monotonic()]

    def listener(topic: str):
        def on_message(msg: JointState) -> None:
            last[0] = time.monotonic()
            received[topic].append(
                {
                    "sec": msg.header.stamp.sec,
                    "nanosec": msg.header.stamp.nanosec,
                    "frame_id": msg.header.frame_id,
                    "name": list(msg.name),
                    "position": list(msg.position),
                    "velocity": list(msg.velocity),
                    "effort": list(msg.effort),
                }
            )

        return on_message

    # The default profile: Reliable, Volatile, KeepLast(10), what Isaac Sim and `ros2 topic echo` use.
    for topic in topics:
        node.create_subscription(JointState, topic, listener(topic), QoSProfile(depth=10))
    sys.stdout.write("ready\n")
    sys.stdout.flush()

    def done() -> bool:
        enough = all(len(m) >= args.count for m in received.values())
        return enough and time.monotonic() - last[0] >= args.idle

    deadline = time.monotonic() + args.timeout
    while time.monotonic() < deadline and not done():
        rclpy.spin_once(node, timeout_sec=0.1)

    publishers = {}
    for topic in topics:
        publishers[topic] = [
            {
                "topic_type": info.topic_type,
                "type_hash": str(info.topic_type_hash),
                "reliability": info.qos_profile.reliability.name,
                "durability": info.qos_profile.durability.name,
                "history": info.qos_profile.history.name,
                "depth": info.qos_profile.depth,
            }
            for info in node.get_publishers_info_by_topic(topic)
        ]
    graph = {name: types for name, types in node.get_topic_names_and_types()}
    # docs/ros2.md has a user write the report under out/, which a fresh checkout has not yet.
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as fh:
        json.dump({"received": received, "publishers": publishers, "graph": graph}, fh)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
