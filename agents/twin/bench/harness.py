"""Process plumbing shared by the benchmark scenarios: the local rig (a private broker and the agent as a
child process, twin.rig.local), the agent's typed HTTP state, load processes, and CPU/RSS sampling with
psutil."""

from __future__ import annotations

import itertools
import json
import math
import statistics
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import psutil

from twin.core.lifetime import die_with_parent
from twin.core.topics import DEFAULT_TOPIC_PREFIX
from twin.rig.local import LocalRig, child_env
from twin.service.state import AgentState


class ProcessSampler:
    """Samples a process's RSS and CPU time in the background (psutil), from start() to stop(), together
    with its child processes' (a sharded agent's workers): CPU is the tree's, RSS both the tree's total and
    the largest single process's."""

    def __init__(self, pid: int, interval_s: float = 0.25) -> None:
        self.process = psutil.Process(pid)
        self.interval_s = interval_s
        self.max_rss = 0
        self.last_rss = 0
        self.max_process_rss = 0
        self.processes = 1
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._cpu0 = 0.0
        self._t0 = 0.0
        self.cpu_s = 0.0
        self.wall_s = 0.0

    def _tree(self) -> list[psutil.Process]:
        try:
            return [self.process, *self.process.children(recursive=True)]
        except psutil.Error:
            return [self.process]

    def _cpu(self) -> float:
        total = 0.0
        for process in self._tree():
            try:
                times = process.cpu_times()
            except psutil.Error:
                continue
            total += times.user + times.system
        return total

    def _sample_rss(self) -> None:
        sizes = []
        for process in self._tree():
            try:
                sizes.append(process.memory_info().rss)
            except psutil.Error:
                continue
        if not sizes:
            return
        self.last_rss = sum(sizes)
        self.processes = len(sizes)
        self.max_rss = max(self.max_rss, self.last_rss)
        self.max_process_rss = max(self.max_process_rss, *sizes)

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            if not self.process.is_running():
                return
            self._sample_rss()

    def start(self) -> ProcessSampler:
        psutil.cpu_percent(interval=None)  # starts the host-wide measurement that stop() reads
        self._cpu0 = self._cpu()
        self._t0 = time.monotonic()
        self._sample_rss()
        self._thread.start()
        return self

    def stop(self) -> dict[str, float | None]:
        self.cpu_s = self._cpu() - self._cpu0
        self.wall_s = time.monotonic() - self._t0
        self._stop.set()
        self._thread.join(2)
        host = psutil.cpu_percent(interval=None)
        return {
            # The whole host over the same interval (100 % = every core busy): publishers and broker share it.
            "host_cpu_percent": host,
            "host_cores": psutil.cpu_count(),
            # Percent of one core, the process and its children together (a sharded agent's workers).
            "cpu_percent": 100.0 * self.cpu_s / self.wall_s if self.wall_s else 0.0,
            "cpu_s": self.cpu_s,
            "processes": self.processes,
            "rss_max_mb": self.max_rss / 2**20,
            "rss_last_mb": self.last_rss / 2**20,
            "rss_max_process_mb": self.max_process_rss / 2**20,
        }


def get_state(base_url: str, timeout: float = 5.0) -> AgentState:
    """The agent's GET /state, parsed into its types."""
    with urllib.request.urlopen(f"{base_url}/state", timeout=timeout) as response:
        return AgentState.from_json(response.read())


@contextmanager
def running_agent(
    rig: LocalRig,
    *,
    max_devices: int = 4096,
    history: str | None = None,
    config_text: str = "",
    workers: int | None = None,
) -> Iterator[tuple[subprocess.Popen[bytes], str]]:
    """`twin run --devices '*'` as a child process on the rig's broker; yields (process, HTTP base URL).

    The fleet bound is raised to the benchmark's size: the default guards a production agent against a
    misbehaving publisher inventing device ids, which is not what is measured here. `history` turns the
    agent's telemetry history on at that URI (`--history`); `config_text` adds sections to its config (e.g.
    [ros2]). `workers` is `--workers` (None: the agent's default, one per core for the whole fleet).
    """
    extra = (
        "--log-level",
        "WARNING",
        *(("--history", history) if history else ()),
        *(("--workers", str(workers)) if workers is not None else ()),
    )
    with rig.agent_process(
        config_text=f"[telemetry]\nmax_devices = {max_devices}\n{config_text}",
        extra_args=extra,
    ) as (proc, base):
        try:
            yield proc, base
        except RuntimeError as exc:
            # A scenario that found the agent gone says so; the agent's own last word says why (a setting
            # it refused, say), and its log goes with the rig's directory.
            reason = exit_reason(rig, base) if proc.poll() is not None else ""
            if not reason:
                raise
            raise RuntimeError(f"{exc}: {reason}") from exc


def _agent_log_lines(rig: LocalRig, base_url: str) -> list[str]:
    """The lines of the log of the agent at `base_url` in the rig's directory (LocalRig.agent_log); none when
    there is no log."""
    try:
        return rig.agent_log(base_url.rsplit(":", 1)[-1]).read_text(errors="replace").splitlines()
    except OSError:
        return []


def exit_reason(rig: LocalRig, base_url: str) -> str:
    """What the agent at `base_url` printed when it exited (`twin run: ...`), from its log in the rig's
    directory (LocalRig.agent_log); "" when it printed none."""
    lines = _agent_log_lines(rig, base_url)
    starts = [i for i, line in enumerate(lines) if line.startswith("twin run: ")]
    if not starts:
        return ""
    # The message may run over lines (a parser's own text); the JSON log lines after it are not part of it.
    said = [lines[starts[-1]].removeprefix("twin run: ")]
    said.extend(itertools.takewhile(lambda line: not line.startswith("{"), lines[starts[-1] + 1 :]))
    return " ".join(line.strip() for line in said if line.strip())


