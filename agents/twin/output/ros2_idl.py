"""The ROS 2 JointState as cyclonedds IDL types (imported only by an open ROS 2 bridge: needs the ros2 extra).

The names are the DDS names rosidl generates (`<package>::msg::dds_::<Type>_`) and every field has its exact
IDL type: a bare Python `int` annotation would make a 64-bit field and shift every byte after it. The bridge
registers its topics with these types (discovery announces the type name); the payloads themselves come
from `twin.output.ros2.JointStateEncoder`, which tests prove byte-identical to `JointState_.serialize`.
"""

# No `from __future__ import annotations`: cyclonedds resolves the field types from the annotations
# themselves, and string annotations such as "sequence[str]" are not resolvable names in this module.
from dataclasses import dataclass

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float64, int32, sequence, uint32


@dataclass
class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):  # noqa: N801 - the DDS name
    sec: int32
    nanosec: uint32


@dataclass
class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):  # noqa: N801
    stamp: Time_
    frame_id: str


@dataclass
class JointState_(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):  # noqa: N801
    header: Header_
    name: sequence[str]
    position: sequence[float64]
    velocity: sequence[float64]
    effort: sequence[float64]
