"""The soak's 2-minute version (`twin bench soak --minutes 2`): 50 arms at 10 Hz through the agent with every
sink on, judged by the bounds of the hour-long run in docs/performance.md: the agent's RSS grows at most 5 %
after the warm-up, nothing is lost (every message received, counted, kept in history; no queue, sink or
history drop; no loss estimated), the rotating sinks stay within their disk budgets once they reach them,
and the agent stops cleanly."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from twin.bench import soak

pytestmark = pytest.mark.slow


@pytest.mark.long(seconds=130)
def test_two_minutes_of_50_arms_with_every_sink_stay_within_the_bounds(tmp_path: Path) -> None:
    result = soak.run(minutes=2.0, arms=50, out=tmp_path)
    saved = json.loads((tmp_path / "soak.json").read_text())
    assert (tmp_path / "soak.png").stat().st_size > 10_000
    assert len(saved["samples"]) >= 20
    verdicts = result["verdicts"]
    assert verdicts["lost"]["ok"], verdicts["lost"]
    assert verdicts["rss"]["ok"], verdicts["rss"]
    assert verdicts["disk"]["ok"], verdicts["disk"]
    # The rotating sinks reached their budgets within the run, so "flat" was judged, not assumed.
    assert verdicts["disk"]["usd"]["reached_at_s"] is not None
    assert verdicts["disk"]["rrd"]["reached_at_s"] is not None
    assert verdicts["clean_stop"]["ok"] and verdicts["ok"]
    assert result["sent"]["sent"] == 50 * 10 * 120


def test_the_short_caps_rrd_grows_with_the_fleet_past_50_arms() -> None:
    # 200 arms' meshes (about 30 MB) fill the 20 MB file: each new file would start due to rotate.
    assert soak.short_caps(50) == soak.SHORT_CAPS
    big = soak.short_caps(200)
    assert big.rrd_max_mb == pytest.approx(80.0) and big.rrd_budget_mb == pytest.approx(240.0)
    assert big.record_max_mb == soak.SHORT_CAPS.record_max_mb
