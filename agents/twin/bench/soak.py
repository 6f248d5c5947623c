"""The soak: a fleet through the agent for minutes or hours, with every sink on, and what time does to it.

One `twin run --workers 1` child process (the Rerun save needs the one process) on a private mosquitto, with
history (a local Delta table), the USD recording, the Rerun save and, where a loopback-only network
namespace can be made, the ROS 2 bridge; `arms` arms publish at `rate` Hz for `minutes`. Every `sample_s`
it samples:

- each process's RSS, open files and threads (the agent, the broker, the publishers);
- the disk each sink takes (history's table, the USD sessions, the .rrd files);
- what was received, processed, lost and dropped, from the agent's /state.

and writes `soak.json` (the settings, every sample, the verdicts) and `soak.png` (one panel per figure over
time) into `out`. The bounds it judges (docs/performance.md, "Soak"):

- RSS: the agent's processes grow at most RSS_GROWTH_LIMIT after the warm-up (the first WARMUP_S, or half
  a short run): the median of the last quarter of the samples against the median of the first quarter
  after the warm-up (the USD stage's memory follows its rotations, so single samples saw-tooth);
- nothing lost: every message published was received, every one received was counted (against its arm or
  as a rejection), none was dropped by a queue, a sink or the history writer, the loss estimate is zero,
  and every decoded message is a row in the history table after the agent stopped;
- disk: once the rotating sinks took half their budget, they never exceed it by more than what one size
  check lets a live file overshoot (FLAT_ALLOWANCE; history grows: it is the data).

The caps are small so a run reaches them early: SOAK_CAPS for a run of LONG_RUN_MINUTES or more, SHORT_CAPS
below (the 2-minute run of `make test`; its .rrd scaled past 50 arms by short_caps). History's maintenance
is one of them: its Delta table state grows with every commit's file until maintenance compacts them (hourly
by default), so an hour at the default interval never reaches that bound (docs/performance.md, "Soak").
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import psutil

from twin.bench import netns
from twin.bench.harness import collect, get_state, last_json_line, publishers, wait_subscribed
from twin.rig.local import LocalRig

RSS_GROWTH_LIMIT = 0.05
FLAT_ALLOWANCE = 1.1
REACHED_SHARE = 0.5
WARMUP_S = 300.0
LONG_RUN_MINUTES = 10.0


@dataclass(frozen=True)
class Caps:
    """The rotating sinks' limits in the soak (MB, seconds), and the USD recording's rate per arm."""

    record_max_mb: float
    record_max_age_s: float
    record_budget_mb: float
    record_rate_hz: float
    rrd_max_mb: float
    rrd_max_age_s: float
    rrd_budget_mb: float
    history_maintain_every_s: float


SOAK_CAPS = Caps(
    record_max_mb=32.0,
    record_max_age_s=120.0,
    record_budget_mb=160.0,
    # Authoring a USD sample cost about 1.4 ms of the sink's thread (about 0.3 ms since; `twin bench usd`),
    # under the one interpreter lock with every other sink: 200 arms at 2 Hz kept up on a quiet host and fell
    # behind (the queue dropped) when the shared host's load average passed 10. A sample a second per arm
    # keeps the recording within reach, and the hour stays comparable with the runs documented before.
    record_rate_hz=1.0,
    # At 200 arms the .rrd grows about 1.5 MB a second and each file starts with the arms' meshes (about
    # 30 MB, logged again at every rotation): a file every few minutes, the budget reached in about ten.
    rrd_max_mb=256.0,
    rrd_max_age_s=600.0,
    rrd_budget_mb=1024.0,
    # The table state held every file of the hour (about 0.2 MB each, a commit every 10 s): 70 MB of RSS
    # growth in the documented hour, which compaction takes back. Every 10 minutes, a run sees that bound.
    history_maintain_every_s=600.0,
)
SHORT_CAPS = Caps(
    record_max_mb=2.0,
    record_max_age_s=15.0,
    record_budget_mb=8.0,
    record_rate_hz=2.0,
    # The first .rrd holds the arms' meshes (about 12 MB at 50 arms), and every later one too.
    rrd_max_mb=20.0,
    rrd_max_age_s=30.0,
    rrd_budget_mb=60.0,
    history_maintain_every_s=3600.0,  # the default: 2 minutes of files are a few MB
)
# The .rrd's meshes take about 0.15 MB an arm: past 50 arms the short caps' file grows with the fleet, so the
# meshes stay under half of it and a file holds samples, not only the statics logged again at each rotation.
SHORT_RRD_MB_PER_ARM = 0.4


def short_caps(arms: int) -> Caps:
    """SHORT_CAPS, with the .rrd's size and budget scaled to a fleet past 50 arms."""
    rrd_max_mb = max(SHORT_CAPS.rrd_max_mb, SHORT_RRD_MB_PER_ARM * arms)
    scale = rrd_max_mb / SHORT_CAPS.rrd_max_mb
    return replace(SHORT_CAPS, rrd_max_mb=rrd_max_mb, rrd_budget_mb=SHORT_CAPS.rrd_budget_mb * scale)


