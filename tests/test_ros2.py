"""twin.output.ros2: the JointState bytes and the RIHS01 type hash equal those of rosbags (an independent
pure-Python ROS 2 serialiser) and of cyclonedds' own IDL serializer; names, settings and the Cyclone
configuration refuse bad input with the fix.

No DDS traffic here: anything that discovers peers runs in a loopback-only namespace
(tests/test_ros2_rclpy.py).
"""

from __future__ import annotations

import dataclasses
import math
import os
import socket
import xml.etree.ElementTree as ET

import msgspec
import numpy as np
import pytest
from conftest import run_twin
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore
from twin.core.telemetry import JointDiagnostics, Telemetry, Units
from twin.output.ros2 import (
    DDS_TYPE_NAME,
    JOINT_NAME_PRESETS,
    ROS_TYPE_NAME,
    JointStateEncoder,
    Ros2Error,
    Ros2Settings,
    check_interface,
    check_peers,
    cyclone_config,
    dds_topic_name,
    encode_joint_state,
    joint_name_map,
    resolve_topic,
    rihs01,
    ros_name_token,
    sample_velocities,
    stamp_from_ms,
    type_hash_user_data,
)
from twin.output.ros2_idl import Header_, JointState_, Time_
from twin.output.sinks import AppliedSample
from twin.robot import so101

STORE = get_typestore(Stores.ROS2_JAZZY)
USD_NAMES = JOINT_NAME_PRESETS["so_arm101_usd"]


def rosbags_bytes(sec, nanosec, frame_id, names, position, *, velocity=(), effort=()) -> bytes:
    msg = STORE.types[ROS_TYPE_NAME](
        header=STORE.types["std_msgs/msg/Header"](
            stamp=STORE.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
        ),
        name=list(names),
        position=np.array(position, dtype=np.float64),
        velocity=np.array(velocity, dtype=np.float64),
        effort=np.array(effort, dtype=np.float64),
    )
    return bytes(STORE.serialize_cdr(msg, ROS_TYPE_NAME))


def idl_bytes(sec, nanosec, frame_id, names, position, *, velocity=(), effort=()) -> bytes:
    header = Header_(Time_(sec, nanosec), frame_id)
    msg = JointState_(header, list(names), list(position), list(velocity), list(effort))
    return msg.serialize(use_version_2=False)


# --- type hash ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("type_name", ["builtin_interfaces/msg/Time", "std_msgs/msg/Header", ROS_TYPE_NAME])
def test_type_hash_equals_rosbags(type_name: str) -> None:
    assert rihs01(type_name) == STORE.hash_rihs01(type_name)


def test_type_hash_user_data_is_what_ros2_parses() -> None:
    data = type_hash_user_data()
    assert data == f"typehash={STORE.hash_rihs01(ROS_TYPE_NAME)};".encode()
    assert data.startswith(b"typehash=RIHS01_") and len(data) == len("typehash=RIHS01_;") + 64


def test_dds_type_name_is_the_one_rosidl_generates() -> None:
    assert JointState_.__idl_typename__ == DDS_TYPE_NAME
    assert Time_.__idl_typename__ == "builtin_interfaces::msg::dds_::Time_"


# --- bytes -------------------------------------------------------------------------------------------------

ARM = [0.1, -0.2, 0.3, -0.4, 0.5, 1.2]
EXTREMES = [math.pi, -math.pi, 1e-300, -0.0, 2.5, 1.7453292]
SPEEDS = [0.0015, -0.003, 0.0, 1.0, -2.0, 0.5]
ODD_NAMES = ("a", "bb", "ccc", "dddd", "e", "fff")
# (sec, nanosec, frame_id, names, position, velocity, effort): names and frame ids of every length mod 4, so
# each string, count and double lands on every alignment once.
MESSAGES = [
    pytest.param((1_706_000_000, 123_000_000, "", so101.JOINT_NAMES, ARM, (), ()), id="so101"),
    pytest.param((1_706_000_000, 0, "base_link", USD_NAMES, [0.0] * 6, (), ()), id="usd-frame"),
    pytest.param((2_000_000_000, 999_000_000, "a", USD_NAMES, EXTREMES, SPEEDS, ()), id="velocity"),
    pytest.param((0, 1, "ab", ODD_NAMES, [1, 2, 3, 4, 5, 6], [], [0.1] * 6), id="effort"),
    pytest.param((-1, 5, "abc", ("x",), [0.5], [0.25], [0.125]), id="one-joint"),
    pytest.param((7, 7, "", (), [], [], []), id="empty"),
]


