"""Telemetry history against real storage: the local filesystem (a real tmpfs for the full disk) and S3
through moto's server mode (ThreadedMotoServer on loopback, in a child process: tests/moto_s3.py).

The rows come from the edge simulator's payloads decoded by the real decoder, so raw and decoded values are
what the agent would store.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import errno
import itertools
import json
import logging
import multiprocessing
import os
import random
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
import types
import urllib.request
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import polars as pl
import pytest
from conftest import NO_BROKER, get_metrics, metric, wait_for, wait_handled
from deltalake import CommitProperties, DeltaTable, Transaction, write_deltalake
from dying_writer import check_that_dies, check_that_hangs, writer_killed_in_its_first_commit
from moto_s3 import MotoS3
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
from twin.edge.payload import encode, make_payload
from twin.ops.history import HistoryArgumentError, HistoryReader, HistoryReadError, parse_time, with_decoded
from twin.output.history import (
    JOINTS,
    REJECTED_TABLE,
    TELEMETRY_TABLE,
    HistoryError,
    HistorySettings,
    HistorySink,
    HistoryWriter,
    raw_column,
    rejected_table,
    telemetry_table,
)
from twin.output.history_feed import WRITER_NICE, HistoryFeed, HistoryProcess, WriterFigures
from twin.output.sinks import AppliedSample, RejectedSample, SinkStats
from twin.service.config import AgentConfig, load_config
from twin.service.state import HistoryState

if TYPE_CHECKING:
    from twin.ops.replay import ReplayConfig

T0 = 1_795_000_000.0  # 2026-11-18T09:46:40Z


def samples(
    n: int,
    *,
    device: str = "arm-001",
    variant: str = "ticks",
    start_s: float = T0,
    period_s: float = 0.1,
    seed: int = 1,
    load_sign: bool = True,
) -> list[AppliedSample]:
    rng = random.Random(seed)
    decoder = TelemetryDecoder(DecoderConfig(units=Units(variant)))
    out = []
    for k in range(n):
        wall = start_s + k * period_s
        payload = encode(
            make_payload(
                device, k * period_s, variant, rng, timestamp_ms=round(wall * 1000) - 5, load_sign=load_sign
            )
        )
        telemetry = decoder.decode(payload)
        out.append(AppliedSample(device, wall, wall, telemetry, telemetry.angles_rad, payload))
    return out


def rows_of(uri: str, table: str = TELEMETRY_TABLE, options: dict[str, str] | None = None) -> pl.DataFrame:
    return pl.read_delta(
        str(Path(uri) / table) if "://" not in uri else f"{uri}/{table}", storage_options=options
    )


# --- rows: raw as sent, decoded as the decoder decodes -----------------------------------------------------


@pytest.mark.parametrize("variant", ["ticks", "degrees"])
def test_rows_keep_raw_readings_and_decoded_positions(variant: str) -> None:
    batch = samples(300, variant=variant)
    table, slow = telemetry_table(batch)
    assert not slow
    frame = pl.from_arrow(table)
    for i, sample in enumerate(batch):
        sent = json.loads(sample.payload)["joints"]
        row = frame.row(i, named=True)
        assert row["device_id"] == "arm-001" and row["units"] == variant
        assert row["edge_time"].timestamp() * 1000 == sample.telemetry.timestamp_ms
        for joint in JOINTS:
            assert row[f"{joint}_position_rad"] == sample.telemetry.angles_rad[joint]
            for name in ("position", "velocity", "load", "temp", "current", "voltage"):
                assert row[raw_column(joint, name)] == sent[joint].get(name)


@pytest.mark.parametrize("variant", ["ticks", "degrees"])
def test_decoded_diagnostics_on_read_equal_the_decoder(variant: str) -> None:
    # load_sign puts the sign bits in the raw registers (ticks) or negative loads (degrees): both rules run.
    batch = samples(400, variant=variant, load_sign=True)
    frame = with_decoded(pl.from_arrow(telemetry_table(batch)[0]).lazy()).collect()
    checked = 0
    for i, sample in enumerate(batch):
        row = frame.row(i, named=True)
        for joint in JOINTS:
            diag = sample.telemetry.diagnostics[joint]
            assert row[f"{joint}_velocity_rad_s"] == pytest.approx(diag.velocity_rad_s, rel=1e-12)
            assert row[f"{joint}_load_percent"] == pytest.approx(diag.load_percent, rel=1e-12)
            assert row[f"{joint}_temperature_c"] == diag.temperature_c
            assert row[f"{joint}_current_a"] == pytest.approx(diag.current_a, rel=1e-12)
            if diag.voltage_v is None:
                assert row[f"{joint}_voltage_v"] is None
            else:
                assert row[f"{joint}_voltage_v"] == pytest.approx(diag.voltage_v, rel=1e-12)
            checked += diag.velocity_rad_s < 0 or diag.load_percent < 0
    assert checked > 100  # negative velocities and loads were really exercised


def test_odd_but_valid_payloads_are_stored_exactly() -> None:
    batch = samples(3)
    pretty = json.dumps(json.loads(batch[0].payload), indent=2).encode()  # newlines as whitespace
    duplicate = batch[1].payload.replace(b'"joints":{', b'"joints":{"shoulder_pan":{"position":1},', 1)
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    odd = [
        AppliedSample("arm-001", T0, T0, decoder.decode(pretty), batch[0].joint_angles, pretty),
        AppliedSample("arm-001", T0 + 1, T0 + 1, decoder.decode(duplicate), batch[1].joint_angles, duplicate),
        AppliedSample("arm-001", T0 + 2, T0 + 2, batch[2].telemetry, batch[2].joint_angles),  # no payload
    ]
    table, slow = telemetry_table(odd)
    assert slow  # Arrow's reader refuses the duplicate key; the stdlib parser (the decoder's) takes it
    frame = pl.from_arrow(table)
    assert frame["shoulder_pan_position_raw"][0] == json.loads(pretty)["joints"]["shoulder_pan"]["position"]
    assert (
        frame["shoulder_pan_position_raw"][1] == json.loads(duplicate)["joints"]["shoulder_pan"]["position"]
    )
    assert frame["shoulder_pan_position_raw"][2] is None
    assert frame["shoulder_pan_position_rad"][2] == batch[2].telemetry.angles_rad["shoulder_pan"]


# --- the sink on the local filesystem ---------------------------------------------------------------------


def test_sink_writes_every_sample_partitioned_by_date_and_flushes_on_close(tmp_path: Path) -> None:
    midnight = dt.datetime(2026, 11, 19, tzinfo=dt.UTC).timestamp()
    # 60 s before to 60 s after midnight UTC, then a 30 s pause (a second session), one rejected message.
    first = samples(1200, start_s=midnight - 60)
    second = samples(100, start_s=midnight + 90, seed=2)
    uri = str(tmp_path / "history")
    sink = HistorySink(HistorySettings(uri=uri, commit_every_s=3600, commit_every_rows=500, chunk_rows=100))
    for sample in first + second:
        sink.applied(sample)
    topic = "dt/lerobot/arm-001/telemetry"
    sink.rejected(RejectedSample("arm-001", topic, midnight, "not_json", "bad", b"{x"))
    sink.close()
    queue = sink.stats()  # `delivered` counts the applied samples; the rejected one shows in its table below
    assert (queue.delivered, queue.dropped, queue.errors) == (1300, 0, 0)
    tables = sink.writer.stats().tables
    assert tables[TELEMETRY_TABLE].rows_committed == 1300
    assert tables[TELEMETRY_TABLE].commits >= 2  # 500-row trigger, then the rest on close
    assert tables[REJECTED_TABLE].rows_committed == 1
    frame = rows_of(uri)
    assert frame.height == 1300
    assert sorted(p.name for p in (tmp_path / "history" / TELEMETRY_TABLE).glob("date=*")) == [
        "date=2026-11-18",
        "date=2026-11-19",
    ]
    rejected = rows_of(uri, REJECTED_TABLE)
    assert rejected["reason"].to_list() == ["not_json"] and rejected["payload"].to_list() == [b"{x"]

    summary = HistoryReader(uri).summary()
    assert [d.device_id for d in summary] == ["arm-001"]
    assert [s.rows for s in summary[0].sessions] == [1200, 100]
    assert HistoryReader(uri).rejected_counts() == {"not_json": 1}


def test_commits_follow_the_row_and_time_settings(tmp_path: Path) -> None:
    uri = str(tmp_path / "h")
    writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=0.2, commit_every_rows=10_000)).start()
    try:
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(50))[0])
        wait_for(lambda: writer.stats().tables[TELEMETRY_TABLE].commits, 30, "a commit")
        # Nothing asked for a flush: the 0.2 s age bound committed the 50 rows on its own.
        assert writer.stats().tables[TELEMETRY_TABLE].rows_committed == 50
    finally:
        writer.close()
    assert rows_of(uri).height == 50


def test_the_writer_process_counts_a_commit_in_its_shared_counters_as_it_is_made(tmp_path: Path) -> None:
    """The writer process's shared counters (what the agent reads of a writer that died) hold a commit once it
    is made, on the committer thread, not at the receiving loop's next turn up to 0.2 s later: a writer
    killed right after a commit has none of the rows it committed counted as lost."""
    from multiprocessing import Array, Pipe
    from multiprocessing.connection import Listener

    from twin.output.history_feed import (
        _COMMITS,
        _COMMITTED,
        _COUNTERS,
        _IN_ROWS,
        _IN_SEQ,
        _IN_TABLE,
        _Receiver,
    )

    writer = HistoryWriter(
        HistorySettings(uri=str(tmp_path / "h"), commit_every_s=3600.0, commit_every_rows=10_000)
    ).start()
    listener = Listener(str(tmp_path / "feeds.sock"), family="AF_UNIX")
    control, _agent_end = Pipe()
    counters = Array("q", _COUNTERS, lock=False)
    receiver = _Receiver(writer, listener, control, counters)
    try:
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(50))[0])
        assert writer.flush()
        # The flush returns after the commit: the counters have it, and the receiver's loop never ran.
        assert (counters[_COMMITTED], counters[_COMMITS]) == (50, 1)
        # The commit it was in (seq 1, 50 rows) was recorded before the append and is no longer in doubt.
        assert (counters[_IN_TABLE], counters[_IN_SEQ], counters[_IN_ROWS]) == (0, 1, 50)
    finally:
        receiver._closed = True  # its accept thread ends with the listener, as at a stop
        listener.close()
        writer.close()


def test_an_outage_keeps_rows_bounded_counts_drops_and_recovers(tmp_path: Path) -> None:
    base = tmp_path / "h"
    base.mkdir()
    blocker = base / TELEMETRY_TABLE
    blocker.write_text("not a directory")  # every commit to <uri>/telemetry fails until it goes
    settings = HistorySettings(
        uri=str(base), commit_every_s=0.05, commit_every_rows=100, max_buffer_rows=300, retry_min_s=0.05
    )
    writer = HistoryWriter(settings).start()
    try:
        batch = samples(600)
        for i in range(0, 600, 100):
            writer.add(TELEMETRY_TABLE, telemetry_table(batch[i : i + 100])[0])
            # Spread over time so commits fail while rows still come (the counts below do not depend on it).
            time.sleep(0.1)
        assert not writer.flush(5)
        stats = writer.stats()
        table = stats.tables[TELEMETRY_TABLE]
        assert not stats.storage_ok and table.commit_failures >= 1
        assert "cannot write history" in stats.last_error
        # The bound held: 300 rows kept (queued plus the batch being retried), the other 300 counted.
        assert table.rows_dropped == 300 and writer.buffered_rows() == 300
        blocker.unlink()
        assert writer.flush(10)
    finally:
        writer.close()
    frame = rows_of(str(base))
    assert frame.height == 300
    assert frame["edge_time"].n_unique() == 300
    assert writer.stats().tables[TELEMETRY_TABLE].rows_committed == 300


def test_storage_reads_failing_while_any_tables_last_commit_failed(tmp_path: Path) -> None:
    """One table failing and another committing set storage_ok back to 1 at each good commit, mid-round:
    the HistoryCommitsFailing gauge could read 0 in a minute and break its alarm's five-minute run."""
    base = tmp_path / "h"
    base.mkdir()
    blocker = base / TELEMETRY_TABLE
    blocker.write_text("not a directory")  # telemetry's commits fail; rejected's work
    writer = HistoryWriter(HistorySettings(uri=str(base), commit_every_s=3600)).start()
    seen: list[bool] = []
    writer.on_commit = lambda: seen.append(writer.stats().storage_ok)  # right after each good commit
    try:
        for k in range(2):  # two rounds: whichever table a round commits first, the other's state counts
            writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=T0 + k))[0])
            bad = RejectedSample("arm-001", "dt/lerobot/arm-001/telemetry", T0 + k, "not_json", "bad", b"{x")
            writer.add(REJECTED_TABLE, rejected_table([bad], 100))
            assert not writer.flush(10)
        assert seen == [False, False] and not writer.stats().storage_ok
        blocker.unlink()
        assert writer.flush(10) and writer.stats().storage_ok
    finally:
        writer.close()
    assert writer.stats().tables[TELEMETRY_TABLE].rows_committed == 20


def writer_with_a_broken_table(
    tmp_path: Path, broken: str, *, commit_every_s: float, retry_min_s: float
) -> tuple[HistoryWriter, list[float]]:
    """A started writer whose `broken` table's commits fail (a file where its directory goes), on a clock
    the test moves (`now[0]`), backing off up to 60 s."""
    base = tmp_path / "h"
    base.mkdir()
    (base / broken).write_text("not a directory")
    now = [1000.0]
    settings = HistorySettings(
        uri=str(base), commit_every_s=commit_every_s, retry_min_s=retry_min_s, retry_max_s=60
    )
    return HistoryWriter(settings, clock=lambda: now[0]).start(), now


def test_a_table_that_keeps_failing_backs_off_while_another_commits(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Each good commit of the rejected table set the backoff back to retry_min_s and let the next failure's
    line through: telemetry failing alone was retried and logged every second."""
    # telemetry's commits fail; rejected's work
    writer, _ = writer_with_a_broken_table(tmp_path, TELEMETRY_TABLE, commit_every_s=3600, retry_min_s=1)
    try:
        with caplog.at_level(logging.ERROR, logger="twin.output.history"):
            for k in range(3):
                writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=T0 + k))[0])
                bad = RejectedSample("arm-001", "dt/lerobot/arm-001/telemetry", T0 + k, "not_json", "", b"{")
                writer.add(REJECTED_TABLE, rejected_table([bad], 100))
                assert not writer.flush(10)
        said = [r.getMessage() for r in caplog.records if "rows kept in memory" in r.getMessage()]
    finally:
        writer.close(timeout=0)
    assert len(said) == 1 and "retrying in 1 s" in said[0], said  # then 2 s, 4 s: within the line's 10 s
    assert writer.stats().tables[REJECTED_TABLE].rows_committed == 3


def test_a_failing_table_does_not_hold_back_the_commits_of_one_whose_storage_works(tmp_path: Path) -> None:
    """Both tables waited out one backoff: with the rejected table failing, telemetry committed once per
    retry_max_s, and at high rates its buffer filled and dropped rows its storage would have taken."""
    # rejected's commits fail; telemetry's work
    writer, now = writer_with_a_broken_table(tmp_path, REJECTED_TABLE, commit_every_s=5, retry_min_s=60)
    try:
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10))[0])
        bad = RejectedSample("arm-001", "dt/lerobot/arm-001/telemetry", T0, "not_json", "", b"{")
        writer.add(REJECTED_TABLE, rejected_table([bad], 100))
        assert not writer.flush(10)  # rejected now waits out its 60 s
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=T0 + 1))[0])
        now[0] += 5  # telemetry's commit_every_s, well within rejected's backoff
        committed = lambda: writer.stats().tables[TELEMETRY_TABLE].rows_committed  # noqa: E731
        wait_for(lambda: committed() == 20, 10, "telemetry's second commit")
        tables = writer.stats().tables
    finally:
        writer.close(timeout=0)
    assert tables[REJECTED_TABLE].commit_failures == 1  # and rejected is not retried before its time


def test_a_commit_failing_at_the_stop_says_it_is_retried_each_second(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A walk stopped an agent on a full disk: for the minute of its stop budget the log said "retrying in
    60 s" (the backoff it had reached) while it retried every second."""
    base = tmp_path / "h"
    base.mkdir()
    (base / TELEMETRY_TABLE).write_text("not a directory")  # every commit fails
    now = [1000.0]
    settings = HistorySettings(uri=str(base), commit_every_s=3600, retry_min_s=60, retry_max_s=60)
    writer = HistoryWriter(settings, clock=lambda: now[0]).start()
    writer.add(TELEMETRY_TABLE, telemetry_table(samples(10))[0])
    with caplog.at_level(logging.ERROR, logger="twin.output.history"):
        assert not writer.flush(5)
        now[0] += 11  # the next error line is due
        writer.close(timeout=1.5)
    said = [r.getMessage() for r in caplog.records if "rows kept in memory" in r.getMessage()]
    assert len(said) >= 2 and "retrying in 60 s" in said[0]
    assert all("retrying in 1 s" in line for line in said[1:-1]), said
    # The last attempt before the deadline: no retry follows it.
    assert "not retried: the stop gives up on them at its deadline" in said[-1], said


def test_a_flush_that_got_a_failing_table_through_puts_its_commits_back_on_schedule(tmp_path: Path) -> None:
    """A flush (and the stop) commits whatever the backoff says; it also ends the backoff's wait, or a table
    whose storage came back during a flush would wait out the rest of its 60 s before its next commit."""
    base = tmp_path / "h"
    base.mkdir()
    broken = base / TELEMETRY_TABLE
    broken.write_text("not a directory")  # every commit fails until it goes
    now = [1000.0]
    settings = HistorySettings(uri=str(base), commit_every_s=5, retry_min_s=60, retry_max_s=60)
    writer = HistoryWriter(settings, clock=lambda: now[0]).start()
    try:
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10))[0])
        assert not writer.flush(10)  # the table now backs off 60 s
        broken.unlink()
        assert writer.flush(10)
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=T0 + 1))[0])
        now[0] += 5  # commit_every_s, well within the 60 s backoff
        committed = lambda: writer.stats().tables[TELEMETRY_TABLE].rows_committed  # noqa: E731
        wait_for(lambda: committed() == 20, 10, "the commit on schedule")
    finally:
        writer.close(timeout=0)


def test_a_full_disk_is_a_clear_error_and_writing_resumes_when_space_returns(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """On a full disk each commit attempt also printed deltalake's Rust panic on stderr ("Already shut
    down", a backtrace with RUST_BACKTRACE set): after the first, the writer fails each retry itself."""
    mount = tmp_path / "small"
    mount.mkdir()
    # A real filesystem that really fills: a 2 MiB tmpfs (the tests run as root, as `make setup` does).
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mount)], check=True)
    try:
        uri = str(mount / "history")
        writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, retry_min_s=0.05)).start()
        try:
            writer.add(TELEMETRY_TABLE, telemetry_table(samples(100))[0])
            assert writer.flush(10)
            filler = mount / "filler"
            with filler.open("wb") as fh:
                try:
                    while True:
                        fh.write(b"\0" * 65536)
                        fh.flush()
                except OSError:
                    pass
            writer.add(TELEMETRY_TABLE, telemetry_table(samples(2000, start_s=T0 + 100))[0])
            assert not writer.flush(10)
            assert "disk is full" in writer.stats().last_error
            capfd.readouterr()  # the first attempt meets the full disk in deltalake, and may panic there
            assert not writer.flush(10)  # a retry is failed before deltalake is called
            assert "bytes free, below the" in writer.stats().last_error
            assert "panicked" not in capfd.readouterr().err
            assert writer.buffered_rows() == 2000
            filler.unlink()
            assert writer.flush(10)
        finally:
            writer.close()
        frame = rows_of(uri)
        assert frame.height == 2100
        assert frame["received_at"].n_unique() == 2100  # nothing written twice
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_retried_commit_that_had_landed_is_not_written_twice(tmp_path: Path) -> None:
    uri = str(tmp_path / "h")
    writer = HistoryWriter(HistorySettings(uri=uri), writer_id="test-writer")
    rows = telemetry_table(samples(10))[0]
    assert writer._append(TELEMETRY_TABLE, rows, seq=1) == 1  # version 0 created the table
    # The same sequence number again, as after a commit whose answer was lost: recognised, skipped.
    assert writer._append(TELEMETRY_TABLE, rows, seq=1) is None
    assert writer._append(TELEMETRY_TABLE, rows, seq=2) == 2
    assert rows_of(uri).height == 20


