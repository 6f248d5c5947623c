"""The churn soak: a steady fleet plus arms that come and go, and whether memory stays flat once it is full.

`twin run --workers W` (no history, USD or Rerun) on a private mosquitto, with
`telemetry.forget_offline_after_s` and `forget_unseen_after_s` set so the agent forgets arms gone silent.
`steady` arms publish at `rate` Hz the whole run ([health] expected_rate_hz is that rate); every
`wave_every_s` a new publisher brings arms with ids never seen before (`churn_per_min` a minute), each
publishing `wave_seconds` at `churn_rate` Hz and then silent, so the agent tracks them, sees them go STALE
and OFFLINE, and forgets them. Every `sample_s` it samples each process's RSS (the receiving process and
every worker, from /state), the devices /state lists, the size of /metrics, and what the stores hold.

What grows while the run is young is not a leak: the event stores fill up to `[twin] events_capacity`
each (the receiving process's and each worker's), with transitions of arms that come and go. So the
figures that matter are taken once a store is full. A store is full when it numbered `events_capacity`
events: it lets none go before (events.EventStore), and ids only grow. The receiving process's count is
the last id of its GET /api/events; a worker's is the number of events it emitted, counted from that
stream by the device each event names (the agent deals devices to workers by WorkerPlan). The bench
follows the stream every EVENTS_POLL_S, so a page it missed (more than EVENTS_ANSWERED events between two
polls) makes the count low and the fill late, never early; `events_missed` says how many.

What the processes hold for the arms they track also grows with the live fleet, which under load (arms
forgotten later) can go on growing after the stores are full. So each process is judged from the later of its
store's fill and the time the live fleet (the devices /state lists) first reached FLEET_NEAR_PEAK of its
largest size in the run: from then on the fleet can add little, and what still grows is not the fleet's.

The verdict (docs/performance.md, "Soak: arms that come and go"): over the samples from that time to the
end, the least-squares line's rise is at most GROWTH_LIMIT of its value at that time, for every process,
judged only with at least MIN_POINTS_JUDGED samples in the window (else not judged).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import time
import urllib.request
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TypeVar

import psutil

from twin.bench.harness import collect, get_state, load_process, publishers, wait_subscribed
from twin.rig.local import LocalRig
from twin.service.events import DEFAULT_CAPACITY
from twin.service.shards import WorkerPlan

GROWTH_LIMIT = 0.05
MIN_POINTS_JUDGED = 8
# The share of its largest size the live fleet reaches before a process's growth counts (module doc).
FLEET_NEAR_PEAK = 0.95
EVENTS_POLL_S = 2.0
# The churned arms' ids start past any steady fleet this bench runs (arm-NNNN naming, twin.bench.load).
FIRST_CHURN_ID = 100_000
# The kinds a mirror emits (a worker's store); the others (agent, broker, worker) are the receiving
# process's own.
MIRROR_KINDS = frozenset({"status", "alarm", "rejected", "twin", "calibration"})
RECEIVING = "receiving"
_T = TypeVar("_T")


@dataclass(frozen=True)
class Churn:
    """The churn soak's settings (module doc)."""

    minutes: float = 40.0
    steady: int = 200
    rate: float = 5.0
    churn_per_min: int = 500
    wave_every_s: float = 15.0
    wave_seconds: float = 10.0
    churn_rate: float = 2.0
    forget_offline_after_s: float = 30.0
    forget_unseen_after_s: float = 60.0
    workers: int = 2
    events_capacity: int = DEFAULT_CAPACITY
    sample_s: float = 30.0

    @property
    def per_wave(self) -> int:
        return max(1, round(self.churn_per_min * self.wave_every_s / 60.0))

    def config(self) -> str:
        # Room for the steady fleet and every churned arm not yet forgotten, and more: the bench measures
        # forgetting, not the fleet bound's refusals.
        max_devices = max(4096, self.steady + 4 * self.churn_per_min)
        return (
            f'[telemetry]\nmax_devices = {max_devices}\nunits = "ticks"\n'
            f"forget_offline_after_s = {self.forget_offline_after_s}\n"
            f"forget_unseen_after_s = {self.forget_unseen_after_s}\n"
            f"[health]\nexpected_rate_hz = {self.rate}\n"
            f"[twin]\nevents_capacity = {self.events_capacity}\n"
        )


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=30) as response:
        return response.read()


