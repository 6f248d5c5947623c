"""Run a command in a fresh network namespace that has loopback only, so DDS discovery (multicast) never
reaches the machine's real interfaces. Needs root or CAP_SYS_ADMIN (`unshare -n`), as CI has."""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
# rclpy from the PyPI wheels, one venv per ROS 2 distribution (make setup builds both).
ROS_PYTHONS = {
    "jazzy": REPO / ".venv-ros2" / "bin" / "python",
    "kilted": REPO / ".venv-ros2-kilted" / "bin" / "python",
}
LISTENER = Path(__file__).with_name("rclpy_listener.py")

# lo is down in a new namespace and has no multicast route: DDS discovery (SPDP) multicasts to 239.255.0.1.
_SETUP = 'ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo && exec "$@"'


def missing_prerequisites() -> str | None:
    """Why the loopback-namespace tests cannot run here, with the fix; None when they can."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare and ip are needed (util-linux, iproute2)"
    for python in ROS_PYTHONS.values():
        if not python.exists():
            return f"{python} is missing: run `make setup` (it builds the rclpy venvs)"
    probe = subprocess.run(
        ["unshare", "-n", "sh", "-c", "ip link set lo up"], capture_output=True, text=True, check=False
    )
    if probe.returncode != 0:
        return f"unshare -n failed ({probe.stderr.strip()}); these tests need root or CAP_SYS_ADMIN"
    return None


def run_in_loopback_namespace(
    argv: Sequence[str], *, env: Mapping[str, str] | None = None, timeout: float = 120.0
) -> subprocess.CompletedProcess[str]:
    """Run argv inside `unshare -n` with lo up and multicast routed over it; returns the finished process."""
    return subprocess.run(
        ["unshare", "-n", "sh", "-c", _SETUP, "netns", *argv],
        env=dict(env) if env is not None else None,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        cwd=REPO,
    )