def test_two_writers_append_to_one_table_and_a_stale_commit_is_retried(tmp_path: Path) -> None:
    uri = str(tmp_path / "h")
    writers = [
        HistoryWriter(
            HistorySettings(uri=uri, commit_every_s=0.02, commit_every_rows=50), writer_id=f"w{i}"
        ).start()
        for i in range(2)
    ]

    def feed(i: int) -> None:
        batch = samples(1000, device=f"arm-00{i + 1}", seed=i)
        for k in range(0, 1000, 50):
            writers[i].add(TELEMETRY_TABLE, telemetry_table(batch[k : k + 50])[0])
            time.sleep(0.005)  # interleave the two writers' commits; nothing below depends on how they fall

    threads = [threading.Thread(target=feed, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for w in writers:
        w.close()
    frame = rows_of(uri)
    assert frame.group_by("device_id").len().sort("device_id")["len"].to_list() == [1000, 1000]
    commits = sum(w.stats().tables[TELEMETRY_TABLE].commits for w in writers)
    table = DeltaTable(str(Path(uri) / TELEMETRY_TABLE))
    assert table.version() == commits  # version 0 created it; then one version a commit, none lost

    # A commit conflict made on purpose: a handle still at the old version appends after another writer.
    stale = DeltaTable(str(Path(uri) / TELEMETRY_TABLE))
    before = stale.version()
    write_deltalake(table, telemetry_table(samples(5, start_s=T0 + 500))[0], mode="append")
    write_deltalake(
        stale,
        telemetry_table(samples(5, start_s=T0 + 600))[0],
        mode="append",
        commit_properties=CommitProperties(app_transactions=[Transaction("stale", 1)]),
    )
    assert stale.version() == before + 2  # the loser re-read the log and committed after the winner
    assert rows_of(uri).height == 2010


def test_only_one_of_two_writers_maintains_a_table_per_window(tmp_path: Path) -> None:
    uri = str(tmp_path / "h")
    settings = HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=3600)
    # One wall clock for both, read by their maintenance processes too: the two runs are in one lease
    # window and the rows in one day whenever the test runs (on the real clock, a run across an hour's
    # turn leased two windows, and one across 00:00 UTC wrote two days).
    writers = [HistoryWriter(settings, writer_id=f"m{i}", wall_clock=lambda: T0).start() for i in range(2)]
    for k in range(5):
        writers[k % 2].add(TELEMETRY_TABLE, telemetry_table(samples(100, start_s=T0 + 20 * k))[0])
        assert writers[k % 2].flush(10)
    for w in writers:
        w.close()
    # Both at once: without the lease, delta-rs 1.6 commits both compactions and every row appears twice.
    threads = [threading.Thread(target=w.maintain_now) for w in writers]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    stats = [w.stats() for w in writers]
    # Each table's lease went to one writer; the other skipped it (two tables, two skips in all).
    assert sum(s.maintenance_skipped for s in stats) == 2
    assert sum(s.maintenance_failures for s in stats) == 0
    assert len(DeltaTable(str(Path(uri) / TELEMETRY_TABLE)).file_uris()) == 1
    assert rows_of(uri).height == 500
    # The maintenance processes leased the window their writers asked in, by the writers' clock.
    window = int(T0 // 3600)
    leases = sorted(p.name for p in (Path(uri) / "_maintenance").glob("*.lease"))
    assert leases == sorted(f"{table}-{window}.lease" for table in (TELEMETRY_TABLE, REJECTED_TABLE))


@pytest.mark.parametrize(("retention_hours", "kept"), [(0, 1), (0.5, 5)])
def test_maintenance_compacts_checkpoints_and_vacuums(
    tmp_path: Path, retention_hours: float, kept: int
) -> None:
    """Compaction replaces the four small files with one; the vacuum removes them at once with a retention
    of 0, and keeps them with half an hour (rounded up to the whole hour delta-rs takes: truncated, it was 0
    and took the files from under a reader still on the version before)."""
    uri = str(tmp_path / "h")
    writer = HistoryWriter(
        HistorySettings(
            uri=uri, commit_every_s=3600, maintain_every_s=0, vacuum_retention_hours=retention_hours
        ),
        wall_clock=lambda: T0,  # the rows' day is the day maintained, whenever the test runs
    ).start()
    for k in range(4):
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(100, start_s=T0 + 20 * k))[0])
        assert writer.flush(10)
    writer.close()
    writer.maintain_now()
    stats = writer.stats()
    assert stats.maintenance_runs >= 1 and stats.maintenance_failures == 0
    location = Path(uri) / TELEMETRY_TABLE
    assert len(DeltaTable(str(location)).file_uris()) == 1
    data_files = [p for p in location.rglob("*.parquet") if "_delta_log" not in p.parts]
    assert len(data_files) == kept  # the four small files vacuumed, or kept for the retention
    assert list((location / "_delta_log").glob("*.checkpoint.parquet"))
    assert rows_of(uri).height == 400


def test_maintenance_runs_in_a_process_that_exits_and_its_log_reaches_ours(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    uri = str(tmp_path / "h")
    writer = HistoryWriter(
        HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0), wall_clock=lambda: T0
    ).start()
    for k in range(3):
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(100, start_s=T0 + 20 * k))[0])
        assert writer.flush(10)
    writer.close()
    caplog.set_level("INFO", logger="twin.output.history")
    writer.maintain_now()
    assert writer.stats().maintenance_runs == 1  # the telemetry table; the rejected one does not exist
    compacted = [r for r in caplog.records if r.getMessage().startswith("history: compacted telemetry/")]
    # Logged by the maintenance process, which is gone: its pid is not ours.
    assert compacted and getattr(compacted[0], "maintenance_pid", os.getpid()) != os.getpid()
    assert getattr(compacted[0], "files_removed", None) == 3
    assert rows_of(uri).height == 300


DAY_S = 86400.0


def _history_on_days(uri: str, days_back: Iterable[int]) -> dict[str, int]:
    """10 telemetry rows on each of the days `days_back` before T0's, and one rejected row on each; the
    rows per UTC date."""
    writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0)).start()
    written: dict[str, int] = {}
    for back in days_back:
        start = T0 - back * DAY_S
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=start))[0])
        rejected = RejectedSample("arm-001", "dt/lerobot/arm-001/telemetry", start, "not_json", "bad", b"{x")
        writer.add(REJECTED_TABLE, rejected_table([rejected], 100))
        written[dt.datetime.fromtimestamp(start, dt.UTC).date().isoformat()] = 10
    assert writer.flush(10)
    writer.close()
    return written


def _rows_per_day(uri: str, table: str = TELEMETRY_TABLE) -> dict[str, int]:
    counts = rows_of(uri, table).group_by("date").len()
    return {str(day): n for day, n in counts.iter_rows()}


def test_keep_days_deletes_the_days_before_the_last_n_and_vacuum_frees_their_files(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    uri = str(tmp_path / "h")
    written = _history_on_days(uri, [40, 3, 2, 1, 0])
    today = dt.datetime.fromtimestamp(T0, dt.UTC).date()
    kept = {day: n for day, n in written.items() if day >= (today - dt.timedelta(days=2)).isoformat()}
    assert len(kept) == 3  # today and the two whole days before it
    settings = HistorySettings(uri=uri, maintain_every_s=0, vacuum_retention_hours=0, keep_days=2)
    wall = [T0]
    writer = HistoryWriter(settings, wall_clock=lambda: wall[0])
    caplog.set_level("INFO", logger="twin.output.history")
    writer.maintain_now(today)  # in the maintenance process, as the agent runs it
    assert _rows_per_day(uri) == kept
    assert set(_rows_per_day(uri, REJECTED_TABLE)) == set(kept)
    stats = writer.stats()
    assert (stats.rows_expired, stats.maintenance_runs, stats.maintenance_failures) == (2 * 10 + 2, 2, 0)
    said = [r.getMessage() for r in caplog.records if "older than keep_days" in r.getMessage()]
    old = sorted(set(written) - set(kept))
    assert f"history: deleted 20 rows of telemetry older than keep_days = 2 ({', '.join(old)})" in said
    # The vacuum (retention 0 here) took the deleted days' files off the disk.
    for table in (TELEMETRY_TABLE, REJECTED_TABLE):
        assert not [p for day in old for p in (Path(uri) / table / f"date={day}").glob("*.parquet")]
    # A second run finds nothing more to delete: it says nothing of it and commits nothing for it.
    caplog.clear()
    wall[0] = T0 + 3600  # the next maintenance window (the lease is per window), the same day
    writer.maintain_now(today)
    assert (writer.stats().rows_expired, writer.stats().maintenance_runs) == (22, 4)
    assert not [r for r in caplog.records if "older than keep_days" in r.getMessage()]
    operations = [c["operation"] for c in DeltaTable(str(Path(uri) / TELEMETRY_TABLE)).history()]
    assert operations.count("DELETE") == 1


def test_keep_days_under_a_wall_clock_stepped_far_forward_keeps_the_newest_days_with_rows(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A wall clock stepped to 2099 (a bad NTP answer at first boot) put every day before keep_days' cut,
    and the first maintenance deleted the whole history. The newest keep_days + 1 days that hold rows stay;
    older ones go only as rows of later days come in."""
    uri = str(tmp_path / "h")
    written = _history_on_days(uri, [40, 3, 2, 1, 0])
    settings = HistorySettings(uri=uri, maintain_every_s=0, vacuum_retention_hours=0, keep_days=2)
    y2099 = dt.datetime(2099, 6, 1, 12, tzinfo=dt.UTC).timestamp()
    wall = [y2099]
    writer = HistoryWriter(settings, wall_clock=lambda: wall[0])
    caplog.set_level("INFO", logger="twin.output.history")
    writer.maintain_now()  # today from the writer's (stepped) clock
    newest = sorted(written)[-3:]
    assert _rows_per_day(uri) == {day: written[day] for day in newest}
    assert set(_rows_per_day(uri, REJECTED_TABLE)) == set(newest)
    said = [r for r in caplog.records if "that the clock (today 2099-06-01)" in r.getMessage()]
    assert said and said[0].levelno == logging.WARNING and "the clock stepped" in said[0].getMessage()
    # The agent writes on at the stepped clock: each new day with rows lets one older day go, no more.
    writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0)).start()
    writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=y2099))[0])
    assert writer.flush(10)
    writer.close()
    wall[0] += 3600  # the next maintenance window (the lease is per window)
    HistoryWriter(settings, wall_clock=lambda: wall[0]).maintain_now()
    assert _rows_per_day(uri) == {**{day: written[day] for day in newest[1:]}, "2099-06-01": 10}


def test_the_rows_keep_days_deleted_reach_state_and_metrics(tmp_path: Path) -> None:
    """Rows deleted on purpose are counted where an operator looks, apart from rows lost: the writer's count
    crosses the process boundary (its figures), becomes /state's, sums over workers, and is on /metrics."""
    from types import SimpleNamespace

    from twin.output.history import TableStats, WriterStats
    from twin.output.history_feed import HistoryFigures, _figures_of
    from twin.service.agent import AgentService
    from twin.service.metrics import render_metrics
    from twin.service.state import AgentInfo, AgentState

    stats = WriterStats(tables={name: TableStats() for name in (TELEMETRY_TABLE, REJECTED_TABLE)})
    stats.rows_expired = 22
    figures = HistoryFigures(_figures_of(stats, 0), pid=None, restarts=0, rows_received=0, rows_lost=0)
    agent = SimpleNamespace(config=load_config(None, {"history.uri": str(tmp_path)}))
    process = SimpleNamespace(figures=lambda: figures)
    history = AgentService._history_state(agent, process)  # type: ignore[arg-type]
    assert (history.rows_expired, history.rows_not_written) == (22, 0)
    text = render_metrics(AgentState(agent=AgentInfo(history=history), devices={}))
    assert "twin_history_rows_expired_total 22.0" in text.splitlines()


def test_a_writer_that_has_not_tried_its_storage_yet_reports_it_unknown_not_ok(tmp_path: Path) -> None:
    """A history writer started again (or new) said its storage was OK before its first commit: /state's
    storage_ok is null and /metrics has no twin_history_storage_ok until then, and CloudWatch's
    HistoryCommitsFailing stays 0 (no commit has failed)."""
    from types import SimpleNamespace

    from twin.output.history_feed import HistoryFigures, _figures_of
    from twin.service.agent import AgentService, fleet_totals
    from twin.service.metrics import render_metrics
    from twin.service.shards import _merge_history
    from twin.service.state import AgentInfo, AgentState

    writer = HistoryWriter(HistorySettings(uri=str(tmp_path / "h"), commit_every_s=3600)).start()
    try:
        assert writer.flush(10)  # nothing queued: no attempt, nothing failed
        untried = writer.stats()
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10))[0])
        assert writer.flush(10)
        tried = writer.stats()
    finally:
        writer.close()
    assert (untried.storage_ok, tried.storage_ok) == (None, True)
    agent = SimpleNamespace(config=load_config(None, {"history.uri": str(tmp_path)}))
    for stats, shown in [(untried, None), (tried, "1.0")]:
        figures = HistoryFigures(_figures_of(stats, 0), pid=None, restarts=0, rows_received=0, rows_lost=0)
        process = SimpleNamespace(figures=lambda f=figures: f)
        history = AgentService._history_state(agent, process)  # type: ignore[arg-type]
        state = AgentState(agent=AgentInfo(history=history), devices={})
        read_back = AgentState.from_json(state.to_json()).agent.history
        assert read_back is not None and read_back.storage_ok is stats.storage_ok
        ok = [ln for ln in render_metrics(state).splitlines() if ln.startswith("twin_history_storage_ok ")]
        assert ok == ([f"twin_history_storage_ok {shown}"] if shown else [])
        assert fleet_totals(state, 10.0).history_commits_failing == 0
    pairs = [(None, None), (None, True), (True, False), (None, False)]
    merged = [_merge_history([HistoryState(storage_ok=a), HistoryState(storage_ok=b)]) for a, b in pairs]
    assert [m.storage_ok for m in merged if m is not None] == [None, True, False, False]


def test_keep_days_0_keeps_every_day(tmp_path: Path) -> None:
    uri = str(tmp_path / "h")
    written = _history_on_days(uri, [400, 40, 1, 0])
    writer = HistoryWriter(HistorySettings(uri=uri, maintain_every_s=0, vacuum_retention_hours=0))
    writer.maintain_now(dt.datetime.fromtimestamp(T0, dt.UTC).date())
    assert _rows_per_day(uri) == written
    assert len(_rows_per_day(uri, REJECTED_TABLE)) == 4
    assert (writer.stats().rows_expired, writer.stats().maintenance_failures) == (0, 0)


def test_keep_days_reaches_the_writer_from_the_config(tmp_path: Path) -> None:
    from twin.service.agent import history_settings

    settings = history_settings(load_config(None, {"history.uri": str(tmp_path), "history.keep_days": 30}))
    assert settings is not None
    settings.pop("writer_nice")  # the writer process's own, not HistorySettings'
    assert HistorySettings(**settings).keep_days == 30


@pytest.mark.parametrize("bad", [-1, 1.5, True, "30"])
def test_a_keep_days_that_is_not_a_whole_number_of_days_is_refused(tmp_path: Path, bad: Any) -> None:
    with pytest.raises(HistoryError, match=re.escape(f"history keep_days = {bad!r} must be a whole number")):
        HistorySettings(uri=str(tmp_path / "h"), keep_days=bad)


def test_a_failed_maintenance_process_is_counted_and_named(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    uri = str(tmp_path / "h")
    writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0)).start()
    writer.add(TELEMETRY_TABLE, telemetry_table(samples(10))[0])
    assert writer.flush(10)
    writer.close()
    writer.maintenance_command = [sys.executable, "-c", "import sys; sys.exit(3)"]
    writer.maintain_now()
    stats = writer.stats()
    assert (stats.maintenance_runs, stats.maintenance_failures) == (0, 1)
    assert "maintenance process failed" in stats.last_error and "exit code 3" in stats.last_error
    assert any("the maintenance process failed" in r.getMessage() for r in caplog.records)
    assert rows_of(uri).height == 10  # nothing of the table was touched


def test_a_running_maintenance_process_is_stopped_at_shutdown(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    uri = str(tmp_path / "h")
    started = tmp_path / "maintenance-started"
    writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0.2))
    # A maintenance process that would outlive any shutdown budget: it says it started, then sleeps.
    writer.maintenance_command = [
        sys.executable,
        "-c",
        "import pathlib, sys, time; pathlib.Path(sys.argv[1]).touch(); time.sleep(600)",
        str(started),
    ]
    writer.start()
    wait_for(started.exists, 60, "the committer to start its maintenance process")
    writer.close(timeout=5)
    # Stopped, not waited for: the committer thread ended within close's wait, and no failure is counted.
    assert not writer._thread.is_alive()
    assert writer.stats().maintenance_failures == 0
    assert any("stopped by the shutdown" in r.getMessage() for r in caplog.records)


# The real maintenance process, held at its start until the test lets it go on.
HELD_MAINTENANCE = (
    "import pathlib, runpy, sys, time\n"
    "started, release = map(pathlib.Path, sys.argv[1:3])\n"
    "started.touch()\n"
    "while not release.exists():\n"
    "    time.sleep(0.05)\n"
    "sys.argv = sys.argv[:1]\n"
    "runpy.run_module('twin.output.history_maintain', run_name='__main__')\n"
)


def test_the_committer_keeps_committing_while_its_maintenance_runs(tmp_path: Path) -> None:
    uri = str(tmp_path / "h")
    started, release = tmp_path / "maintenance-started", tmp_path / "maintenance-may-go-on"
    now = [0.0]
    writer = HistoryWriter(
        HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=100),
        clock=lambda: now[0],
        wall_clock=lambda: T0,
    )
    writer.maintenance_command = [sys.executable, "-c", HELD_MAINTENANCE, str(started), str(release)]
    writer.start()
    try:
        for k in range(3):
            writer.add(TELEMETRY_TABLE, telemetry_table(samples(100, start_s=T0 + 20 * k))[0])
            assert writer.flush(10)
        now[0] = 150.0  # maintenance is due: the committer sees it within a second
        wait_for(started.exists, 60, "the committer to start its maintenance process")
        for k in range(3, 6):
            writer.add(TELEMETRY_TABLE, telemetry_table(samples(100, start_s=T0 + 20 * k))[0])
            assert writer.flush(10), "a commit waited for the maintenance process"
        stats = writer.stats()
        assert stats.maintenance_runs == 0 and stats.tables[TELEMETRY_TABLE].commits == 6
        assert stats.lag_s == 0.0
        release.touch()
        wait_for(lambda: writer.stats().maintenance_runs == 1, 120, "the maintenance run to finish")
        # The next append reopens the table maintenance changed, and still lands.
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(100, start_s=T0 + 200))[0])
        assert writer.flush(10)
    finally:
        writer.close()
    stats = writer.stats()
    assert stats.maintenance_failures == 0 and stats.tables[TELEMETRY_TABLE].opens == 2
    assert rows_of(uri).height == 700


def test_appends_during_a_compaction_of_their_partition_keep_every_row_once(tmp_path: Path) -> None:
    uri = str(tmp_path / "h")
    writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0)).start()
    for k in range(40):
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(50, start_s=T0 + 10 * k))[0])
        assert writer.flush(10)
    compactor = HistoryWriter(
        HistorySettings(uri=uri, maintain_every_s=0), writer_id="compactor", maintain_in_child=False
    )
    done = threading.Event()

    def compact() -> None:
        try:
            compactor.maintain_now(today=dt.datetime.fromtimestamp(T0, dt.UTC).date())
        finally:
            done.set()

    thread = threading.Thread(target=compact)
    thread.start()
    appended = 0
    # Appends to the day being compacted, for as long as the compaction runs (at least three).
    while not done.is_set() or appended < 3:
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(50, start_s=T0 + 400 + 10 * appended))[0])
        assert writer.flush(10)
        appended += 1
    thread.join()
    writer.close()
    stats = compactor.stats()
    assert (stats.maintenance_runs, stats.maintenance_failures, stats.maintenance_conflicts) == (1, 0, 0)
    frame = rows_of(uri)
    assert frame.height == 50 * (40 + appended)
    assert frame.select("device_id", "received_at").is_duplicated().sum() == 0
    operations = [h.get("operation") for h in DeltaTable(str(Path(uri) / TELEMETRY_TABLE)).history()]
    assert "OPTIMIZE" in operations


def test_maintain_now_with_maintenance_off_does_not_make_the_committer_maintain(tmp_path: Path) -> None:
    uri = str(tmp_path / "h")
    writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0)).start()
    try:
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10))[0])
        assert writer.flush(10)
        writer.maintain_now()
        assert writer.stats().maintenance_runs == 1
        # The committer checks for due maintenance after each commit round: the second flush waits for
        # whatever the first one's round started. Maintenance off means it started none.
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=T0 + 60))[0])
        assert writer.flush(10)
        assert writer.flush(10)
        stats = writer.stats()
        assert (stats.maintenance_runs, stats.maintenance_skipped) == (1, 0)
    finally:
        writer.close()


