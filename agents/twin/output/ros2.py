"""ROS 2 bridge: each applied sample as `sensor_msgs/JointState` on DDS, with no ROS install.

A ROS 2 node (Isaac Sim's action graph, RViz's robot_state_publisher, MoveIt, a logger) subscribes to a topic;
under the hood that is a DDS topic with a mangled name and type, carrying plain CDR. The PyPI package
`cyclonedds` (it bundles the C library) speaks that wire format directly, so the agent publishes the ROS 2
message without rclpy. What a ROS 2 subscriber needs to match us:

- DDS topic `rt/<ros topic without its leading '/'>` ("rt" = ROS topic), type name
  `sensor_msgs::msg::dds_::JointState_` (the IDL module path plus the `dds_` module and `_` suffix that
  rosidl adds for DDS);
- plain little-endian CDR (XCDR1, encapsulation 0x0001), exactly the IDL's field types: a Python int would
  default to a 64-bit field, while `builtin_interfaces/Time.sec` is int32 and `nanosec` uint32;
- QoS Reliable, Volatile, KeepLast(10) (the ROS 2 default profile);
- the RIHS01 type hash as writer user data `typehash=RIHS01_<hex>;` (Jazzy and later; REP 2011,
  rosidl_generator_type_description): ROS 2 shows it in `ros2 topic info -v` and uses it to report type
  mismatches;
- Cyclone's `<Compatibility><IgnoreTypeInformation>1.15</IgnoreTypeInformation>`: 1.15 is eProsima's DDS
  vendor id. Fast DDS 3.x (ROS 2 Kilted's default middleware) announces XTypes type information that Cyclone
  rejects as invalid, and Cyclone then never matches that reader: it receives nothing. Ignoring eProsima's
  type information makes Cyclone match on type names, as ROS 2 itself does.

The blocking half (DDS writes) runs on a `QueuedSink` thread, so a slow or absent ROS side never slows the
mirror. `cyclonedds` is the optional `ros2` extra and is imported only when a bridge is opened. Everything
above the `Ros2Bridge` class is pure and testable without it: names, the CDR encoder, the type hash, the
Cyclone configuration. docs/ros2.md is the user's guide.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import logging
import math
import os
import re
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from twin.output.edge_time import EdgeTime
from twin.output.sinks import AppliedSample, QueuedSink, RejectedSample
from twin.robot import so101

log = logging.getLogger(__name__)

ROS_TYPE_NAME = "sensor_msgs/msg/JointState"
DDS_TYPE_NAME = "sensor_msgs::msg::dds_::JointState_"
DDS_TOPIC_PREFIX = "rt"
ARM_PLACEHOLDER = "{arm}"
DEFAULT_TOPIC = "/{arm}/joint_states"
# ROS 2's default profile (rmw_qos_profile_default); what `ros2 topic echo` and Isaac Sim subscribe with.
HISTORY_DEPTH = 10
# How long a write may wait for a reliable reader's acknowledgements before it gives up (counted as an error
# of the bridge, never felt by the mirror). Short: a live view wants the next sample, not a late one.
MAX_BLOCKING_S = 0.05
# ROS_DOMAIN_ID range usable on Linux: Cyclone computes ports as 7400 + 250 * domain, which must stay < 65536.
DOMAIN_ID_MAX = 232
EPROSIMA_VENDOR_ID = "1.15"
# `pip` is not in the venv `make setup` and `make demo` build (uv fills it): in a checkout the command is
# `make setup`, which installs every extra.
INSTALL_HINT = (
    "install the ros2 extra: in this checkout `make setup` (every extra, into .venv); in an environment of "
    "your own, pip install 'so101-twin[ros2]'"
)

# Joint names as the ROS side knows them, in the edge's joint order (so101.JOINT_NAMES). "so101" keeps the
# telemetry names, which are also the joint names of the SO-101 URDF and of our MJCF (RViz with
# robot_state_publisher). "so_arm101_usd" is the community SO-ARM101 USD for Isaac Sim, converted from the
# same so101_new_calib model, whose ROS 2 action graph expects these names (MuammerBay/so-arm101-ros2-bridge,
# IgnacioSanchezAlvarado/iotcore-to-isaac-sim-dt backend/joint_converter.py).
JOINT_NAME_PRESETS: dict[str, tuple[str, ...]] = {
    "so101": so101.JOINT_NAMES,
    "so_arm101_usd": ("Rotation", "Pitch", "Elbow", "Wrist_Pitch", "Wrist_Roll", "Jaw"),
}

_INT32_MAX = 2**31 - 1
_NAME_TOKEN_BAD = re.compile(r"[^A-Za-z0-9_]")
_TOPIC_RE = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
_IFACE_RE = re.compile(r"^[A-Za-z0-9_.:-]{1,64}$")
_PEER_RE = re.compile(r"^[A-Za-z0-9_.:\[\]-]{1,255}$")


class Ros2Error(ValueError):
    """A ROS 2 bridge setting is invalid or the bridge cannot start; the message says what to change."""


# --- names -------------------------------------------------------------------------------------------------


def ros_name_token(device_id: str) -> str:
    """A device id as one ROS name token: ASCII letters, digits and '_', not starting with a digit.

    `arm-001` -> `arm_001`, `7th.arm` -> `_7th_arm`. Two ids can map to one token (`arm-1`, `arm_1`); the
    bridge publishes the first arm it sees on a topic and refuses the second, with an error naming both.
    """
    token = _NAME_TOKEN_BAD.sub("_", device_id)
    if not token or token[0].isdigit():
        token = "_" + token
    return token


def resolve_topic(pattern: str, device_id: str) -> str:
    """The ROS topic an arm publishes on: the pattern with `{arm}` replaced by the device's name token."""
    return pattern.replace(ARM_PLACEHOLDER, ros_name_token(device_id))


