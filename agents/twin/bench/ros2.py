"""ROS 2 bridge cost: the same fleet through the agent without and with the bridge, and a ROS 2 reader.

Two agent phases against one private mosquitto with the same offered load (throughput.agent_phase): first
`twin run` as it is, then `twin run` with `[ros2] enabled = true` while a separate reader process subscribes
to every arm's JointState topic (Reliable, KeepLast(10), the ROS 2 default) and takes every sample. The cost
of the bridge is the difference in the agent process's CPU and in its mirrored rate; the ROS 2 sink's own
counters (delivered, dropped, errors) and what the reader received show that the messages really flowed.

DDS discovers its peers by multicast, so the whole run (broker, publishers, agent, reader) happens inside a
loopback-only network namespace: `run()` re-executes the scenario there (twin.bench.netns).
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys
from typing import Any

from twin.bench import netns
from twin.bench.harness import last_json_line, load_process
from twin.bench.throughput import agent_phase
from twin.bench.unavailable import Unavailable
from twin.rig.local import LocalRig

# The bridge as deployed, with the default topic pattern and joint names.
ROS2_CONFIG = "[ros2]\nenabled = true\n"


def _reader(arms: int, seconds: float) -> Any:
    reader = load_process("ros2-reader", "--first", "1", "--count", str(arms), "--seconds", str(seconds))
    assert reader.stdout is not None and reader.stderr is not None  # load_process pipes both
    ready = reader.stdout.readline()
    if '"ready"' not in ready:
        reader.kill()
        raise RuntimeError(f"the ROS 2 reader did not start: {reader.stderr.read()[-800:]}")
    return reader


def measure(*, arms: int, rate: float, seconds: float) -> dict[str, Any]:
    """Both phases; must run inside a loopback-only namespace."""
    with LocalRig() as rig:
        without = agent_phase(rig, arms, rate, seconds)
        reader = _reader(arms, seconds + 60)
        try:
            with_bridge = agent_phase(rig, arms, rate, seconds, config_text=ROS2_CONFIG)
        finally:
            reader.terminate()
            out, _ = reader.communicate(timeout=30)
    received = last_json_line(out)
    sink = next((s for s in with_bridge["sinks"] if s["name"] == "ros2"), None)
    return {
        "scenario": "ros2",
        "arms": arms,
        "rate_hz": rate,
        "seconds": seconds,
        "offered_rate": arms * rate,
        "without_bridge": without,
        "with_bridge": with_bridge,
        "ros2_sink": sink,
        "reader": received,
        "bridge_cpu_percent": with_bridge["cpu_percent"] - without["cpu_percent"],
        "mirrored_rate_ratio": (
            with_bridge["mirrored_rate"] / without["mirrored_rate"] if without["mirrored_rate"] else None
        ),
        "load_average": list(os.getloadavg()),
        "notes": (
            "agent CPU is the agent process only (percent of one core); publishers, broker and the ROS 2 "
            "reader share the host's cores; run inside a loopback-only network namespace"
        ),
    }


def run(*, arms: int = 100, rate: float = 10.0, seconds: float = 20.0) -> dict[str, Any]:
    """The scenario's figures; re-executes itself in a loopback-only namespace unless already inside one."""
    # Inside the namespace its absence would only surface as the child's error, a failure of the step.
    if importlib.util.find_spec("cyclonedds") is None:
        raise Unavailable(
            "cyclonedds is not installed: `make setup` installs it (the `ros2` extra of the agent package: "
            "pip install 'so101-twin[ros2]')"
        )
    if netns.inside():
        return measure(arms=arms, rate=rate, seconds=seconds)
    argv = [sys.executable, "-m", "twin.bench.ros2", str(arms), str(rate), str(seconds)]
    proc = netns.run_in_loopback_namespace(argv, timeout=2 * seconds + 300)
    if proc.returncode != 0:
        raise RuntimeError(f"the ros2 scenario failed ({proc.returncode}): {proc.stderr[-1500:]}")
    return last_json_line(proc.stdout)


def _main() -> int:
    arms, rate, seconds = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
    sys.stdout.write(json.dumps(measure(arms=arms, rate=rate, seconds=seconds)) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(_main())