def _config(data: Path, caps: Caps, arms: int, ros2: bool) -> str:
    return (
        f'[telemetry]\nmax_devices = {max(4096, arms)}\nunits = "ticks"\n'
        f'[twin]\nrecord_dir = "{data / "usd"}"\nrecord_max_mb = {caps.record_max_mb}\n'
        f"record_max_age_s = {caps.record_max_age_s}\nrecord_budget_mb = {caps.record_budget_mb}\n"
        f"record_rate_hz = {caps.record_rate_hz}\n"
        f'state_file = "{data / "state.json"}"\n'
        f'[history]\nuri = "{data / "history"}"\nmaintain_every_s = {caps.history_maintain_every_s}\n'
        f'[rerun]\nsave = "{data / "rrd" / "twin.rrd"}"\nsave_max_mb = {caps.rrd_max_mb}\n'
        f"save_max_age_s = {caps.rrd_max_age_s}\nsave_budget_mb = {caps.rrd_budget_mb}\n"
        # The bridge's default queue (1,000 samples) dropped a 200-arm fleet's first samples while it created
        # a writer per arm; the soak measures what time does, so the queue holds the start's burst.
        + ("[ros2]\nenabled = true\nmax_pending = 20000\n" if ros2 else "")
    )


def _du(path: Path, pattern: str = "**/*") -> tuple[int, int]:
    """(bytes, files) under `path` matching `pattern`."""
    total = files = 0
    for p in path.glob(pattern):
        try:
            if p.is_file():
                total += p.stat().st_size
                files += 1
        except OSError:
            continue
    return total, files


def _process(proc: psutil.Process, role: str) -> dict[str, Any] | None:
    try:
        with proc.oneshot():
            return {
                "role": role,
                "pid": proc.pid,
                "name": proc.name(),
                "rss_mb": proc.memory_info().rss / 2**20,
                "open_files": proc.num_fds(),
                "threads": proc.num_threads(),
            }
    except psutil.Error:
        return None


def _processes(agent: psutil.Process, broker_pid: int | None, loads: list[Any]) -> list[dict[str, Any]]:
    out = []
    try:
        tree = [(agent, "agent"), *((c, "agent child") for c in agent.children(recursive=True))]
    except psutil.Error:
        tree = [(agent, "agent")]
    others = [(broker_pid, "broker")] if broker_pid is not None else []
    others += [(p.pid, "publisher") for p in loads if p.poll() is None]
    for pid, role in others:
        # A publisher may end between its poll() and here: it is then not sampled.
        with contextlib.suppress(psutil.Error):
            tree.append((psutil.Process(pid), role))
    for proc, role in tree:
        sample = _process(proc, role)
        if sample is not None:
            out.append(sample)
    return out