def dds_topic_name(ros_topic: str) -> str:
    """ROS topic `/arm_001/joint_states` -> DDS topic `rt/arm_001/joint_states`."""
    return DDS_TOPIC_PREFIX + ros_topic


def validate_topic_pattern(pattern: str) -> str:
    """Refuse a pattern that cannot become a valid absolute ROS topic; returns it unchanged."""
    sample = pattern.replace(ARM_PLACEHOLDER, "arm_001")
    if "{" in sample or "}" in sample:
        raise Ros2Error(
            f"ros2.topic = {pattern!r}: the only placeholder is {ARM_PLACEHOLDER} (the device id as a ROS "
            'name); e.g. topic = "/{arm}/joint_states", or a fixed "/joint_states" for one arm'
        )
    if not _TOPIC_RE.match(sample):
        raise Ros2Error(
            f"ros2.topic = {pattern!r} is not an absolute ROS topic name: it must start with '/', hold "
            "tokens of letters, digits and '_' that do not start with a digit, separated by single '/', "
            "and not end with '/'; e.g. topic = \"/{arm}/joint_states\""
        )
    if len(dds_topic_name(sample)) > 200:
        raise Ros2Error(f"ros2.topic = {pattern!r} is too long for a DDS topic name; shorten it")
    return pattern


def joint_name_map(spec: Sequence[str]) -> tuple[str, ...]:
    """ROS joint names in the edge's joint order, from a preset name alone or six names.

    `("so_arm101_usd",)` -> the preset; `("j1", ..., "j6")` -> those names for shoulder_pan..gripper.
    """
    spec = tuple(spec)
    if len(spec) == 1 and spec[0] in JOINT_NAME_PRESETS:
        return JOINT_NAME_PRESETS[spec[0]]
    n = len(so101.JOINT_NAMES)
    if len(spec) != n:
        raise Ros2Error(
            f"ros2.joint_names = {list(spec)!r} must be one preset ({', '.join(JOINT_NAME_PRESETS)}) or "
            f"{n} names for {', '.join(so101.JOINT_NAMES)} in that order; e.g. joint_names = "
            '["so_arm101_usd"] for the community SO-ARM101 USD in Isaac Sim'
        )
    for name in spec:
        if not name or not name.isprintable() or name != name.strip():
            raise Ros2Error(
                f"ros2.joint_names holds {name!r}; a joint name must be non-empty printable text without "
                "surrounding spaces (it must equal the joint's name in the URDF or USD)"
            )
    if len(set(spec)) != n:
        raise Ros2Error(
            f"ros2.joint_names = {list(spec)!r} names a joint twice; give each joint its own name"
        )
    return spec


