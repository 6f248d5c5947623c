"""Cost: the agent's CPU per message, in units of `json.loads` of the same edge message, measured in one run.

An absolute figure (microseconds a message) moves two or three times between machines and between minutes
on a shared one; a ratio to a yardstick timed on the same cores at the same moment does not. So each run
starts a probe process that times `json.loads` of the edge's message (its CPU time, four times a second, all
through the run: twin.bench.load `loads-probe`), and divides the agent's CPU time per message by the probe's
median over the measured window.

One run: a private mosquitto, `twin run --devices '*'` as a child process (its defaults: one worker process
per core), N arms publishing at R Hz for S seconds (publisher processes writing to the broker's socket, as in
`twin bench throughput`). Over the window from just before the first message to the moment the agent has
gone quiet again, the CPU time of every process and thread of the agent is read from outside (psutil,
/proc; `/state` is read before and after the window, since answering it costs CPU too), and the mirrors'
own stage timers from `/state` (`agent.worker.stage_cpu_s`: CPU time of each worker thread's stages). The
totals (by process) are exact; the workers' stage timers are sampled: they time one batch in 16 on average
(and every batch of 128 messages or more) and scale what they time (twin.service.stagetiming), because the
thread CPU clock they read costs more than a small batch's decoding. So the workers' split between their
stages is an estimate, and `other` (the workers' CPU the timers do not cover) also takes its error. The
stages:

- receive: the awscrt event-loop threads of the receiving process (socket, MQTT, the callback into Python
  and the agent's routing of the message to its shard's queue);
- hand_over: the receiving process's sender threads (batches written to the workers' pipes) and the workers
  reading and unpacking them;
- decode, twin, health_alarms (health, latency, loss estimate, servo alarms), sinks: the worker threads' stage
  timers; sinks also counts the history writer's process and the worker processes' sink threads;
- other: the rest of the agent's CPU (the receiving process's other threads; the workers' control threads,
  garbage collector and idle wake-ups).

Reported per run: received and mirrored (applied to a twin), CPU per received and per mirrored message in
microseconds and in `json.loads` units, the stages in `json.loads` units per received message, the probe's
median and spread, internal latency, and the 1-minute load average before and after. With `runs` > 1 each
fleet size is run that many times and summarised (median, min, max).

    twin bench cost [--arms 100 1000 2000] [--seconds 20] [--runs 3] [--history] [--workers N] [--no-alarms]
                    [--json]
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil

from twin.bench.harness import (
    collect,
    drained,
    get_state,
    load_process,
    publishers,
    running_agent,
    spread,
    sum_devices,
    wait_subscribed,
)
from twin.rig.local import LocalRig
from twin.service.stagetiming import STAGE_SAMPLE_EVERY, STAGE_TIMED_FROM
from twin.service.state import AgentState

STAGES = ("receive", "hand_over", "decode", "twin", "health_alarms", "sinks", "other")
# The names awscrt gives its event-loop threads (aws-c-io), and the agent its senders (service.logs
# name_native_thread); its other threads (HTTP, supervisor, the pool's scaler) count as "other".
CRT_THREAD_PREFIX = "AwsEventLoop"
SENDER_THREAD_PREFIX = "twin-send-"


@dataclass(frozen=True)
class _Threads:
    """CPU seconds (user + system) of each thread of one process, by thread id, with the thread's name."""

    pid: int
    cpu: dict[int, tuple[str, float]]

    def total(self) -> float:
        return sum(cpu for _, cpu in self.cpu.values())


def _threads(pid: int) -> _Threads | None:
    try:
        process = psutil.Process(pid)
        threads = process.threads()
    except psutil.Error:
        return None
    cpu = {}
    for t in threads:
        try:
            name = Path(f"/proc/{pid}/task/{t.id}/comm").read_text().strip()
        except OSError:
            name = ""
        cpu[t.id] = (name, t.user_time + t.system_time)
    return _Threads(pid, cpu)


