"""History benchmarks: bytes per arm-day and the read-back time of one device's hour.

- storage: one arm's day at 10 Hz (864,000 messages) built by the edge simulator (`make_payload`, the edge's
  mock mode: smooth sine motion, diagnostics drawn uniformly at random every message) and decoded by the real
  decoder, written through `HistoryWriter` one commit per simulated 10 minutes, then compacted as the writer's
  maintenance does. Reported: the day's data files after compaction, and the whole table directory.
- read: a fleet's hour (default 100 arms) written with the agent's default cadence (a commit per 10 s of
  data), then one device's hour read back with `HistoryReader.window(...).collect()` (decoded columns
  included), before and after compaction. Fleet messages reuse a few pre-decoded poses per arm with fresh
  timestamps (the cost of decoding 3.6 million messages would dominate the setup and is not what is measured).

The on/off comparison of the mirror itself is `twin bench history-load` (throughput with and without
`--history`), which runs the agent as a child process.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import random
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec

from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
from twin.edge.payload import encode, make_payload
from twin.ops.history import HistoryReader
from twin.output.history import TELEMETRY_TABLE, HistorySettings, HistoryWriter, telemetry_table
from twin.output.sinks import AppliedSample

RATE_HZ = 10.0
# 2026-11-18T00:00:00Z: a whole UTC day, so the day is exactly one partition.
DAY_START_S = 1_795_046_400.0
POSES_PER_ARM = 50


def _dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _active_bytes(uri: str) -> tuple[int, int]:
    from deltalake import DeltaTable  # noqa: PLC0415

    actions = DeltaTable(f"{uri}/{TELEMETRY_TABLE}").get_add_actions(flatten=True)
    sizes = actions.column("size_bytes").to_pylist()
    return int(sum(sizes)), len(sizes)


def storage(*, hours: float = 24.0, variant: str = "ticks", workdir: Path | None = None) -> dict[str, Any]:
    """Bytes one arm's `hours` of 10 Hz telemetry take, compacted; scaled to a day when hours < 24."""
    tmp = Path(tempfile.mkdtemp(prefix="twin-bench-history-", dir=workdir))
    uri = str(tmp / "history")
    try:
        rng = random.Random(7)
        decoder = TelemetryDecoder(DecoderConfig(units=Units(variant)))
        writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0)).start()
        n = round(hours * 3600 * RATE_HZ)
        per_commit = round(600 * RATE_HZ)
        started = time.monotonic()
        batch: list[AppliedSample] = []
        for k in range(n):
            wall = DAY_START_S + k / RATE_HZ
            payload = encode(
                make_payload("arm-001", k / RATE_HZ, variant, rng, timestamp_ms=round(wall * 1000))
            )
            telemetry = decoder.decode(payload)
            batch.append(
                AppliedSample("arm-001", wall + 0.004, 0.0, telemetry, telemetry.angles_rad, payload)
            )
            if len(batch) == per_commit or k == n - 1:
                writer.add(TELEMETRY_TABLE, telemetry_table(batch)[0])
                writer.flush(120)
                batch = []
        write_s = time.monotonic() - started
        before, files_before = _active_bytes(uri)
        writer.close()
        started = time.monotonic()
        # The writer's maintenance, run for the measured day (same target size and zstd level), in its own
        # process as the writer runs it: that process's start is part of compact_s.
        writer.maintain_now(today=dt.datetime.fromtimestamp(DAY_START_S, dt.UTC).date())
        compact_s = time.monotonic() - started
        after, files_after = _active_bytes(uri)
        scale = 24.0 / hours
        return {
            "scenario": "history-storage",
            "variant": variant,
            "hours": hours,
            "messages": n,
            "write_s": round(write_s, 1),
            "compact_s": round(compact_s, 1),
            "data_bytes_before_compaction": before,
            "files_before_compaction": files_before,
            "data_bytes": after,
            "files": files_after,
            "bytes_per_message": round(after / n, 2),
            "mb_per_arm_day": round(after * scale / 1e6, 2),
            "table_dir_bytes": _dir_bytes(tmp / "history" / TELEMETRY_TABLE),
            "notes": (
                "edge mock mode: diagnostics are uniform random each message, so they compress worst; "
                "mb_per_arm_day is the compacted data files" + (" scaled to 24 h" if hours < 24 else "")
            ),
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _fleet_templates(arms: int) -> dict[str, list[AppliedSample]]:
    rng = random.Random(3)
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    out = {}
    for i in range(1, arms + 1):
        device = f"arm-{i:04d}"
        poses = []
        for k in range(POSES_PER_ARM):
            payload = encode(make_payload(device, k * 0.7, "ticks", rng, timestamp_ms=1_795_046_400_000))
            telemetry = decoder.decode(payload)
            poses.append(AppliedSample(device, 0.0, 0.0, telemetry, telemetry.angles_rad, payload))
        out[device] = poses
    return out


def read(*, arms: int = 100, minutes: float = 60.0, commit_every_s: float = 10.0) -> dict[str, Any]:
    """Seconds to read one device's hour from a fleet table, before and after compaction."""
    tmp = Path(tempfile.mkdtemp(prefix="twin-bench-history-read-"))
    uri = str(tmp / "history")
    try:
        writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0)).start()
        steps = round(minutes * 60 * RATE_HZ)
        started = time.monotonic()
        commits = _write_fleet_hour(writer, _fleet_templates(arms), steps, round(commit_every_s * RATE_HZ))
        write_s = time.monotonic() - started
        reader = HistoryReader(uri)
        since = dt.datetime.fromtimestamp(DAY_START_S + 3600, dt.UTC)
        until = since + dt.timedelta(minutes=minutes)

        def timed_read() -> tuple[float, int]:
            t = time.perf_counter()
            rows = reader.window("arm-0001", since, until).collect().height
            return time.perf_counter() - t, rows

        cold_s, rows = timed_read()
        warm_s, _ = timed_read()
        _, files_before = _active_bytes(uri)
        writer.close()
        t = time.monotonic()
        writer.maintain_now(today=dt.datetime.fromtimestamp(DAY_START_S, dt.UTC).date())
        compact_s = time.monotonic() - t
        _, files_after = _active_bytes(uri)
        compacted_s, rows_after = timed_read()
        return {
            "scenario": "history-read",
            "arms": arms,
            "minutes": minutes,
            "rows_in_table": steps * arms,
            "commits": commits,
            "write_s": round(write_s, 1),
            "device_rows_read": rows,
            "files_before_compaction": files_before,
            "read_s_before_compaction": round(cold_s, 3),
            "read_s_before_compaction_warm": round(warm_s, 3),
            "compact_s": round(compact_s, 1),
            "files_after_compaction": files_after,
            "read_s_after_compaction": round(compacted_s, 3),
            "rows_match": rows == rows_after == steps,
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _write_fleet_hour(
    writer: HistoryWriter, templates: dict[str, list[AppliedSample]], steps: int, per_commit: int
) -> int:
    """`steps` 10 Hz samples of every arm from an hour into the day, a commit per `per_commit` steps (the
    agent's default cadence); returns the commits made."""
    commits = 0
    for first in range(0, steps, per_commit):
        batch = []
        for k in range(first, min(steps, first + per_commit)):
            wall = DAY_START_S + 3600 + k / RATE_HZ
            ms = round(wall * 1000)
            for poses in templates.values():
                pose = poses[k % POSES_PER_ARM]
                before, _, after = pose.payload.partition(b"1795046400000")
                telemetry = msgspec.structs.replace(pose.telemetry, timestamp_ms=ms)  # a frozen Struct
                payload = before + str(ms).encode() + after
                batch.append(
                    dataclasses.replace(pose, received_wall_s=wall, telemetry=telemetry, payload=payload)
                )
        writer.add(TELEMETRY_TABLE, telemetry_table(batch)[0])
        writer.flush(120)
        commits += 1
    return commits


def load(*, arms: int = 1000, rate: float = 10.0, seconds: float = 20.0) -> dict[str, Any]:
    """The mirror with history off, then on, under the same offered load; and the table against the sink.

    Both phases run `twin run` as a child process on one private broker (twin.bench.throughput). After
    the second the agent is stopped with SIGTERM (its final commit), and the rows in the tables are compared
    with the messages the agent handed to the history sink (every decoded one + rejected).
    """
    from twin.bench.throughput import agent_phase  # noqa: PLC0415
    from twin.rig.local import LocalRig  # noqa: PLC0415

    tmp = Path(tempfile.mkdtemp(prefix="twin-bench-history-load-"))
    uri = str(tmp / "history")
    try:
        with LocalRig() as rig:
            off = agent_phase(rig, arms, rate, seconds)
            on = agent_phase(rig, arms, rate, seconds, history=uri)
        reader = HistoryReader(uri)
        rows = sum(d.rows for d in reader.summary())
        rejected_rows = sum(reader.rejected_counts().values())
        handed = on["decoded"] + on["rejected"]
        # What the agent's stop said it could not write: history rows it could not commit or hand over, and
        # those its feeds wrote to a writer that never read them.
        unwritten = on["stop"]["unwritten"]
        counted = unwritten.get("history_rows", 0) + unwritten.get("history_rows_unread", 0)

        def ratio(key: str, sub: str | None = None) -> float | None:
            a = off[key] if sub is None else off[key][sub]
            b = on[key] if sub is None else on[key][sub]
            return round(b / a, 4) if a else None

        return {
            "scenario": "history-load",
            "arms": arms,
            "rate_hz": rate,
            "seconds": seconds,
            "off": off,
            "on": on,
            "mirrored_rate_on_over_off": ratio("mirrored_rate"),
            "internal_p99_on_over_off": ratio("internal_latency_s", "p99"),
            "rows_written": rows + rejected_rows,
            "telemetry_rows": rows,
            "rejected_rows": rejected_rows,
            "rows_handed_to_history": handed,
            "rows_equal": rows + rejected_rows == handed,
            "rows_counted_unwritten": counted,
            # Handed, and neither written nor counted as lost: 0 unless rows go missing unseen.
            "rows_unaccounted": handed - (rows + rejected_rows) - counted,
            "table_bytes": _dir_bytes(tmp / "history"),
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