# --- settings ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Ros2Settings:
    """What the bridge publishes and how it finds its peers (the agent config's [ros2] section)."""

    enabled: bool = False
    # `{arm}` is the device id as a ROS name; a fixed topic ("/joint_states") suits a single arm only.
    topic: str = DEFAULT_TOPIC
    # One preset name (JOINT_NAME_PRESETS) or six names in the edge's joint order.
    joint_names: tuple[str, ...] = ("so101",)
    # -1: ROS_DOMAIN_ID from the environment, else 0 (as every ROS 2 node does).
    domain_id: int = -1
    frame_id: str = ""
    # Servo speeds in `velocity` when every joint reports one. Isaac Sim's articulation controller applies
    # velocity targets too, which fights the position targets: the Isaac recipe turns this off.
    velocity: bool = True
    # Network interface (name or address) DDS uses; empty: Cyclone picks one. EC2: the ENA device.
    interface: str = ""
    # Unicast discovery peers (addresses or host names), for networks without multicast such as EC2.
    peers: tuple[str, ...] = ()
    # About one second of a 100-arm fleet at 10 Hz: a live view wants the present, not a replay of a stall.
    max_pending: int = 1_000

    def __post_init__(self) -> None:
        validate_topic_pattern(self.topic)
        joint_name_map(self.joint_names)
        if not (self.domain_id == -1 or 0 <= self.domain_id <= DOMAIN_ID_MAX):
            raise Ros2Error(
                f"ros2.domain_id = {self.domain_id} is outside 0..{DOMAIN_ID_MAX}; use the ROS_DOMAIN_ID of "
                "the ROS 2 side, or -1 to take ROS_DOMAIN_ID from the environment"
            )
        if self.interface and not _IFACE_RE.match(self.interface):
            raise Ros2Error(
                f"ros2.interface = {self.interface!r} is not an interface name or address; e.g. "
                'interface = "ens5" (ip -br addr lists them) or leave it empty'
            )
        for peer in self.peers:
            if not _PEER_RE.match(peer):
                raise Ros2Error(
                    f"ros2.peers holds {peer!r}, which is not a host name or address; e.g. peers = "
                    '["10.0.1.23"] (the private address of the machine running the ROS 2 side)'
                )
        if not self.frame_id.isprintable():
            raise Ros2Error(f"ros2.frame_id = {self.frame_id!r} must be printable text, e.g. base_link")
        if self.max_pending < 1:
            raise Ros2Error(f"ros2.max_pending = {self.max_pending} must be at least 1")

    @property
    def fixed_topic(self) -> bool:
        """True when every arm would land on the same topic: one arm only."""
        return ARM_PLACEHOLDER not in self.topic

    @property
    def ros_joint_names(self) -> tuple[str, ...]:
        return joint_name_map(self.joint_names)

    def effective_domain_id(self, environ: Mapping[str, str] | None = None) -> int:
        """The configured domain, or ROS_DOMAIN_ID like any ROS 2 node (0 when unset)."""
        if self.domain_id != -1:
            return self.domain_id
        env = os.environ if environ is None else environ
        text = env.get("ROS_DOMAIN_ID", "").strip()
        if not text:
            return 0
        if not text.isdigit() or int(text) > DOMAIN_ID_MAX:
            raise Ros2Error(
                f"ROS_DOMAIN_ID={text!r} is not a domain id 0..{DOMAIN_ID_MAX}; fix the environment or set "
                "ros2.domain_id"
            )
        return int(text)


# --- type hash (RIHS01, REP 2011) ---------------------------------------------------------------------------

# type_description_interfaces/msg/FieldType: 1 = nested type, 6 int32, 7 uint32, 11 float64 ("double"),
# 17 string; an unbounded sequence of a type adds 144.
FIELD_NESTED = 1
FIELD_INT32 = 6
FIELD_UINT32 = 7
FIELD_FLOAT64 = 11
FIELD_STRING = 17
UNBOUNDED_SEQUENCE = 144