def _tree(pid: int) -> dict[int, _Threads]:
    """Every process of the agent (the receiving process and its children) with its threads' CPU."""
    pids = [pid]
    with contextlib.suppress(psutil.Error):
        pids += [c.pid for c in psutil.Process(pid).children(recursive=True)]
    out = {}
    for p in pids:
        threads = _threads(p)
        if threads is not None:
            out[p] = threads
    return out


def _delta(before: _Threads | None, after: _Threads | None) -> dict[int, tuple[str, float]]:
    """Per thread, its CPU over the window (threads that ended in it are lost: the agent's do not). A thread
    whose CPU went down is a new one under an ended one's id (ids are reused once they wrap at the host's
    pid_max, 32,768 on this machine), so all of its CPU is in the window."""
    if after is None:
        return {}
    old = before.cpu if before is not None else {}
    out = {}
    for tid, (name, cpu) in after.cpu.items():
        was = old.get(tid, ("", 0.0))[1]
        out[tid] = (name, cpu - was if cpu >= was else cpu)
    return out


def _quiet(pid: int, *, below: float = 0.05, step_s: float = 0.25, timeout_s: float = 15.0) -> None:
    """Wait until the agent's processes together use less than `below` of a core over `step_s`."""
    deadline = time.monotonic() + timeout_s
    last = _total(_tree(pid))
    while time.monotonic() < deadline:
        time.sleep(step_s)
        now = _total(_tree(pid))
        if now - last < below * step_s:
            return
        last = now


def _total(tree: dict[int, _Threads]) -> float:
    return sum(threads.total() for threads in tree.values())


def _stage_cpu(state: AgentState) -> dict[str, float]:
    return dict(state.agent.worker.stage_cpu_s)


def _split(
    before: dict[int, _Threads],
    after: dict[int, _Threads],
    *,
    receiving: int,
    workers: Iterable[int],
    history_pid: int | None,
    stages: dict[str, float],
) -> tuple[dict[str, float], dict[str, float]]:
    """(CPU seconds by process role, CPU seconds by stage) over the window."""
    roles = {"receiving_process": 0.0, "workers": 0.0, "history_writer": 0.0, "other_processes": 0.0}
    by_stage = dict.fromkeys(STAGES, 0.0)
    workers = set(workers)
    for pid in after:
        threads = _delta(before.get(pid), after.get(pid))
        total = sum(cpu for _, cpu in threads.values())
        if pid == receiving:
            roles["receiving_process"] += total
            # Each thread's CPU goes to one stage, summed thread by thread: `total - crt - senders` would
            # read a hair below zero (-4e-16) when the other threads used none in the window.
            for name, cpu in threads.values():
                if name.startswith(CRT_THREAD_PREFIX):
                    by_stage["receive"] += cpu
                elif name.startswith(SENDER_THREAD_PREFIX):
                    by_stage["hand_over"] += cpu
                else:
                    by_stage["other"] += cpu
        elif pid in workers:
            roles["workers"] += total
        elif pid == history_pid:
            roles["history_writer"] += total
            by_stage["sinks"] += total
        else:
            roles["other_processes"] += total
    # The workers' own timers split their CPU; what they do not cover is "other".
    timed = 0.0
    for stage, cpu in stages.items():
        key = stage if stage in by_stage else "other"
        by_stage[key] += cpu
        timed += cpu
    by_stage["other"] += max(0.0, roles["workers"] - timed) + roles["other_processes"]
    return roles, by_stage


def _probe_rounds(text: str) -> list[tuple[float, float]]:
    rounds = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line.startswith("{"):
            continue
        doc = json.loads(line)
        if "us" in doc:
            rounds.append((float(doc["at"]), float(doc["us"])))
    return rounds


def _spread(values: list[float]) -> dict[str, float | int | None]:
    """`spread`, and how many figures it rests on (the probe's rounds in a window vary with the load)."""
    return {**spread(values), "samples": len(values)}


@dataclass(frozen=True)
class _Window:
    """What one run saw of the agent at both ends of its window: /state and every thread's CPU time."""

    pid: int
    start: float
    end: float
    sent: int
    state0: AgentState
    state1: AgentState
    tree0: dict[int, _Threads]
    tree1: dict[int, _Threads]