@pytest.mark.parametrize("message", MESSAGES)
def test_bytes_equal_rosbags_and_cyclonedds(message: tuple) -> None:
    sec, nanosec, frame_id, names, position, velocity, effort = message
    args = (sec, nanosec, frame_id, names, position)
    ours = encode_joint_state(*args, velocity=velocity, effort=effort)
    assert ours == rosbags_bytes(*args, velocity=velocity, effort=effort)
    assert ours == idl_bytes(*args, velocity=velocity, effort=effort)
    assert ours[:4] == b"\x00\x01\x00\x00"  # CDR little-endian, what every ROS 2 middleware reads


def test_stamp_fields_are_32_bit() -> None:
    # The int pitfall: a bare Python int annotation would make sec an int64 and the body 4 bytes longer.
    body = encode_joint_state(1, 2, "", (), [])[4:]
    assert body[:8] == (1).to_bytes(4, "little") + (2).to_bytes(4, "little")
    assert len(Time_(1, 2).serialize(use_version_2=False)) == 4 + 8


_name = st.text(
    st.characters(min_codepoint=33, max_codepoint=0x2FFF, exclude_categories=("Cs",)), max_size=12
)
_value = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=150, deadline=None)
@given(
    frame_id=_name,
    names=st.lists(_name.filter(bool), min_size=6, max_size=6),
    position=st.lists(_value, min_size=6, max_size=6),
    velocity=st.one_of(st.none(), st.lists(_value, min_size=6, max_size=6)),
    timestamp_ms=st.integers(946_684_800_000, 2_147_483_647_999),
)
def test_per_arm_encoder_equals_rosbags(frame_id, names, position, velocity, timestamp_ms) -> None:
    sec, nanosec = divmod(timestamp_ms, 1000)
    ours = JointStateEncoder(frame_id, names).encode(timestamp_ms, position, velocity)
    assert ours == rosbags_bytes(sec, nanosec * 1_000_000, frame_id, names, position, velocity=velocity or ())


def test_stamp_is_the_edge_timestamp_and_refuses_what_int32_cannot_carry() -> None:
    assert stamp_from_ms(1_706_000_000_123) == (1_706_000_000, 123_000_000)
    assert stamp_from_ms(2_147_483_647_999) == (2_147_483_647, 999_000_000)
    with pytest.raises(Ros2Error, match="2038"):
        stamp_from_ms(2_147_483_648_000)


def test_encoder_refuses_a_position_count_that_does_not_match_the_names() -> None:
    with pytest.raises(Ros2Error, match="5 positions for 6 joint names"):
        JointStateEncoder("", so101.JOINT_NAMES).encode(1_706_000_000_000, [0.0] * 5)


def _sample(velocities: list[float | None]) -> AppliedSample:
    angles = dict.fromkeys(so101.JOINT_NAMES, 0.0)
    diagnostics = {
        j: JointDiagnostics(velocity_rad_s=v) for j, v in zip(so101.JOINT_NAMES, velocities, strict=True)
    }
    telemetry = Telemetry("arm-001", 1_706_000_000_000, Units.TICKS, angles, 50.0, diagnostics)
    return AppliedSample("arm-001", 0.0, 0.0, telemetry, angles)


def test_velocity_only_when_every_joint_reports_one() -> None:
    assert sample_velocities(_sample([0.1, 0.2, 0.3, 0.4, 0.5, 0.6])) == [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    assert sample_velocities(_sample([0.1, 0.2, None, 0.4, 0.5, 0.6])) is None
    sample = _sample([0.0] * 6)
    # Telemetry is a frozen msgspec Struct: a copy without diagnostics.
    no_diag = dataclasses.replace(sample, telemetry=msgspec.structs.replace(sample.telemetry, diagnostics={}))
    assert sample_velocities(no_diag) is None


# --- names -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("device", "token"),
    [
        ("arm-001", "arm_001"),
        ("arm_001", "arm_001"),
        ("Arm.7", "Arm_7"),
        ("7th-arm", "_7th_arm"),
        ("bras-é", "bras__"),
        ("x", "x"),
    ],
)
def test_device_id_becomes_a_ros_name_token(device: str, token: str) -> None:
    assert ros_name_token(device) == token


