"""The figure in docs/performance.md: latency percentiles from the throughput runs, and fidelity traces."""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # no display: the benchmark runs headless
import matplotlib.pyplot as plt

from twin.bench import fidelity
from twin.service.persist import write_atomically


def write(results: dict[str, Any], path: Path) -> Path:
    fig, (lat_ax, fid_ax) = plt.subplots(1, 2, figsize=(12, 4.5))

    runs = [r for r in results.get("throughput", []) if r]
    labels: list[str] = []
    series: dict[str, list[float]] = {
        "internal p50": [],
        "internal p99": [],
        "end-to-end p50": [],
        "end-to-end p99": [],
    }
    for run in runs:
        labels.append(f"{run['arms']} arms x {run['rate_hz']:g} Hz")
        agent = run["agent"]
        series["internal p50"].append(1000 * (agent["internal_latency_s"]["p50"] or 0))
        series["internal p99"].append(1000 * (agent["internal_latency_s"]["p99"] or 0))
        series["end-to-end p50"].append(1000 * (agent["end_to_end_latency_s"]["p50"] or 0))
        series["end-to-end p99"].append(1000 * (agent["end_to_end_latency_s"]["p99"] or 0))
    width = 0.2
    for k, (name, values) in enumerate(series.items()):
        xs = [i + (k - 1.5) * width for i in range(len(values))]
        lat_ax.bar(xs, values, width, label=name)
    lat_ax.set_xticks(range(len(labels)), labels)
    lat_ax.set_ylabel("latency (ms)")
    lat_ax.set_yscale("log")
    lat_ax.set_title("Agent latency (receive -> twin updated; publish -> twin updated)")
    lat_ax.legend(fontsize=8)

    trace_hold: list[tuple[float, float, float, float]] = []
    trace_pred: list[tuple[float, float, float, float]] = []
    fidelity.replay("hold", seconds=8, jitter_ms=50, series=trace_hold)
    fidelity.replay("predict", seconds=8, jitter_ms=50, series=trace_pred)
    window = [row for row in trace_pred if 4.0 <= row[0] <= 6.0]
    fid_ax.plot([r[0] for r in window], [math.degrees(r[2]) for r in window], "k-", lw=2, label="true motion")
    hold = [row for row in trace_hold if 4.0 <= row[0] <= 6.0]
    fid_ax.plot([r[0] for r in hold], [math.degrees(r[3]) for r in hold], "C1-", label="hold last value")
    fid_ax.plot(
        [r[0] for r in window], [math.degrees(r[3]) for r in window], "C0--", label="prediction (ours)"
    )
    fid_ax.set_xlabel("edge time (s)")
    fid_ax.set_ylabel("shoulder_pan (deg)")
    fid_ax.set_title("Fidelity at 60 Hz display, 10 Hz telemetry, 50 ms jitter")
    fid_ax.legend(fontsize=8)
    fig.tight_layout()
    # Drawn in memory, then written whole: Ctrl-C or an error mid-save leaves the old plot as it was.
    image = io.BytesIO()
    try:
        fig.savefig(image, dpi=110, format=path.suffix.lstrip(".") or "png")
    finally:
        plt.close(fig)
    write_atomically(path, image.getvalue())
    return path