# name, field type id, nested type name ("" for primitives): the .msg files of Jazzy.
MessageFields = tuple[tuple[str, int, str], ...]
INTERFACES: dict[str, MessageFields] = {
    "builtin_interfaces/msg/Time": (("sec", FIELD_INT32, ""), ("nanosec", FIELD_UINT32, "")),
    "std_msgs/msg/Header": (
        ("stamp", FIELD_NESTED, "builtin_interfaces/msg/Time"),
        ("frame_id", FIELD_STRING, ""),
    ),
    ROS_TYPE_NAME: (
        ("header", FIELD_NESTED, "std_msgs/msg/Header"),
        ("name", FIELD_STRING + UNBOUNDED_SEQUENCE, ""),
        ("position", FIELD_FLOAT64 + UNBOUNDED_SEQUENCE, ""),
        ("velocity", FIELD_FLOAT64 + UNBOUNDED_SEQUENCE, ""),
        ("effort", FIELD_FLOAT64 + UNBOUNDED_SEQUENCE, ""),
    ),
}


def _individual_description(type_name: str) -> dict[str, Any]:
    return {
        "type_name": type_name,
        "fields": [
            {
                "name": name,
                "type": {
                    "type_id": type_id,
                    "capacity": 0,
                    "string_capacity": 0,
                    "nested_type_name": nested,
                },
            }
            for name, type_id, nested in INTERFACES[type_name]
        ],
    }


def type_description(type_name: str) -> dict[str, Any]:
    """The hashable TypeDescription of a message: itself plus every type it references, sorted by name."""
    referenced: set[str] = set()
    pending = [type_name]
    while pending:
        for _name, _type_id, nested in INTERFACES[pending.pop()]:
            if nested and nested not in referenced:
                referenced.add(nested)
                pending.append(nested)
    return {
        "type_description": _individual_description(type_name),
        "referenced_type_descriptions": [_individual_description(n) for n in sorted(referenced)],
    }


def rihs01(type_name: str) -> str:
    """The RIHS01 type hash: SHA-256 of the type description as JSON with ', ' and ': ' separators, in field
    order, without default values (REP 2011; rosidl_generator_type_description computes it the same way)."""
    text = json.dumps(type_description(type_name), separators=(", ", ": "), ensure_ascii=True)
    return "RIHS01_" + hashlib.sha256(text.encode("utf-8")).hexdigest()


def type_hash_user_data(type_name: str = ROS_TYPE_NAME) -> bytes:
    """Writer USER_DATA as ROS 2 (rmw_dds_common) encodes it: `typehash=<RIHS01 string>;`."""
    return f"typehash={rihs01(type_name)};".encode("ascii")


# --- CDR ---------------------------------------------------------------------------------------------------

# Plain CDR, little-endian (XCDR1 "CDR_LE"), with the 4-byte encapsulation header ROS 2 uses. Alignment is
# relative to the end of that header.
CDR_LE_HEADER = b"\x00\x01\x00\x00"


def _pad(size: int, align: int) -> bytes:
    return b"\x00" * (-size % align)


def _cdr_string(out: bytearray, text: str) -> None:
    data = text.encode("utf-8")
    if b"\x00" in data:
        raise Ros2Error(f"{text!r} holds a NUL character, which a CDR string cannot carry")
    out += _pad(len(out), 4)
    out += struct.pack("<I", len(data) + 1)
    out += data + b"\x00"


def _cdr_float64_sequence(out: bytearray, values: Sequence[float]) -> None:
    out += _pad(len(out), 4)
    out += struct.pack("<I", len(values))
    if values:
        out += _pad(len(out), 8)
        out += struct.pack(f"<{len(values)}d", *values)


def stamp_from_ms(timestamp_ms: int) -> tuple[int, int]:
    """Epoch milliseconds -> builtin_interfaces/Time (sec int32, nanosec uint32)."""
    sec, ms = divmod(int(timestamp_ms), 1000)
    if not -(2**31) <= sec <= _INT32_MAX:
        raise Ros2Error(
            f"timestamp {timestamp_ms} ms is beyond builtin_interfaces/Time's int32 seconds (after "
            "2038-01-19); ROS 2 cannot carry it"
        )
    return sec, ms * 1_000_000