def test_topic_from_pattern_and_dds_name() -> None:
    assert resolve_topic("/{arm}/joint_states", "arm-001") == "/arm_001/joint_states"
    assert resolve_topic("/twin/{arm}/joint_states", "7") == "/twin/_7/joint_states"
    assert resolve_topic("/joint_states", "arm-001") == "/joint_states"
    assert dds_topic_name("/arm_001/joint_states") == "rt/arm_001/joint_states"


@pytest.mark.parametrize(
    ("pattern", "fix"),
    [
        ("{arm}/joint_states", "must start with '/'"),
        ("/{arm}/joint_states/", "not end with '/'"),
        ("//joint_states", "single '/'"),
        ("/{device}/joint_states", "the only placeholder is {arm}"),
        ("/1st/joint_states", "do not start with a digit"),
        ("/joint-states", "letters, digits and '_'"),
        ("", "must start with '/'"),
    ],
)
def test_bad_topic_patterns_are_refused_with_the_fix(pattern: str, fix: str) -> None:
    with pytest.raises(Ros2Error, match=r"ros2\.topic") as excinfo:
        Ros2Settings(topic=pattern)
    assert fix in str(excinfo.value)


def test_joint_name_presets_and_explicit_names() -> None:
    assert joint_name_map(("so101",)) == so101.JOINT_NAMES
    usd = ("Rotation", "Pitch", "Elbow", "Wrist_Pitch", "Wrist_Roll", "Jaw")
    assert joint_name_map(("so_arm101_usd",)) == usd
    assert joint_name_map(("a", "b", "c", "d", "e", "f")) == ("a", "b", "c", "d", "e", "f")
    assert Ros2Settings(joint_names=("so_arm101_usd",)).ros_joint_names == USD_NAMES


@pytest.mark.parametrize(
    ("names", "fix"),
    [
        (("isaac",), "one preset (so101, so_arm101_usd) or 6 names"),
        (("a", "b", "c", "d", "e"), "6 names"),
        (("a", "b", "c", "d", "e", "a"), "names a joint twice"),
        (("a", "b", "c", "d", "e", " f"), "without surrounding spaces"),
        (("a", "b", "c", "d", "e", ""), "non-empty"),
    ],
)
def test_bad_joint_names_are_refused_with_the_fix(names: tuple[str, ...], fix: str) -> None:
    with pytest.raises(Ros2Error, match=r"ros2\.joint_names") as excinfo:
        Ros2Settings(joint_names=names)
    assert fix in str(excinfo.value)


# --- settings ----------------------------------------------------------------------------------------------


def test_domain_id_follows_ros_domain_id_unless_set() -> None:
    assert Ros2Settings().effective_domain_id({}) == 0
    assert Ros2Settings().effective_domain_id({"ROS_DOMAIN_ID": "42"}) == 42
    assert Ros2Settings(domain_id=7).effective_domain_id({"ROS_DOMAIN_ID": "42"}) == 7
    with pytest.raises(Ros2Error, match="ROS_DOMAIN_ID='abc'"):
        Ros2Settings().effective_domain_id({"ROS_DOMAIN_ID": "abc"})
    with pytest.raises(Ros2Error, match=r"0\.\.232"):
        Ros2Settings().effective_domain_id({"ROS_DOMAIN_ID": "233"})
    with pytest.raises(Ros2Error, match=r"ros2\.domain_id = 300 is outside 0\.\.232"):
        Ros2Settings(domain_id=300)