def _start_probe(seconds: float) -> subprocess.Popen[str]:
    """The json.loads yardstick, running before the agent starts so it covers the whole window."""
    probe = load_process("loads-probe", "--seconds", str(seconds + 120))
    assert probe.stdout is not None
    if '"ready"' not in probe.stdout.readline():
        probe.kill()
        raise RuntimeError("the json.loads probe did not start")
    return probe


def _stop_probe(probe: subprocess.Popen[str]) -> str:
    """Stop the probe; its output, one line a round."""
    probe.terminate()
    out, _ = probe.communicate(timeout=30)
    return out


def _measure_window(
    rig: LocalRig,
    arms: int,
    rate: float,
    seconds: float,
    *,
    history: str | None,
    workers: int | None,
    alarms: bool = True,
) -> _Window:
    """Start the agent, publish the fleet's messages, and read the agent at both ends of the window."""
    config_text = "" if alarms else "[alarms]\nenabled = false\n"
    with running_agent(rig, history=history, workers=workers, config_text=config_text) as (proc, base):
        wait_subscribed(base, proc)
        state0 = get_state(base)
        tree0 = _tree(proc.pid)
        t0 = time.monotonic()
        pubs = publishers(rig.broker.url, arms, rate, seconds)
        sent = collect(pubs, timeout=seconds + 60)
        # The end of the window: once the agent has gone quiet (it has handled what it received), read
        # from outside; /state comes after, since answering it costs the agent CPU of its own.
        _quiet(proc.pid)
        tree1 = _tree(proc.pid)
        t1 = time.monotonic()
        state1 = drained(base)
        if proc.poll() is not None:
            raise RuntimeError(f"the agent exited during the run (code {proc.returncode})")
    return _Window(proc.pid, t0, t1, sent["sent"], state0, state1, tree0, tree1)


def _cost_per_message(window: _Window, loads: dict[str, float | int | None]) -> dict[str, Any]:
    """The agent's CPU over the window, by process role and by stage, per message and in json.loads units."""
    state0, state1 = window.state0, window.state1
    received = state1.agent.broker.messages - state0.agent.broker.messages
    mirrored = sum_devices(state1, "applied") - sum_devices(state0, "applied")
    stages = {k: v - _stage_cpu(state0).get(k, 0.0) for k, v in _stage_cpu(state1).items()}
    timed = state1.agent.worker.stage_timed_batches - state0.agent.worker.stage_timed_batches
    batches = state1.agent.worker.batches - state0.agent.worker.batches
    history_pid = state0.agent.history.writer_pid if state0.agent.history else None
    roles, by_stage = _split(
        window.tree0,
        window.tree1,
        receiving=window.pid,
        workers={w.pid for w in state0.agent.workers},
        history_pid=history_pid,
        stages=stages,
    )
    cpu = sum(roles.values())
    unit = loads["median"]
    per_received = cpu / received * 1e6 if received else None
    per_mirrored = cpu / mirrored * 1e6 if mirrored else None

    def in_loads(us: float | None) -> float | None:
        return us / unit if us is not None and unit else None

    history_state = state1.agent.history
    return {
        "workers": len(state1.agent.workers) or 1,
        "sent": window.sent,
        "received": received,
        "mirrored": mirrored,
        "mirrored_of_received": mirrored / received if received else None,
        "window_s": window.end - window.start,
        "cpu_s": {**roles, "total": cpu},
        "cpu_us_per_received": per_received,
        "cpu_us_per_mirrored": per_mirrored,
        "json_loads_us": loads,
        "loads_per_received": in_loads(per_received),
        "loads_per_mirrored": in_loads(per_mirrored),
        "stages_loads_per_received": {
            stage: in_loads(cpu_s / received * 1e6) if received else None for stage, cpu_s in by_stage.items()
        },
        # What the workers' sampled stage figures rest on: batches handled, and how many were timed.
        "worker_batches": {"handled": batches, "stages_timed": timed},
        # Messages the servo alarm engine evaluated in the window (none with --no-alarms).
        "alarm_evaluations": state1.agent.worker.alarm_rows - state0.agent.worker.alarm_rows,
        "internal_latency_s": dataclasses.asdict(state1.agent.latency.internal_s),
        "history_rows": (
            {
                "committed": history_state.rows_committed + history_state.rejected_rows_committed,
                "dropped": history_state.rows_dropped,
            }
            if history_state
            else None
        ),
    }