def encode_joint_state(
    sec: int,
    nanosec: int,
    frame_id: str,
    names: Sequence[str],
    position: Sequence[float],
    *,
    velocity: Sequence[float] = (),
    effort: Sequence[float] = (),
) -> bytes:
    """One `sensor_msgs/JointState` as a ROS 2 DDS payload (encapsulation header + CDR body)."""
    if not -(2**31) <= sec <= _INT32_MAX or not 0 <= nanosec < 2**32:
        raise Ros2Error(f"stamp ({sec}, {nanosec}) does not fit builtin_interfaces/Time (int32, uint32)")
    body = bytearray(struct.pack("<iI", sec, nanosec))
    _cdr_string(body, frame_id)
    body += _pad(len(body), 4)
    body += struct.pack("<I", len(names))
    for name in names:
        _cdr_string(body, name)
    _cdr_float64_sequence(body, position)
    _cdr_float64_sequence(body, velocity)
    _cdr_float64_sequence(body, effort)
    return CDR_LE_HEADER + bytes(body)


class JointStateEncoder:
    """Encodes one arm's JointState fast: everything but the stamp and the numbers is fixed per arm, so it is
    encoded once and a message is a few struct packs. cyclonedds' generic Python serializer builds the same
    bytes about 30 times slower (4 us against 134 us per message, timeit, best of 5, on the shared 2-core
    development machine), which at fleet rates would make the bridge cost more than the mirror."""

    def __init__(self, frame_id: str, names: Sequence[str]) -> None:
        self.names = tuple(names)
        fixed = bytearray(b"\x00" * 8)  # the stamp's place
        _cdr_string(fixed, frame_id)
        fixed += _pad(len(fixed), 4)
        fixed += struct.pack("<I", len(self.names))
        for name in self.names:
            _cdr_string(fixed, name)
        fixed += _pad(len(fixed), 4)  # the position count is 4-aligned
        self._fixed = bytes(fixed[8:])
        n = len(self.names)
        offset = len(fixed)
        # position: count, padding to 8, n doubles; the offset after it is the same for every message.
        self._pos_pad = _pad(offset + 4, 8)
        after_pos = offset + 4 + len(self._pos_pad) + 8 * n
        self._vel_pad = _pad(after_pos, 4)
        self._after_pos = after_pos + len(self._vel_pad)
        self._seq = struct.Struct(f"<I{len(self._pos_pad)}x{n}d")
        # velocity starts at a fixed offset too; with it, effort's count needs this padding.
        vel_pad = _pad(self._after_pos + 4, 8)
        self._vel_seq = struct.Struct(f"<I{len(vel_pad)}x{n}d")
        self._effort_after_vel = _pad(self._after_pos + self._vel_seq.size, 4) + b"\x00\x00\x00\x00"
        self._effort_after_none = _pad(self._after_pos + 4, 4) + b"\x00\x00\x00\x00"
        self._stamp = struct.Struct("<iI")
        self._n = n

    def encode(
        self,
        timestamp_ms: int,
        position: Sequence[float],
        velocity: Sequence[float] | None = None,
    ) -> bytes:
        """A payload for one sample: the edge stamp, positions, and velocities or none (effort empty)."""
        if len(position) != self._n:
            raise Ros2Error(f"{len(position)} positions for {self._n} joint names")
        sec, nanosec = stamp_from_ms(timestamp_ms)
        parts = [
            CDR_LE_HEADER,
            self._stamp.pack(sec, nanosec),
            self._fixed,
            self._seq.pack(self._n, *position),
            self._vel_pad,
        ]
        # effort stays empty: servo health has no physical torque.
        if velocity:
            if len(velocity) != self._n:
                raise Ros2Error(f"{len(velocity)} velocities for {self._n} joint names")
            parts += (self._vel_seq.pack(self._n, *velocity), self._effort_after_vel)
        else:
            parts += (b"\x00\x00\x00\x00", self._effort_after_none)
        return b"".join(parts)


def sample_velocities(sample: AppliedSample) -> list[float] | None:
    """Servo speeds (rad/s) in the edge's joint order, or None unless every joint reports one."""
    diagnostics = sample.telemetry.diagnostics
    out = []
    for joint in so101.JOINT_NAMES:
        diag = diagnostics.get(joint)
        value = diag.velocity_rad_s if diag is not None else None
        if value is None or not math.isfinite(value):
            return None
        out.append(value)
    return out


# --- Cyclone configuration ---------------------------------------------------------------------------------


