"""The churn soak (`twin bench churn`): its analysis on made-up series whose answer is known (when each store
filled, the slope after it, the verdict against the 5 % bound), and a short real run at a small scale that
shows the bench measures what it says (stores filled, arms forgotten, every process sampled)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
from twin.bench import churn
from twin.cli.main import build_parser
from twin.service.shards import WorkerPlan

CAPACITY = 5000


def _series(
    after_fill_mb_h: float, *, minutes: float = 40.0, restarts: int = 0, fleet_until_s: float = 0.0
) -> list[dict[str, Any]]:
    """Samples every 30 s: the receiving process's store fills at 480 s (10 events a second), each worker's
    at 1000 s (5 a second); RSS climbs 40 MB until its store's fill, then `after_fill_mb_h`, with a
    saw-tooth of +-2 MB on top (what the real runs' noise looks like). With `fleet_until_s` the live fleet
    grows from 400 to 1,200 arms until then (arms forgotten late) and every process holds 0.05 MB an arm."""
    samples = []
    for i in range(int(minutes * 2) + 1):
        t = 30.0 * i
        fleet = 800.0 * min(t, fleet_until_s) / fleet_until_s if fleet_until_s else 0.0
        rss = {}
        for name, fill in (("receiving", 480.0), ("worker 0", 1000.0), ("worker 1", 1000.0)):
            climb = 100.0 + 40.0 * min(t, fill) / fill + 0.05 * fleet
            rss[name] = climb + after_fill_mb_h * max(0.0, t - fill) / 3600.0 + (2.0 if i % 2 else -2.0)
        samples.append(
            {
                "t_s": t,
                "rss_mb": rss,
                "events": {"receiving": int(10.5 * t), "worker 0": int(5 * t), "worker 1": int(5 * t)},
                "events_missed": 0,
                "forgotten": int(t // 2),
                "devices": 400 + int(fleet) + i % 3,
                "metrics_bytes": 3_000_000 + 1000 * (i % 5),
                "worker_restarts": restarts,
            }
        )
    return samples


def test_the_stores_fill_times_and_a_flat_memory_after_them_pass() -> None:
    figures = churn.analyse(_series(0.0), CAPACITY)
    receiving = figures["processes"]["receiving"]
    worker = figures["processes"]["worker 0"]
    # 10.5 events a second reach 5,000 at 476 s: the first sample at or after it is 480 s.
    assert receiving["store_full_at_s"] == 480.0
    assert worker["store_full_at_s"] == 1020.0 and figures["all_stores_full_at_s"] == 1020.0
    assert receiving["rss_start_mb"] == pytest.approx(98.0)
    assert receiving["rss_end_mb"] == pytest.approx(138.0)
    assert receiving["judged_from_s"] == 480.0 and worker["judged_from_s"] == 1020.0
    assert abs(receiving["slope_mb_h"]) < 1.0
    assert abs(worker["growth"]) < 0.01
    assert figures["verdict"]["ok"] is True
    assert figures["devices"] == {"min": 400, "max": 402}
    assert figures["metrics_bytes_after_fill"] == {"min": 3_000_000, "max": 3_004_000}
    assert figures["forgotten"] == 1200


def test_memory_that_keeps_growing_after_the_fill_fails_the_bound() -> None:
    # 40 MB/h over the workers' 23 minutes after their fill: about 15 MB on 140, past 5 %.
    figures = churn.analyse(_series(40.0), CAPACITY)
    worker = figures["processes"]["worker 1"]
    assert worker["slope_mb_h"] == pytest.approx(40.0, abs=2.0)
    assert worker["growth"] > churn.GROWTH_LIMIT and worker["ok"] is False
    assert figures["verdict"]["ok"] is False


def test_memory_that_follows_a_fleet_still_growing_after_the_fill_is_judged_once_the_fleet_settles() -> None:
    """Under load arms are forgotten late, so the live fleet may grow on after the stores fill (a 20-minute
    run: 450 to 1,181 arms, the receiving process following it, then flat). Memory the fleet needs is not a
    leak; the window starts when the fleet first reached 95 % of its largest size."""
    figures = churn.analyse(_series(0.0, fleet_until_s=1500.0), CAPACITY)
    # 400 + 800 t / 1500 >= 0.95 x 1,202 (1,141.9) first at t = 1,410 s, after every store's fill.
    assert figures["fleet_near_peak_at_s"] == 1410.0
    worker = figures["processes"]["worker 0"]
    assert worker["store_full_at_s"] == 1020.0 and worker["judged_from_s"] == 1410.0
    assert abs(worker["growth"]) < 0.01 and figures["verdict"]["ok"] is True
    # What still grows after the fleet settled is counted as before.
    growing = churn.analyse(_series(40.0, fleet_until_s=1500.0), CAPACITY)
    assert growing["processes"]["worker 0"]["ok"] is False and growing["verdict"]["ok"] is False


def test_a_store_that_never_filled_or_a_restarted_worker_is_not_judged() -> None:
    never = churn.analyse(_series(0.0), capacity=100_000)
    assert never["all_stores_full_at_s"] is None
    assert never["processes"]["receiving"]["ok"] is None and never["verdict"]["ok"] is None
    # Filled at 1,020 s of a 20-minute run: 7 samples after it, one short of the least judged.
    short = churn.analyse(_series(0.0, minutes=20.0), CAPACITY)
    assert short["processes"]["worker 0"]["samples_judged"] == 7
    assert short["verdict"]["ok"] is None
    assert churn.analyse(_series(0.0, restarts=1), CAPACITY)["verdict"]["ok"] is None


def test_a_request_the_agent_does_not_answer_is_noted_and_the_run_goes_on() -> None:
    """A busy host once kept the agent from answering a sample's /metrics within 30 s, and the timeout ended
    a 55-minute run with nothing written."""
    unanswered: list[dict[str, Any]] = []

    def timed_out() -> int:
        raise TimeoutError("timed out")

    assert churn.answered(timed_out, 541.04, unanswered, "sample") is None
    assert churn.answered(lambda: 7, 543.0, unanswered, "events") == 7
    assert unanswered == [{"t_s": 541.0, "what": "sample", "error": "timed out"}]


def test_the_slope_of_a_line_is_exact_and_of_two_points_undefined() -> None:
    b, se, first = churn.slope([0.0, 1.0, 2.0, 3.0], [5.0, 7.0, 9.0, 11.0])
    assert (b, se, first) == pytest.approx((2.0, 0.0, 5.0))
    assert all(math.isnan(v) for v in churn.slope([0.0, 1.0], [1.0, 2.0]))


def test_events_are_counted_to_the_worker_that_mirrors_their_device() -> None:
    counts = churn.EventCounts("http://127.0.0.1:9", workers=2)
    plan = WorkerPlan(2)
    devices = [f"arm-{i:04d}" for i in range(20)]
    for device in devices:
        counts._count({"kind": "status", "device": device, "data": {}})
    counts._count({"kind": "twin", "device": devices[0], "data": {"action": "forgotten"}})
    counts._count({"kind": "agent", "device": "", "data": {}})
    counts._count({"kind": "status", "device": "", "data": {}})
    expected = [sum(1 for d in devices if plan.worker_of(d) == w) for w in (0, 1)]
    expected[plan.worker_of(devices[0])] += 1
    assert counts.per_worker == expected
    assert counts.forgotten == 1 and counts.unattributed == 1


@pytest.mark.slow
@pytest.mark.long(seconds=45)
def test_a_short_churn_run_fills_the_stores_and_forgets_arms(tmp_path: Path) -> None:
    settings = churn.Churn(
        minutes=0.5,
        steady=10,
        rate=5.0,
        churn_per_min=240,
        wave_every_s=5.0,
        wave_seconds=3.0,
        forget_offline_after_s=11.0,
        forget_unseen_after_s=11.0,
        events_capacity=100,
        sample_s=3.0,
    )
    summary = churn.run(settings, out=tmp_path)
    saved = json.loads((tmp_path / "churn.json").read_text())
    assert len(saved["samples"]) >= 5
    figures = summary["analysis"]
    assert set(figures["processes"]) == {"receiving", "worker 0", "worker 1"}
    # 20 new ids every 5 s, each ONLINE then STALE: the receiving store's 100 fill within the run.
    assert figures["processes"]["receiving"]["store_full_at_s"] is not None
    assert figures["forgotten"] > 0 and summary["churned_ids"] >= 100
    assert figures["metrics_bytes"]["min"] > 0 and figures["devices"]["max"] >= 10
    assert all(p["rss_start_mb"] > 10 for p in figures["processes"].values())


def test_twin_bench_churn_passes_its_options_to_the_bench(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[tuple[churn.Churn, Path]] = []
    monkeypatch.setattr(churn, "run", lambda settings, out: seen.append((settings, out)) or {"ran": True})
    argv = ["bench", "churn", "--minutes", "25", "--steady", "50", "--events-capacity", "5000", "--out", "x"]
    args = build_parser().parse_args(argv)
    assert args.func(args) == 0
    settings, out = seen[0]
    assert (settings.minutes, settings.steady, settings.events_capacity, out) == (25.0, 50, 5000, Path("x"))
    # Left out, the agent's own capacity: the bench's settings default to it.
    defaults = build_parser().parse_args(["bench", "churn"])
    assert defaults.func(defaults) == 0
    assert seen[1][0].events_capacity == churn.DEFAULT_CAPACITY and seen[1][0].workers == 2