def one_run(
    rig: LocalRig,
    arms: int,
    rate: float,
    seconds: float,
    *,
    history: str | None = None,
    workers: int | None = None,
    alarms: bool = True,
) -> dict[str, Any]:
    """One fleet size once: the agent's CPU per message over the window, divided by the probe's median.
    `alarms` False runs the agent with `[alarms] enabled = false`: what the rest of the agent costs."""
    load_before = os.getloadavg()
    probe = _start_probe(seconds)
    try:
        window = _measure_window(rig, arms, rate, seconds, history=history, workers=workers, alarms=alarms)
    finally:
        out = _stop_probe(probe)
    loads = _spread([us for at, us in _probe_rounds(out) if window.start <= at <= window.end])
    return {
        "arms": arms,
        "rate_hz": rate,
        "seconds": seconds,
        "history": history is not None,
        "alarms": alarms,
        **_cost_per_message(window, loads),
        "load_average_1m": {"before": load_before[0], "after": os.getloadavg()[0]},
    }


def _summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    def pick(key: str) -> list[float]:
        return [r[key] for r in runs if r.get(key) is not None]

    return {
        "runs": len(runs),
        "loads_per_received": _spread(pick("loads_per_received")),
        "loads_per_mirrored": _spread(pick("loads_per_mirrored")),
        "mirrored_of_received": _spread(pick("mirrored_of_received")),
        "cpu_us_per_received": _spread(pick("cpu_us_per_received")),
        "json_loads_us": _spread([m for r in runs if (m := r["json_loads_us"]["median"]) is not None]),
        "internal_p99_s": _spread(
            [r["internal_latency_s"]["p99"] for r in runs if r["internal_latency_s"]["p99"] is not None]
        ),
        "load_average_1m": _spread([r["load_average_1m"]["before"] for r in runs]),
    }


def run(
    *,
    arms: Iterable[int] = (100, 1000, 2000),
    rate: float = 10.0,
    seconds: float = 20.0,
    runs: int = 1,
    history: bool = False,
    workers: int | None = None,
    alarms: bool = True,
) -> dict[str, Any]:
    """Every fleet size `runs` times (the sizes interleaved, so a slow spell of the machine does not fall on
    one size only); per size its runs and their summary."""
    sizes = list(arms)
    results: dict[int, list[dict[str, Any]]] = {n: [] for n in sizes}
    tmp = Path(tempfile.mkdtemp(prefix="twin-bench-cost-")) if history else None
    try:
        with LocalRig() as rig:
            for k in range(runs):
                for n in sizes:
                    uri = str(tmp / f"history-{n}-{k}") if tmp is not None else None
                    results[n].append(
                        one_run(rig, n, rate, seconds, history=uri, workers=workers, alarms=alarms)
                    )
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return {
        "scenario": "cost",
        "method": (
            "agent CPU (every process and thread, psutil) over the window from the first message to the "
            "drained end, per received and per mirrored message, divided by the median CPU time of "
            "json.loads of the edge message timed by a probe process all through the same window"
        ),
        "stages": list(STAGES),
        "stage_timing": (
            f"the workers' stages (hand_over's worker part, decode, twin, health_alarms, sinks) are sampled: "
            f"timed on 1 in {STAGE_SAMPLE_EVERY} worker turns at random and on every batch of "
            f"{STAGE_TIMED_FROM} messages or more, each timed figure scaled by the inverse of its chance of "
            "being timed; totals by process are exact, the split by stage an estimate"
        ),
        "sizes": [{"arms": n, "summary": _summary(results[n]), "runs": results[n]} for n in sizes],
    }


__all__ = ["STAGES", "one_run", "run"]