def test_the_writer_opens_its_table_anew_every_n_commits(tmp_path: Path) -> None:
    uri = str(tmp_path / "h")
    writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600), reopen_every=2).start()
    try:
        for k in range(5):
            writer.add(TELEMETRY_TABLE, telemetry_table(samples(20, start_s=T0 + 10 * k))[0])
            assert writer.flush(10)
        table = writer.stats().tables[TELEMETRY_TABLE]
        # Opened for commits 1, 3 and 5; each commit still saw the versions before it.
        assert (table.commits, table.opens) == (5, 3)
        assert table.last_commit_version == 5  # version 0 is the table's creation
    finally:
        writer.close()
    assert rows_of(uri).height == 100
    with pytest.raises(ValueError, match="reopen_every"):
        HistoryWriter(HistorySettings(uri=uri), reopen_every=0)


def test_settings_refuse_bad_values_with_the_fix() -> None:
    with pytest.raises(HistoryError, match="uri is empty"):
        HistorySettings(uri=" ")
    # The shared rule for locations (core.locations), as `[history] uri` and `--history` take it: the value
    # named, with a directory or s3:// to give instead.
    for uri, problem in (
        ("gs://bucket/h", "is not a directory or s3://bucket/prefix"),
        ("s3a://bucket/h", "is not a directory or s3://bucket/prefix"),
        ("s3:/bucket/h", "lacks the '//'"),
        ("s3:///h", "names no bucket"),
    ):
        with pytest.raises(HistoryError, match=re.escape(f"history uri {uri!r} {problem}")) as refused:
            HistorySettings(uri=uri)
        assert '"s3://bucket/history"' in str(refused.value)
    with pytest.raises(HistoryError, match="max_buffer_rows"):
        HistorySettings(uri="h", max_buffer_rows=10, commit_every_rows=100)


def test_reader_errors_and_times() -> None:
    now = dt.datetime(2026, 11, 21, 12, tzinfo=dt.UTC)
    assert parse_time("2h", now=now) == now - dt.timedelta(hours=2)
    assert parse_time("now", now=now) == now
    assert parse_time("-30m", now=now) == now - dt.timedelta(minutes=30)
    assert parse_time("2026-11-21T10:00:00") == dt.datetime(2026, 11, 21, 10, tzinfo=dt.UTC)
    assert parse_time("2026-11-21T10:00:00+01:00") == dt.datetime(2026, 11, 21, 9, tzinfo=dt.UTC)
    assert parse_time("1795000000") == dt.datetime.fromtimestamp(1_795_000_000, dt.UTC)
    with pytest.raises(HistoryReadError, match="ISO 8601"):
        parse_time("yesterday-ish")
    # Out of datetime's range: an OverflowError or ValueError traceback in a walk, now a usage error.
    for far in ("1e20", "99999999999999", "100000000d"):
        with pytest.raises(HistoryArgumentError, match=f"time '{far}' is out of range"):
            parse_time(far, now=now)
    # A bare negative number was epoch seconds before 1970: --since=-5 selected everything, said nowhere.
    with pytest.raises(HistoryArgumentError, match=r"'-5' is epoch seconds before 1970.*-5m, -5h or -5d"):
        parse_time("-5", now=now)
    with pytest.raises(HistoryReadError, match="no history table"):
        HistoryReader("/nonexistent/history").scan()


def test_a_history_location_one_level_off_is_answered_with_where_the_history_is(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk after `make demo` typed `twin history ls` (the default out/history), then --history out/demo
    and out/demo/history/telemetry: each said only that nothing was recorded there."""
    from twin.cli import main

    monkeypatch.chdir(tmp_path)
    _history_with(tmp_path / "out" / "demo", samples(5))
    said = {}
    for uri in (None, "out/demo", "out/demo/history/telemetry"):
        assert main(["history", "ls", *(["--history", uri] if uri else [])]) == 1
        said[uri] = capsys.readouterr().err
    assert said[None].endswith("; there is history at --history out/demo/history\n")
    assert said["out/demo"].endswith("; history lies one level down: --history out/demo/history\n")
    assert (
        "is a table itself: give the directory that holds it, --history out/demo/history"
        in said["out/demo/history/telemetry"]
    )


def test_the_docs_way_to_remove_old_history_keeps_the_tables_readable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """History has no budget, so docs/history.md gives a way to drop old days; these are its lines, run."""
    docs = (Path(__file__).parents[1] / "docs/history.md").read_text()
    section = docs.split("## Removing old history", 1)[1]
    code = section.split("```python\n", 1)[1].split("```", 1)[0]
    monkeypatch.chdir(tmp_path)
    day = 86400.0
    uri = _history_with_a_rejection(tmp_path / "out")  # T0's day, both tables
    _history_with(tmp_path / "out", samples(10, start_s=T0 + 3 * day))
    cut = dt.datetime.fromtimestamp(T0 + day, dt.UTC).date().isoformat()
    exec(code.replace("2026-11-01", cut), {})  # the docs' own lines
    reader = HistoryReader(uri)
    assert reader.collect(reader.window()).height == 10
    # On the table itself: rejected_counts() is {} for a table that is gone or unreadable too.
    assert DeltaTable(str(Path(uri) / REJECTED_TABLE)).to_pyarrow_table().num_rows == 0
    assert reader.rejected_counts() == {}


def test_the_docs_setting_to_remove_old_history_is_one_the_agent_reads(tmp_path: Path) -> None:
    docs = (Path(__file__).parents[1] / "docs/history.md").read_text()
    section = docs.split("## Removing old history", 1)[1].split("\n## ", 1)[0]
    toml = section.split("```toml\n", 1)[1].split("```", 1)[0]
    (tmp_path / "agent.toml").write_text(toml)
    config = load_config(tmp_path / "agent.toml", {"history.uri": str(tmp_path / "h")})
    assert config.history.keep_days == 90


@pytest.mark.parametrize("command", ["ls", "plot", "export"])
def test_a_time_not_understood_is_a_usage_error(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Exit 2, as for any bad argument (the module doc's codes); 1 is nothing to show or unreadable storage.
    from twin.cli.main import main

    device = ["--device", "arm-001"] if command == "plot" else []
    assert main(["history", command, "--history", str(tmp_path), "--since", "yesterday", *device]) == 2
    assert f"twin history {command}: time 'yesterday' is not understood" in capsys.readouterr().err
    assert main(["history", "ls", "--history", str(tmp_path / "none")]) == 1


# --- S3 (moto server mode) --------------------------------------------------------------------------------


@pytest.fixture
def s3() -> Iterator[MotoS3]:
    server = MotoS3()
    try:
        yield server
    finally:
        server.close()


@pytest.mark.slow
def test_s3_two_writers_an_outage_and_read_back(s3: MotoS3) -> None:
    """S3 is moto's server mode (ThreadedMotoServer) on 127.0.0.1, not AWS: the same HTTP API and the
    conditional PUT (If-None-Match) delta-rs commits with."""
    uri = f"s3://{s3.bucket}/history"
    options = s3.storage_options()

    def settings() -> HistorySettings:
        return HistorySettings(
            uri=uri, storage_options=options, commit_every_s=0.05, commit_every_rows=100, retry_min_s=0.1
        )

    writers = [HistoryWriter(settings(), writer_id=f"s3-w{i}").start() for i in range(2)]
    batches = [samples(600, device=f"arm-00{i + 1}", seed=i) for i in range(2)]

    def feed(i: int, lo: int, hi: int) -> None:
        for k in range(lo, hi, 100):
            writers[i].add(TELEMETRY_TABLE, telemetry_table(batches[i][k : k + 100])[0])
            time.sleep(0.02)  # interleave the two writers' commits; nothing below depends on how they fall

    threads = [threading.Thread(target=feed, args=(i, 0, 300)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(w.flush(30) for w in writers)

    s3.stop()  # the endpoint goes away
    feed(0, 300, 600)
    feed(1, 300, 600)
    assert not writers[0].flush(15)
    stats = writers[0].stats()
    assert not stats.storage_ok and "cannot write history" in stats.last_error
    assert writers[0].buffered_rows() == 300
    s3.start()  # and comes back with the same bucket
    assert all(w.flush(30) for w in writers)
    for w in writers:
        w.close()
        assert w.stats().tables[TELEMETRY_TABLE].rows_dropped == 0

    reader = HistoryReader(uri, options)
    summary = {d.device_id: d.rows for d in reader.summary()}
    assert summary == {"arm-001": 600, "arm-002": 600}
    frame = reader.window("arm-002").collect()
    assert frame["edge_time"].is_sorted() and frame["edge_time"].n_unique() == 600
    keys = [o["Key"] for o in s3.client().list_objects_v2(Bucket=s3.bucket)["Contents"]]
    assert all(k.startswith("history/telemetry/") for k in keys)
    assert any("/date=2026-11-18/" in k for k in keys)


def test_the_agent_keeps_every_decoded_message_also_those_the_twin_ignores(tmp_path: Path) -> None:
    from conftest import fed_agent

    uri = str(tmp_path / "agent-history")
    with fed_agent(12, **{"history.uri": uri, "history.commit_every_s": 0.2}) as agent:
        t0 = agent.state().devices["arm-001"].timestamp_ms - 1100
        # A late message (between two applied ones) and a repeat of the last: valid, decoded, not applied.
        # Each is handled before the next goes in: two in one batch that the worker takes late (a loaded
        # host) would be caught up, the older one coalesced rather than ignored as stale.
        for handled, stamp in ((15, t0 + 150), (16, t0 + 1100)):
            payload = encode(make_payload("arm-001", 0.0, "ticks", random.Random(1), timestamp_ms=stamp))
            agent.feed("dt/lerobot/arm-001/telemetry", payload)
            # Counted once handled (`processed` counts a message when the worker takes it, before that).
            counters = wait_handled(agent.state, handled).devices["arm-001"].health.counters
    assert (counters.decoded, counters.applied, counters.ignored_stale) == (14, 12, 2)
    rows = rows_of(uri)
    assert rows.height == 14  # every decoded message, applied or not
    assert sorted(rows["edge_time"].dt.epoch("ms").to_list()).count(t0 + 1100) == 2
    # The two garbage messages of the fed agent are rejected rows.
    assert rows_of(uri, REJECTED_TABLE).height == 2


def _nices(thread_ids: Iterable[int | None]) -> list[int]:
    """The nice value of each of these threads (Linux keeps one per thread) that is still running."""
    nices = []
    for tid in thread_ids:
        if tid is None:
            continue
        try:
            nices.append(os.getpriority(os.PRIO_PROCESS, tid))
        except ProcessLookupError:  # a pool thread that ended after the listing
            continue
    assert nices, "none of the threads is running"
    return nices


def _thread_nices(pid: int) -> list[int]:
    """The nice value of each thread of process `pid`."""
    return _nices(int(tid) for tid in os.listdir(f"/proc/{pid}/task"))


def test_the_writer_process_writes_what_it_received_and_a_crash_is_counted_and_survived(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """History is written by a process of its own. It commits every row the mirror handed it; when it dies
    holding rows not yet committed, the agent counts them as lost, starts it again, and the mirror's feed
    carries on with the new one. Rows the feed had written into the dead writer's socket are counted at the
    stop: nothing goes missing uncounted."""
    import signal

    from twin.service.agent import AgentService

    uri = str(tmp_path / "history")
    overrides = {
        # A commit per 20 rows and none by time: rows 21..27 wait in the writer when it is killed.
        "history.commit_every_rows": 20,
        "cloudwatch.emf_file": str(tmp_path / "emf.log"),
    }
    config = _fed_agent_config(uri, **overrides)
    # CloudWatch's documents: none within the test but the one the agent writes at its stop (an interval the
    # settings refuse, as the stack's per-minute alarms could not read it: set past them).
    config = dataclasses.replace(config, cloudwatch=dataclasses.replace(config.cloudwatch, interval_s=3600.0))
    rng = random.Random(8)
    t0 = int(time.time() * 1000)
    caplog.set_level(logging.INFO, logger="twin.service.agent")
    agent = AgentService(config)
    agent.start()
    try:

        def feed(first: int, count: int) -> None:
            for i in range(first, first + count):
                payload = encode(make_payload("arm-001", 0.1 * i, "ticks", rng, timestamp_ms=t0 + 100 * i))
                agent.feed("dt/lerobot/arm-001/telemetry", payload)

        def history() -> HistoryState:
            state = agent.state().agent.history
            assert state is not None
            return state

        feed(0, 20)
        wait_for(lambda: history().rows_committed == 20, 60, "the first 20 rows committed")
        writer_pid = history().writer_pid
        assert writer_pid is not None
        # It commits at a lower priority than the mirrors, in every thread (deltalake's have run by now).
        writer_nice = min(19, os.nice(0) + WRITER_NICE)
        assert set(_thread_nices(writer_pid)) == {writer_nice}
        # The agent's own threads keep the test's. Only the Python threads: a native library may run a thread
        # of its own lower (Mesa's shader-cache thread runs at 19 once a test has rendered in this process).
        assert set(_nices(t.native_id for t in threading.enumerate())) == {os.nice(0)}
        feed(20, 7)
        wait_for(lambda: history().rows_received == 27, 60, "7 more rows in the writer, not yet committed")
        first = history()
        assert first.writer_pid is not None and first.writer_pid != os.getpid()
        # Stopped, it reads nothing more: 4 rows go into its socket, delivered as far as the feed can tell.
        # (The agent's state would wait for the stopped writer's figures: the mirror's own report is read.)
        os.kill(first.writer_pid, signal.SIGSTOP)
        feed(27, 4)

        def delivered() -> int:
            assert agent._mirror is not None
            return next(s.delivered for s in agent._mirror.report().sinks if s.name == "history")

        wait_for(lambda: delivered() == 31, 60, "4 rows written into the stopped writer's socket")
        os.kill(first.writer_pid, signal.SIGKILL)

        def restarted() -> HistoryState | None:
            state = history()
            running = state.writer_pid is not None and state.writer_pid != first.writer_pid
            return state if state.writer_restarts == 1 and running else None

        again = wait_for(restarted, 60, "the history writer started again")
        assert again.writer_pid is not None
        assert set(_thread_nices(again.writer_pid)) == {writer_nice}
        assert again.rows_lost == 7  # received, not committed when it died: counted
        # ... and paged: CloudWatch's history drops include them, its worker restarts the writer's.
        from twin.service.agent import fleet_totals

        totals = fleet_totals(agent.state(), config.health.expected_rate_hz)
        assert (totals.history_rows_dropped, totals.worker_restarts) == (7, 1)
        samples = get_metrics(agent.http_url)
        assert metric(samples, "twin_history_rows_lost_total") == 7
        assert metric(samples, "twin_history_writer_restarts_total") == 1

        # ... and told on the Events page, as a worker's exit is: a session's hole has its cause beside it.
        def writer_events() -> list[dict[str, Any]] | None:
            with urllib.request.urlopen(f"{agent.http_url}/api/events?kind=worker", timeout=10) as answer:
                events = json.load(answer)["events"]
            return events if len(events) == 2 else None

        exited, running = wait_for(writer_events, 60, "the writer's exit and its restart as events")
        assert (exited["level"], exited["data"]["history_rows_lost"]) == ("error", "7"), exited
        assert (running["level"], running["data"]["pid"]) == ("info", str(again.writer_pid)), running
        feed(31, 20)
        # The figures run on across the restart.
        wait_for(lambda: history().rows_committed == 40, 60, "the new writer's first commit")
        assert history().rows_received == 27 + 20
    finally:
        agent.stop()
    # The 4 no writer read are counted at the stop, in the agent's last line and with the rows lost.
    line = next(r for r in caplog.records if r.getMessage().startswith("agent stopped"))
    assert line.levelno == logging.ERROR and "4 history_rows_unread" in line.getMessage()
    assert line.unwritten == {"history_rows_unread": 4}  # type: ignore[attr-defined]
    assert agent.state().agent.history.rows_lost == 7 + 4  # type: ignore[union-attr]
    # ... and CloudWatch has them: the document written at the stop counts every lost row.
    from test_emf import validate_emf_line

    docs = [validate_emf_line(text) for text in (tmp_path / "emf.log").read_text().splitlines()]
    assert sum(d.get("HistoryRowsDropped", 0) for d in docs) == 7 + 4
    rows = rows_of(uri)
    # The 20 before the crash and the 20 after; the 7 the dead writer held and the 4 it never read are the
    # ones counted lost.
    assert rows.height == 40
    stamps = sorted(rows["edge_time"].dt.epoch("ms").to_list())
    assert stamps == [t0 + 100 * i for i in (*range(20), *range(31, 51))]


@pytest.mark.slow
def test_rows_no_writer_read_are_counted_at_the_stop_after_a_worker_restart(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The feeds count the rows they deliver in memory the agent shares with its workers, so a worker
    process that died and was started again does not take its count with it: rows left unread in a dead
    writer's socket are still counted at the stop (before, a worker restart skipped the check)."""
    import signal

    from twin.service.agent import AgentService

    config = _fed_agent_config(str(tmp_path / "history"))
    rng = random.Random(9)
    t0 = int(time.time() * 1000)
    caplog.set_level(logging.INFO, logger="twin.service.agent")
    agent = AgentService(config, workers=2)
    agent.start()
    history_process = agent._history
    assert history_process is not None
    try:

        def feed(first: int, count: int) -> None:
            for i in range(first, first + count):
                payload = encode(make_payload("arm-001", 0.1 * i, "ticks", rng, timestamp_ms=t0 + 100 * i))
                agent.feed("dt/lerobot/arm-001/telemetry", payload)

        def settled(decoded: int) -> HistoryState | None:
            # Every message decoded (the checkpoint's and the replayed ones after a restart), every row
            # handed over, and the writer has read all the feeds delivered.
            state = agent.state()
            device = state.devices.get("arm-001")
            feed_pending = sum(s.pending for s in state.agent.sinks if s.name == "history")
            history = state.agent.history
            assert history is not None
            done = device is not None and device.health.counters.decoded >= decoded and feed_pending == 0
            return history if done and history.rows_received == history_process.delivered() else None

        feed(0, 10)
        wait_for(lambda: settled(10), 60, "10 rows read by the writer")
        (worker,) = [w for w in agent.state().agent.workers if w.devices]
        os.kill(worker.pid, signal.SIGKILL)

        def restarted() -> bool:
            info = agent.state().agent.workers[worker.index]
            return info.restarts == 1 and info.pid not in (0, worker.pid) and info.alive

        wait_for(restarted, 120, "the worker started again")
        feed(10, 5)
        first = wait_for(lambda: settled(15), 60, "the restarted worker's rows read by the writer")
        assert first.writer_pid is not None
        delivered = history_process.delivered()
        # Stopped, the writer reads nothing more: the 4 rows go into its socket, delivered as far as the new
        # worker's feed can tell (read from the shared counts: the agent's state would wait for the writer).
        os.kill(first.writer_pid, signal.SIGSTOP)
        feed(15, 4)
        wait_for(
            lambda: history_process.delivered() == delivered + 4, 60, "4 rows in the stopped writer's socket"
        )
        os.kill(first.writer_pid, signal.SIGKILL)

        def writer_again() -> HistoryState | None:
            state = agent.state().agent.history
            assert state is not None
            running = state.writer_pid is not None and state.writer_pid != first.writer_pid
            return state if state.writer_restarts == 1 and running else None

        held = wait_for(writer_again, 60, "the history writer started again").rows_lost
        assert held == first.rows_received  # none committed: every row it read was lost with it
    finally:
        agent.stop()
    line = next(r for r in caplog.records if r.getMessage().startswith("agent stopped"))
    assert line.unwritten == {"history_rows_unread": 4}  # type: ignore[attr-defined]
    assert agent.state().agent.history.rows_lost == held + 4  # type: ignore[union-attr]


@pytest.mark.slow
@pytest.mark.parametrize("checkpoint_before_kill", [False, True], ids=["replayed", "checkpointed"])
def test_a_killed_worker_s_messages_reach_history_once_whichever_its_feed_had_delivered(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, checkpoint_before_kill: bool
) -> None:
    """A worker with history on is killed after its feed delivered some rows and while it holds others (the
    writer, stopped, reads nothing, so the feed's socket fills and the rest wait in its queue). Replayed:
    no checkpoint counts the messages, the new worker is sent every one again and hands history only the
    rows the dead feed had not delivered. Checkpointed: a checkpoint counts them all, nothing is sent again,
    and the rows the dead feed still held are counted as lost. Either way each message is written at most
    once, and rows written + rows counted lost = messages handled."""
    import signal

    import twin.service.agent as agent_module
    from twin.service.agent import AgentService
    from twin.service.shards import ReportRequest, report_of

    # No checkpoint but those the test takes: the kill comes before any other could count the messages.
    monkeypatch.setattr(agent_module, "CHECKPOINT_EVERY_S", 3600.0)
    uri = str(tmp_path / "history")
    agent = AgentService(_fed_agent_config(uri, **{"history.commit_every_s": 0.2}), workers=2)
    agent.start()
    history_process = agent._history
    assert history_process is not None
    rng = random.Random(11)
    t0 = int(time.time() * 1000)
    fed = garbage = 0

    def feed(count: int) -> None:
        nonlocal fed, garbage
        for _ in range(count):
            i, fed = fed, fed + 1
            if i % 100 == 7:  # a rejected row now and then: they are replayed and skipped alike
                agent.feed("dt/lerobot/arm-001/telemetry", b"not telemetry")
                garbage += 1
            payload = encode(make_payload("arm-001", 0.1 * i, "ticks", rng, timestamp_ms=t0 + 10 * i))
            agent.feed("dt/lerobot/arm-001/telemetry", payload)

    (worker,) = [w for w in agent.state().agent.workers if w.devices]
    shard = agent._shards[worker.index]

    def feed_figures() -> SinkStats:
        # The worker's own report: the agent's state would ask the stopped writer and wait.
        report = report_of(shard.request(ReportRequest())())
        return next(s for s in report.sinks if s.name == "history")

    writer_pid = None
    try:
        feed(30)
        wait_for(lambda: history_process.delivered() == 30 + garbage, 60, "the first rows delivered")
        writer_pid = agent.state().agent.history.writer_pid  # type: ignore[union-attr]
        assert writer_pid is not None
        os.kill(writer_pid, signal.SIGSTOP)

        def stuck() -> bool | None:
            # Every row handed to the feed (None until then), and some not delivered.
            figures = feed_figures()
            if figures.pending + figures.delivered < fed + garbage:
                return None
            return history_process.delivered() < fed + garbage

        # More than the writer's socket holds: the feed blocks in a write, the rest wait in its queue (a
        # thousand more while this host's socket takes them all). Each answer is read once: the worker's
        # figures are read while its feed still writes, so two reads may disagree (a batch counted in neither
        # pending nor delivered for a moment), and a second read once failed a run that held rows.
        for _ in range(20):
            feed(1000)
            (held,) = wait_for(lambda: None if (s := stuck()) is None else (s,), 120, "every row handed")
            if held:
                break
        else:
            pytest.fail("the writer's socket took every row: the worker held none when it would be killed")
        total = fed + garbage  # every message fed, each a row
        if checkpoint_before_kill:
            agent._keep_state()
            assert shard.checkpoint is not None and shard.checkpoint.taken == total
        os.kill(worker.pid, signal.SIGKILL)

        def restarted() -> bool:
            return shard.restarts == 1 and shard.alive

        wait_for(restarted, 120, "the worker started again")
        os.kill(writer_pid, signal.SIGCONT)
        writer_pid = None

        def settled() -> bool:
            state = agent.state()
            feed_pending = sum(s.pending for s in state.agent.sinks if s.name == "history")
            history = state.agent.history
            assert history is not None
            device = state.devices.get("arm-001")
            handled = device is not None and device.health.counters.received >= total
            return handled and feed_pending == 0 and history.rows_received == history_process.delivered()

        wait_for(settled, 120, "every row the new worker handed read by the writer")
    finally:
        if writer_pid is not None:
            os.kill(writer_pid, signal.SIGCONT)
        agent.stop()
    history = agent.state().agent.history
    assert history is not None
    rows, rejected = rows_of(uri), rows_of(uri, REJECTED_TABLE)
    # Each message at most once: one row per edge timestamp.
    assert rows["edge_time"].n_unique() == rows.height
    written = rows.height + rejected.height
    assert written + history.rows_not_written == total
    if checkpoint_before_kill:
        assert history.rows_lost > 0  # what the dead feed held: nothing sends those messages again
    else:
        assert history.rows_not_written == 0
        assert (rows.height, rejected.height) == (total - garbage, garbage)


def _fed_agent_config(uri: str, **overrides: Any) -> AgentConfig:
    """An agent for arm-001 in ticks, fed through `feed()` (its broker never answers), with history at `uri`
    committed by row count only (no commit by time: rows wait in the writer until `overrides` say)."""

    return load_config(
        None,
        {
            "broker.url": NO_BROKER,
            "http.listen": "127.0.0.1:0",
            "telemetry.devices": ["arm-001"],
            "telemetry.units": "ticks",
            "history.uri": uri,
            "history.commit_every_s": 3600.0,
            **overrides,
        },
    )


def _writer_and_feed(
    uri: str, *, commit_every_rows: int, target: Callable[..., None] | None = None
) -> tuple[HistoryProcess, HistoryFeed, Callable[[int], None]]:
    """A history writer process at `uri` with no agent around it (no commits by time; `target`, if given,
    what the process runs), one feed to it, and `send(n)`: n more rows of arm-001 through that feed."""
    import multiprocessing

    history = HistoryProcess(
        {"uri": uri, "commit_every_s": 3600.0, "commit_every_rows": commit_every_rows},
        multiprocessing.get_context("spawn"),
    )
    if target is not None:
        history.target = target
    history.launch()
    feed = HistoryFeed(history.link, max_pending=1000, payload_max_bytes=64)
    stamp = itertools.count(1_700_000_000_000, 100)

    def send(count: int) -> None:
        for _ in range(count):
            feed.telemetry(("arm-001", time.time(), next(stamp), "ticks", (0.0,) * 6, b"{}"))

    return history, feed, send


def test_the_writer_runs_as_much_nicer_as_the_config_says(tmp_path: Path) -> None:
    """[history] writer_nice reaches the writer process: every thread of it, deltalake's included, runs that
    much nicer than the agent (2 here: neither the default 5 nor the agent's own priority)."""
    import multiprocessing

    from twin.service.agent import history_settings

    overrides = {
        "history.uri": str(tmp_path / "history"),
        "history.writer_nice": 2,
        "history.commit_every_rows": 1,
    }
    settings = history_settings(load_config(None, overrides))
    assert settings is not None
    history = HistoryProcess(settings, multiprocessing.get_context("spawn"))
    history.launch()
    feed = HistoryFeed(history.link, max_pending=1000, payload_max_bytes=64)
    try:
        # A commit first, so that deltalake's threads have started when they are looked at.
        feed.telemetry(("arm-001", time.time(), 1_700_000_000_000, "ticks", (0.0,) * 6, b"{}"))
        wait_for(lambda: (history.figures().stats or WriterFigures()).rows_committed == 1, 30, "a commit")
        assert history.pid is not None
        assert set(_thread_nices(history.pid)) == {min(19, os.nice(0) + 2)}
    finally:
        feed.close()
        history.stop()


def test_rows_left_unread_in_a_dead_writers_socket_are_counted_at_the_stop(tmp_path: Path) -> None:
    """A feed counts a row delivered once it is in the writer's socket. Rows a writer never read (it died, or
    stopped reading at its budget) reach no table and no counter of the writer's: at the stop, the agent
    gives the feeds' delivered rows to `count_unread`, which counts the difference as lost."""
    import signal

    uri = str(tmp_path / "history")
    # A commit per 5 rows: the first writer commits its 10 rows before it dies.
    history, feed, send = _writer_and_feed(uri, commit_every_rows=5)
    try:
        send(10)
        wait_for(
            lambda: (history.figures().stats or WriterFigures()).rows_committed == 10, 30, "10 rows committed"
        )
        first = history.pid
        assert first is not None
        os.kill(first, signal.SIGSTOP)  # it reads nothing more; the socket takes what the feed writes
        send(5)
        wait_for(lambda: feed.stats().delivered == 15, 30, "5 more rows in the stopped writer's socket")
        os.kill(first, signal.SIGKILL)
        wait_for(lambda: not history.alive, 30, "the writer gone")
        history.supervise()  # it died within 30 s of its start: started again after a pause, not yet
        # Meanwhile its figures are what it said last, once: it held nothing uncommitted, and the 5 rows in
        # its socket are not known yet.
        during = history.figures()
        assert during.pid is None and during.stats is not None
        assert (during.stats.rows_committed, during.rows_received, during.rows_lost) == (10, 10, 0)

        def restarted() -> bool:
            history.supervise()
            return history.alive and history.pid != first

        wait_for(restarted, 120, "the writer started again")
        assert history.restarts == 1
        send(3)
        feed.close(timeout=30.0)  # the new writer gets these 3
        assert feed.stats().delivered == 18 and feed.stats().pending == 0
    finally:
        feed.close(timeout=1.0)
        history.stop(timeout=30.0)
    assert history.figures().rows_received == 13
    assert history.unwritten_rows() == 0  # the new writer committed its 3 at the stop
    # The feed counted its rows in the link's shared memory too: the stop reads them there.
    assert history.delivered() == feed.stats().delivered == 18
    assert history.count_unread() == 5
    after = history.figures()
    assert after.rows_lost == 5 and after.stats is not None and after.stats.rows_committed == 13
    assert rows_of(uri).height == 13


def _writer_to_kill_in_a_commit(
    uri: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, when: str
) -> tuple[HistoryProcess, HistoryFeed, Callable[[int], None]]:
    """`_writer_and_feed` with a writer that commits every 7 rows and is killed in its first commit (`when`:
    writer_killed_in_its_first_commit)."""
    marker = tmp_path / "die"
    marker.write_text(when)
    monkeypatch.setenv("TWIN_TEST_DIE_MARKER", str(marker))
    return _writer_and_feed(uri, commit_every_rows=7, target=writer_killed_in_its_first_commit)


@pytest.mark.parametrize(("when", "landed"), [("after", True), ("before", False)])
def test_a_writer_killed_in_a_commit_has_the_next_writer_ask_the_table_whether_it_landed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, when: str, landed: bool
) -> None:
    """A writer killed after Delta accepted its commit and before it counted it had written those rows;
    counting them as lost overstated the losses CloudWatch pages on. The writer records the commit it is in;
    the agent counts those rows as neither until the next writer has asked the table for the dead writer's
    app transaction: written if it landed, lost if not."""
    uri = str(tmp_path / "history")
    caplog.set_level(logging.INFO, logger="twin.output.history_feed")
    history, feed, send = _writer_to_kill_in_a_commit(uri, tmp_path, monkeypatch, when)
    try:
        first, first_id = history.pid, history.writer_id
        send(7)  # its first commit, of these 7 rows
        wait_for(lambda: not history.alive, 60, "the writer killed in its first commit")

        def restarted() -> bool:
            history.supervise()
            return history.alive and history.pid != first

        wait_for(restarted, 120, "the writer started again")
        assert history.writer_id != first_id
        figures = history.figures()
        assert figures.stats is not None and figures.rows_received == 7
        assert (figures.stats.rows_committed, figures.rows_lost) == ((7, 0) if landed else (0, 7))
        said = [r.getMessage() for r in caplog.records]
        assert any("and 7 in a commit the next writer checks" in m for m in said), said
        if landed:
            assert any("had committed its last 7 rows to telemetry: written, not lost" in m for m in said)
        else:
            assert any("(7 rows to telemetry) did not land: counted as lost" in m for m in said)
        send(3)
        feed.close(timeout=30.0)
    finally:
        feed.close(timeout=1.0)
        history.stop(timeout=30.0)
    after = history.figures()
    assert after.stats is not None and after.rows_received == 10
    written = 10 if landed else 3
    assert (after.stats.rows_committed, after.rows_lost) == (written, 10 - written)
    assert rows_of(uri).height == written
    # The table names the dead writer's commit as its own: 1 if it landed.
    assert DeltaTable(str(Path(uri) / TELEMETRY_TABLE)).transaction_version(first_id) == (
        1 if landed else None
    )