def _counts(base: str) -> dict[str, Any]:
    state = get_state(base, timeout=30)
    agent = state.agent
    devices = state.devices.values()
    history = agent.history
    recording = agent.recording
    sinks = {s.name: s for s in agent.sinks}
    return {
        "received": agent.broker.messages,
        "processed": agent.worker.processed,
        "counted": sum(d.health.counters.received for d in devices) + sum(state.untracked_rejected.values()),
        "decoded": sum(d.health.counters.decoded for d in devices),
        "applied": sum(d.health.counters.applied for d in devices),
        "rejected": sum(d.health.counters.rejected_total for d in devices)
        + sum(state.untracked_rejected.values()),
        "loss_estimated": agent.loss.lost,
        "queue_dropped": agent.mailbox.overwritten_total,
        "sink_dropped": {name: s.dropped for name, s in sinks.items()},
        "sink_skipped": {name: s.skipped for name, s in sinks.items()},
        "sink_pending": {name: s.pending for name, s in sinks.items()},
        "history_rows_dropped": history.rows_not_written if history else 0,
        "history_rows_committed": history.rows_committed if history else 0,
        "history_lag_s": history.lag_s if history else 0.0,
        "history_commit_failures": history.commit_failures if history else 0,
        # Maintenance runs in a process of its own: these say it ran, and whether it failed.
        "history_maintenance_runs": history.maintenance_runs if history else 0,
        "history_maintenance_failures": history.maintenance_failures if history else 0,
        "recording_rotations": recording.rotations if recording else 0,
        "recording_files_deleted": recording.files_deleted if recording else 0,
        "internal_p99_ms": 1000 * (agent.latency.internal_s.p99 or 0.0),
        "devices": len(state.devices),
    }


def _fresh_data(out: Path) -> Path:
    """The sinks' folders under `out`, emptied of an earlier run's (and the rig's workdir removed)."""
    out.mkdir(parents=True, exist_ok=True)
    data = out / "data"
    shutil.rmtree(data, ignore_errors=True)
    shutil.rmtree(out / "rig", ignore_errors=True)
    for sub in ("usd", "rrd", "history"):
        (data / sub).mkdir(parents=True, exist_ok=True)
    return data


def _sample(
    t_s: float, base: str, data: Path, *, agent: psutil.Process, broker_pid: int | None, loads: list[Any]
) -> dict[str, Any]:
    """One sample: the load, every process, the disk each sink takes, and the agent's counts."""
    return {
        "t_s": t_s,
        "load_average": list(os.getloadavg()),
        "processes": _processes(agent, broker_pid, loads),
        "disk": {
            "history": _du(data / "history"),
            "usd": _du(data / "usd", "session-*"),
            "rrd": _du(data / "rrd", "*.rrd"),
        },
        "counts": _counts(base),
    }


def _sample_while_publishing(
    proc: subprocess.Popen[bytes],
    base: str,
    data: Path,
    *,
    broker_pid: int | None,
    loads: list[Any],
    started: float,
    interval: float,
) -> list[dict[str, Any]]:
    """A sample every `interval` until the publishers have finished, the last one taken after they did."""
    agent = psutil.Process(proc.pid)
    samples = []
    while True:
        done = all(p.poll() is not None for p in loads)
        now = time.monotonic() - started
        if proc.poll() is not None:
            raise RuntimeError(f"the agent exited during the soak (code {proc.returncode})")
        samples.append(_sample(now, base, data, agent=agent, broker_pid=broker_pid, loads=loads))
        if done:
            return samples
        time.sleep(interval)  # the sampling period: a figure every `interval`, not synchronisation


