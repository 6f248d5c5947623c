"""End to end inside the loopback-only namespace: mosquitto, the edge simulator and `twin run --ros2`, with
the real rclpy listener on the other side.

The listener subscribes first; then the edge simulator publishes every arm for a few seconds and stops. The
listener ends once it has its messages and the arms have gone quiet, and only then is the agent's `/state`
read: the last JointState of each arm must be the pose `/state` shows. Writes {"state": ..., "listener":
..., "edge": ...} to --out; the agent's log is copied next to it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import urllib.request
from pathlib import Path

from listener_process import start_listener
from twin.output.ros2 import Ros2Settings, resolve_topic
from twin.rig.local import LocalRig, wait_until


def _state(base: str) -> dict:
    with urllib.request.urlopen(f"{base}/state", timeout=5) as response:
        return json.loads(response.read())


def _subscribed(base: str, proc: subprocess.Popen) -> bool:
    if proc.poll() is not None:
        raise RuntimeError(f"twin run exited with code {proc.returncode}")
    try:
        return _state(base)["agent"]["broker"]["subscribes"] > 0
    except OSError:
        return False


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--ros-python", required=True)
    parser.add_argument("--listener", required=True)
    parser.add_argument("--devices", required=True)
    parser.add_argument("--config", required=True, help="the agent's TOML config ([ros2] settings)")
    parser.add_argument("--seconds", type=float, default=4.0, help="how long the edge publishes")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()

    out = Path(args.out)
    devices = args.devices.split(",")
    settings = Ros2Settings()  # the default topic pattern, as the agent config below leaves it
    topics = [resolve_topic(settings.topic, d) for d in devices]
    report = out.with_suffix(".listener.json")
    options = ["--count", "10", "--idle", "2", "--timeout", "60"]
    listener = start_listener(args.ros_python, args.listener, topics, report, options)
    if listener is None:
        return 1

    with LocalRig(out.parent / "rig") as rig:
        agent = rig.agent_process(
            devices=args.devices, config_text=args.config, extra_args=["--ros2"], log_name="agent"
        )
        with agent as (proc, base):
            try:
                wait_until(lambda: _subscribed(base, proc), 30.0, "the agent to subscribe")
                edge = rig.start_edge(devices, seconds=args.seconds, rate_hz=10.0)
                edge_report = edge.join(args.seconds + 30)
                listener.wait(70)
                state = _state(base)
            finally:
                for log in rig.workdir.glob("agent-*.log"):
                    shutil.copy(log, out.with_suffix(".agent.log"))
    result = {
        "state": state,
        "listener": json.loads(report.read_text()) if report.exists() else None,
        "edge": {"published": edge_report.published, "per_device": edge_report.per_device},
    }
    out.write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