def test_a_commit_in_doubt_waits_for_a_writer_that_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A writer killed in a commit, then one that dies before it is ready (it checked nothing): the commit
    stays in doubt until a writer starts and asks the table. Before, the second death wiped it, and the 7
    rows were neither written nor lost in the figures."""
    uri = str(tmp_path / "history")
    caplog.set_level(logging.INFO, logger="twin.output.history_feed")
    history, feed, send = _writer_to_kill_in_a_commit(uri, tmp_path, monkeypatch, "after,start")
    try:
        send(7)
        wait_for(lambda: not history.alive, 60, "the writer killed in its first commit")

        def running() -> bool:
            history.supervise()
            return history.alive

        wait_for(running, 120, "a writer that starts, after one that did not")
        assert history.restarts == 2
        # One exit the Events page tells (the writer that ran), not the start that failed before it was ready.
        assert history.exits == 1
        figures = history.figures()
        assert figures.stats is not None and figures.rows_received == 7
        assert (figures.stats.rows_committed, figures.rows_lost) == (7, 0)
    finally:
        feed.close(timeout=1.0)
        history.stop(timeout=30.0)
    said = [r.getMessage() for r in caplog.records]
    assert any("could not be started again" in m for m in said), said
    assert any("had committed its last 7 rows to telemetry: written, not lost" in m for m in said), said


@pytest.mark.parametrize(
    "case",
    [("after", True, 0), ("before", True, 7), ("after", False, 7)],
    ids=["landed", "lost", "unchecked"],
)
def test_a_commit_in_doubt_when_the_agent_stops_first_is_asked_of_the_table_at_the_stop(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    case: tuple[str, bool, int],
) -> None:
    """A writer killed in a commit, and the agent stops before another writer could ask the table: the stop
    asks it (in a process of its own). Before, the rows of that commit were counted as lost even when they
    were in the table. A check that cannot answer (its process dies here) still counts them as lost: a loss
    is never left uncounted."""
    when, checked, lost = case  # where the writer is killed; whether the check answers; the rows lost
    uri = str(tmp_path / "history")
    caplog.set_level(logging.INFO, logger="twin.output.history_feed")
    history, feed, send = _writer_to_kill_in_a_commit(uri, tmp_path, monkeypatch, when)
    if not checked:
        history.check_target = check_that_dies
    try:
        send(7)
        wait_for(lambda: not history.alive, 60, "the writer killed in its first commit")
        history.supervise()  # it died within 30 s of its start: started again after a pause, not yet
        during = history.figures()
        assert (during.rows_received, during.rows_lost) == (7, 0)  # in doubt: neither written nor lost yet
    finally:
        feed.close(timeout=1.0)
        history.stop(timeout=30.0)
    assert history.restarts == 0  # no writer was started again to check it
    assert history.figures().rows_lost == lost and history.unwritten_rows() == 0
    assert _table_rows(uri) == (7 if when == "after" else 0)
    said = [r.getMessage() for r in caplog.records]
    if not lost:
        expected = "had committed its last 7 rows to telemetry: written, not lost"
    else:
        why = "did not land" if checked else "could not be checked"
        expected = f"(7 rows to telemetry) {why}: counted as lost"
    assert any(expected in m for m in said), said


def test_a_check_of_a_commit_in_doubt_that_hangs_at_the_stop_is_killed_at_its_timeout(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The stop's check of a dead writer's commit (a store that never answers, say) ignores SIGINT, and no
    SIGTERM comes while the agent runs: the agent waits for it until its timeout (the stop's rest, at least
    CHECK_MIN_S), kills it, and counts the rows as lost."""
    from twin.output import history_feed

    monkeypatch.setattr(history_feed, "CHECK_MIN_S", 2.0)
    uri = str(tmp_path / "history")
    caplog.set_level(logging.INFO, logger="twin.output.history_feed")
    history, feed, send = _writer_to_kill_in_a_commit(uri, tmp_path, monkeypatch, "after")
    history.check_target = check_that_hangs
    try:
        send(7)
        wait_for(lambda: not history.alive, 60, "the writer killed in its first commit")
        history.supervise()
    finally:
        feed.close(timeout=1.0)
        history.stop(timeout=0.5)
    left = [p for p in multiprocessing.active_children() if p.name == "twin-history-check"]
    for process in left:  # else the test run would wait for it at its exit
        process.kill()
        process.join(5.0)
    assert not left, left
    assert history.figures().rows_lost == 7 and history.unwritten_rows() == 0
    said = [r.getMessage() for r in caplog.records]
    assert any("the check of the last writer's last commit took over 2 s" in m for m in said), said
    assert any("(7 rows to telemetry) could not be checked: counted as lost" in m for m in said), said


def test_a_check_of_a_commit_in_doubt_stuck_on_its_store_ends_on_sigterm_and_leaves_the_table(
    tmp_path: Path,
) -> None:
    """A check stuck reading the table (here a file whose open blocks: a store or file system that never
    answers) ignored SIGTERM too, so an operator's kill, or systemd's stop once the agent that would kill it
    was gone, left it running for as long as the read hung. It now ends within CHECK_TERM_GRACE_S of a
    SIGTERM without answering (its rows count as not checked), and the table is as it was."""
    from twin.output import history_feed

    uri = tmp_path / "history"
    table = uri / TELEMETRY_TABLE
    stuck, before = _table_with_a_stuck_read(uri)
    log_dir = stuck.parent
    ctx = multiprocessing.get_context("spawn")
    answers, child = ctx.Pipe()
    doubt = history_feed._InDoubt("a-dead-writer", TELEMETRY_TABLE, 1, 5)
    check = ctx.Process(target=history_feed.check_main, args=({"uri": str(uri)}, doubt, child))
    check.start()
    child.close()
    try:
        wait_for(lambda: _opening_a_fifo(check.pid), 60, "the check stuck opening the table's file")
        os.kill(check.pid, signal.SIGTERM)
        check.join(history_feed.CHECK_TERM_GRACE_S + 10.0)
        ended = not check.is_alive()
    finally:
        check.kill()
        check.join(5.0)
    assert ended, "the stuck check was still running after SIGTERM"
    assert check.exitcode == 1
    with pytest.raises(EOFError):  # nothing answered: the agent counts the rows as not checked
        answers.recv()
    stuck.unlink()
    assert {p.name: p.read_bytes() for p in log_dir.iterdir()} == before
    assert DeltaTable(str(table)).version() == 0 and rows_of(str(uri)).height == 3


def _table_with_a_stuck_read(uri: Path) -> tuple[Path, dict[str, bytes]]:
    """A telemetry table at `uri` whose log has a file that blocks whoever opens it to read (a store that
    never answers), and its log's files as they were before: (that file, the files)."""
    table = uri / TELEMETRY_TABLE
    pl.DataFrame({"a": [1, 2, 3]}).write_delta(str(table))
    log_dir = table / "_delta_log"
    before = {p.name: p.read_bytes() for p in log_dir.iterdir()}
    stuck = log_dir / "_last_checkpoint"
    os.mkfifo(stuck)  # opening it to read blocks until something opens it to write: nothing will
    return stuck, before


def test_a_writer_stuck_checking_a_commit_in_doubt_at_its_start_ends_on_sigterm_holding_no_row(
    tmp_path: Path,
) -> None:
    """A writer started again asks the table about the dead one's commit in doubt before it takes any row.
    Stuck there (a store that never answers), it ignored SIGTERM as a running writer does, so it outlived an
    agent systemd stopped, and the agent's stop waited on its start. It now ends within CHECK_TERM_GRACE_S of
    a SIGTERM (its start fails, nothing read), the commit stays in doubt, and the agent's stop asks the table
    itself: the dead writer's 5 rows did not land and count as lost, once."""
    from twin.output import history_feed

    uri = tmp_path / "history"
    stuck, before = _table_with_a_stuck_read(uri)
    history = HistoryProcess({"uri": str(uri)}, multiprocessing.get_context("spawn"))
    history._in_doubt = history_feed._InDoubt("a-dead-writer", TELEMETRY_TABLE, 1, 5)
    failed: list[Exception] = []

    def launch() -> None:
        try:
            history.launch()
        except history_feed.HistoryStartError as exc:
            failed.append(exc)

    starting = threading.Thread(target=launch, daemon=True)
    starting.start()
    try:
        wait_for(lambda: history._process is not None, 30, "the writer process started")
        writer = history._process
        assert writer is not None and writer.pid is not None
        wait_for(lambda: _opening_a_fifo(writer.pid), 60, "the writer stuck reading the table at its start")
        os.kill(writer.pid, signal.SIGTERM)
        starting.join(history_feed.CHECK_TERM_GRACE_S + 10.0)
        ended = not starting.is_alive()
    finally:
        if history._process is not None:
            history._process.kill()
        starting.join(10.0)
    assert ended, "the writer stuck in its check was still starting after SIGTERM"
    assert history._process.exitcode == 1
    assert failed and "exited while starting" in str(failed[0])
    assert history.figures().rows_received == 0 and history.figures().rows_lost == 0  # not counted yet
    stuck.unlink()
    history.stopping()
    history.stop(timeout=30.0)
    assert history.figures().rows_lost == 5 and history.unwritten_rows() == 0
    assert {p.name: p.read_bytes() for p in (uri / TELEMETRY_TABLE / "_delta_log").iterdir()} == before