def measure(
    *,
    minutes: float,
    arms: int,
    rate: float,
    out: Path,
    sample_s: float | None = None,
    caps: Caps | None = None,
) -> dict[str, Any]:
    """The soak itself, in this process (run() puts it in a loopback namespace when ROS 2 can be on)."""
    ros2 = netns.inside() and importlib.util.find_spec("cyclonedds") is not None
    if caps is None:
        caps = SOAK_CAPS if minutes >= LONG_RUN_MINUTES else short_caps(arms)
    seconds = minutes * 60.0
    warmup = min(WARMUP_S, seconds / 2.0)
    interval = sample_s if sample_s is not None else max(2.0, min(15.0, seconds / 60.0))
    data = _fresh_data(out)
    load_before = os.getloadavg()
    with LocalRig(workdir=out / "rig") as rig:
        config = _config(data, caps, arms, ros2)
        args = ("--workers", "1", "--log-level", "INFO")
        with rig.agent_process(config_text=config, extra_args=args) as (proc, base):
            wait_subscribed(base, proc, timeout=120.0)
            loads = publishers(rig.broker.url, arms, rate, seconds)
            started = time.monotonic()
            samples = _sample_while_publishing(
                proc, base, data, broker_pid=rig.broker.pid, loads=loads, started=started, interval=interval
            )
            sent = collect(loads, timeout=120)
            final = _drained(base, sent["sent"])
            samples.append({**samples[-1], "t_s": time.monotonic() - started, "counts": final})
            # A clean stop: SIGTERM, history's last commit, exit 0 within the shutdown budget.
            proc.send_signal(signal.SIGTERM)
            exit_code = proc.wait(120)
        history_rows = _history_rows(data / "history")
        agent_log = next(rig.workdir.glob("agent-*.log")).read_text(errors="replace")
    return {
        "scenario": "soak",
        "minutes": minutes,
        "arms": arms,
        "rate_hz": rate,
        "sample_s": interval,
        "warmup_s": warmup,
        "sinks": ["history", "usd", "rerun", *(["ros2"] if ros2 else [])],
        "ros2": ros2,
        "caps": asdict(caps),
        "sent": sent,
        "exit_code": exit_code,
        "history_rows_in_table": history_rows,
        "load_average_before": list(load_before),
        "shutdown_log": [line for line in agent_log.splitlines() if '"agent stopped' in line][-1:],
        "samples": samples,
        "verdicts": verdicts(samples, sent, history_rows, caps, warmup, exit_code),
    }


def _drained(base: str, sent: int, timeout: float = 120.0) -> dict[str, Any]:
    """The counts once the agent received what was sent and its queues are empty (bounded wait)."""
    deadline = time.monotonic() + timeout
    counts = _counts(base)
    while time.monotonic() < deadline:
        pending = sum(counts["sink_pending"].values())
        counted = counts["counted"] == counts["processed"] >= counts["received"] - counts["queue_dropped"]
        if counts["received"] >= sent and counted and not pending:
            return counts
        time.sleep(0.5)
        counts = _counts(base)
    return counts


def _history_rows(uri: Path) -> dict[str, int]:
    """Rows in the history tables after the agent stopped (read back with delta-rs)."""
    from deltalake import DeltaTable  # noqa: PLC0415 - the history extra; the soak keeps history

    rows = {}
    for table in ("telemetry", "rejected"):
        try:
            rows[table] = int(DeltaTable(str(uri / table)).to_pyarrow_dataset().count_rows())
        except Exception:  # no table: nothing was written to it
            rows[table] = 0
    return rows


def _agent_rss(sample: dict[str, Any]) -> float:
    return sum(p["rss_mb"] for p in sample["processes"] if p["role"].startswith("agent"))