def answered(call: Callable[[], _T], t_s: float, unanswered: list[dict[str, Any]], what: str) -> _T | None:
    """`call()`'s result, or None when the agent did not answer it: noted in `unanswered` and the run goes on.
    On a host busy enough that the agent, at its priority, took more than _get's 30 s over a /metrics render,
    one timed-out sample ended a 55-minute run at its ninth minute with nothing written. The next poll reads
    the events on from where the last one stopped; a sample missed is a gap in the series."""
    try:
        return call()
    except OSError as exc:  # TimeoutError, URLError, a connection reset
        unanswered.append({"t_s": round(t_s, 1), "what": what, "error": str(exc)})
        return None


class EventCounts:
    """Follows the agent's GET /api/events: how many events each store numbered (module doc), the arms
    forgotten, and the events the follower missed."""

    def __init__(self, base: str, workers: int) -> None:
        self._base = base
        self._plan = WorkerPlan(workers) if workers > 1 else None
        self.last_id = 0
        self.per_worker = [0] * workers if workers > 1 else []
        self.unattributed = 0
        self.forgotten = 0
        self.missed = 0
        self.kinds: Counter[str] = Counter()

    def poll(self) -> None:
        page = json.loads(_get(f"{self._base}/api/events?after={self.last_id}&limit=1000"))
        events = page["events"]
        if events:
            self.missed += events[-1]["id"] - self.last_id - len(events)
        for event in events:
            self._count(event)
        self.last_id = max(self.last_id, int(page["last_id"]))

    def _count(self, event: dict[str, Any]) -> None:
        kind = event["kind"]
        self.kinds[kind] += 1
        if kind == "twin" and event.get("data", {}).get("action") == "forgotten":
            self.forgotten += 1
        if self._plan is None or kind not in MIRROR_KINDS:
            return
        if event.get("device"):
            self.per_worker[self._plan.worker_of(event["device"])] += 1
        else:
            self.unattributed += 1  # counted to no worker: its fill can only come later

    def stores(self) -> dict[str, int]:
        """Events each store numbered: the receiving process's, then each worker's."""
        return {RECEIVING: self.last_id, **{f"worker {i}": n for i, n in enumerate(self.per_worker)}}


def _rss_mb(pid: int) -> float | None:
    try:
        return psutil.Process(pid).memory_info().rss / 2**20
    except psutil.Error:
        return None


def _sample(t_s: float, base: str, agent_pid: int, events: EventCounts) -> dict[str, Any]:
    """One sample: each process's RSS, the stores' counts, the fleet /state lists, the size of /metrics."""
    state = get_state(base, timeout=30)
    pids = {RECEIVING: agent_pid, **{f"worker {w.index}": w.pid for w in state.agent.workers}}
    # Read before this sample's /metrics render: what the process holds between scrapes, not the peak of
    # the render the bench itself is about to ask for.
    rss_mb = {name: _rss_mb(pid) for name, pid in pids.items()}
    metrics = _get(f"{base}/metrics").decode()
    return {
        "t_s": t_s,
        "load_average": list(os.getloadavg()),
        "pids": pids,
        "rss_mb": rss_mb,
        # And once it is answered: what is left of that render's peak then. The agent trims its heap after
        # sending the answer, so this read may come before or after the trim; reported, never judged.
        "rss_after_metrics_mb": {name: _rss_mb(pid) for name, pid in pids.items()},
        "events": events.stores(),
        "events_missed": events.missed,
        "events_unattributed": events.unattributed,
        "forgotten": events.forgotten,
        "devices": len(state.devices),
        "metrics_bytes": len(metrics),
        "metrics_samples": sum(1 for line in metrics.splitlines() if line and not line.startswith("#")),
        "received": state.agent.broker.messages,
        "queue_dropped": state.agent.mailbox.overwritten_total,
        "worker_restarts": sum(w.restarts for w in state.agent.workers),
    }