def cyclone_config(settings: Ros2Settings, environ: Mapping[str, str] | None = None) -> str:
    """The Cyclone DDS configuration for the bridge's domain.

    A user's own CYCLONEDDS_URI (files or XML) is appended, so anything set there wins over ours.
    """
    # Here, not at the top: xml.sax.saxutils pulls in urllib.request and the email package (about 40 ms), and
    # the config loader imports this module on every cold start (docs/performance.md, "Footprint").
    from xml.sax.saxutils import quoteattr  # noqa: PLC0415

    general = ""
    if settings.interface:
        iface = settings.interface
        kind = "address" if _is_address(iface) else "name"
        general = f"<General><Interfaces><NetworkInterface {kind}={quoteattr(iface)}/></Interfaces></General>"
    discovery = ""
    if settings.peers:
        peers = "".join(f"<Peer address={quoteattr(p)}/>" for p in settings.peers)
        # With unicast peers, a participant index makes our unicast ports predictable for the peers' probes.
        discovery = (
            f"<Discovery><Peers>{peers}</Peers><ParticipantIndex>auto</ParticipantIndex>"
            "<MaxAutoParticipantIndex>100</MaxAutoParticipantIndex></Discovery>"
        )
    xml = (
        '<CycloneDDS><Domain Id="any">'
        f"{general}"
        f"<Compatibility><IgnoreTypeInformation>{EPROSIMA_VENDOR_ID}</IgnoreTypeInformation></Compatibility>"
        f"{discovery}"
        "</Domain></CycloneDDS>"
    )
    env = os.environ if environ is None else environ
    user = env.get("CYCLONEDDS_URI", "").strip()
    return f"{xml},{user}" if user else xml


def _is_address(interface: str) -> bool:
    # An address (IPv4 or IPv6) selects by address, anything else by interface name.
    return interface.replace(".", "").isdigit() or ":" in interface


def check_interface(interface: str) -> None:
    """Ros2Error when `interface` names a network interface, or an address, this machine does not have.

    Cyclone fails either with a "Non specific error" of its domain; this names the setting and what the
    machine has. An address is tried as the kernel would take it: a socket bound to it.
    """
    if not interface:
        return
    import socket  # noqa: PLC0415 - as in _resolve_ipv4

    if _is_address(interface):
        address = interface.strip("[]")
        family = socket.AF_INET6 if ":" in address else socket.AF_INET
        try:
            _not_a_group_or_any(address)
            with socket.socket(family, socket.SOCK_DGRAM) as probe:
                probe.bind((address, 0))
        except (OSError, ValueError) as exc:
            raise Ros2Error(
                f"ros2.interface = {interface!r} is not an address of this machine ({exc}); give one of its "
                "interfaces' addresses or names (ip -br addr lists them), or leave it empty"
            ) from exc
        return
    names = [name for _, name in socket.if_nameindex()]
    if interface not in names:
        raise Ros2Error(
            f"ros2.interface = {interface!r} is not a network interface of this machine (it has "
            f"{', '.join(names) or 'none'}; ip -br addr lists them with their addresses)"
        )


def _not_a_group_or_any(address: str) -> None:
    """ValueError for a multicast or the unspecified address: a socket binds to either (so the probe took
    them), but neither is one of the machine's, and Cyclone selects no interface by it."""
    import ipaddress  # noqa: PLC0415 - only when an address is given

    parsed = ipaddress.ip_address(address)
    if parsed.is_multicast:
        raise ValueError("a multicast group address, not an interface's")
    if parsed.is_unspecified:
        raise ValueError("the any address, which names no one interface")


def check_peers(peers: Sequence[str]) -> None:
    """Ros2Error naming the peer when Cyclone DDS could not use it: not an IPv4 address or a name that
    resolves to one, with an optional `:port`.

    Cyclone does not fail such a peer with an error: it aborts the whole process (SIGABRT), which took the
    agent down with one line on stderr. So each peer is resolved here first, before the domain starts.
    """
    for peer in peers:
        host, _, port = peer.rpartition(":") if peer.count(":") == 1 else (peer, "", "")
        if port and not (port.isdigit() and 0 < int(port) < 65536):
            raise Ros2Error(
                f'ros2.peers holds {peer!r}, whose port is not 1..65535; e.g. peers = ["10.0.1.23"] '
                "(the discovery port follows from the domain id, so none is needed)"
            )
        if ":" in host or host.startswith("["):
            raise Ros2Error(
                f"ros2.peers holds {peer!r}, an IPv6 address; the bridge's DDS runs over IPv4: give the "
                "ROS 2 machine's IPv4 address or a name that resolves to one"
            )
        _resolve_ipv4(peer, host)


