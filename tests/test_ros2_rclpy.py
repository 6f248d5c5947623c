"""The ROS 2 bridge against real ROS 2: rclpy from the PyPI wheels of Jazzy (Fast DDS 2.14) and Kilted
(Fast DDS 3.2), ROS 2's default middleware, subscribes and must receive exactly what the bridge sent. Each
test runs in a fresh network namespace with loopback only, so DDS discovery never leaves it.

A Cyclone-to-Cyclone test alone would not do: it passes in set-ups where real ROS 2 receives nothing (type
names, CDR layout, QoS and XTypes matching all have to agree with rmw_fastrtps).
"""

from __future__ import annotations

import itertools
import json
import os
import sys
from pathlib import Path

import pytest
from ros2_helpers.paths import LISTENER, REPO, ROS_PYTHONS, missing_prerequisites
from twin.bench.netns import run_in_loopback_namespace
from twin.output.ros2 import JOINT_NAME_PRESETS, rihs01
from twin.robot import so101

pytestmark = pytest.mark.slow

DRIVER = REPO / "tests" / "ros2_helpers" / "bridge_driver.py"


@pytest.fixture(scope="module", autouse=True)
def _prerequisites() -> None:
    reason = missing_prerequisites()
    if reason is not None:
        pytest.fail(reason)