def test_a_stop_during_a_restart_abandons_the_start_and_keeps_its_budget(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A writer killed in a commit that landed, and the one started again stuck checking it (a store that
    never answers). The supervisor held the writer's lock through that start, which may wait START_TIMEOUT_S,
    and the agent's stop needs the lock to send its _Stop: the stop waited for the start on top of its
    budget, past the unit's stop timeout. The stop now abandons the start (the writer holds no row yet: it is
    killed), the feeds give up at once, the stop asks the table itself, and every row handed is counted once:
    written, or not written."""
    from twin.output import history_feed

    monkeypatch.setattr(history_feed, "QUICK_DEATH_S", 0.0)  # started again at the next supervise
    monkeypatch.setattr(history_feed, "START_TIMEOUT_S", 600.0)  # the start would outlast any budget
    uri = str(tmp_path / "history")
    caplog.set_level(logging.INFO, logger="twin.output.history_feed")
    history, feed, send = _writer_to_kill_in_a_commit(uri, tmp_path, monkeypatch, "after")
    first = history._process
    assert history.figures().stats is not None  # its answer (nothing written yet) is the last one known
    supervisor = threading.Thread(target=history.supervise, name="test-supervisor", daemon=True)
    stopper = threading.Thread(target=history.stop, args=(2.0,), name="test-stop", daemon=True)
    try:
        send(7)  # its first commit: it lands, and the writer is killed before counting it
        wait_for(lambda: not history.alive, 60, "the writer killed in its first commit")
        stuck = Path(uri) / TELEMETRY_TABLE / "_delta_log" / "_last_checkpoint"
        os.mkfifo(stuck)  # the next writer's check of that commit opens it and blocks: a store that hangs
        send(5)  # they wait in the feed while no writer runs
        supervisor.start()
        wait_for(lambda: history._process is not first, 30, "a writer started again")
        second = history._process
        assert second is not None and second.pid is not None
        wait_for(lambda: _opening_a_fifo(second.pid), 60, "the writer started again stuck in its check")
        # Meanwhile /state answers at once, from the last writer's counts (the supervisor held the lock the
        # figures are asked under for the whole start).
        answers: list[Any] = []
        asker = threading.Thread(target=lambda: answers.append(history.figures()), daemon=True)
        asker.start()
        asker.join(history_feed.ASK_TIMEOUT_S)
        during = list(answers)  # (one that waited for the start answers once the writer is killed, below)
        stuck.unlink()  # it stays stuck in its open; the stop's own check can read the table
        history.stopping()
        feed.close(timeout=20.0)
        gave_up = not feed._thread.is_alive()  # it did not wait its whole budget for that writer
        stopper.start()
        # Its budget: 2 s, a second for the writer to exit, and the check (at least CHECK_MIN_S).
        stopper.join(2.0 + 1.0 + history_feed.CHECK_MIN_S + 15.0)
        within = not stopper.is_alive()
    finally:
        feed.close(timeout=1.0)
        for process in (history._process, first):
            if process is not None and process.is_alive():
                process.kill()
        if supervisor.is_alive():
            supervisor.join(30.0)
        if stopper.ident is None:
            history.stop(timeout=1.0)
        else:
            stopper.join(60.0)  # one that waited for the start goes on once the writer is killed
    assert during and (during[0].rows_received, during[0].rows_lost) == (7, 0), "/state waited for the start"
    assert within, "the stop waited for the writer's start"
    assert gave_up and feed.stats().pending == 5, "the feed waited for a writer being started at the stop"
    assert not supervisor.is_alive()
    assert second.exitcode == -signal.SIGKILL
    # 7 written (the commit in doubt, checked by the stop), 5 not delivered (the feed's pending): 12 handed.
    after = history.figures()
    assert after.stats is not None
    assert (after.stats.rows_committed, after.rows_lost) == (7, 0)
    assert (history.unwritten_rows(), history.count_unread()) == (0, 0)
    assert _table_rows(uri) == 7
    said = [r.getMessage() for r in caplog.records]
    assert any("start abandoned: the agent is stopping" in m for m in said), said
    assert any("had committed its last 7 rows to telemetry: written, not lost" in m for m in said), said


def test_a_start_that_times_out_kills_the_writer_it_started_and_the_next_is_started_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A writer that did not say it was ready within START_TIMEOUT_S (stuck checking a commit in doubt on a
    store that never answers) was left running: the supervisor saw it alive and never started another, and
    only the agent's stop killed it. It is now killed at the timeout, and the next supervise starts a writer
    again, which checks the commit: it did not land, its 5 rows count as lost."""
    from twin.output import history_feed

    monkeypatch.setattr(history_feed, "START_TIMEOUT_S", 3.0)
    monkeypatch.setattr(history_feed, "QUICK_DEATH_S", 0.0)
    uri = tmp_path / "history"
    stuck, _ = _table_with_a_stuck_read(uri)
    history = HistoryProcess({"uri": str(uri)}, multiprocessing.get_context("spawn"))
    history._in_doubt = history_feed._InDoubt("a-dead-writer", TELEMETRY_TABLE, 1, 5)
    try:
        with pytest.raises(history_feed.HistoryStartError, match="did not start within 3 s"):
            history.launch()
        first = history._process
        assert first is not None and not first.is_alive(), "the writer that did not start was left running"
        stuck.unlink()

        def running() -> bool:
            history.supervise()
            return history.alive

        wait_for(running, 120, "a writer started again after the one that timed out")
        assert history.restarts == 1 and history._process is not first
        assert history.figures().rows_lost == 5  # the new writer asked the table: the commit did not land
    finally:
        if history._process is not None and history._process.is_alive() and history.restarts == 0:
            history._process.kill()
        history.stop(timeout=10.0)


# A parent that starts a history process stuck reading the table (as the agent starts them: spawned, the
# parent holding its end of the control pipe), says its pid in argv[3], and waits for it.
_PARENT_OF_A_STUCK_READ = """
import multiprocessing, os, sys
from pathlib import Path
from twin.output import history_feed as hf

uri, kind, said = sys.argv[1:]
ctx = multiprocessing.get_context("spawn")
doubt = hf._InDoubt("a-dead-writer", hf.TELEMETRY_TABLE, 1, 5)
control, child = ctx.Pipe()
if kind == "check":
    args = ({"uri": uri}, doubt, child)
    process = ctx.Process(target=hf.check_main, args=args)
else:
    link = hf.HistoryLink.new(str(Path(said).with_name("writer.sock")), os.urandom(32), ctx)
    counters = ctx.Array("q", hf._COUNTERS, lock=False)
    args = ({"uri": uri}, link, child, counters, hf._Launch("a-new-writer", doubt))
    process = ctx.Process(target=hf.writer_main, args=args)
process.start()
child.close()
Path(said + ".part").write_text(str(process.pid))
os.replace(said + ".part", said)
process.join()
"""


def _gone(pid: int) -> bool:
    """Whether process `pid` has ended (a zombie its new parent has not reaped yet counts as ended)."""
    import psutil

    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


@pytest.mark.parametrize("kind", ["check", "writer"])
def test_a_history_process_stuck_reading_the_table_ends_when_the_agent_is_killed(
    tmp_path: Path, kind: str
) -> None:
    """The check of a commit in doubt and a writer checking one at its start, stuck on a store that never
    answers, ran on for as long as the read hung when their agent was killed (SIGKILL: the OOM killer, a
    `kill -9`): orphaned, no one was left to stop them. They now watch the agent's end of their control pipe
    and end when it closes (nothing read yet: no row is lost), and the table is as it was."""
    uri = tmp_path / "history"
    stuck, before = _table_with_a_stuck_read(uri)
    said = tmp_path / "pid"
    parent = subprocess.Popen(
        [sys.executable, "-c", _PARENT_OF_A_STUCK_READ, str(uri), kind, str(said)], start_new_session=True
    )
    child = 0
    try:
        wait_for(said.exists, 60, f"the {kind} process started")
        child = int(said.read_text())
        wait_for(lambda: _opening_a_fifo(child), 60, f"the {kind} stuck reading the table")
        parent.kill()
        parent.wait(10.0)
        wait_for(lambda: _gone(child), 15, f"the {kind} ended with its agent")
    finally:
        if parent.poll() is None:
            parent.kill()
        if child and not _gone(child):
            os.kill(child, signal.SIGKILL)
        parent.wait(10.0)
    stuck.unlink()
    assert {p.name: p.read_bytes() for p in (uri / TELEMETRY_TABLE / "_delta_log").iterdir()} == before


def _opening_a_fifo(pid: int) -> bool:
    """Whether a thread of process `pid` waits in the kernel to open a FIFO (for a writer to open it too)."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            if (task / "wchan").read_text().strip() == "wait_for_partner":
                return True
    return False


def _table_rows(uri: str) -> int:
    """The rows in the telemetry table at `uri`; 0 when a writer died before it made the table."""
    if not (Path(uri) / TELEMETRY_TABLE / "_delta_log").exists():
        return 0
    return rows_of(uri).height


@pytest.mark.parametrize(("when", "landed"), [("after", True), ("before", False)])
def test_a_writer_killed_in_its_last_commit_at_the_stop_has_the_agent_ask_the_table(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, when: str, landed: bool
) -> None:
    """A writer killed in the stop's last commit (the first it makes here), after Delta accepted the append
    and before it counted it ("after"), or as the append began ("before"). No writer is started again to ask
    the table, so the agent asks it: before, the 7 rows of a commit that landed were counted as not written
    as well (the stop said 7 unwritten with 7 in the table: rows written + rows counted lost = 14 of 7)."""
    uri = str(tmp_path / "history")
    caplog.set_level(logging.INFO, logger="twin.output.history_feed")
    marker = tmp_path / "die"
    marker.write_text(when)
    monkeypatch.setenv("TWIN_TEST_DIE_MARKER", str(marker))
    history, feed, send = _writer_and_feed(
        uri, commit_every_rows=10_000, target=writer_killed_in_its_first_commit
    )
    try:
        send(7)
        wait_for(lambda: history.figures().rows_received == 7, 30, "the 7 rows read, none committed")
        feed.close(timeout=30.0)
    finally:
        feed.close(timeout=1.0)
        history.stop(timeout=30.0)
    assert not history.alive and history.restarts == 0 and not marker.exists()  # it died in that commit
    written = _table_rows(uri)
    assert written == (7 if landed else 0)
    unwritten = history.unwritten_rows()
    unread = history.count_unread()
    after = history.figures()
    assert after.stats is not None
    # Each row handed in once: written, or counted as not written.
    assert (after.stats.rows_committed, unwritten, unread, after.rows_lost) == (written, 7 - written, 0, 0)
    said = [r.getMessage() for r in caplog.records]
    if landed:
        assert any("had committed its last 7 rows to telemetry: written" in m for m in said), said
    else:
        assert any("(7 rows to telemetry) did not land: counted as not written" in m for m in said), said


def test_at_the_stop_the_writer_reads_each_feed_to_its_end_for_half_the_budget(tmp_path: Path) -> None:
    """The agent stops the writer once every feed has closed, so what the sockets hold is all there is; the
    writer reads it to the end for up to half its budget, however long that takes, then commits. Here a feed
    still sends 6 s into the stop (as a writer that reads slowly on a saturated host sees it): with a 20 s
    budget every row is written; a reading window of a fixed 5 s (as before) lost them."""
    uri = str(tmp_path / "history")
    history, feed, send = _writer_and_feed(uri, commit_every_rows=10_000)
    stopper = threading.Thread(target=history.stop, kwargs={"timeout": 20.0})
    try:
        send(10)
        wait_for(lambda: history.figures().rows_received == 10, 30, "the feed connected and read")
        stopper.start()
        # Not a wait for something to happen: the late feed is the case under test (longer than 5 s).
        time.sleep(6.0)
        send(5)
    finally:
        feed.close(timeout=10.0)
        stopper.join(30.0)
    assert not stopper.is_alive()
    assert feed.stats().delivered == 15
    assert history.unwritten_rows() == 0 and history.delivered() == 15 and history.count_unread() == 0
    assert rows_of(uri).height == 15


def test_a_feed_that_cannot_reach_the_writer_keeps_its_bound_and_counts_what_it_drops(tmp_path: Path) -> None:
    from twin.output.history_feed import HistoryLink

    # Nobody listens here: the feed keeps trying, its queue holds at most max_pending rows.
    feed = HistoryFeed(
        HistoryLink(str(tmp_path / "nobody.sock"), b"key"), max_pending=50, payload_max_bytes=8
    )
    try:
        for i in range(120):
            feed.telemetry(("arm-001", 1.0 + i, 1_700_000_000_000 + i, "ticks", (0.0,) * 6, b"{}"))
        stats = feed.stats()
        assert feed.handed == 120
        # At most max_pending wait in the queue, and the feed's thread may hold one batch it took before the
        # queue filled.
        assert stats.dropped >= 120 - 2 * 50 and stats.pending <= 2 * 50
        assert stats.delivered == 0
        wait_for(lambda: feed.stats().errors > 0, 30, "the feed to try the writer")
        stats = feed.stats()
        assert "history writer out of reach" in stats.last_error
        # Every row handed is waiting (the batch in the thread's hand too) or dropped and counted.
        assert stats.dropped + stats.pending == 120 and stats.delivered == 0
    finally:
        feed.close(timeout=1.0)


def test_a_marked_feed_hands_over_whole_batches_and_records_where_they_reach(tmp_path: Path) -> None:
    """Once its mirror marks it, a feed hands the writer the rows up to the latest mark only (a hand-over
    ends where a batch of the mirror ended) and records, in the memory it shares with the agent, the stream
    position its deliveries reached and the rows handed up to there, over the slot's processes (`resume`).
    A restart counts the rows handed before where it takes up that no feed delivered, once."""
    from twin.output.history_feed import Resume, resume_point

    history, feed, send = _writer_and_feed(str(tmp_path / "history"), commit_every_rows=1000)
    small = HistoryFeed(history.link, max_pending=2, payload_max_bytes=64, slot=1)
    try:
        feed.resume(100)  # the rows a dead predecessor of this slot was handed, and delivered
        assert history.link.delivered is not None
        history.link.delivered[0] = 100
        send(3)
        feed.mark(10)  # 3 rows of the messages before position 10
        feed.rejected((1.0, "dt/lerobot/arm-001/telemetry", "arm-001", "bad", "detail", b"x", 1))
        feed.mark(12)
        send(2)  # a batch not marked yet: its rows wait
        wait_for(lambda: history.link.reached(0) == (12, 104), 30, "the marked rows delivered")
        assert (feed.stats().delivered, feed.stats().pending, feed.handed_in_all) == (4, 2, 106)
        feed.mark(15)
        wait_for(lambda: history.link.reached(0) == (15, 106), 30, "the next batch delivered")
        # A worker of slot 0 started again from a checkpoint at 13 resumes at 15, replaying from 13.
        assert resume_point(history.link, 0, taken=13, taken_rows=105, replay_from=13).skip_to == 15
        # From one at 20 (rows its feed held for 15..20 are sent again by nobody): counted lost, once.
        for _ in range(2):
            again = resume_point(history.link, 0, taken=20, taken_rows=109, replay_from=20)
            assert (again.skip_to, again.rows) == (20, 109)
        assert history.link.lost_at_restarts() == 3
        # A feed whose queue overflowed: 5 rows of one batch (waiting for its mark), 3 of them dropped.
        small.mark(0)
        for i in range(5):
            small.telemetry(("arm-002", time.time(), 1_700_000_000_000 + i, "ticks", (0.0,) * 6, b"{}"))
        small.mark(5)
        wait_for(lambda: history.link.reached(1) == (5, 5), 30, "the 2 rows left delivered")
        assert small.stats().dropped == 3
        # Its process dies, and the count with it: the restart counts them, once.
        for _ in range(2):
            assert resume_point(history.link, 1, taken=5, taken_rows=5, replay_from=5) == Resume(5, 5)
        assert history.figures().rows_lost == 3 + 3
    finally:
        small.close(timeout=10.0)
        feed.close(timeout=10.0)
        history.stop(timeout=10.0)


def test_a_second_restart_takes_up_history_in_the_renumbered_stream() -> None:
    """The agent kept fewer messages than the checkpoint missed (first kept 150, checkpoint at 100): the new
    worker numbers them from 100, so the dead feed's position 170 is 120 in its numbers. A worker that dies
    again before its feed records a delivery of its own must take up at 120 again, not at 170 (which would
    skip, uncounted, rows never written)."""
    import multiprocessing

    from twin.output.history_feed import HistoryLink, Resume, resume_point

    link = HistoryLink.new("unused.sock", b"k", multiprocessing.get_context("spawn"))
    assert link.delivered is not None
    link.record_reached(0, 170, 170)
    link.delivered[0] = 170
    first = resume_point(link, 0, taken=100, taken_rows=100, replay_from=150)
    assert first == Resume(120, 170)
    again = resume_point(link, 0, taken=100, taken_rows=100, replay_from=100)
    assert again == Resume(120, 170)
    assert link.lost_at_restarts() == 0


def test_demo_style_uri_is_created(tmp_path: Path) -> None:
    nested = tmp_path / "a" / "b" / "history"
    HistoryWriter(HistorySettings(uri=str(nested))).close()
    assert nested.is_dir()
    assert os.access(nested, os.W_OK)


# --- commands and replay ------------------------------------------------------------------------------------


def _history_with(tmp_path: Path, batch: list[AppliedSample]) -> str:
    uri = str(tmp_path / "history")
    sink = HistorySink(HistorySettings(uri=uri))
    for sample in batch:
        sink.applied(sample)
    sink.close()
    return uri


def _replay_config(uri: str, broker_url: str, *, speed: float = 8.0, **extra: Any) -> ReplayConfig:
    """Arm-001's replay of the window the samples of these tests are stamped in, through `broker_url`."""
    from twin.ops.replay import ReplayConfig
    from twin.transport.broker import BrokerConfig

    return ReplayConfig(
        uri=uri,
        device="arm-001",
        start=dt.datetime.fromtimestamp(T0 - 1, dt.UTC),
        end=dt.datetime.fromtimestamp(T0 + 60, dt.UTC),
        broker=BrokerConfig(url=broker_url, client_id_prefix="replay-"),
        speed=speed,
        **extra,
    )


