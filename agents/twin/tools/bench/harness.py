"""Process plumbing shared by the benchmark scenarios: a private broker, the agent as a child process, its
HTTP state, and CPU/RSS sampling of a process tree with psutil."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
import urllib.request
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import psutil

from twin.tools.mosquitto import MosquittoBroker, free_port


def child_env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def twin_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "twin.cli", *args]


class ProcessSampler:
    """Samples a process's RSS and CPU time in the background (psutil), from start() to stop()."""

    def __init__(self, pid: int, interval_s: float = 0.25) -> None:
        self.process = psutil.Process(pid)
        self.interval_s = interval_s
        self.max_rss = 0
        self.last_rss = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._cpu0 = 0.0
        self._t0 = 0.0
        self.cpu_s = 0.0
        self.wall_s = 0.0

    def _cpu(self) -> float:
        times = self.process.cpu_times()
        return times.user + times.system

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.last_rss = self.process.memory_info().rss
            except psutil.Error:
                return
            self.max_rss = max(self.max_rss, self.last_rss)

    def start(self) -> ProcessSampler:
        psutil.cpu_percent(interval=None)  # starts the host-wide measurement that stop() reads
        self._cpu0 = self._cpu()
        self._t0 = time.monotonic()
        self.last_rss = self.process.memory_info().rss
        self.max_rss = self.last_rss
        self._thread.start()
        return self

    def stop(self) -> dict[str, float]:
        self.cpu_s = self._cpu() - self._cpu0
        self.wall_s = time.monotonic() - self._t0
        self._stop.set()
        self._thread.join(2)
        host = psutil.cpu_percent(interval=None)
        return {
            # The whole host over the same interval (100 % = every core busy): publishers and broker share it.
            "host_cpu_percent": host,
            "host_cores": psutil.cpu_count(),
            "cpu_percent": 100.0 * self.cpu_s / self.wall_s if self.wall_s else 0.0,
            "cpu_s": self.cpu_s,
            "rss_max_mb": self.max_rss / 2**20,
            "rss_last_mb": self.last_rss / 2**20,
        }


def get_json(url: str, timeout: float = 5.0) -> dict[str, Any]:
    with urllib.request.urlopen(url, timeout=timeout) as response:
        return json.loads(response.read())


@contextmanager
def running_agent(
    broker_url: str,
    *,
    devices: str = "*",
    max_devices: int = 4096,
    extra: tuple[str, ...] = (),
    log_dir: Path,
):
    """`twin run` as a child process; yields (Popen, http base URL). Stopped with SIGTERM on exit.

    The fleet bound is raised to the benchmark's size: the default guards a production agent against a
    misbehaving publisher inventing device ids, which is not what is measured here.
    """
    port = free_port()
    log_dir.mkdir(parents=True, exist_ok=True)
    config = log_dir / f"agent-{port}.toml"
    config.write_text(f"[telemetry]\nmax_devices = {max_devices}\n")
    log_file = (log_dir / f"agent-{port}.log").open("wb")
    cmd = twin_command(
        "run",
        "--config",
        str(config),
        "--broker",
        broker_url,
        "--devices",
        devices,
        "--http",
        f"127.0.0.1:{port}",
        "--log-level",
        "WARNING",
        *extra,
    )
    proc = subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT, env=child_env())
    try:
        yield proc, f"http://127.0.0.1:{port}"
    finally:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        log_file.close()


def wait_subscribed(base_url: str, proc: subprocess.Popen, timeout: float = 30.0) -> float:
    """Poll /state until the agent's broker connection is subscribed; returns when (monotonic)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the agent exited with code {proc.returncode} before subscribing")
        try:
            state = get_json(f"{base_url}/state", timeout=1.0)
            if state["agent"]["broker"]["subscribes"] > 0:
                return time.monotonic()
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.02)
    raise RuntimeError(f"the agent did not subscribe within {timeout} s")


@contextmanager
def private_broker(workdir: Path):
    broker = MosquittoBroker(workdir=workdir)
    broker.start()
    try:
        yield broker
    finally:
        broker.close()


# The edge's default topic prefix; the load processes and the agent under test both use it.
PREFIX = "dt/lerobot"


def start_publisher(url: str, first: int, count: int, rate: float, seconds: float) -> subprocess.Popen:
    """A publisher process for arms first..first+count-1 (twin.tools.bench.load), at `rate` Hz each."""
    args = ["--url", url, "--first", str(first), "--count", str(count), "--rate", str(rate)]
    return load_process("publish", *args, "--seconds", str(seconds), "--prefix", PREFIX)


def load_process(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "twin.tools.bench.load", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=child_env(),
    )


def last_json_line(text: str) -> dict[str, Any]:
    for raw in reversed(text.strip().splitlines()):
        line = raw.strip()
        if line.startswith("{"):
            return json.loads(line)
    raise RuntimeError(f"no JSON result in load process output: {text[-500:]!r}")