def _resolve_ipv4(peer: str, host: str) -> None:
    # Here, not at the top: the config loader imports this module on every cold start, and only a bridge
    # with peers needs a resolver.
    import socket  # noqa: PLC0415

    try:
        socket.getaddrinfo(host, None, family=socket.AF_INET)
    except (OSError, UnicodeError) as exc:  # socket.gaierror is an OSError
        raise Ros2Error(
            f"ros2.peers holds {peer!r}, which does not resolve to an IPv4 address ({exc}); give the "
            'address of the ROS 2 machine, e.g. peers = ["10.0.1.23"]'
        ) from None


# --- the bridge --------------------------------------------------------------------------------------------


@dataclass
class _Arm:
    device_id: str
    topic: str
    writer: Any
    encoder: JointStateEncoder
    published: int = 0
    # header.stamp never runs backwards per arm (twin.output.edge_time): tf and bag players need it in order.
    edge: EdgeTime = field(default_factory=EdgeTime)


@dataclass
class BridgeCounters:
    arms: int = 0
    published: int = 0
    refused: int = 0
    refused_devices: set[str] = field(default_factory=set)


def check_available() -> None:
    """Ros2Error with the install hint when cyclonedds is not installed, without loading it: an agent whose
    mirrors are worker processes checks here before it connects, not when a worker opens the bridge."""
    try:
        found = importlib.util.find_spec("cyclonedds") is not None
    except (ImportError, ValueError):  # ValueError: blocked in sys.modules (None there)
        found = False
    if not found:
        raise Ros2Error(f"the ROS 2 bridge needs cyclonedds (not installed); {INSTALL_HINT}")


def preflight(settings: Ros2Settings) -> None:
    """Every check the bridge makes before DDS starts, without starting it: for an agent whose workers
    open their bridges only after it has connected, so a bad setting is told before it connects."""
    check_available()
    settings.effective_domain_id()
    check_interface(settings.interface)
    check_peers(settings.peers)


def _load_cyclonedds() -> Any:
    # Imported here, not at the top: cyclonedds is the optional ros2 extra, needed only when a bridge opens.
    try:
        from cyclonedds import core, domain, pub, qos, topic, util  # noqa: PLC0415
        from cyclonedds._clayer import ddspy_write  # noqa: PLC0415
    except ImportError as exc:
        raise Ros2Error(f"the ROS 2 bridge needs cyclonedds ({exc}); {INSTALL_HINT}") from None
    return core, domain, pub, qos, topic, util, ddspy_write


