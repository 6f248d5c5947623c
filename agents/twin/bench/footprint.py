"""Footprint: cold start to the first mirrored pose, and the agent's memory idle and with a large fleet."""

from __future__ import annotations

import subprocess
import time
from typing import Any

import psutil

from twin.bench.harness import get_state, running_agent, start_publisher, wait_subscribed
from twin.rig.local import LocalRig
from twin.service.state import AgentState


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


def _rss_mb(pid: int) -> list[float]:
    """RSS (MB) of the agent process and of each of its workers (a sharded agent's), the agent first; the
    multiprocessing resource tracker, which holds no agent state, is left out."""
    process = psutil.Process(pid)
    sizes = [process.memory_info().rss / 2**20]
    for child in process.children(recursive=True):
        try:
            if any("resource_tracker" in part for part in child.cmdline()):
                continue
            sizes.append(child.memory_info().rss / 2**20)
        except psutil.Error:
            continue
    return sizes


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
    """RSS idle (connected, no traffic), then with `fleet` arms publishing at `rate` Hz: of each process (the
    agent, then its workers) and in all."""
    with running_agent(rig) as (proc, base):
        wait_subscribed(base, proc)
        time.sleep(2.0)
        idle = _rss_mb(proc.pid)
        half = fleet // 2
        pubs = [start_publisher(rig.broker.url, first, half, rate, fleet_seconds) for first in (1, 1 + half)]
        peak = idle
        while any(p.poll() is None for p in pubs):
            now = _rss_mb(proc.pid)
            peak = now if sum(now) > sum(peak) else peak
            time.sleep(0.25)
        time.sleep(1.0)
        state = get_state(base, timeout=30)
        at_fleet = _rss_mb(proc.pid)
    return {
        "processes": len(at_fleet),
        "workers": len(state.agent.workers) or 1,
        "rss_idle_mb": sum(idle),
        "rss_idle_per_process_mb": idle,
        "fleet_arms": fleet,
        "fleet_devices_mirrored": _mirrored(state),
        "rss_at_fleet_mb": sum(at_fleet),
        "rss_at_fleet_per_process_mb": at_fleet,
        "rss_at_fleet_largest_process_mb": max(at_fleet),
        "rss_peak_mb": max(sum(peak), sum(at_fleet)),
    }


def run(*, fleet: int = 1000, rate: float = 10.0, fleet_seconds: float = 8.0) -> dict[str, Any]:
    with LocalRig() as rig:
        cold = _cold_start_s(rig)
        memory = _memory(rig, fleet, rate, fleet_seconds)
    return {"scenario": "footprint", "cold_start_to_first_pose_s": cold, **memory}
