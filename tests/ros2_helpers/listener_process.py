"""Start the rclpy listener (rclpy_listener.py, in an rclpy venv) and wait until it has subscribed.

Shared by the drivers, which run as scripts inside the loopback-only namespace (this folder is their
sys.path[0]).
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path


def start_listener(
    ros_python: str, listener: str, topics: Sequence[str], report: Path, options: Sequence[str]
) -> subprocess.Popen[str] | None:
    """The listener process once it printed "ready", or None (after saying so on stderr) if it did not."""
    proc = subprocess.Popen(
        [ros_python, listener, "--topics", ",".join(topics), *options, "--out", str(report)],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    if proc.stdout.readline().strip() != "ready":
        proc.wait(10)
        sys.stderr.write("the rclpy listener did not start\n")
        return None
    return proc