def test_history_on_s3_without_aws_credentials_names_the_fix(
    aws_env: None, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """deltalake's error for a machine with no AWS credentials is the chain of every provider it tried, with
    no way to give it some; `twin history` adds the ways, as the other AWS commands give them."""
    from twin.cli import main

    for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
        monkeypatch.delenv(name)
    assert main(["history", "ls", "--history", "s3://so101-no-such-bucket/history"]) == 1
    said = capsys.readouterr().err
    assert "no AWS credentials found: run `aws configure`" in said, said


def test_history_in_a_bucket_that_does_not_exist_names_where_the_name_comes_from(s3: MotoS3) -> None:
    """deltalake's error for a mistyped bucket is a failed GET, S3's XML answer and a terminal's colour
    codes; `twin history` says there is no such bucket and where its name is given."""
    reader = HistoryReader("s3://so101-no-such-bucket/history", s3.storage_options())
    with pytest.raises(HistoryReadError) as caught:
        reader.summary()
    said = str(caught.value)
    assert said == (
        "cannot read history at s3://so101-no-such-bucket/history/telemetry: there is no bucket "
        "'so101-no-such-bucket' (S3: NoSuchBucket); give --history the stack's HistoryUri output, as "
        "docs/getting-started.md prints it"
    ), said
    # Any other of deltalake's errors keeps its text, without the colour codes.
    from twin.ops.history import _unreadable

    chain = Exception("Generic S3 error\n  \x1b[31m↳\x1b[0m builder error")
    assert _unreadable("s3://b/h/telemetry", chain) == (
        "cannot read history at s3://b/h/telemetry: Generic S3 error\n  ↳ builder error"
    )


def test_a_replay_to_iot_core_without_a_region_names_the_fix(
    tmp_path: Path, aws_env: None, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """What only building the IoT Core client finds out (here: no region anywhere) is said with its fix and
    exit 1, as `twin edge-sim` says it, not as a traceback."""
    from twin.cli import main

    monkeypatch.delenv("AWS_DEFAULT_REGION")
    uri = _history_with(tmp_path, samples(20))
    window = ["--from", str(T0 - 1), "--to", str(T0 + 60)]
    code = main(["replay", "--history", uri, "--device", "arm-001", *window, "--broker", "iot"])
    assert code == 1
    assert "no AWS region for IoT Core: give --region" in capsys.readouterr().err


def test_a_replay_to_a_port_nobody_listens_on_says_so_at_once_and_names_the_fix(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A walk: a replay to a mistyped port sat silent for 15 s, then said only "check that the broker
    runs". Its first failed connect is logged at once, and the error names it with what to check."""
    from twin.ops.replay import replay

    uri = _history_with(tmp_path, samples(20))
    config = dataclasses.replace(_replay_config(uri, NO_BROKER), connect_timeout_s=2.0)
    logged = caplog.at_level(logging.WARNING, logger="twin.ops.replay")
    with logged, pytest.raises(HistoryReadError) as caught:
        replay(config)
    said = str(caught.value)
    assert said.startswith(f"could not connect to the broker {NO_BROKER} within 2 s: "), said
    assert "Is a broker listening on 127.0.0.1 port 1" in said and "fix the URL in --broker" in said, said
    (line,) = [r.getMessage() for r in caplog.records if "could not connect" in r.getMessage()]
    assert "Is a broker listening" in line and "retrying for up to 2 s" in line, line


@pytest.mark.slow
def test_replay_says_it_has_begun_and_how_far_it_got(
    tmp_path: Path, mosquitto: Any, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """`twin replay` printed nothing until it ended, minutes for a long window: a line as it begins, how far
    it got at most every PROGRESS_EVERY_S (here: after every message), and a line before each pause in the
    window (here 26 s recorded, 6.5 s at 4x; told from PAUSE_S, here 1 s)."""
    from twin.cli import main
    from twin.cli.commands import replay as replay_command
    from twin.ops import replay as replay_module

    monkeypatch.setattr(replay_command, "PROGRESS_EVERY_S", 0.0)
    monkeypatch.setattr(replay_module, "PAUSE_S", 1.0)
    uri = _history_with(tmp_path, samples(40) + samples(40, start_s=T0 + 30, seed=2))
    window = ["--from", str(T0 - 1), "--to", str(T0 + 60), "--speed", "4"]
    args = ["replay", "--history", uri, "--device", "arm-001", *window, "--broker", mosquitto.url]
    assert main(args) == 0
    out, err = capsys.readouterr()
    lines = err.splitlines()
    begun = f"twin replay: replaying arm-001 as arm-001 to {mosquitto.url} at 4x, from 20"
    assert lines[0].startswith(begun) and lines[0].endswith("Z (Ctrl-C stops)"), lines
    assert re.fullmatch(r"twin replay: replayed 1 messages, recorded up to \S+Z", lines[1]), lines
    (pause,) = [line for line in lines if "pauses" in line]
    assert re.fullmatch(
        r"twin replay: replayed 40 messages; the recording pauses after \S+Z: "
        r"the next message is in \d s at 4x",
        pause,
    ), pause
    assert lines[-1].startswith("twin replay: replayed 80 messages, recorded up to"), lines
    assert out.startswith("replayed 80 messages of arm-001"), out


def test_history_ls_splits_sessions_as_the_console_does(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One meaning of "session": `twin history ls` splits at the console's gap ([http] session_gap_s) unless
    told otherwise; a 20 s pause is one session on both, two with --gap 10."""
    from twin.cli import main
    from twin.cli.commands.history import SESSION_GAP_S
    from twin.ops.history import DEFAULT_SESSION_GAP_S
    from twin.service.config import load_config

    assert SESSION_GAP_S == DEFAULT_SESSION_GAP_S == load_config(None, {}).http.session_gap_s
    # 10 s of messages, a 20 s pause, 10 s more.
    uri = _history_with(tmp_path, samples(100) + samples(100, start_s=T0 + 30, seed=2))
    counts = []
    # --gap inf (never split) and one past timedelta's range were an OverflowError traceback in a walk.
    for extra in ([], ["--gap", "10"], ["--gap", "inf"], ["--gap", "1e300"]):
        assert main(["history", "ls", "--history", uri, "--json", *extra]) == 0
        counts.append(len(json.loads(capsys.readouterr().out)["devices"][0]["sessions"]))
    assert counts == [1, 2, 1, 1]


@pytest.mark.slow
def test_history_commands_list_plot_and_export(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from PIL import Image
    from twin.cli import main

    uri = _history_with(tmp_path, samples(600) + samples(300, device="arm-002", start_s=T0 + 30))
    assert main(["history", "ls", "--history", uri, "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [(d["device_id"], d["rows"], len(d["sessions"])) for d in listed["devices"]] == [
        ("arm-001", 600, 1),
        ("arm-002", 300, 1),
    ]
    assert listed["devices"][0]["sessions"][0]["rate_hz"] == pytest.approx(10.0, rel=0.01)

    png = tmp_path / "plot.png"
    since = dt.datetime.fromtimestamp(T0 + 10, dt.UTC).isoformat()
    assert (
        main(
            ["history", "plot", "--history", uri, "--device", "arm-001", "--since", since, "--out", str(png)]
        )
        == 0
    )
    assert "500 messages of arm-001" in capsys.readouterr().out
    with Image.open(png) as image:
        assert image.size == (1200, 1000)
        grey = np.asarray(image.convert("L"))
    assert len(np.unique(grey)) > 50  # lines were drawn, not a blank canvas

    for fmt in ("csv", "parquet"):
        out = tmp_path / f"export.{fmt}"
        assert (
            main(
                [
                    "history",
                    "export",
                    "--history",
                    uri,
                    "--format",
                    fmt,
                    "--device",
                    "arm-002",
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
        frame = pl.read_csv(out) if fmt == "csv" else pl.read_parquet(out)
        assert frame.height == 300 and "elbow_flex_current_a" in frame.columns

    assert (
        main(["history", "plot", "--history", uri, "--device", "arm-404", "--out", str(tmp_path / "4.png")])
        == 1
    )
    assert "arm-001, arm-002" in capsys.readouterr().err


def test_export_takes_its_format_from_out_and_plot_writes_no_png_under_another_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk's findings: `export --out a.csv` wrote Parquet into a.csv (and `--format csv --out b.parquet`
    CSV into b.parquet), and `plot --out p.svg` wrote PNG bytes into p.svg, each saying "wrote"."""
    from twin.cli import main

    uri = _history_with(tmp_path, samples(20))

    def run(*args: str) -> int:
        return main(["history", *args, "--history", uri])

    assert run("export", "--out", str(tmp_path / "a.CSV")) == 0
    assert pl.read_csv(tmp_path / "a.CSV").height == 20
    assert "wrote" in capsys.readouterr().out
    assert run("export", "--format", "csv", "--out", str(tmp_path / "b.parquet")) == 2
    assert "names a .parquet file but --format is csv" in capsys.readouterr().err
    assert run("export", "--format", "csv", "--out", str(tmp_path / "b.txt")) == 0
    assert pl.read_csv(tmp_path / "b.txt").height == 20
    assert run("plot", "--device", "arm-001", "--out", str(tmp_path / "p.svg")) == 2
    assert "plot writes PNG only; give a name ending .png" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.CSV", "b.txt", "history"]


def _history_with_a_rejection(tmp_path: Path) -> str:
    """600 messages of arm-001, 300 of arm-002 from T0 + 30 s, one rejected message of each at T0 + 5 s."""
    uri = str(tmp_path / "history")
    sink = HistorySink(HistorySettings(uri=uri))
    for sample in samples(600) + samples(300, device="arm-002", start_s=T0 + 30):
        sink.applied(sample)
    for device in ("arm-001", "arm-002"):
        topic = f"dt/lerobot/{device}/telemetry"
        sink.rejected(RejectedSample(device, topic, T0 + 5, "not_json", "bad", b"{x"))
    sink.close()
    return uri


@pytest.mark.slow
def test_history_commands_keep_what_a_person_had_and_refuse_a_selection_of_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk's findings: an export replaced an existing file silently, even with no row (and said "wrote"
    while exiting 1); an interrupted one left a cut file that looked whole; `--out` a directory was a
    traceback, and plot's `--out x` wrote x.png; an end before its start, and a mistyped device, read as an
    empty hour; and `ls --device` counted the whole table's rejections."""
    from twin.cli import main

    uri = _history_with_a_rejection(tmp_path)
    kept = tmp_path / "k.csv"
    kept.write_text("precious\n")

    def run(*args: str) -> tuple[int, str]:
        code = main(["history", *args[:1], "--history", uri, *args[1:]])
        return code, capsys.readouterr().err

    code, err = run("export", "--format", "csv", "--out", str(kept))
    assert code == 2 and "exists; pass --force" in err and kept.read_text() == "precious\n"
    code, err = run("export", "--format", "csv", "--device", "nobody", "--out", str(kept), "--force")
    assert code == 1 and "nothing was written" in err and kept.read_text() == "precious\n"
    assert "devices with history are arm-001, arm-002" in err
    assert run("export", "--format", "csv", "--device", "arm-002", "--out", str(kept), "--force")[0] == 0
    assert pl.read_csv(kept).height == 300
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no partial file left
    code, err = run("export", "--out", str(tmp_path))
    assert code == 2 and "is a directory" in err
    code, err = run("ls", "--since", str(T0 + 60), "--until", str(T0))
    assert code == 2 and "--until (" in err and "must be after --since" in err
    code, err = run("ls", "--device", "arm-0O1")
    assert code == 1 and "devices with history are arm-001, arm-002" in err
    code, err = run("ls", "--device", "ARM-001")
    assert code == 1 and "case-sensitive, and 'arm-001' has history" in err
    assert run("ls", "--gap", "0")[0] == 2
    plot = tmp_path / "x"
    assert run("plot", "--device", "arm-001", "--out", str(plot))[0] == 0
    assert plot.is_file() and not (tmp_path / "x.png").exists()
    assert run("plot", "--device", "arm-001", "--out", str(plot))[0] == 2  # exists: not replaced
    # The rejections of the selection only: arm-002's one, not the table's two.
    assert main(["history", "ls", "--history", uri, "--device", "arm-002", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["rejected"] == {"not_json": 1}
    assert main(["history", "ls", "--history", uri, "--json", "--since", str(T0 + 10)]) == 0
    assert json.loads(capsys.readouterr().out)["rejected"] == {}


def test_a_damaged_log_entry_is_named_with_its_fix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk's finding: a log entry that is not whole JSON stopped every command with deltalake's "Json
    error: Encountered unexpected 'g'" and two `<unknown>` backtrace frames, naming neither entry nor
    fix."""
    from twin.cli import main

    uri = _history_with(tmp_path, samples(20))
    _history_with(tmp_path, samples(30, start_s=T0 + 10, seed=2))
    entries = sorted((Path(uri) / TELEMETRY_TABLE / "_delta_log").glob("*.json"))
    assert len(entries) >= 2
    for entry, fix in ((entries[0], "put back a whole copy"), (entries[-1], "move it out of _delta_log")):
        whole = entry.read_bytes()
        entry.write_bytes(whole[:50])
        assert main(["history", "ls", "--history", uri]) == 1
        err = capsys.readouterr().err
        assert f"its log entry {entry} is not whole JSON" in err and fix in err, err
        assert "<unknown>" not in err
        entry.write_bytes(whole)
    # The fix for the newest holds: out of the log, the table reads as before its commit.
    entries[-1].rename(tmp_path / entries[-1].name)
    assert main(["history", "ls", "--history", uri, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["devices"][0]["rows"] == 20


def _three_commits(uri: str) -> list[Path]:
    """Three commits of 10 telemetry rows each; the table's log entries, oldest first."""
    for i in range(3):
        writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0)).start()
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=T0 + 10 * i, seed=i))[0])
        assert writer.flush(10)
        writer.close()
    return sorted((Path(uri) / TELEMETRY_TABLE / "_delta_log").glob("*.json"))


def test_an_empty_newest_log_entry_is_named_to_a_reader_and_set_aside_by_the_writer(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """A commit cut short by a crash or a full disk can leave its log entry empty: deltalake reads it as a
    commit with no action, so every read left its rows out without a word, and the writer committed on top
    of it, after which it could no longer be moved out."""
    from twin.cli import main
    from twin.output.history import SET_ASIDE_DIR, LogCheck, check_log
    from twin.output.history_feed import _figures_of
    from twin.service.metrics import render_metrics
    from twin.service.state import AgentInfo, AgentState

    uri = str(tmp_path / "h")
    entries = _three_commits(uri)
    data_files = set((Path(uri) / TELEMETRY_TABLE).rglob("*.parquet"))
    entries[-1].write_bytes(b"")
    assert main(["history", "ls", "--history", uri]) == 1
    err = capsys.readouterr().err
    assert f"its newest log entry {entries[-1]} is empty" in err and "move it out of _delta_log" in err, err
    caplog.set_level("ERROR", logger="twin.output.history")
    writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0)).start()
    try:
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=T0 + 100, seed=9))[0])
        assert writer.flush(10)
        stats = writer.stats()
    finally:
        writer.close()
    moved = Path(uri) / TELEMETRY_TABLE / SET_ASIDE_DIR / entries[-1].name
    assert moved.is_file() and moved.read_bytes() == b""  # kept, not deleted
    assert any(str(moved) in r.getMessage() for r in caplog.records)
    assert stats.tables[TELEMETRY_TABLE].log_entries_set_aside == 1
    assert check_log(f"file://{uri}/{TELEMETRY_TABLE}") == check_log(f"{uri}/{TELEMETRY_TABLE}") != LogCheck()
    state = AgentState(agent=AgentInfo(history=HistoryState(log_entries_set_aside=1)), devices={})
    assert "twin_history_log_entries_set_aside_total 1.0" in render_metrics(state).splitlines()
    assert _figures_of(stats, 0).log_entries_set_aside == 1
    assert data_files <= set((Path(uri) / TELEMETRY_TABLE).rglob("*.parquet"))  # no data file went
    assert main(["history", "ls", "--history", uri, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["devices"][0]["rows"] == 30  # two commits and the new one


@pytest.mark.parametrize("damage", [b"", b'{"add": {"path": "part'])
def test_a_damaged_log_entry_that_is_not_the_newest_empty_one_refuses_commits_with_the_fix(
    tmp_path: Path, damage: bytes
) -> None:
    """An empty entry with later ones after it, or an entry that is not whole JSON, cannot be moved out:
    the writer keeps the rows, counts each refused commit and names the entry and the fix, and goes on
    once the log is mended."""
    from twin.output.history import NO_ACTION_ENTRY

    uri = str(tmp_path / "h")
    entries = _three_commits(uri)
    damaged = entries[1] if damage == b"" else entries[-1]
    whole = damaged.read_bytes()
    damaged.write_bytes(damage)
    writer = HistoryWriter(
        HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0, retry_min_s=0.05)
    ).start()
    try:
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=T0 + 100, seed=9))[0])
        assert not writer.flush(10)
        stats = writer.stats()
        said = "is empty" if damage == b"" else "is not whole JSON"
        assert f"its log entry {damaged} {said}" in stats.last_error, stats.last_error
        fix = NO_ACTION_ENTRY if damage == b"" else "move it out of _delta_log"
        assert fix in stats.last_error
        assert stats.tables[TELEMETRY_TABLE].commit_failures >= 1 and writer.buffered_rows() == 10
        assert sorted((Path(uri) / TELEMETRY_TABLE / "_delta_log").glob("*.json")) == entries  # moved none
        # Maintenance leaves it too: a checkpoint over the entry would make the damage part of the table.
        keeper = HistoryWriter(HistorySettings(uri=uri, maintain_every_s=0), maintain_in_child=False)
        keeper.maintain_now(dt.datetime.fromtimestamp(T0, dt.UTC).date())
        assert keeper.stats().maintenance_failures == 1 and str(damaged) in keeper.stats().last_error
        assert not list((Path(uri) / TELEMETRY_TABLE / "_delta_log").glob("*.checkpoint.parquet"))
        damaged.write_bytes(NO_ACTION_ENTRY.encode() if damage == b"" else whole)
        assert writer.flush(10)
    finally:
        writer.close()
    assert rows_of(uri).height == (30 if damage == b"" else 40)


def test_a_trailing_run_of_empty_and_nul_entries_is_set_aside_newest_first(tmp_path: Path) -> None:
    """A power loss often leaves several newest entries cut short: empty (ext4 writes a file's blocks late)
    or all NUL bytes (XFS). The writer set aside only an empty newest one and refused the rest."""
    from twin.output.history import SET_ASIDE_DIR, check_log

    uri = str(tmp_path / "h")
    entries = _three_commits(uri)
    entries[-1].write_bytes(b"")
    entries[-2].write_bytes(b"\0" * len(entries[-2].read_bytes()))
    check = check_log(f"{uri}/{TELEMETRY_TABLE}", parse=False)
    assert check.trailing_empty == (entries[-1], entries[-2]) and check.newest_empty_only
    writer = HistoryWriter(HistorySettings(uri=uri, commit_every_s=3600, maintain_every_s=0)).start()
    try:
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=T0 + 100, seed=9))[0])
        assert writer.flush(10), writer.stats().last_error
        assert writer.stats().tables[TELEMETRY_TABLE].log_entries_set_aside == 2
    finally:
        writer.close()
    aside = Path(uri) / TELEMETRY_TABLE / SET_ASIDE_DIR
    assert sorted(p.name for p in aside.iterdir()) == [entries[-2].name, entries[-1].name]
    assert rows_of(uri).height == 20  # the first commit and the new one


