"""SO-101 follower constants: joint names and ranges shared by the decoder, the twin and the viewer.

Figures come from the upstream models that docs/robot-model.md names (TheRobotStudio/SO-ARM100
so101_new_calib.xml, google-deepmind/mujoco_menagerie robotstudio_so101/so101.xml). The names match the edge
telemetry exactly.
"""

from __future__ import annotations

import math

# Motor ids 1..6 in this order, as the edge publishes them.
JOINT_NAMES: tuple[str, ...] = (
    "shoulder_pan",
    "shoulder_lift",
    "elbow_flex",
    "wrist_flex",
    "wrist_roll",
    "gripper",
)
ARM_JOINTS: tuple[str, ...] = JOINT_NAMES[:5]
# The bus id of each joint's servo (LeRobot's SO-101 follower sets them 1..6 at motor setup, and its
# calibration file records them): what a person at the arm finds the servo by, so alarms name it too.
MOTOR_IDS: dict[str, int] = {name: i for i, name in enumerate(JOINT_NAMES, start=1)}
GRIPPER = "gripper"

# Joint ranges of the "new calibration" model, radians. LeRobot degrees map onto these 1:1 (zero = middle of
# the calibrated range). wrist_roll follows the upstream joint range (= the menagerie ctrlrange), which is
# asymmetric; elbow_flex carries upstream's 5-degree calibration margin.
JOINT_RANGES_RAD: dict[str, tuple[float, float]] = {
    "shoulder_pan": (-1.91986, 1.91986),
    "shoulder_lift": (-1.7453293, 1.7453293),
    "elbow_flex": (-1.69, 1.69),
    "wrist_flex": (-1.658063, 1.658063),
    "wrist_roll": (-2.7438473, 2.8412063),
    "gripper": (-0.174533, 1.7453292),
}

# Feetech STS3215: 12-bit magnetic encoder, 4096 steps per turn, position mode reads 0..4095.
TICKS_PER_TURN = 4096
TICK_MAX = 4095
# LeRobot's half-turn homing makes the calibration pose read int(4095 / 2).
TICK_HOME = 2047

# Bodies of our MJCF, base to tip, and the tool-centre-point site at the gripper tip.
BODY_NAMES: tuple[str, ...] = (
    "base",
    "shoulder",
    "upper_arm",
    "lower_arm",
    "wrist",
    "gripper",
    "moving_jaw",
)
TCP_SITE = "tcp"
# MJCF geom groups: the part meshes people see, and the primitive boxes contacts use (hidden by default).
VISUAL_GROUP = 2
COLLISION_GROUP = 3

DEG = math.pi / 180.0


def servo_name(joint: str) -> str:
    """`joint`'s servo as a person at the arm finds it: "elbow_flex servo (motor id 3)"; a joint outside the
    SO-101's six keeps its name alone."""
    motor = MOTOR_IDS.get(joint)
    return f"{joint} servo" if motor is None else f"{joint} servo (motor id {motor})"