@pytest.mark.parametrize(
    ("kwargs", "fix"),
    [
        ({"interface": "eth0; rm"}, "ros2.interface"),
        ({"peers": ("10.0.0.1", "bad peer")}, "ros2.peers holds 'bad peer'"),
        ({"frame_id": "a\nb"}, "ros2.frame_id"),
        ({"max_pending": 0}, "ros2.max_pending"),
    ],
)
def test_bad_settings_are_refused_with_the_fix(kwargs: dict, fix: str) -> None:
    with pytest.raises(Ros2Error, match=r"ros2\.") as excinfo:
        Ros2Settings(**kwargs)
    assert fix in str(excinfo.value)


def test_peers_cyclone_could_not_use_are_refused_with_the_fix(monkeypatch) -> None:
    check_peers(["10.0.1.23", "10.0.1.23:7410", "localhost"])
    for peer, fix in [
        ("::1", "an IPv6 address"),
        ("[::1]:7410", "an IPv6 address"),
        ("10.0.1.23:abc", "port is not 1..65535"),
        ("10.0.1.23:70000", "port is not 1..65535"),
    ]:
        with pytest.raises(Ros2Error, match=r"ros2\.peers holds") as excinfo:
            check_peers([peer])
        assert fix in str(excinfo.value), peer

    def no_such_host(host, *args, **kwargs):
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    # A stand-in resolver: the test must not wait on the machine's DNS.
    monkeypatch.setattr(socket, "getaddrinfo", no_such_host)
    with pytest.raises(Ros2Error, match=r"'rviz\.internal', which does not resolve to an IPv4 address"):
        check_peers(["rviz.internal"])


def test_an_interface_the_machine_lacks_is_refused_by_name() -> None:
    """A walk: `interface = "eth9"` stopped the agent with Cyclone's "Non specific error"; the error must
    name the setting and the interfaces there are. An address the machine lacks did the same."""
    from twin.output.ros2 import Ros2Bridge

    check_interface("lo")
    check_interface("127.0.0.1")
    # 192.0.2.0/24 is for documentation only (RFC 5737): no machine has it.
    lacked = r"ros2\.interface = '192\.0\.2\.7' is not an address of this machine"
    with pytest.raises(Ros2Error, match=lacked):
        check_interface("192.0.2.7")
    # A socket binds to a multicast group and to the any address alike: neither is the machine's.
    for group in ("239.255.0.1", "ff02::1"):
        with pytest.raises(Ros2Error, match=r"is not an address of this machine \(a multicast group address"):
            check_interface(group)
    with pytest.raises(Ros2Error, match=r"\(the any address, which names no one interface\)"):
        check_interface("0.0.0.0")
    with pytest.raises(Ros2Error, match=r"ros2\.interface = 'nosuchif0' is not a network interface") as exc:
        Ros2Bridge(Ros2Settings(enabled=True, interface="nosuchif0"))
    assert "lo" in str(exc.value)


@pytest.mark.slow
def test_twin_run_refuses_a_peer_cyclone_would_abort_on(tmp_path) -> None:
    """A walk: `peers = ["::1"]` (or a name that did not resolve) made Cyclone DDS abort the agent (SIGABRT,
    exit 134) with one line of its own on stderr; the agent must exit 2 and name the peer."""
    config = tmp_path / "agent.toml"
    config.write_text('[broker]\nurl = "mqtt://127.0.0.1:1"\n[ros2]\nenabled = true\npeers = ["::1"]\n')
    args = ["run", "--config", str(config), "--workers", "1", "--http", "127.0.0.1:0"]
    proc = run_twin(args, os.environ, timeout=60)
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert "ros2.peers holds '::1', an IPv6 address" in proc.stderr, proc.stderr


def test_fixed_topic_is_detected() -> None:
    assert Ros2Settings(topic="/joint_states").fixed_topic
    assert not Ros2Settings().fixed_topic


# --- Cyclone configuration ---------------------------------------------------------------------------------


def _domain(xml: str) -> ET.Element:
    root = ET.fromstring(xml)
    assert root.tag == "CycloneDDS"
    domain = root.find("Domain")
    assert domain is not None and domain.get("Id") == "any"
    return domain


def test_cyclone_config_ignores_fast_dds_type_information_by_default() -> None:
    domain = _domain(cyclone_config(Ros2Settings(), environ={}))
    assert domain.findtext("Compatibility/IgnoreTypeInformation") == "1.15"
    assert domain.find("General") is None and domain.find("Discovery") is None


