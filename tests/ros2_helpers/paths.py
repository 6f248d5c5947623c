"""Where the ROS 2 tests find their pieces: the rclpy venvs `make setup` builds, and the listener script."""

from __future__ import annotations

from pathlib import Path

from twin.bench.netns import missing_prerequisites as namespace_missing

REPO = Path(__file__).resolve().parents[2]
LISTENER = Path(__file__).with_name("rclpy_listener.py")
# rclpy from the PyPI wheels, one venv per ROS 2 distribution (make setup builds both).
ROS_PYTHONS = {
    "jazzy": REPO / ".venv-ros2" / "bin" / "python",
    "kilted": REPO / ".venv-ros2-kilted" / "bin" / "python",
}


def missing_prerequisites() -> str | None:
    """Why the ROS 2 namespace tests cannot run here, with the fix; None when they can."""
    for python in ROS_PYTHONS.values():
        if not python.exists():
            return f"{python} is missing: run `make setup` (it builds the rclpy venvs)"
    return namespace_missing()