def _rss_verdict(samples: list[dict[str, Any]], warmup_s: float) -> dict[str, Any]:
    """The agent's RSS growth after the warm-up: the last quarter's median against the first quarter's."""
    after = [s for s in samples[:-1] if s["t_s"] >= warmup_s]
    quarter = max(1, len(after) // 4)
    first = statistics.median(_agent_rss(s) for s in after[:quarter]) if after else 0.0
    last = statistics.median(_agent_rss(s) for s in after[-quarter:]) if after else 0.0
    growth = (last - first) / first if first else 0.0
    return {
        "first_quarter_after_warmup_mb": first,
        "last_quarter_mb": last,
        "growth": growth,
        "limit": RSS_GROWTH_LIMIT,
        "ok": growth <= RSS_GROWTH_LIMIT,
    }


def _lost_verdict(
    final: dict[str, Any], sent: dict[str, Any], history_rows: dict[str, int]
) -> dict[str, Any]:
    """Every message published, received, counted and kept in history; none dropped or estimated lost."""
    dropped = {
        "queue": final["queue_dropped"],
        "sinks": sum(final["sink_dropped"].values()),
        "history_rows": final["history_rows_dropped"],
    }
    lost = {
        "not_received": sent["sent"] - final["received"],
        "not_counted": final["processed"] - final["counted"],
        "loss_estimated": final["loss_estimated"],
        "not_in_history": final["decoded"] - history_rows.get("telemetry", 0),
        **dropped,
    }
    return {**lost, "ok": all(v == 0 for v in lost.values())}


def _disk_verdict(samples: list[dict[str, Any]], caps: Caps) -> dict[str, Any]:
    """Each rotating sink within its budget once it reached half of it; history's size at the end."""
    budgets = {"usd": caps.record_budget_mb, "rrd": caps.rrd_budget_mb}
    disk: dict[str, Any] = {}
    for sink, budget in budgets.items():
        sizes = [s["disk"][sink][0] / 2**20 for s in samples]
        # Reached: half the budget taken. The sink deletes its oldest files to keep within the budget with the
        # live file counted at its largest, so the total settles between about budget - one file and budget.
        reached = next((i for i, size in enumerate(sizes) if size >= REACHED_SHARE * budget), None)
        peak_after = max(sizes[reached:]) if reached is not None else None
        disk[sink] = {
            "budget_mb": budget,
            "reached_at_s": samples[reached]["t_s"] if reached is not None else None,
            "peak_mb": max(sizes),
            "peak_after_reached_mb": peak_after,
            # The budget counts the live file at its largest; it may pass that by what one size check (a
            # second), the closing flush, and the arms' static parts still following after a rotation (a .rrd
            # rotates only once they are in) add: a tenth of the budget is the allowance.
            "flat": peak_after is None or peak_after <= FLAT_ALLOWANCE * budget,
        }
    history_mb = samples[-1]["disk"]["history"][0] / 2**20
    return {**disk, "history_mb_end": history_mb, "ok": all(d["flat"] for d in disk.values())}


def verdicts(  # noqa: PLR0917 - the figures a soak produced, each its own
    samples: list[dict[str, Any]],
    sent: dict[str, Any],
    history_rows: dict[str, int],
    caps: Caps,
    warmup_s: float,
    exit_code: int,
) -> dict[str, Any]:
    """The three bounds (module doc), each with the figures it rests on, and a clean stop."""
    rss = _rss_verdict(samples, warmup_s)
    lost = _lost_verdict(samples[-1]["counts"], sent, history_rows)
    disk = _disk_verdict(samples, caps)
    return {
        "rss": rss,
        "lost": lost,
        "disk": disk,
        "clean_stop": {"exit_code": exit_code, "ok": exit_code == 0},
        "ok": rss["ok"] and lost["ok"] and disk["ok"] and exit_code == 0,
    }


def plot(result: dict[str, Any], path: Path) -> Path:
    """soak.png: one panel per figure over time (RSS, open files, threads, disk, counts, lost and dropped)."""
    import matplotlib  # noqa: PLC0415 - only when plotting

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    samples = result["samples"]
    t = [s["t_s"] / 60.0 for s in samples]
    fig, axes = plt.subplots(3, 2, figsize=(13, 11), sharex=True)
    keys = sorted({(p["role"], p["name"], p["pid"]) for s in samples for p in s["processes"]})
    for ax, field, title in (
        (axes[0][0], "rss_mb", "RSS (MB) per process"),
        (axes[1][0], "open_files", "open files per process"),
        (axes[1][1], "threads", "threads per process"),
    ):
        for role, name, pid in keys:
            if role == "publisher" and field != "rss_mb":
                continue
            values = [
                next((p[field] for p in s["processes"] if p["pid"] == pid), float("nan")) for s in samples
            ]
            ax.plot(t, values, label=f"{role} {name} {pid}")
        ax.set_title(title)
    axes[0][0].axvline(result["warmup_s"] / 60.0, color="grey", ls=":", label="end of warm-up")
    axes[0][0].legend(fontsize=6)
    ax = axes[0][1]
    for sink in ("history", "usd", "rrd"):
        ax.plot(t, [s["disk"][sink][0] / 2**20 for s in samples], label=sink)
    caps = result["caps"]
    ax.axhline(caps["record_budget_mb"], color="C1", ls=":", label="usd budget")
    ax.axhline(caps["rrd_budget_mb"], color="C2", ls=":", label="rrd budget")
    ax.set_title("disk per sink (MB)")
    ax.legend(fontsize=7)
    ax = axes[2][0]
    for key in ("received", "processed", "applied", "history_rows_committed"):
        ax.plot(t, [s["counts"][key] for s in samples], label=key)
    ax.set_title("messages (running totals)")
    ax.legend(fontsize=7)
    ax = axes[2][1]
    ax.plot(t, [s["counts"]["loss_estimated"] for s in samples], label="loss estimate")
    ax.plot(t, [s["counts"]["queue_dropped"] for s in samples], label="queue dropped")
    ax.plot(t, [sum(s["counts"]["sink_dropped"].values()) for s in samples], label="sink dropped")
    ax.plot(t, [s["counts"]["history_rows_dropped"] for s in samples], label="history rows dropped")
    ax.plot(t, [s["counts"]["history_lag_s"] for s in samples], label="history lag (s)", ls="--")
    ax.set_title("lost and dropped")
    ax.legend(fontsize=7)
    for ax in axes[2]:
        ax.set_xlabel("minutes")
    v = result["verdicts"]
    fig.suptitle(
        f"soak: {result['arms']} arms x {result['rate_hz']:g} Hz, {result['minutes']:g} min, sinks "
        f"{', '.join(result['sinks'])}; RSS growth {100 * v['rss']['growth']:.1f} %, lost "
        f"{sum(x for k, x in v['lost'].items() if k != 'ok')}, disk flat: {v['disk']['ok']}"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def run(
    *, minutes: float = 60.0, arms: int = 200, rate: float = 10.0, out: Path = Path("out/soak")
) -> dict[str, Any]:
    """The soak, its soak.json and soak.png in `out`; inside a loopback-only network namespace (so the ROS 2
    bridge can be on) when one can be made here, else without ROS 2."""
    out = out.resolve()
    if netns.inside() or netns.missing_prerequisites() is not None:
        result = measure(minutes=minutes, arms=arms, rate=rate, out=out)
    else:
        argv = [sys.executable, "-m", "twin.bench.soak", str(minutes), str(arms), str(rate), str(out)]
        proc = netns.run_in_loopback_namespace(argv, timeout=minutes * 60.0 + 900.0)
        if proc.returncode != 0:
            raise RuntimeError(f"the soak failed ({proc.returncode}): {proc.stderr[-2000:]}")
        result = last_json_line(proc.stdout)
    (out / "soak.json").write_text(json.dumps(result, indent=1))
    result["plot"] = str(plot(result, out / "soak.png"))
    shutil.rmtree(out / "data", ignore_errors=True)
    shutil.rmtree(out / "rig", ignore_errors=True)
    return summary(result)


def summary(result: dict[str, Any]) -> dict[str, Any]:
    """What `twin bench soak` prints: everything but the samples (they are in soak.json)."""
    return {k: v for k, v in result.items() if k != "samples"}


def _main() -> int:
    minutes, arms, rate, out = float(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), Path(sys.argv[4])
    sys.stdout.write(json.dumps(measure(minutes=minutes, arms=arms, rate=rate, out=out)) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(_main())
