"""Footprint: cold start to the first mirrored pose, and the agent's memory idle and with a large fleet."""

from __future__ import annotations

import subprocess
import time
from typing import Any

import psutil

from twin.service.state import AgentState
from twin.tools.bench.harness import get_state, running_agent, start_publisher, wait_subscribed
from twin.tools.rig import LocalRig


def _mirrored(state: AgentState) -> int:
    return sum(1 for d in state.devices.values() if d.joints_rad)


def _first_pose_s(base: str, proc: subprocess.Popen[bytes], started: float, timeout: float = 60.0) -> float:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the agent exited with code {proc.returncode}")
        try:
            if _mirrored(get_state(base, timeout=1.0)):
                return time.monotonic() - started
        except (OSError, ValueError):
            pass
        time.sleep(0.005)
    raise RuntimeError(f"no mirrored pose within {timeout} s")


def _rss_mb(pid: int) -> float:
    return psutil.Process(pid).memory_info().rss / 2**20


def _cold_start_s(rig: LocalRig) -> float:
    """One arm is already publishing when the agent process is spawned; the clock runs from spawn to the
    first pose visible in /state (imports, model load, connect, first message)."""
    pub = start_publisher(rig.broker.url, 1, 1, 10.0, 60.0)
    try:
        time.sleep(1.0)
        started = time.monotonic()
        with running_agent(rig) as (proc, base):
            return _first_pose_s(base, proc, started)
    finally:
        pub.kill()
        pub.wait(10)


def _memory(rig: LocalRig, fleet: int, rate: float, fleet_seconds: float) -> dict[str, Any]:
    """RSS idle (connected, no traffic), then with `fleet` arms publishing at `rate` Hz."""
    with running_agent(rig) as (proc, base):
        wait_subscribed(base, proc)
        time.sleep(2.0)
        idle = _rss_mb(proc.pid)
        half = fleet // 2
        pubs = [start_publisher(rig.broker.url, first, half, rate, fleet_seconds) for first in (1, 1 + half)]
        peak = idle
        while any(p.poll() is None for p in pubs):
            peak = max(peak, _rss_mb(proc.pid))
            time.sleep(0.25)
        time.sleep(1.0)
        state = get_state(base, timeout=30)
        at_fleet = _rss_mb(proc.pid)
    return {
        "rss_idle_mb": idle,
        "fleet_arms": fleet,
        "fleet_devices_mirrored": _mirrored(state),
        "rss_at_fleet_mb": at_fleet,
        "rss_peak_mb": max(peak, at_fleet),
    }


def run(*, fleet: int = 1000, rate: float = 10.0, fleet_seconds: float = 8.0) -> dict[str, Any]:
    with LocalRig() as rig:
        cold = _cold_start_s(rig)
        memory = _memory(rig, fleet, rate, fleet_seconds)
    return {"scenario": "footprint", "cold_start_to_first_pose_s": cold, **memory}