class _Waves:
    """The churned arms: a publisher every `wave_every_s` with `per_wave` ids never used before."""

    def __init__(self, churn: Churn, url: str, seconds: float) -> None:
        self._churn = churn
        self._url = url
        self._seconds = seconds
        self._next_s = 0.0
        self.next_id = FIRST_CHURN_ID
        self.running: list[subprocess.Popen[str]] = []
        self.sent = 0

    def tick(self, t_s: float) -> None:
        c = self._churn
        if t_s >= self._next_s and t_s < self._seconds - c.wave_seconds:
            args = ("--url", self._url, "--first", str(self.next_id), "--count", str(c.per_wave))
            timing = ("--rate", str(c.churn_rate), "--seconds", str(c.wave_seconds))
            self.running.append(load_process("publish", *args, *timing))
            self.next_id += c.per_wave
            self._next_s += c.wave_every_s
        for proc in [p for p in self.running if p.poll() is not None]:
            self.running.remove(proc)
            self.sent += collect([proc], timeout=30)["sent"]

    def finish(self) -> None:
        self.sent += collect(self.running, timeout=120)["sent"]
        self.running = []


def measure(churn: Churn, out: Path) -> dict[str, Any]:
    """The churn soak itself: the samples, the settings and what was sent (run() adds the analysis)."""
    out.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(out / "rig", ignore_errors=True)
    seconds = churn.minutes * 60.0
    load_before = os.getloadavg()
    samples: list[dict[str, Any]] = []
    with LocalRig(workdir=out / "rig") as rig:
        args = ("--workers", str(churn.workers), "--log-level", "WARNING")
        with rig.agent_process(config_text=churn.config(), extra_args=args) as (proc, base):
            wait_subscribed(base, proc, timeout=120.0)
            steady = publishers(rig.broker.url, churn.steady, churn.rate, seconds)
            waves = _Waves(churn, rig.broker.url, seconds)
            events = EventCounts(base, churn.workers)
            started = time.monotonic()
            next_sample = 0.0
            unanswered: list[dict[str, Any]] = []

            def sample(t_s: float) -> None:
                taken = answered(lambda: _sample(t_s, base, proc.pid, events), t_s, unanswered, "sample")
                if taken is not None:
                    samples.append(taken)

            while (t_s := time.monotonic() - started) < seconds:
                if proc.poll() is not None:
                    raise RuntimeError(f"the agent exited during the churn soak (code {proc.returncode})")
                waves.tick(t_s)
                answered(events.poll, t_s, unanswered, "events")
                if t_s >= next_sample:
                    sample(t_s)
                    next_sample += churn.sample_s
                time.sleep(EVENTS_POLL_S)  # the events' polling period, not synchronisation
            sent = collect(steady, timeout=120)
            waves.finish()
            t_s = time.monotonic() - started
            answered(events.poll, t_s, unanswered, "events")
            sample(t_s)
    shutil.rmtree(out / "rig", ignore_errors=True)
    return {
        "scenario": "churn",
        "settings": asdict(churn),
        "churned_ids": waves.next_id - FIRST_CHURN_ID,
        "sent": {"steady": sent["sent"], "churned": waves.sent},
        "load_average_before": list(load_before),
        "kinds": dict(events.kinds),
        "samples": samples,
        "unanswered": unanswered,
    }


def slope(xs: Sequence[float], ys: Sequence[float]) -> tuple[float, float, float]:
    """The least-squares line through (xs, ys): (slope, its standard error, the line's value at xs[0])."""
    n = len(xs)
    if n < 3:
        return math.nan, math.nan, math.nan
    mx, my = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    if sxx == 0:
        return math.nan, math.nan, math.nan
    b = sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sxx
    residuals = sum((y - my - b * (x - mx)) ** 2 for x, y in zip(xs, ys, strict=True))
    return b, math.sqrt(residuals / (n - 2) / sxx), my + b * (xs[0] - mx)


def _fill_s(samples: Sequence[dict[str, Any]], store: str, capacity: int) -> float | None:
    return next((s["t_s"] for s in samples if s["events"].get(store, 0) >= capacity), None)


def fleet_near_peak_s(samples: Sequence[dict[str, Any]]) -> float | None:
    """When the live fleet first reached FLEET_NEAR_PEAK of its largest size in the run (module doc)."""
    peak = max((s["devices"] for s in samples), default=0)
    return next((s["t_s"] for s in samples if s["devices"] >= FLEET_NEAR_PEAK * peak), None) if peak else None


def _series(samples: Sequence[dict[str, Any]], key: str, name: str) -> list[tuple[float, float]]:
    """(time, MB) of one process's RSS read `key` ("rss_mb", "rss_after_metrics_mb"), where it was read."""
    return [(s["t_s"], s[key][name]) for s in samples if s.get(key, {}).get(name) is not None]