def drive(
    tmp_path: Path,
    devices: list[str],
    settings: dict,
    *,
    env: dict[str, str] | None = None,
    ros: str = "jazzy",
    extra: tuple[str, ...] = (),
) -> dict:
    out = tmp_path / "result.json"
    proc = run_in_loopback_namespace(
        [
            sys.executable,
            str(DRIVER),
            "--ros-python",
            str(ROS_PYTHONS[ros]),
            "--listener",
            str(LISTENER),
            "--devices",
            ",".join(devices),
            "--settings",
            json.dumps(settings),
            "--out",
            str(out),
            *extra,
        ],
        env={**os.environ, **(env or {})},
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    assert result["listener"] is not None, proc.stderr[-3000:]
    return result


def by_stamp(sent: list[dict]) -> dict[tuple[int, int], dict]:
    return {divmod(s["timestamp_ms"], 1000): s for s in sent}


def test_rclpy_receives_every_arm_with_names_positions_velocity_and_type_hash(tmp_path: Path) -> None:
    result = drive(
        tmp_path, ["arm-001", "arm-002"], {"joint_names": ["so_arm101_usd"]}, env={"ROS_DOMAIN_ID": "42"}
    )
    assert result["bridge"]["domain_id"] == 42
    assert result["stats"]["errors"] == 0, result["stats"]["last_error"]
    listener = result["listener"]
    for device, topic in (("arm-001", "/arm_001/joint_states"), ("arm-002", "/arm_002/joint_states")):
        messages = listener["received"][topic]
        assert len(messages) >= 5, f"{topic}: rclpy received {len(messages)} messages"
        sent = by_stamp(result["sent"][device])
        for msg in messages:
            expected = sent[(msg["sec"], msg["nanosec"] // 1_000_000)]
            assert msg["nanosec"] % 1_000_000 == 0
            assert msg["name"] == list(JOINT_NAME_PRESETS["so_arm101_usd"])
            assert msg["position"] == expected["position"]  # bit for bit: doubles end to end
            assert msg["velocity"] == expected["velocity"]
            assert msg["effort"] == []
            assert msg["frame_id"] == ""
        [publisher] = listener["publishers"][topic]
        assert publisher["topic_type"] == "sensor_msgs/msg/JointState"
        assert publisher["type_hash"] == rihs01("sensor_msgs/msg/JointState")
        assert (publisher["reliability"], publisher["durability"]) == ("RELIABLE", "VOLATILE")
        assert listener["graph"][topic] == ["sensor_msgs/msg/JointState"]


def test_stamps_never_go_backwards_after_an_edge_clock_reset(tmp_path: Path) -> None:
    """An edge clock set 30 s back (the mirror then applies samples older than the arm's last one) stamped
    JointState 30 s before the message rclpy had just received: tf buffers and bag players that expect a
    frame's stamps in order dropped or misordered it. The stamps now go on from the last one, as far after it
    as the agent received the sample after it (the driver's receive times are 100 ms apart)."""
    extra = ("--count", "30", "--reset-after", "15", "--reset-back-ms", "30000")
    result = drive(tmp_path, ["arm-001"], {}, extra=extra)
    assert result["stats"]["errors"] == 0, result["stats"]["last_error"]
    messages = result["listener"]["received"]["/arm_001/joint_states"]
    stamps_ms = [m["sec"] * 1000 + m["nanosec"] // 1_000_000 for m in messages]
    sent = result["sent"]["arm-001"]
    before = {s["timestamp_ms"] for s in sent if not s["reset"]}
    # rclpy received messages from both sides of the reset (the driver resets only once the writer matched).
    assert stamps_ms[0] in before and stamps_ms[-1] not in before, stamps_ms
    steps = [b - a for a, b in itertools.pairwise(stamps_ms)]
    assert all(step > 0 for step in steps), steps
    # Across the reset: not 30 s back, nor 1 ms on (a velocity from the stamps would spike), but the 100 ms
    # that passed between the two receive times.
    crossing = next(i for i, stamp in enumerate(stamps_ms) if stamp not in before)
    assert stamps_ms[crossing] - stamps_ms[crossing - 1] == 100, stamps_ms


def test_fixed_topic_over_unicast_peer_on_a_named_interface_carries_one_arm(tmp_path: Path) -> None:
    settings = {
        "topic": "/joint_states",
        "interface": "lo",
        "peers": ["127.0.0.1"],
        "velocity": False,
        "frame_id": "base_link",
    }
    result = drive(tmp_path, ["solo", "other"], settings)
    # A fixed topic suits one arm: the second is refused (logged with the fix), never interleaved.
    assert result["bridge"]["refused_devices"] == ["other"]
    assert result["bridge"]["arms"] == 1
    messages = result["listener"]["received"]["/joint_states"]
    assert len(messages) >= 5
    sent = by_stamp(result["sent"]["solo"])
    for msg in messages:
        expected = sent[(msg["sec"], msg["nanosec"] // 1_000_000)]
        assert msg["name"] == list(so101.JOINT_NAMES)
        assert msg["position"] == expected["position"]
        assert msg["velocity"] == []
        assert msg["frame_id"] == "base_link"


def test_fast_dds_3_receives_thanks_to_ignoring_its_type_information(tmp_path: Path) -> None:
    # Kilted's Fast DDS 3.2 announces type information that Cyclone rejects as invalid
    # ("ddsi_xt_type_init_impl with invalid type object"), and then never matches the reader: without
    # <IgnoreTypeInformation>1.15</IgnoreTypeInformation> this subscriber received nothing (docs/ros2.md).
    result = drive(tmp_path, ["arm-001"], {}, ros="kilted")
    messages = result["listener"]["received"]["/arm_001/joint_states"]
    assert len(messages) >= 5
    sent = by_stamp(result["sent"]["arm-001"])
    for msg in messages:
        expected = sent[(msg["sec"], msg["nanosec"] // 1_000_000)]
        assert msg["name"] == list(so101.JOINT_NAMES)
        assert msg["position"] == expected["position"]
        assert msg["velocity"] == expected["velocity"]
    [publisher] = result["listener"]["publishers"]["/arm_001/joint_states"]
    assert publisher["type_hash"] == rihs01("sensor_msgs/msg/JointState")


AGENT_DRIVER = REPO / "tests" / "ros2_helpers" / "agent_driver.py"
AGENT_CONFIG = """
[telemetry]
units = "ticks"
[ros2]
joint_names = ["so_arm101_usd"]
"""


def test_end_to_end_rclpy_sees_what_state_shows(tmp_path: Path) -> None:
    # mosquitto + edge simulator + `twin run --ros2`, all inside the namespace; rclpy on the other side.
    devices = ["arm-001", "arm-002"]
    out = tmp_path / "e2e.json"
    proc = run_in_loopback_namespace(
        [
            sys.executable,
            str(AGENT_DRIVER),
            "--ros-python",
            str(ROS_PYTHONS["jazzy"]),
            "--listener",
            str(LISTENER),
            "--devices",
            ",".join(devices),
            "--config",
            AGENT_CONFIG,
            "--out",
            str(out),
        ],
        timeout=180,
        cwd=REPO,
    )
    agent_log = out.with_suffix(".agent.log")
    context = proc.stderr[-2000:] + (agent_log.read_text()[-3000:] if agent_log.exists() else "")
    assert proc.returncode == 0, context
    result = json.loads(out.read_text())
    state = result["state"]
    [sink] = [s for s in state["agent"]["sinks"] if s["name"] == "ros2"]
    assert sink["errors"] == 0, sink["last_error"]
    usd_names = list(JOINT_NAME_PRESETS["so_arm101_usd"])
    for device in devices:
        topic = f"/{device.replace('-', '_')}/joint_states"
        messages = result["listener"]["received"][topic]
        assert len(messages) >= 10, f"{topic}: {len(messages)} messages; {context}"
        stamps = [(m["sec"], m["nanosec"]) for m in messages]
        assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
        # The edge has stopped: the last JointState is the pose the agent's /state shows, bit for bit.
        last = messages[-1]
        shown = state["devices"][device]
        assert last["name"] == usd_names
        assert last["position"] == [shown["joints_rad"][j] for j in so101.JOINT_NAMES]
        assert last["sec"] * 1000 + last["nanosec"] // 1_000_000 == shown["timestamp_ms"]
        assert len(last["velocity"]) == 6  # the simulator reports servo speeds on every joint
    assert sink["delivered"] >= sum(
        len(result["listener"]["received"][t]) for t in result["listener"]["received"]
    )


BRIDGE_START = """
import sys
from twin.output.ros2 import Ros2Bridge, Ros2Error, Ros2Settings
try:
    bridge = Ros2Bridge(Ros2Settings(enabled=True, interface=sys.argv[1]))
except Ros2Error as exc:
    print("refused:", exc)
else:
    bridge.close()
    print("started")
"""


def test_the_users_cyclone_config_is_read_and_a_bad_one_stops_the_bridge_with_the_fix() -> None:
    user = (
        "<CycloneDDS><Domain><General><MaxMessageSize>1400B</MaxMessageSize></General></Domain></CycloneDDS>"
    )
    good = run_in_loopback_namespace(
        [sys.executable, "-c", BRIDGE_START, "lo"], env={**os.environ, "CYCLONEDDS_URI": user}, timeout=60
    )
    assert good.stdout.strip() == "started", good.stderr[-1500:]
    bad_user = user.replace("MaxMessageSize", "NoSuchOption")
    bad = run_in_loopback_namespace(
        [sys.executable, "-c", BRIDGE_START, "lo"], env={**os.environ, "CYCLONEDDS_URI": bad_user}, timeout=60
    )
    assert "refused: cannot start DDS on domain" in bad.stdout, bad.stderr[-1500:]
    assert "CYCLONEDDS_URI" in bad.stdout
    no_such_interface = run_in_loopback_namespace([sys.executable, "-c", BRIDGE_START, "eth9"], timeout=60)
    # Named before DDS starts, with what the machine has (Cyclone's own words were "Non specific error").
    said = "refused: ros2.interface = 'eth9' is not a network interface of this machine (it has lo;"
    assert said in no_such_interface.stdout, no_such_interface.stderr[-1500:]