def test_cyclone_config_interface_by_name_or_address_and_unicast_peers() -> None:
    by_name = _domain(cyclone_config(Ros2Settings(interface="ens5"), environ={}))
    assert by_name.find("General/Interfaces/NetworkInterface").attrib == {"name": "ens5"}
    by_address = _domain(cyclone_config(Ros2Settings(interface="10.0.1.5"), environ={}))
    assert by_address.find("General/Interfaces/NetworkInterface").attrib == {"address": "10.0.1.5"}
    peers = _domain(cyclone_config(Ros2Settings(peers=("10.0.1.23", "rviz.internal")), environ={}))
    assert [p.get("address") for p in peers.findall("Discovery/Peers/Peer")] == ["10.0.1.23", "rviz.internal"]
    assert peers.findtext("Discovery/ParticipantIndex") == "auto"


def test_cyclone_config_appends_the_users_cyclonedds_uri_so_it_wins() -> None:
    config = cyclone_config(Ros2Settings(), environ={"CYCLONEDDS_URI": "file:///etc/cyclone.xml"})
    ours, user = config.rsplit(",", 1)
    _domain(ours)
    assert user == "file:///etc/cyclone.xml"


@pytest.mark.slow
def test_twin_run_ros2_without_the_extra_exits_2_and_says_how_to_install(tmp_path) -> None:
    # A cyclonedds that cannot be imported stands in for a host without the ros2 extra.
    fake = tmp_path / "site" / "cyclonedds"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text('raise ImportError("No module named cyclonedds")\n')
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "site")}
    proc = run_twin(["run", "--ros2", "--broker", "mqtt://127.0.0.1:1"], env, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "pip install 'so101-twin[ros2]'" in proc.stderr
    # The venv of a checkout has no pip: the hint names what works there (a walk found pip's failing).
    assert "in this checkout `make setup`" in proc.stderr


@pytest.mark.slow
def test_an_agent_with_worker_processes_refuses_a_missing_ros2_extra_before_it_connects(tmp_path) -> None:
    """A walk: with worker processes the agent connected and subscribed, then stopped with "2
    messages_not_mirrored", as if data had been lost, when a worker could not open the bridge."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text("import sys\nsys.modules['cyclonedds'] = None\n")
    env = {**os.environ, "PYTHONPATH": str(site)}
    args = ["run", "--ros2", "--workers", "2", "--broker", "mqtt://127.0.0.1:1", "--http", "127.0.0.1:0"]
    proc = run_twin(args, env, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "the ROS 2 bridge needs cyclonedds (not installed)" in proc.stderr, proc.stderr
    out = proc.stdout + proc.stderr
    assert "could not connect" not in out and "messages_not_mirrored" not in out, out


@pytest.mark.slow
@pytest.mark.parametrize(
    ("ros2", "env", "said"),
    [
        ("", {"ROS_DOMAIN_ID": "abc"}, "ROS_DOMAIN_ID='abc' is not a domain id"),
        ('peers = ["::1"]\n', {}, "ros2.peers holds '::1', an IPv6 address"),
        ('interface = "nosuchif0"\n', {}, "ros2.interface = 'nosuchif0' is not a network interface"),
    ],
)
def test_an_agent_with_worker_processes_refuses_bad_ros2_settings_before_it_connects(
    tmp_path, ros2: str, env: dict, said: str
) -> None:
    """A walk: with worker processes these were told only after the agent had connected, with "not
    everything was written: N messages_not_mirrored" (an unresolvable peer: "worker 0 exited", code -6)."""
    config = tmp_path / "agent.toml"
    config.write_text(f'[broker]\nurl = "mqtt://127.0.0.1:1"\n[ros2]\nenabled = true\n{ros2}')
    args = ["run", "--config", str(config), "--workers", "2", "--http", "127.0.0.1:0"]
    proc = run_twin(args, {**os.environ, **env}, timeout=60)
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert said in proc.stderr, proc.stderr
    out = proc.stdout + proc.stderr
    assert "connecting to" not in out and "messages_not_mirrored" not in out, out[-2000:]