def stop_figures(rig: LocalRig, base_url: str) -> dict[str, Any]:
    """What the stopped agent at `base_url` said it could not write, from its `agent stopped` line in its log
    (the line's `unwritten` and `workers_killed`); both empty when it logged no such line at the run's level
    (it logs one at INFO when everything was written)."""
    figures: dict[str, Any] = {"unwritten": {}, "workers_killed": []}
    for line in _agent_log_lines(rig, base_url):
        if not line.startswith("{"):
            continue
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if str(record.get("msg", "")).startswith("agent stopped"):
            figures = {
                "unwritten": record.get("unwritten", {}),
                "workers_killed": record.get("workers_killed", []),
            }
    return figures


def wait_subscribed(base_url: str, proc: subprocess.Popen[bytes], timeout: float = 30.0) -> float:
    """Poll /state until the agent's broker connection is subscribed; returns when (monotonic)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the agent exited with code {proc.returncode} before subscribing")
        try:
            if get_state(base_url, timeout=1.0).agent.broker.subscribes > 0:
                return time.monotonic()
        except (OSError, ValueError):
            pass
        time.sleep(0.02)
    raise RuntimeError(f"the agent did not subscribe within {timeout} s")


# The edge's default topic prefix; the load processes and the agent under test both use it.
PREFIX = DEFAULT_TOPIC_PREFIX


def start_publisher(
    url: str, first: int, count: int, rate: float, seconds: float, *, jitter_ms: float = 0.0
) -> subprocess.Popen:
    """A publisher process for arms first..first+count-1 (twin.bench.load), at `rate` Hz each, each
    message delayed 0..jitter_ms after its sample."""
    args = ["--url", url, "--first", str(first), "--count", str(count), "--rate", str(rate)]
    return load_process(
        "publish", *args, "--seconds", str(seconds), "--prefix", PREFIX, "--jitter-ms", str(jitter_ms)
    )


def load_process(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "twin.bench.load", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=child_env(),
        # A benchmark killed outright must not leave publishers loading the machine the next one measures.
        preexec_fn=die_with_parent(),  # noqa: PLW1509 - only prctl
    )


def last_json_line(text: str) -> dict[str, Any]:
    for raw in reversed(text.strip().splitlines()):
        line = raw.strip()
        if line.startswith("{"):
            return json.loads(line)
    raise RuntimeError(f"no JSON result in load process output: {text[-500:]!r}")


# One Python publisher process sustains well over 10,000 msg/s with pre-encoded payloads; beyond that the
# load is split so the publisher is not what limits the figure.
MSGS_PER_PUBLISHER = 10_000


def publishers(url: str, arms: int, rate: float, seconds: float, *, jitter_ms: float = 0.0) -> list[Any]:
    """Publisher processes for arms 1..`arms` at `rate` Hz each, enough of them that none is the limit."""
    count = max(1, min(4, math.ceil(arms * rate / MSGS_PER_PUBLISHER)))
    per = math.ceil(arms / count)
    procs = []
    for first in range(1, arms + 1, per):
        n = min(per, arms + 1 - first)
        procs.append(start_publisher(url, first, n, rate, seconds, jitter_ms=jitter_ms))
    return procs


def collect(procs: list[Any], timeout: float) -> dict[str, Any]:
    """Wait for the publishers; what they sent, failed to send and published late, summed."""
    sent = failures = late = 0
    elapsed = 0.0
    for proc in procs:
        out, err = proc.communicate(timeout=timeout)
        if proc.returncode != 0:
            raise RuntimeError(f"a publisher failed ({proc.returncode}): {err[-800:]}")
        result = last_json_line(out)
        sent += result["sent"]
        failures += result["publish_failures"]
        late += result["late_slots"]
        elapsed = max(elapsed, result["elapsed_s"])
    return {"sent": sent, "publish_failures": failures, "late_slots": late, "elapsed_s": elapsed}


def spread(values: Sequence[float]) -> dict[str, float | None]:
    """The median, smallest and largest of a scenario's repeated figures (each None when there are none)."""
    if not values:
        return {"median": None, "min": None, "max": None}
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def sum_devices(state: AgentState, counter: str) -> int:
    """A per-device counter summed over the fleet."""
    return sum(getattr(d.health.counters, counter) for d in state.devices.values())


def drained(base: str, timeout: float = 30.0) -> AgentState:
    """The state once the agent has handled what it already received: nothing queued for a mirror, no
    sink holding a sample, and neither the messages received nor those processed moved over half a second
    (a half-second stall alone, on a loaded host, is not the end). Bounded by `timeout`: a sink that cannot
    deliver (its store down) must not hang the benchmark; its figures then show it."""
    deadline = time.monotonic() + timeout
    state = get_state(base, timeout=30)
    while time.monotonic() < deadline:
        time.sleep(0.5)
        newer = get_state(base, timeout=30)
        agent = newer.agent
        still = (agent.broker.messages, agent.worker.processed) == (
            state.agent.broker.messages,
            state.agent.worker.processed,
        )
        if still and agent.mailbox.pending == 0 and all(s.pending == 0 for s in agent.sinks):
            return newer
        state = newer
    return state
