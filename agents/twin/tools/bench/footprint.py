"""Footprint: cold start to the first mirrored pose, and the agent's memory idle and with a large fleet."""

from __future__ import annotations

import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil

from twin.tools.bench.harness import get_json, private_broker, running_agent, start_publisher, wait_subscribed


def _first_pose_s(base: str, proc: subprocess.Popen, started: float, timeout: float = 60.0) -> float:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the agent exited with code {proc.returncode}")
        try:
            state = get_json(f"{base}/state", timeout=1.0)
            if any(d.get("joints_rad") for d in state["devices"].values()):
                return time.monotonic() - started
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.005)
    raise RuntimeError(f"no mirrored pose within {timeout} s")


def _rss_mb(pid: int) -> float:
    return psutil.Process(pid).memory_info().rss / 2**20


def run(*, fleet: int = 1000, rate: float = 10.0, fleet_seconds: float = 8.0) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="twin-bench-") as tmp:
        workdir = Path(tmp)
        with private_broker(workdir / "broker") as broker:
            # Cold start: one arm is already publishing when the agent process is spawned; the clock runs
            # from spawn to the first pose visible in /state (imports, model load, connect, first message).
            pub = start_publisher(broker.url, 1, 1, 10.0, 60.0)
            try:
                time.sleep(1.0)
                started = time.monotonic()
                with running_agent(broker.url, log_dir=workdir) as (proc, base):
                    cold = _first_pose_s(base, proc, started)
            finally:
                pub.kill()
                pub.wait(10)

            with running_agent(broker.url, log_dir=workdir) as (proc, base):
                wait_subscribed(base, proc)
                time.sleep(2.0)
                idle = _rss_mb(proc.pid)
                half = fleet // 2
                pubs = [
                    start_publisher(broker.url, first, half, rate, fleet_seconds) for first in (1, 1 + half)
                ]
                peak = idle
                while any(p.poll() is None for p in pubs):
                    peak = max(peak, _rss_mb(proc.pid))
                    time.sleep(0.25)
                time.sleep(1.0)
                state = get_json(f"{base}/state", timeout=30)
                at_fleet = _rss_mb(proc.pid)
                peak = max(peak, at_fleet)
                devices = sum(1 for d in state["devices"].values() if d.get("joints_rad"))
    return {
        "scenario": "footprint",
        "cold_start_to_first_pose_s": cold,
        "rss_idle_mb": idle,
        "fleet_arms": fleet,
        "fleet_devices_mirrored": devices,
        "rss_at_fleet_mb": at_fleet,
        "rss_peak_mb": peak,
    }