def _process(
    samples: Sequence[dict[str, Any]], name: str, capacity: int, limit: float, fleet_s: float | None
) -> dict[str, Any]:
    """One process's figures: RSS at the start, when judging starts (the later of its store's fill and
    `fleet_s`) and at the end, and from then on the least-squares slope (MB/h), the line's rise over the
    window against its value at the window's start, the verdict."""
    points = _series(samples, "rss_mb", name)
    fill = _fill_s(samples, name, capacity)
    start = None if fill is None or fleet_s is None else max(fill, fleet_s)
    window = [(t, r) for t, r in points if start is not None and t >= start]
    b, se, at_start = slope([t for t, _ in window], [r for _, r in window])
    peaks = [
        (t, r) for t, r in _series(samples, "rss_after_metrics_mb", name) if start is not None and t >= start
    ]
    peak_b = slope([t for t, _ in peaks], [r for _, r in peaks])[0]
    rise = b * (window[-1][0] - window[0][0]) if window and not math.isnan(b) else math.nan
    growth = rise / at_start if window and at_start else math.nan
    judged = len(window) >= MIN_POINTS_JUDGED and not math.isnan(growth)
    return {
        "store_full_at_s": fill,
        "judged_from_s": start,
        "rss_start_mb": points[0][1] if points else None,
        "rss_judged_from_mb": window[0][1] if window else None,
        "rss_end_mb": points[-1][1] if points else None,
        "samples_judged": len(window),
        "slope_mb_h": b * 3600.0,
        "slope_se_mb_h": se * 3600.0,
        "rise_mb": rise,
        "growth": growth,
        # Not judged: what a render left when its answer arrived, before or after the agent's trim.
        "after_metrics_max_mb": max((r for _, r in peaks), default=None),
        "after_metrics_slope_mb_h": peak_b * 3600.0,
        "ok": (growth <= limit) if judged else None,
    }


def _span(values: Sequence[float]) -> dict[str, float | None]:
    return {"min": min(values), "max": max(values)} if values else {"min": None, "max": None}


def analyse(samples: Sequence[dict[str, Any]], capacity: int, limit: float = GROWTH_LIMIT) -> dict[str, Any]:
    """The figures and the verdict of a churn soak's samples (module doc). `ok` is None when not judged: a
    store never filled, too few samples in the window, or a worker was started again (its store emptied)."""
    names = list(dict.fromkeys(name for s in samples for name in s["rss_mb"]))
    fleet_s = fleet_near_peak_s(samples)
    processes = {name: _process(samples, name, capacity, limit, fleet_s) for name in names}
    fills = [p["store_full_at_s"] for p in processes.values()]
    all_full = max(fills) if fills and None not in fills else None
    after = [s for s in samples if all_full is not None and s["t_s"] >= all_full]
    restarts = samples[-1]["worker_restarts"] if samples else 0
    oks = [p["ok"] for p in processes.values()]
    ok = None if restarts or None in oks or not oks else all(oks)
    return {
        "processes": processes,
        "all_stores_full_at_s": all_full,
        "fleet_near_peak_at_s": fleet_s,
        "metrics_bytes": _span([s["metrics_bytes"] for s in samples]),
        "metrics_bytes_after_fill": _span([s["metrics_bytes"] for s in after]),
        "devices": _span([s["devices"] for s in samples]),
        "devices_after_fill": _span([s["devices"] for s in after]),
        "forgotten": samples[-1]["forgotten"] if samples else 0,
        "events_missed": samples[-1]["events_missed"] if samples else 0,
        "worker_restarts": restarts,
        "verdict": {"growth_limit": limit, "min_samples_judged": MIN_POINTS_JUDGED, "ok": ok},
    }


def run(churn: Churn, out: Path = Path("out/churn")) -> dict[str, Any]:
    """The churn soak, its churn.json (settings, samples, analysis) in `out`; returns all but the samples."""
    out = out.resolve()
    result = measure(churn, out)
    result["analysis"] = analyse(result["samples"], churn.events_capacity)
    (out / "churn.json").write_text(json.dumps(result, indent=1))
    return {k: v for k, v in result.items() if k != "samples"}