def test_setting_an_entry_aside_never_lands_on_an_entry_another_writer_committed_meanwhile(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Once the empty entry N was moved aside, a second writer could commit a new N (with rows) and N + 1;
    the put back (a rename) then replaced that new N with the empty one."""
    from twin.output import history

    log_dir = tmp_path / "t" / "_delta_log"
    log_dir.mkdir(parents=True)
    (log_dir / f"{0:020d}.json").write_text('{"commitInfo":{}}\n')
    entry = log_dir / f"{1:020d}.json"
    entry.write_bytes(b"")
    theirs = b'{"add":{"path":"theirs.parquet"}}\n'
    unlink = os.unlink

    def another_writer_commits(path: Any) -> None:
        unlink(path)
        if Path(path) == entry:  # the moment after the move aside
            entry.write_bytes(theirs)
            (log_dir / f"{2:020d}.json").write_text('{"commitInfo":{}}\n')

    monkeypatch.setattr(history.os, "unlink", another_writer_commits)
    moved = history._set_aside(entry)
    assert entry.read_bytes() == theirs
    assert moved is not None and moved.read_bytes() == b""  # ours stays aside, kept


@pytest.mark.parametrize("code", [errno.EPERM, errno.EOPNOTSUPP, errno.EXDEV])
def test_an_entry_is_set_aside_where_the_filesystem_has_no_hard_links(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, code: int
) -> None:
    """On vfat, exFAT, CIFS and some FUSE filesystems os.link is refused: setting an empty entry aside failed,
    and with it every commit to the table."""
    from twin.output import history

    def no_links(*_: Any) -> None:
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(history.os, "link", no_links)
    log_dir = tmp_path / "t" / "_delta_log"
    aside = tmp_path / "t" / history.SET_ASIDE_DIR
    aside.mkdir(parents=True)
    log_dir.mkdir()
    (log_dir / f"{0:020d}.json").write_text('{"commitInfo":{}}\n')
    entry = log_dir / f"{1:020d}.json"
    entry.write_bytes(b"")
    (aside / entry.name).write_bytes(b"set aside before")
    with caplog.at_level(logging.WARNING, logger="twin.output.history"):
        moved = history._set_aside(entry)
    assert moved == aside / f"{entry.name}.1" and not entry.exists()
    assert (aside / entry.name).read_bytes() == b"set aside before"  # not replaced
    assert "no hard links" in caplog.text
    # A later entry appeared meanwhile: ours goes back, unless another writer committed this version anew.
    entry.write_bytes(b"")
    rename = os.rename

    def a_later_entry_appears(source: Any, target: Any) -> None:
        rename(source, target)
        if Path(source) == entry:
            (log_dir / f"{2:020d}.json").write_text('{"commitInfo":{}}\n')

    monkeypatch.setattr(history.os, "rename", a_later_entry_appears)
    assert history._set_aside(entry) is None and entry.read_bytes() == b""
    theirs = b'{"add":{"path":"theirs.parquet"}}\n'

    def another_writer_commits(source: Any, target: Any) -> None:
        rename(source, target)
        if Path(source) == entry:
            entry.write_bytes(theirs)

    monkeypatch.setattr(history.os, "rename", another_writer_commits)
    moved = history._set_aside(entry)
    assert entry.read_bytes() == theirs and moved is not None and moved.read_bytes() == b""


def test_the_log_check_looks_at_no_entry_before_the_last_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A log kept 30 days at a commit each 10 s holds some 259k entries: the check listed and sorted them
    all at each read (each console /sessions request), 0.67 s a call, to look at the few after the
    checkpoint."""
    from twin.output.history import check_log

    log_dir = tmp_path / "t" / "_delta_log"
    log_dir.mkdir(parents=True)
    for version in range(200):
        (log_dir / f"{version:020d}.json").write_text('{"commitInfo":{}}\n')
    (log_dir / f"{201:020d}.json").write_bytes(b"")
    (log_dir / "_last_checkpoint").write_text('{"version": 197, "size": 1}')
    looked: list[str] = []
    stat = os.stat

    def counted(path: Any, *args: Any, **kwargs: Any) -> Any:
        looked.append(Path(path).name)
        return stat(path, *args, **kwargs)

    monkeypatch.setattr(os, "stat", counted)
    monkeypatch.setattr(Path, "glob", lambda *_: pytest.fail("the check lists the log"))
    monkeypatch.setattr(os, "scandir", lambda *_: pytest.fail("the check lists the log"))
    for parse in (False, True):
        looked.clear()
        check = check_log(str(tmp_path / "t"), parse=parse)
        assert check.newest == log_dir / f"{199:020d}.json" and check.empty == ()  # 200 is missing
        entries = [name for name in looked if name.endswith(".json")]
        assert entries and min(entries) == f"{198:020d}.json", looked


@pytest.mark.parametrize("pointer", [150, -7, 10**15, "not a version"])
def test_the_log_check_finds_damage_after_a_stale_checkpoint_pointer(tmp_path: Path, pointer: object) -> None:
    """A pointer to a checkpoint since cleaned up (or out of range) named no entry: the check found nothing,
    and the writer committed after the empty entry, whose commit's rows were lost without a word."""
    from twin.output.history import check_log

    log_dir = tmp_path / "t" / "_delta_log"
    log_dir.mkdir(parents=True)
    for version in range(300, 500):
        (log_dir / f"{version:020d}.json").write_text('{"commitInfo":{}}\n')
    (log_dir / f"{500:020d}.json").write_bytes(b"")
    (log_dir / "_last_checkpoint").write_text(json.dumps({"version": pointer, "size": 1}))
    for parse in (False, True):
        check = check_log(str(tmp_path / "t"), parse=parse)
        assert check.empty == (log_dir / f"{500:020d}.json",) and check.newest == check.empty[0]
    (log_dir / f"{400:020d}.checkpoint.parquet").write_bytes(b"")  # the newest checkpoint is where to start
    assert check_log(str(tmp_path / "t")).empty == (log_dir / f"{500:020d}.json",)


@pytest.mark.parametrize(
    "figures",
    [
        {"f_blocks": 0, "f_frsize": 0, "f_bavail": 0, "f_bfree": 0},  # FUSE, some network filesystems
        {"f_blocks": 1000, "f_frsize": 0, "f_bavail": 0, "f_bfree": 0},
        {"f_blocks": 1000, "f_frsize": 4096, "f_bavail": 0, "f_bfree": 500},  # root may use the reserve
    ],
)
def test_the_free_space_check_trusts_no_figures_statvfs_does_not_tell(
    monkeypatch: pytest.MonkeyPatch, figures: dict[str, int]
) -> None:
    """statvfs on a FUSE or network filesystem can report zero blocks: every commit was refused for good;
    as root, the agent stopped at ext4's reserve, which root may write into."""
    from twin.output import history

    monkeypatch.setattr(history.os, "statvfs", lambda _: types.SimpleNamespace(**figures))
    monkeypatch.setattr(history.os, "geteuid", lambda: 0)
    history._require_free_space("/anywhere")  # no ENOSPC


def test_the_free_space_check_waits_for_a_commit_failed_on_a_full_disk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Checked before every commit, a statvfs that misreports refused them all: only a commit after one
    that failed on a full disk (where deltalake panicked at each retry) is checked first."""
    from twin.output import history

    full = types.SimpleNamespace(f_blocks=1000, f_frsize=4096, f_bavail=0, f_bfree=0)
    monkeypatch.setattr(history.os, "statvfs", lambda _: full)
    writer = HistoryWriter(
        HistorySettings(uri=str(tmp_path / "h"), commit_every_s=3600, maintain_every_s=0, retry_min_s=0.05)
    ).start()
    try:
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10))[0])
        assert writer.flush(10), writer.stats().last_error
        writer._disk_was_full = True  # as _failed leaves it after ENOSPC
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10, start_s=T0 + 100))[0])
        assert not writer.flush(2)
        assert "bytes free, below the" in writer.stats().last_error
    finally:
        writer.close(timeout=0)


@pytest.mark.parametrize(
    "failure",
    [
        OSError(errno.ENOSPC, "No space left on device"),
        OSError(errno.EFBIG, "File too large"),
        RuntimeError("Generic LocalFileSystem error: File too large (os error 27)"),
    ],
)
def test_a_commit_failed_on_a_full_disk_makes_the_next_one_check_free_space_first(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failure: BaseException
) -> None:
    """The free-space check waits for a commit failed on a full disk: `_failed` must know one when it sees
    it, a file too large as `_describe_storage_error` tells it."""
    import deltalake

    def full(*_: Any, **__: Any) -> None:
        raise failure

    monkeypatch.setattr(deltalake, "write_deltalake", full)
    writer = HistoryWriter(
        HistorySettings(uri=str(tmp_path / "h"), commit_every_s=3600, maintain_every_s=0, retry_min_s=60)
    ).start()
    try:
        assert not writer._disk_was_full
        writer.add(TELEMETRY_TABLE, telemetry_table(samples(10))[0])
        assert not writer.flush(2)
        assert "the disk is full" in writer.stats().last_error
        assert writer._disk_was_full
    finally:
        writer.close(timeout=0)


def test_rows_jumping_past_keep_days_warn_once_per_table(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An arm used weekly with keep_days = 2 saw a WARNING about the host's clock at every maintenance."""
    from twin.output import history

    monkeypatch.setattr(history, "_CLOCK_WARNED", {})  # what another test warned about must not count here
    caplog.set_level("INFO", logger="twin.output.history")
    days = ["2026-01-01", "2026-01-08", "2026-01-15"]
    for _ in range(2):
        assert history._expiry_cut("weekly-table", days, dt.date(2026, 1, 16), 1) == "2026-01-08"
    said = [r for r in caplog.records if "weekly-table" in r.getMessage()]
    assert [r.levelno for r in said] == [logging.WARNING, logging.INFO]
    assert "the clock stepped" in said[0].getMessage() and "no rows for 7 days" in said[0].getMessage()


def test_a_new_jump_of_a_table_already_warned_about_warns_again(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Once a table was warned about (an arm used weekly), the clock stepping to 2099 later was only INFO."""
    from twin.output import history

    monkeypatch.setattr(history, "_CLOCK_WARNED", {})
    caplog.set_level("INFO", logger="twin.output.history")
    weekly = ["2026-01-01", "2026-01-08", "2026-01-15"]
    for days, today in ((weekly, dt.date(2026, 1, 16)), (weekly, dt.date(2026, 1, 16))):
        history._expiry_cut("t", days, today, 1)
    history._expiry_cut("t", [*weekly, "2099-06-01"], dt.date(2099, 6, 1), 1)
    history._expiry_cut("t", [*weekly, "2099-06-01"], dt.date(2099, 6, 1), 1)
    assert [r.levelno for r in caplog.records if "that the clock" in r.getMessage()] == [
        logging.WARNING,
        logging.INFO,
        logging.WARNING,
        logging.INFO,
    ]
    assert history._CLOCK_WARNED == {"t": ("2026-01-15", "2099-06-01")}  # one entry a table


def test_the_clock_warning_is_said_once_across_maintenance_processes(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Maintenance runs in a process of its own, new at each run: a warning remembered there alone was said
    again at every run."""
    uri = str(tmp_path / "h")
    _history_on_days(uri, [40, 3, 2, 1, 0])
    settings = HistorySettings(uri=uri, maintain_every_s=0, vacuum_retention_hours=0, keep_days=2)
    wall = [dt.datetime(2099, 6, 1, 12, tzinfo=dt.UTC).timestamp()]
    writer = HistoryWriter(settings, wall_clock=lambda: wall[0])
    caplog.set_level("INFO", logger="twin.output.history")
    levels = []
    for _ in range(2):
        caplog.clear()
        writer.maintain_now()
        wall[0] += 3600  # the next maintenance window (the lease is per window)
        said = [r for r in caplog.records if "that the clock (today" in r.getMessage()]
        levels.append({r.levelno for r in said})
        # the table's name, as every other line says it, not its location
        assert said and {getattr(r, "table", None) for r in said} <= {TELEMETRY_TABLE, REJECTED_TABLE}
        assert not any(uri in r.getMessage() for r in said)
    assert levels == [{logging.WARNING}, {logging.INFO}], levels


def test_a_partition_without_a_day_takes_no_day_keep_days_keeps() -> None:
    """A null partition value became "None", sorted after every date, and held one of the newest days."""
    from twin.output.history import PARTITION_COLUMN, _partition_days

    days = ["2026-01-02", None, "2026-01-01"]
    table = types.SimpleNamespace(partitions=lambda: [{PARTITION_COLUMN: day} for day in days])
    assert _partition_days(table) == ["2026-01-01", "2026-01-02"]


def test_a_table_whose_rows_were_all_deleted_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk's finding: with every day deleted (keep_days, or a delete by hand), `ls` said only "no rows
    for this selection", and plot, export and replay that the "devices with history are none"."""
    from deltalake import DeltaTable
    from twin.cli import main

    uri = _history_with(tmp_path, samples(20))
    DeltaTable(f"{uri}/{TELEMETRY_TABLE}").delete("date < '2100-01-01'")
    out = ["--out", str(tmp_path / "out.png")]
    for args in (["ls"], ["ls", "--device", "arm-001"], ["plot", "--device", "arm-001", *out], ["export"]):
        assert main(["history", *args, "--history", uri]) == 1
        err = capsys.readouterr().err
        assert "the table holds no row of any device now" in err and "none" not in err, err


def test_a_history_uri_the_agent_would_refuse_is_refused_by_the_commands(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk's finding: `--history gs://x/h` or `http://x/h` was answered "no history table ... nothing was
    recorded there yet", and a file as a table not there; the agent refuses each as `[history] uri`."""
    from twin.cli import main

    a_file = tmp_path / "history"
    a_file.write_text("not a directory\n")
    said = {
        "gs://x/h": "'gs://x/h' is not a directory or s3://bucket/prefix",
        "s3://": "'s3://' names no bucket",
        "s3:/x/h": "'s3:/x/h' lacks the '//' after 's3:', as in s3://bucket/prefix",
        str(a_file): f"'{a_file}' is a file; give the directory that holds the history",
    }
    for uri, why in said.items():
        for command in (["history", "ls"], ["replay", "--device", "arm-001", "--from", "1h", "--to", "now"]):
            with pytest.raises(SystemExit) as exited:
                main([*command, "--history", uri])
            assert exited.value.code == 2
            err = capsys.readouterr().err
            assert f"argument --history: {why}" in err, err


def test_a_window_that_misses_the_rows_says_when_they_are(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk's finding: `--since` past the rows (or a local time taken for UTC) was answered "no rows in
    this selection", as a device that never published is. Each command now says when the rows are."""
    from twin.cli import main
    from twin.ops.history import iso_utc

    uri = _history_with_a_rejection(tmp_path)
    times = pl.scan_delta(f"{uri}/{TELEMETRY_TABLE}").select("device_id", "received_at").collect()
    ones = times.filter(pl.col("device_id") == "arm-001")["received_at"]
    later = str(T0 + 3600)

    def said(*args: str) -> str:
        assert main(["history", *args[:1], "--history", uri, *args[1:]]) == 1
        return capsys.readouterr().err

    arm = f"arm-001's rows span {iso_utc(ones.min())} .. {iso_utc(ones.max())}"  # type: ignore[arg-type]
    table = f"its rows span {iso_utc(times['received_at'].min())} .. "  # type: ignore[arg-type]
    assert table in said("ls", "--since", later)
    assert arm in said("ls", "--device", "arm-001", "--since", later)
    # With --json, the reason too, on stderr: stdout is the JSON alone.
    assert main(["history", "ls", "--history", uri, "--device", "arm-001", "--since", later, "--json"]) == 1
    out, err = capsys.readouterr()
    assert json.loads(out)["devices"] == [] and arm in err, err
    assert arm in said("export", "--device", "arm-001", "--since", later, "--out", str(tmp_path / "a.csv"))
    assert arm in said("plot", "--device", "arm-001", "--since", later, "--out", str(tmp_path / "a.png"))


@pytest.mark.parametrize("damage", ["cut", "missing", "inside"])
def test_a_damaged_or_missing_data_file_is_named_with_the_fix(
    damage: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """A walk cut one data file of the demo's history short (a copy that stopped half way) and removed
    another: every history command ended in a polars traceback, a Rust panic for the cut file, naming
    neither the file nor what to do. A later walk damaged bytes inside one, its footer whole: the commands
    said "every data file its log names reads whole now", which sent the user nowhere."""
    from twin.cli import main

    _history_with(tmp_path, samples(50))
    uri = _history_with(tmp_path, samples(50, start_s=T0 + 60, seed=2))
    table = Path(uri) / TELEMETRY_TABLE
    victim = sorted(table.glob("date=*/*.parquet"))[0]
    if damage == "cut":
        victim.write_bytes(victim.read_bytes()[:100])
    elif damage == "inside":
        data = bytearray(victim.read_bytes())
        pages_end = len(data) - 8 - int.from_bytes(data[-8:-4], "little")  # the footer stays whole
        for i in range(4, pages_end):  # every column's pages: `ls` reads only a few columns
            data[i] ^= 0xFF
        victim.write_bytes(bytes(data))
    else:
        victim.unlink()
    out = tmp_path / "e.csv"
    for args in (
        ["ls"],
        ["plot", "--device", "arm-001", "--out", str(tmp_path / "p.png")],
        ["export", "--format", "csv", "--out", str(out)],
    ):
        assert main(["history", args[0], "--history", uri, *args[1:]]) == 1
        err = capsys.readouterr().err
        assert f"a data file its log names is missing or damaged: {victim}" in err, err
        repair = f"from deltalake import DeltaTable; print(DeltaTable('{table}').repair())"
        assert _repair_command(err)[-1] == repair
    assert not out.exists() and not (tmp_path / "p.png").exists()
    # The console's Sessions page, empty either way, says why in the log when the table is there.
    from twin.ops.sessions import HistorySessions

    with caplog.at_level(logging.DEBUG, logger="twin.ops.sessions"):
        assert HistorySessions(str(tmp_path / "none")).sessions(30.0) == []
        assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
        catalog = HistorySessions(uri)
        assert catalog.sessions(30.0) == [] and catalog.sessions(30.0) == []  # each refresh reads again
        # ... and says why to the page, which read "no session yet" of it.
        assert catalog.unreadable is not None and "missing or damaged" in catalog.unreadable
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and warned[0].startswith("history: the console lists no sessions: cannot read")
    assert "missing or damaged" in warned[0]
    # The fix as said: the cut file out of the table, its entry out of the log; the other rows read again.
    victim.unlink(missing_ok=True)
    DeltaTable(str(table)).repair()
    assert main(["history", "ls", "--history", uri, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["devices"][0]["rows"] == 50
    assert catalog.sessions(30.0) and catalog.unreadable is None


def _damage_inside(path: Path) -> bytes:
    """Flip the bytes of every page of a Parquet file, its footer whole; the file's bytes before."""
    before = path.read_bytes()
    data = bytearray(before)
    pages_end = len(data) - 8 - int.from_bytes(data[-8:-4], "little")
    for i in range(4, pages_end):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))
    return before


def test_the_deep_walk_of_a_damaged_table_is_done_once_until_its_files_change(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A review: the Sessions page asks every 10 s, and each time the walk read every page of every file of
    a table damaged inside (seconds on a large one). Once per table state; a file put back is seen."""
    from twin.ops import history as history_ops
    from twin.ops.sessions import HistorySessions

    _history_with(tmp_path, samples(50))
    uri = _history_with(tmp_path, samples(50, start_s=T0 + 60, seed=2))
    first, second = sorted((Path(uri) / TELEMETRY_TABLE).glob("date=*/*.parquet"))[:2]
    kept = _damage_inside(first)
    _damage_inside(second)
    walks: list[bool] = []
    walk = history_ops._walk

    def counted(uris: list[str], *, deep: bool) -> list[str]:
        walks.append(deep)
        return walk(uris, deep=deep)

    monkeypatch.setattr(history_ops, "_walk", counted)
    catalog = HistorySessions(uri)
    for _ in range(3):
        assert catalog.sessions(30.0) == []
        assert catalog.unreadable is not None and str(first) in catalog.unreadable, catalog.unreadable
    assert walks.count(True) == 1, walks
    first.write_bytes(kept)  # put back whole: the next answer names only the other
    assert catalog.sessions(30.0) == []
    assert catalog.unreadable is not None and str(second) in catalog.unreadable, catalog.unreadable
    assert str(first) not in catalog.unreadable and walks.count(True) == 2, walks


def test_the_sessions_page_warns_once_per_error_however_its_details_vary(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each console refresh reads the history again: a storage refusal carries another request id each time
    (a set keyed on the whole text grew by one and warned at every refresh). The set stays bounded."""
    from twin.ops import sessions as sessions_module
    from twin.ops.history import HistoryReader

    said: list[str] = []

    def summary(self: Any, **_: Any) -> Any:
        raise HistoryReadError(said[-1])

    monkeypatch.setattr(HistoryReader, "summary", summary)
    catalog = sessions_module.HistorySessions("s3://b/h")
    with caplog.at_level(logging.DEBUG, logger="twin.ops.sessions"):
        for n in range(5):
            said.append(f"cannot read history at s3://b/h/telemetry: the storage refused it (id {n:08x}a1)")
            assert catalog.sessions(30.0) == []
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1
    monkeypatch.setattr(sessions_module, "MAX_WARNED", 3)
    for n in range(10):  # distinct errors past the bound: the set starts again, never past it
        said.append(f"error kind {chr(ord('g') + n)}")
        catalog.sessions(30.0)
        assert len(catalog._warned) <= 3


def _repair_command(err: str) -> list[str]:
    """The repair command line a damaged-file message prints, split as a shell would."""
    match = re.search(r"from its log: (.*) \(their rows", err)
    assert match, err
    return shlex.split(match.group(1))


def test_the_repair_command_printed_runs_for_a_path_with_quotes_and_a_dollar(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The printed repair command put the path in '...' inside "...": a `'` in it ended the Python string,
    and a `$` was expanded by the shell."""
    from twin.cli import main

    base = tmp_path / "it's$HOME"  # (a `"` is one of the characters polars reads no table under)
    _history_with(base, samples(20))
    uri = _history_with(base, samples(20, start_s=T0 + 60, seed=2))
    victim = sorted((Path(uri) / TELEMETRY_TABLE).glob("date=*/*.parquet"))[0]
    victim.unlink()
    assert main(["history", "ls", "--history", uri]) == 1
    command = _repair_command(capsys.readouterr().err)
    subprocess.run(command, check=True, capture_output=True)
    assert main(["history", "ls", "--history", uri, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["devices"][0]["rows"] == 20


def test_a_read_whose_files_were_vacuumed_meanwhile_is_told_to_run_again(tmp_path: Path) -> None:
    """Maintenance may compact and vacuum a table while a reader streams an older version of it: the files
    are gone, not damaged, and the repair the damaged-file message gives would do nothing."""
    _history_with(tmp_path, samples(20))
    uri = _history_with(tmp_path, samples(20, start_s=T0 + 60, seed=2))
    from twin.ops.history import reading

    location = str(Path(uri) / TELEMETRY_TABLE)
    table = DeltaTable(location)
    before = table.version()
    table.optimize.compact()
    table.vacuum(retention_hours=0, enforce_retention_duration=False, dry_run=False)
    # What a reader that listed the table's files before the vacuum then reads.
    gone = pytest.raises(HistoryReadError, match=r"vacuumed it meanwhile .*; run the command again")
    with gone, reading(location):
        pl.scan_delta(location, version=before).collect()
    assert HistoryReader(uri).collect(HistoryReader(uri).window()).height == 40


def test_only_a_data_files_error_is_given_the_missing_file_advice(tmp_path: Path) -> None:
    """Any polars error of a read was said as a missing or vacuumed data file: a missing column, a failed
    strict cast or expired S3 credentials were told to repair the table or run again."""
    from twin.ops.history import reading

    location = str(Path(_history_with(tmp_path, samples(20))) / TELEMETRY_TABLE)
    with pytest.raises(pl.exceptions.ColumnNotFoundError), reading(location):
        pl.scan_delta(location).select("nope").collect()
    with pytest.raises(pl.exceptions.InvalidOperationError), reading(location):
        pl.scan_delta(location).select(pl.col("device_id").cast(pl.Int64, strict=True)).collect()
    # The storage's refusal is one line with its own fix, not a file's advice nor a traceback.
    expired = pl.exceptions.ComputeError("Generic S3 error: ExpiredToken: The provided token has expired")
    refused = pytest.raises(HistoryReadError, match=r"storage refused it .*ExpiredToken.* refresh the AWS")
    with refused, reading("s3://twin-history/history/telemetry"):
        raise expired
    # A local table is refused by no object store; a file name holding 403 is no HTTP 403.
    local = pl.exceptions.ComputeError("Generic S3 error: ExpiredToken")
    with pytest.raises(pl.exceptions.ComputeError), reading(location):
        raise local
    named = pl.exceptions.ComputeError("cannot read part-00403-abc.zstd.parquet: unexpected token")
    with pytest.raises(HistoryReadError) as caught, reading("s3://twin-history/history/telemetry"):
        raise named
    assert "storage refused" not in str(caught.value)
    # A Parquet error, with every file whole now, is the error: nothing was vacuumed, as ENOENT would say.
    footer = pl.exceptions.ComputeError("parquet: File out of specification: invalid footer")
    said = pytest.raises(HistoryReadError, match=r"invalid footer \(every data file")
    with said as caught, reading(location):
        raise footer
    assert "vacuumed" not in str(caught.value)
    with pytest.raises(HistoryReadError, match="vacuumed it meanwhile"), reading(location):
        raise FileNotFoundError(2, "No such file or directory")


def test_a_history_whose_path_has_a_space_is_not_called_damaged(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk kept its history under a folder with a space: every command called each data file damaged and
    said to move them all out of the table. deltalake gives their paths escaped (`a%20b`), which polars then
    fails to open; the files are whole."""
    from twin.cli import main
    from twin.ops.history import _damaged_files

    uri = _history_with(tmp_path / "my data", samples(20))
    table = Path(uri) / TELEMETRY_TABLE
    assert _damaged_files(str(table)) == []
    assert main(["history", "ls", "--history", uri]) == 1
    err = capsys.readouterr().err
    assert "reads no table whose path holds a space or another character a URI escapes (' ')" in err, err
    assert "damaged" not in err and "vacuumed" not in err
    # A file that is really cut short is still the one named.
    victim = sorted(table.glob("date=*/*.parquet"))[0]
    victim.write_bytes(victim.read_bytes()[:100])
    assert _damaged_files(str(table)) == [str(victim)]


def test_an_error_naming_the_hidden_file_written_first_names_out_instead(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """plot writes beside --out, then renames: a refusal to write that file (permissions) named it, a hidden
    `.name.partial-N` the person never asked for."""
    import matplotlib.figure
    from twin.cli import main

    uri = _history_with(tmp_path, samples(20))
    out = tmp_path / "picture.png"

    def refused(self: Any, path: Any, **_: Any) -> None:
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", refused)
    code = main(["history", "plot", "--history", uri, "--device", "arm-001", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and f"cannot use {out}: Permission denied" in err and ".partial-" not in err, err


def test_a_reads_error_during_an_export_is_not_blamed_on_out(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Only a write's own failures (a full disk, a read-only one) name --out: too many open files while
    reading a large table is no fault of the file written, and `twin` must not say to free space there."""
    from twin.ops.history import HistoryReader, export

    uri = _history_with(tmp_path, samples(20))
    out = tmp_path / "rows.parquet"

    def too_many(self: Any, path: Any, **_: Any) -> None:
        raise pl.exceptions.ComputeError("Too many open files (os error 24)")

    monkeypatch.setattr(pl.LazyFrame, "sink_parquet", too_many)
    with pytest.raises(pl.exceptions.ComputeError, match="Too many open files"):
        export(HistoryReader(uri), out, "parquet")
    assert not out.exists()


@pytest.mark.parametrize("what", ["plot", "csv", "parquet"])
def test_a_full_disk_keeps_the_file_a_person_had_and_names_the_path(
    what: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A walk wrote to a full disk: both ended in a traceback naming no path (polars and PIL raise the error
    without one), and `plot --force` left a cut PNG where the picture it replaced had been. The default
    export, Parquet, still did: polars raises its full disk as a ComputeError, not an OSError."""
    import matplotlib.figure
    from twin.cli import main

    uri = _history_with(tmp_path, samples(50))
    out = tmp_path / "kept.out"
    out.write_text("before\n")
    error = pl.exceptions.ComputeError if what == "parquet" else OSError

    def full(self: Any, path: Any, **_: Any) -> None:
        Path(path).write_text("half a file\n")
        raise error("No space left on device (os error 28)")  # as polars raises it: no errno, no path

    command, args = "export", ["--format", what]
    if what == "plot":
        monkeypatch.setattr(matplotlib.figure.Figure, "savefig", full)
        command, args = "plot", ["--device", "arm-001"]
    else:
        monkeypatch.setattr(pl.LazyFrame, f"sink_{what}", full)
    code = main(["history", command, "--history", uri, *args, "--out", str(out), "--force"])
    assert code == 1
    assert f"cannot use {out}: No space left on device; free some space" in capsys.readouterr().err
    assert out.read_text() == "before\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["history", "kept.out"]


def test_plot_and_replay_of_a_device_with_no_history_name_a_few_others_and_its_case_twin(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk asked plot for ARM-003: unlike ls and export, it did not say ids are case-sensitive, and it
    named every device of the table, which for a fleet is a screenful."""
    from twin.cli import main
    from twin.ops.history import HINT_DEVICES

    batch = [s for i in range(HINT_DEVICES + 5) for s in samples(3, device=f"arm-{i:03}")]
    uri = _history_with(tmp_path, batch)

    def plot(device: str) -> str:
        args = ["--device", device, "--out", str(tmp_path / "p.png")]
        assert main(["history", "plot", "--history", uri, *args]) == 1
        return capsys.readouterr().err

    assert "case-sensitive, and 'arm-003' has history" in plot("ARM-003")
    err = plot("arm-404")
    assert f"arm-{HINT_DEVICES - 1:03} and 5 more" in err and f"arm-{HINT_DEVICES:03}" not in err
    # Replay, too: it worked out every session of the table to name every device.
    from twin.ops.replay import replay

    for device, said in (
        ("ARM-003", "'arm-003' has history"),
        ("arm-404", f"arm-{HINT_DEVICES - 1:03} and 5"),
    ):
        config = dataclasses.replace(_replay_config(uri, NO_BROKER), device=device)
        with pytest.raises(HistoryReadError) as refused:
            replay(config)
        assert said in str(refused.value) and f"arm-{HINT_DEVICES:03}" not in str(refused.value)


def test_an_interrupted_export_leaves_the_file_as_it_was(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C half way left a file with half the rows and no word; now nothing is written and it says so."""
    import polars
    from twin.cli import main

    uri = _history_with(tmp_path, samples(50))
    out = tmp_path / "e.csv"
    out.write_text("before\n")

    def interrupted(self: Any, path: Path, **_: Any) -> None:
        Path(path).write_text("half a file\n")
        raise KeyboardInterrupt

    monkeypatch.setattr(polars.LazyFrame, "sink_csv", interrupted)
    code = main(["history", "export", "--history", uri, "--format", "csv", "--out", str(out), "--force"])
    assert code == 130 and "interrupted: nothing written" in capsys.readouterr().err
    assert out.read_text() == "before\n" and sorted(p.name for p in tmp_path.iterdir()) == [
        "e.csv",
        "history",
    ]


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["ticks", "degrees"])
def test_replay_publishes_what_was_recorded_and_the_agent_mirrors_it(
    tmp_path: Path, mosquitto: object, variant: str
) -> None:
    from twin.ops.replay import replay
    from twin.service.agent import AgentService
    from twin.service.config import config_from_mapping
    from twin.transport.broker import BrokerConfig
    from twin.transport.subscriber import TelemetrySubscriber

    batch = samples(40, variant=variant)
    uri = _history_with(tmp_path, batch)
    received: list[bytes] = []
    sub = TelemetrySubscriber(
        BrokerConfig(url=mosquitto.url, client_id_prefix="replay-test-"),
        ["dt/lerobot/+/telemetry"],
        lambda _topic, payload, _t: received.append(payload),
    )
    agent = AgentService(
        config_from_mapping(
            {
                "broker": {"url": mosquitto.url},
                "telemetry": {"devices": ["arm-001"], "units": "auto"},
                "http": {"listen": "127.0.0.1:0"},
                # The agent keeps its own history of the replay: applied rows with raw readings, rejections.
                "history": {"uri": str(tmp_path / "agent-history"), "commit_every_s": 0.5},
            }
        )
    )
    sub.start()
    agent.start()
    try:
        assert sub.wait_subscribed(30) and agent.wait_subscribed(30)
        started = time.time()
        report = replay(_replay_config(uri, mosquitto.url, speed=4.0))
        wait_for(lambda: len(received) >= 40, 60, "the replayed messages at the subscriber")
        # The agent is a second subscriber: it is done once it has counted all 40 and its twin shows the last.
        wait_handled(agent.state, 40)
        last_stamp = json.loads(received[-1])["timestamp"]
        wait_for(
            lambda: agent.state().devices["arm-001"].timestamp_ms == last_stamp,
            60,
            "the twin at the last message",
        )
        state = agent.state()
    finally:
        agent.stop()
        sub.stop()
    assert report.published == 40 and report.publish_failures == 0
    # Its times as the history commands print them: UTC, milliseconds, Z.
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", report.first_recorded or "")
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", report.last_recorded or "")
    # 3.9 s recorded, at 4x: never early (the schedule), and well under the recording's own pace however
    # busy the machine is (the stamps below pin the 4x exactly).
    assert 3.9 / 4 * 0.9 < report.elapsed_s < 3.9
    assert len(received) == 40
    decoder = TelemetryDecoder(DecoderConfig(units=Units(variant)))
    stamps = []
    for original, payload in zip(batch, received, strict=True):
        again = decoder.decode(payload)
        assert again.angles_rad == original.telemetry.angles_rad  # the same message, decoded the same
        assert again.diagnostics == original.telemetry.diagnostics
        stamps.append(again.timestamp_ms)
    assert stamps[0] >= started * 1000 - 50  # retimed to start now ...
    assert all(b - a == 25 for a, b in itertools.pairwise(stamps))  # ... keeping 100 ms spacing at 4x
    mirrored = state.devices["arm-001"]
    # units=auto needs a few messages to decide, then mirrors: the last replayed pose is the twin's pose.
    applied = mirrored.health.counters.applied
    # (A worker behind, on a busy machine, applies each batch's newest and counts the rest as coalesced.)
    assert mirrored.health.counters.decoded >= 30 and applied >= 1
    last = batch[-1].telemetry.angles_rad
    # The mock motion stays inside the model's joint ranges, so nothing was clamped.
    assert mirrored.joints_rad == pytest.approx(last, abs=1e-9)

    # The agent's history (flushed by stop()) holds every decoded message with its raw readings, and the
    # messages auto-units held back as rejected rows.
    agent_rows = rows_of(str(tmp_path / "agent-history"))
    assert agent_rows.height == mirrored.health.counters.decoded >= applied
    stored = agent_rows.sort("edge_time").row(-1, named=True)
    sent_last = json.loads(received[-1])["joints"]
    assert stored["wrist_flex_load_raw"] == sent_last["wrist_flex"]["load"]
    assert stored["gripper_position_rad"] == last["gripper"]
    rejected = rows_of(str(tmp_path / "agent-history"), REJECTED_TABLE)
    assert rejected.height == mirrored.health.counters.rejected_total + sum(state.untracked_rejected.values())
    assert set(rejected["reason"].to_list()) == {"units_undecided"}
    history = state.agent.history
    # Read before the stop's commit: None if no commit was attempted yet, never a failure.
    assert history is not None and history.storage_ok is not False and history.commit_failures == 0


@pytest.mark.slow
def test_replay_refuses_an_arm_that_is_live_and_replays_it_under_another_id(
    tmp_path: Path, mosquitto: object
) -> None:
    """A replay under the id of an arm that is publishing would interleave two arms' poses in one twin (and
    its history and alarms): the replay listens on the topic first and refuses, naming the fix. Under
    another id it goes ahead beside the live arm; a retained message is not an arm publishing."""
    from awscrt import mqtt5
    from conftest import Publisher
    from twin.ops.replay import ReplayRefusedError, replay
    from twin.transport.broker import BrokerConfig
    from twin.transport.subscriber import TelemetrySubscriber

    uri = _history_with(tmp_path, samples(40))
    received: dict[str, list[bytes]] = {}
    sub = TelemetrySubscriber(
        BrokerConfig(url=mosquitto.url, client_id_prefix="replay-test-"),
        ["dt/lerobot/+/telemetry"],
        lambda topic, payload, _t: received.setdefault(topic.split("/")[2], []).append(payload),
    )
    live = b'{"live": true}'
    edge = Publisher(mosquitto.url)
    running = threading.Event()

    def publish_live() -> None:
        while not running.wait(0.1):  # the edge's 10 Hz
            edge.publish("arm-001", live)

    publisher = threading.Thread(target=publish_live, daemon=True)
    sub.start()
    try:
        assert sub.wait_subscribed(30)
        publisher.start()
        wait_for(lambda: len(received.get("arm-001", [])) >= 3, 30, "the live arm at the subscriber")
        # What an earlier run left retained on arm-002's topic is delivered on subscribing, not published.
        edge.client.publish(
            mqtt5.PublishPacket(
                topic="dt/lerobot/arm-002/telemetry", payload=live, qos=mqtt5.QoS.AT_LEAST_ONCE, retain=True
            )
        ).result(30)

        def config(**extra: Any) -> ReplayConfig:
            return _replay_config(uri, mosquitto.url, **extra)

        with pytest.raises(ReplayRefusedError) as refused:
            replay(config())
        said = str(refused.value)
        assert "arm-001 is live" in said and "--as-device arm-001-replay" in said, said
        for target in ("arm-001-replay", "arm-002"):
            report = replay(config(as_device=target))
            assert report.published == 40 and report.publish_failures == 0
            wait_for(lambda t=target: len(received.get(t, [])) >= 40, 60, f"the replay as {target}")
    finally:
        running.set()
        publisher.join(5)
        edge.client.publish(  # the retained message cleared, as a broker's owner would
            mqtt5.PublishPacket(topic="dt/lerobot/arm-002/telemetry", payload=b"", retain=True)
        ).result(30)
        edge.close()
        sub.stop()
    # Nothing of the refused replay reached the live arm's topic: only the live arm's own messages.
    assert set(received["arm-001"]) == {live}
    assert all(json.loads(p)["device_id"] == "arm-001-replay" for p in received["arm-001-replay"])


def test_replay_refused_its_topic_by_the_broker_publishes_nothing_and_names_the_rights(
    tmp_path: Path, mosquitto: object
) -> None:
    """On IoT Core, a replay whose identity may publish but not subscribe to the arm's topic cannot check that
    the arm is not live: the SUBACK refuses the filter (the quota proxy's policy stand-in does as IoT Core
    does), and the replay refuses to go ahead, naming the two rights it needs."""
    from twin.ops.replay import ReplayRefusedError, replay
    from twin.rig.quota_proxy import QuotaProxy

    uri = _history_with(tmp_path, samples(5))
    topic = "dt/lerobot/arm-001/telemetry"
    with QuotaProxy("127.0.0.1", mosquitto.port, budget=None, denied_filters=[topic]) as proxy:
        config = _replay_config(uri, proxy.url)
        with pytest.raises(ReplayRefusedError) as refused:
            replay(config)
        (connection,) = proxy.connections()
    assert connection.subscriptions_denied == 1
    assert connection.forwarded_to_broker == 0  # not one message published
    said = str(refused.value)
    assert f"the subscription to {topic} was refused (NOT_AUTHORIZED)" in said, said
    assert "iot:Subscribe and iot:Receive" in said


def test_every_worker_has_a_slot_for_its_feeds_delivered_count(tmp_path: Path) -> None:
    # One slot per mirror, by its shard's index: as many as twin.workers allows, and a feed outside them is
    # refused when it is made, not when its thread first delivers.
    import multiprocessing

    from twin.output.history_feed import FEED_SLOTS, HistoryLink
    from twin.service.config import MAX_WORKERS

    assert FEED_SLOTS >= MAX_WORKERS
    link = HistoryLink(
        str(tmp_path / "nobody.sock"), b"key", multiprocessing.get_context("spawn").Array("q", 2, lock=False)
    )
    with pytest.raises(ValueError, match=r"slot is 0\.\.1, not 2"):
        HistoryFeed(link, max_pending=10, payload_max_bytes=8, slot=2)


def test_a_feeds_rows_are_counted_while_its_thread_builds_their_batch(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stress run: a report taken while the feed's thread built a batch (rows off the queue, not yet in
    hand) saw those rows nowhere: waiting + delivered fell below the rows handed in. Read at that moment now,
    every row is counted once."""
    import multiprocessing

    from twin.output import history_feed
    from twin.output.history_feed import HistoryLink

    seen: list[tuple[int, int]] = []  # (waiting + delivered, handed) as the batch is built
    build = history_feed._batch_of
    feed: HistoryFeed | None = None

    def counting_batch_of(telemetry: Any, rejected: Any) -> Any:
        assert feed is not None
        handed, stats = feed.handed, feed.stats()  # rows are handed in on this test's thread only
        seen.append((stats.pending + stats.delivered, handed))
        return build(telemetry, rejected)

    monkeypatch.setattr(history_feed, "_batch_of", counting_batch_of)
    link = HistoryLink(  # no writer listens: the batch stays in hand
        str(tmp_path / "nobody.sock"), b"key", multiprocessing.get_context("spawn").Array("q", 1, lock=False)
    )
    feed = HistoryFeed(link, max_pending=1000, payload_max_bytes=64)
    try:
        with feed._drop_lock:  # all five queued before the feed's thread takes any
            for i in range(5):
                feed.telemetry(("arm-001", time.time(), 1_700_000_000_000 + i, "ticks", (0.0,) * 6, b"{}"))
        wait_for(lambda: seen, 30, "the feed's thread to build a batch")
        assert seen[0] == (5, 5), seen
        assert feed.stats().pending == 5
    finally:
        feed.close(timeout=0.1)


def test_the_writer_process_logs_as_the_agent_does(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """Two walks found the writer's lines plain text and its INFO lines (a maintenance run's length) missing:
    a spawned process starts with no logging. It now sets up the agent's JSON lines at the agent's level."""
    import multiprocessing

    from twin.service.logs import setup_logging

    history = HistoryProcess(
        {
            "uri": str(tmp_path / "history"),
            "commit_every_s": 3600.0,
            "commit_every_rows": 1,
            "maintain_every_s": 0.5,
        },
        multiprocessing.get_context("spawn"),
        log=(setup_logging, "INFO"),
    )
    history.launch()
    feed = HistoryFeed(history.link, max_pending=1000, payload_max_bytes=64)
    out: list[str] = []

    def maintained() -> bool:
        out.append(capfd.readouterr().out)
        return "history: maintenance took" in "".join(out)

    try:
        feed.telemetry(("arm-001", time.time(), 1_700_000_000_000, "ticks", (0.0,) * 6, b"{}"))
        wait_for(maintained, 60, "the writer's line of a maintenance run", interval=0.2)
    finally:
        feed.close()
        history.stop()
    line = next(line for line in "".join(out).splitlines() if "history: maintenance took" in line)
    record = json.loads(line)  # one of the agent's JSON lines, not plain text
    assert (record["level"], record["logger"]) == ("INFO", "twin.output.history"), record


def test_the_hint_for_a_device_without_history_names_a_large_fleet_in_part() -> None:
    """A mistyped id at a fleet of 2,000 named every one of them in the error; a case slip names its twin."""
    from twin.ops.history import HINT_DEVICES, devices_hint

    class Known:
        def __init__(self, devices: list[str]) -> None:
            self.devices = devices

        def known_devices(self) -> list[str]:
            return self.devices

    fleet = Known([f"arm-{i:04d}" for i in range(2000)])
    hint = devices_hint(fleet, "arm-9999")  # type: ignore[arg-type]
    named = hint.split("devices with history are ")[1]
    assert named.endswith(f" and {2000 - HINT_DEVICES} more")
    assert named.count("arm-") == HINT_DEVICES and "arm-0000, arm-0001" in named
    assert devices_hint(fleet, "ARM-0007") == (  # type: ignore[arg-type]
        "; no row of 'ARM-0007' at all: device ids are case-sensitive, and 'arm-0007' has history"
    )
    assert devices_hint(fleet, "arm-0007") == ""  # type: ignore[arg-type]
    empty = devices_hint(Known([]), "arm-1")  # type: ignore[arg-type]
    assert empty == "; the table holds no row of any device now (keep_days, or a delete, removed them)"
