"""Footprint: cold start to the first mirrored pose, and the agent's memory idle and with a large fleet.

    twin bench footprint [--arms 1000] [--seconds 8] [--model scene.xml] [--json]

`--model` runs the agent with `[twin] model` set to that MJCF file (made absolute here, as the agent's own
working directory is the rig's), so a custom model's cold start and memory are measured the same way as the
bundled scene's.
"""

from __future__ import annotations

import importlib.util
import json
import os
import struct
import subprocess
import time
import urllib.error
import urllib.request
from collections.abc import Sequence
from pathlib import Path
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


def _rss_mb(pid: int, workers: Sequence[int]) -> list[float]:
    """RSS (MB) of the agent process and of each of its worker processes (pids from /state), the agent first;
    the multiprocessing helpers (resource tracker, the workers' fork server) hold no agent state and are left
    out (`_fork_server_mb`)."""
    sizes = [psutil.Process(pid).memory_info().rss / 2**20]
    for worker in workers:
        try:
            sizes.append(psutil.Process(worker).memory_info().rss / 2**20)
        except psutil.Error:
            continue
    return sizes


def _fork_server_mb(pid: int, workers: Sequence[int]) -> float | None:
    """RSS (MB) of the workers' fork server, the workers' parent when that is not the agent (it imported the
    mirror once; most of its pages are shared with the workers forked from it, whose RSS counts them too);
    None without one."""
    for worker in workers:
        try:
            parent = psutil.Process(worker).ppid()
            if parent != pid:
                return psutil.Process(parent).memory_info().rss / 2**20
        except psutil.Error:
            continue
    return None


def model_path(model: str | Path | None) -> Path | None:
    """`model` as the absolute path the agent is given (None: the bundled scene)."""
    return None if model is None else Path(model).expanduser().resolve()


def model_config(model: str | Path | None) -> str:
    """The `[twin] model` section that runs the agent on `model` ("" for the bundled scene); RuntimeError
    (what `twin bench` reports as a scenario that could not run) when the file is not there, before any
    agent starts."""
    path = model_path(model)
    if path is None:
        return ""
    if not path.is_file():
        raise RuntimeError(
            f"--model {model}: no such file; give the path of an MJCF scene "
            "(robots/so101/scene.xml is the bundled one)"
        )
    # A JSON string is a TOML basic string for any path (quotes, backslashes and non-ASCII escaped alike).
    return f"[twin]\nmodel = {json.dumps(str(path))}\n"


def _cold_start_s(rig: LocalRig, config_text: str = "") -> float:
    """One arm is already publishing when the agent process is spawned; the clock runs from spawn to the
    first pose visible in /state (imports, model load, connect, first message)."""
    pub = start_publisher(rig.broker.url, 1, 1, 10.0, 60.0)
    try:
        time.sleep(1.0)
        started = time.monotonic()
        with running_agent(rig, config_text=config_text) as (proc, base):
            return _first_pose_s(base, proc, started)
    finally:
        pub.kill()
        pub.wait(10)


def _memory(
    rig: LocalRig, fleet: int, rate: float, fleet_seconds: float, config_text: str = ""
) -> dict[str, Any]:
    """RSS idle (connected, no traffic), then with `fleet` arms publishing at `rate` Hz: of each process (the
    agent, then its workers) and in all."""
    with running_agent(rig, config_text=config_text) as (proc, base):
        wait_subscribed(base, proc)
        time.sleep(2.0)
        workers = [w.pid for w in get_state(base, timeout=30).agent.workers if w.pid != proc.pid]
        idle = _rss_mb(proc.pid, workers)
        half = fleet // 2
        pubs = [start_publisher(rig.broker.url, first, half, rate, fleet_seconds) for first in (1, 1 + half)]
        peak = idle
        healthz_ms: list[float] = []
        started = time.monotonic()
        while any(p.poll() is None for p in pubs):
            now = _rss_mb(proc.pid, workers)
            peak = now if sum(now) > sum(peak) else peak
            if time.monotonic() - started > fleet_seconds / 2 and len(healthz_ms) < HEALTHZ_CALLS:
                healthz_ms.append(_healthz_ms(base))
            time.sleep(0.25)
        time.sleep(1.0)
        state = get_state(base, timeout=30)
        at_fleet = _rss_mb(proc.pid, workers)
        fork_server = _fork_server_mb(proc.pid, workers)
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
        "rss_fork_server_mb": fork_server,
        "healthz_ms_at_fleet": healthz_ms,
    }


# /healthz calls timed in the second half of the fleet's publishing (health checks come often, whatever the
# fleet's size: docs/http-api.md).
HEALTHZ_CALLS = 4


def _healthz_ms(base: str) -> float:
    """Milliseconds of one GET /healthz (200 or 503 alike: the answer's time is what is measured)."""
    started = time.perf_counter()
    try:
        with urllib.request.urlopen(f"{base}/healthz", timeout=30) as response:
            response.read()
    except urllib.error.HTTPError as err:
        err.read()
    return (time.perf_counter() - started) * 1000.0


# Modules an agent's start imports, one per kind of install: the agent's own package (editable in a checkout),
# and a few of the largest it imports from site-packages.
BYTECODE_PROBES = ("twin.service.mirror", "numpy", "msgspec", "OpenGL")


def bytecode_cached(modules: Sequence[str] = BYTECODE_PROBES) -> dict[str, bool]:
    """Whether each module has bytecode Python would use (its __pycache__ file, made from the source as it is
    now). Without it every process compiles the module at its start; where PYTHONDONTWRITEBYTECODE is set it
    is never written, and a cold start measures the compiling (docs/cost-per-message.md, "Bytecode")."""
    return {name: _has_bytecode(name) for name in modules}


def _has_bytecode(module: str) -> bool:
    try:
        spec = importlib.util.find_spec(module)
    except (ImportError, ValueError):
        return False
    origin = spec.origin if spec is not None else None
    if not origin or not origin.endswith(".py"):
        return False
    try:
        source = os.stat(origin)
        with open(importlib.util.cache_from_source(origin), "rb") as pyc:
            header = pyc.read(16)
    except OSError:
        return False
    # PEP 552: magic, flags (0: checked against the source's mtime and size), mtime, size.
    magic, flags, mtime, size = header[:4], *struct.unpack("<3I", header[4:16].ljust(12, b"\0"))
    return (
        magic == importlib.util.MAGIC_NUMBER
        and flags == 0
        and mtime == int(source.st_mtime) & 0xFFFFFFFF
        and size == source.st_size & 0xFFFFFFFF
    )


def run(
    *, fleet: int = 1000, rate: float = 10.0, fleet_seconds: float = 8.0, model: str | Path | None = None
) -> dict[str, Any]:
    """The cold start and the memory of an agent on the bundled scene, or on `model` (an MJCF file)."""
    config_text = model_config(model)
    cached = bytecode_cached()
    with LocalRig() as rig:
        cold = _cold_start_s(rig, config_text)
        memory = _memory(rig, fleet, rate, fleet_seconds, config_text)
    return {
        "scenario": "footprint",
        "model": str(path) if (path := model_path(model)) is not None else None,
        "cold_start_to_first_pose_s": cold,
        "bytecode_cached": cached,
        **memory,
    }