class Ros2Bridge:
    """The blocking half of the ROS 2 sink: one DDS participant, one writer per arm (made on its first
    sample). Runs on the `QueuedSink` thread only; `open_ros2_sink` builds both."""

    def __init__(self, settings: Ros2Settings) -> None:
        core, domain, pub, qos, topic, util, ddspy_write = _load_cyclonedds()
        from twin.output.ros2_idl import JointState_  # noqa: PLC0415 - imports cyclonedds

        self.settings = settings
        self.domain_id = settings.effective_domain_id()
        self._names = settings.ros_joint_names
        self._topic_cls = topic.Topic
        self._writer_cls = pub.DataWriter
        self._write = ddspy_write
        self._idl_type = JointState_
        self._velocity = settings.velocity
        check_interface(settings.interface)
        check_peers(settings.peers)
        config = cyclone_config(settings)
        try:
            # The domain object carries our configuration; it must outlive the participant.
            self._domain = domain.Domain(self.domain_id, config)
            self._participant = domain.DomainParticipant(self.domain_id)
        except core.DDSException as exc:
            raise Ros2Error(
                f"cannot start DDS on domain {self.domain_id} ({exc}); check ros2.interface, ros2.peers and "
                "CYCLONEDDS_URI"
            ) from exc
        policy = qos.Policy
        self._qos = qos.Qos(
            policy.Reliability.Reliable(util.duration(seconds=MAX_BLOCKING_S)),
            policy.Durability.Volatile,
            policy.History.KeepLast(HISTORY_DEPTH),
            policy.DataRepresentation(use_cdrv0_representation=True),
            policy.Userdata(type_hash_user_data()),
        )
        self._arms: dict[str, _Arm] = {}
        self._topics: dict[str, str] = {}
        self.counters = BridgeCounters()
        log.info(
            "ROS 2 bridge started",
            extra={
                "domain_id": self.domain_id,
                "topic": settings.topic,
                "joint_names": list(self._names),
                "interface": settings.interface or None,
                "peers": list(settings.peers),
            },
        )

    def _arm(self, device_id: str) -> _Arm:
        arm = self._arms.get(device_id)
        if arm is not None:
            return arm
        ros_topic = resolve_topic(self.settings.topic, device_id)
        owner = self._topics.get(ros_topic)
        if owner is not None:
            # Raised, not logged: the sink counts it as an error per sample not published, shows the reason in
            # /state (agent.sinks[].last_error) and logs it once.
            self.counters.refused += 1
            self.counters.refused_devices.add(device_id)
            fix = (
                'use a topic with {arm} (topic = "/{arm}/joint_states") for several arms'
                if self.settings.fixed_topic
                else "rename one of the devices so that their ROS names differ"
            )
            raise Ros2Error(f"{device_id} is not published: ROS 2 topic {ros_topic} carries {owner}; {fix}")
        dds_topic = self._topic_cls(self._participant, dds_topic_name(ros_topic), self._idl_type)
        writer = self._writer_cls(self._participant, dds_topic, qos=self._qos)
        arm = _Arm(device_id, ros_topic, writer, JointStateEncoder(self.settings.frame_id, self._names))
        self._arms[device_id] = arm
        self._topics[ros_topic] = device_id
        self.counters.arms += 1
        log.info("ROS 2 topic opened", extra={"device": device_id, "topic": ros_topic})
        return arm

    def handle_applied(self, sample: AppliedSample) -> None:
        arm = self._arm(sample.device_id)
        angles = sample.joint_angles
        position = [angles[joint] for joint in so101.JOINT_NAMES]
        velocity = sample_velocities(sample) if self._velocity else None
        stamp_ms = arm.edge.place(
            sample.timestamp_ms, sample.received_mono_s, device=sample.device_id, output="ros2"
        )
        payload = arm.encoder.encode(stamp_ms, position, velocity)
        # cyclonedds' DataWriter.write(sample) is sample.serialize() + this call; the payload above is the
        # same bytes (tests/test_ros2.py checks it against cyclonedds' and rosbags' serializers).
        ret = self._write(arm.writer._ref, payload)
        if ret < 0:
            raise Ros2Error(f"DDS write on {arm.topic} failed with code {ret}")
        arm.published += 1
        self.counters.published += 1

    def handle_rejected(self, sample: RejectedSample) -> None:
        """Rejected messages have no pose to publish."""

    def idle(self) -> None:
        """Nothing is buffered between samples."""

    def close(self) -> None:
        # cyclonedds deletes an entity when its last Python reference goes: writers first, then the
        # participant (remote readers see the writers leave), then the domain.
        self._arms.clear()
        self._topics.clear()
        self._participant = None
        self._domain = None
        log.info(
            "ROS 2 bridge stopped",
            extra={"published": self.counters.published, "arms": self.counters.arms},
        )

    def topics(self) -> dict[str, str]:
        """Device id -> ROS topic, for the arms published so far."""
        return {device: arm.topic for device, arm in self._arms.items()}


def open_ros2_sink(settings: Ros2Settings) -> QueuedSink:
    """The bridge behind its own thread and bounded queue. Raises Ros2Error (with the fix) when cyclonedds is
    missing or DDS cannot start, so the agent refuses to start instead of mirroring without ROS output."""
    bridge = Ros2Bridge(settings)
    # A 10 ms hand-off keeps a large fleet's samples from waking the bridge one by one; a ROS 2 follower sees
    # them at most that much later.
    return QueuedSink("ros2", bridge, max_pending=settings.max_pending, hand_off_s=0.01)
