"""The events over a restart (twin.service.event_journal): written as the store numbers them, read back with
their ids, bounded on disk and in memory, a cut-short line skipped, a failed write counted and told; and
the agent that reads them back says whether the run before it stopped."""

from __future__ import annotations

import json
import logging
import random
import threading
import time
from collections.abc import Callable
from pathlib import Path

import msgspec
import pytest
from conftest import unbrokered_agent, wait_for
from twin.core.alarms import AlarmEvent, AlarmKind, AlarmState, Severity
from twin.edge.payload import encode, make_payload
from twin.output.sinks import SinkStats
from twin.robot import so101
from twin.service import event_journal
from twin.service.event_journal import EventJournal, bulk_path
from twin.service.events import (
    DEFAULT_CAPACITY,
    Event,
    EventKind,
    EventLevel,
    EventQuery,
    EventStore,
    FleetWatch,
)


class Clock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def journaled_store(path: Path, **kwargs: int) -> tuple[EventStore, EventJournal]:
    store, journal = EventStore(wall_clock=Clock()), EventJournal(path, **kwargs)
    store.subscribe(journal.add)
    return store, journal


def emit(
    store: EventStore, n: int, device: str = "arm-001", kind: EventKind = EventKind.STATUS
) -> list[Event]:
    return [
        store.emit(kind, EventLevel.WARNING, f"{device} went STALE ({k})", device=device) for k in range(n)
    ]


def raise_alarms(store: EventStore, n: int) -> list[Event]:
    data = {"action": "raised", "alarm_id": "arm-001/elbow_flex/over_temperature"}
    return [
        store.emit(EventKind.ALARM, EventLevel.WARNING, f"hot ({k})", device="arm-001", data=data)
        for k in range(n)
    ]


def test_events_come_back_as_they_were_numbered_and_the_next_are_numbered_on(tmp_path: Path) -> None:
    path = tmp_path / "state" / "events.jsonl"  # its directory is made on the first write
    store, journal = journaled_store(path)
    made = emit(store, 5)
    assert journal.pending == 5 and not path.exists()  # nothing written until a flush
    assert journal.flush() and journal.written == 5
    journal.close()

    again = EventStore(wall_clock=Clock())
    heard: list[Event] = []
    again.subscribe(heard.append)
    assert again.restore(EventJournal(path).load()) == 5
    assert again.query(EventQuery()) == made  # every field, the ids too
    assert heard == []  # no alert again for what was told before the restart
    assert again.emit(EventKind.AGENT, EventLevel.INFO, "the agent started").id == 6
    with pytest.raises(ValueError, match="before it numbers any"):
        again.restore(made)


def test_a_reader_after_the_gap_between_two_runs_gets_exactly_what_followed(tmp_path: Path) -> None:
    # A run whose last events were not written (killed between two flushes) leaves a gap in the ids: the
    # next run numbers on from the last it read, and `after` must find the start across the gap.
    store = EventStore(wall_clock=Clock())
    kept = [e for e in emit(store, 10) if e.id not in (8, 9)]
    again = EventStore(wall_clock=Clock())
    again.restore(kept)
    new = emit(again, 3)
    assert [e.id for e in new] == [11, 12, 13]
    for after in range(0, 14):
        expected = [e.id for e in (*kept, *new) if e.id > after]
        assert [e.id for e in again.after(after)] == expected, after
        assert [e.id for e in again.after(after, limit=2)] == expected[:2], after


def test_a_pair_of_files_stays_within_twice_its_size_and_keeps_the_newest(tmp_path: Path) -> None:
    path = tmp_path / "events.jsonl"
    store, journal = journaled_store(path, max_bytes=4_000)
    for _ in range(40):
        emit(store, 7)
        journal.flush()
    journal.close()
    files = {p.name for p in tmp_path.iterdir()}
    # Two at most (the last flush may just have renamed the current one away): the status events' pair.
    assert "events.bulk.jsonl.1" in files and files <= {"events.bulk.jsonl", "events.bulk.jsonl.1"}, files
    # Each file is renamed away within one flush of passing the size (a flush here is about 700 bytes).
    assert all(p.stat().st_size < 4_000 + 1_000 for p in tmp_path.iterdir())
    newest = EventJournal(path).load(limit=20)
    assert [e.id for e in newest] == list(range(261, 281))
    assert len(EventJournal(path).load(limit=10_000)) < 280  # the oldest went with the renames


def test_a_line_cut_short_by_a_kill_is_skipped_and_told(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "events.jsonl"
    store, journal = journaled_store(path)
    made = emit(store, 3)
    journal.close()
    with path.open("ab") as f:
        f.write(b'{"kind":"status","level":"warn')  # the kill came in the middle of a write
    reader = EventJournal(path)
    with caplog.at_level(logging.WARNING, logger="twin.service.event_journal"):
        assert reader.load() == made
    assert reader.unreadable == 1
    assert "1 line(s) that are not events" in caplog.text
    # The next run appends after the cut line: its own events are read back whole.
    store2, journal2 = journaled_store(path)
    store2.restore(made)
    emit(store2, 2)
    journal2.close()
    assert [e.id for e in EventJournal(path).load()] == [1, 2, 3, 4, 5]


def test_a_failed_write_is_counted_told_with_its_fix_and_tried_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "events.jsonl"
    path.mkdir()  # what opening it for appending fails on, as a full or read-only disk would
    clock = Clock()
    store, journal = EventStore(wall_clock=clock), EventJournal(path, clock=clock)
    store.subscribe(journal.add)
    with caplog.at_level(logging.ERROR, logger="twin.service.event_journal"):
        raise_alarms(store, 2)
        assert not journal.flush()
        raise_alarms(store, 1)
        assert not journal.flush()  # within WARN_EVERY_S: counted, not told again
    assert journal.not_written == 3
    stats, bulk, lifecycle = journal.sinks()  # each pair an output's figures in /state: SinkDrops counts them
    assert (stats.name, stats.dropped, stats.errors) == ("events_journal", 3, 2)
    assert "IsADirectoryError" in stats.last_error
    assert (bulk.name, bulk.dropped, bulk.errors, bulk.last_error) == ("events_journal_bulk", 0, 0, "")
    assert (lifecycle.name, lifecycle.dropped) == ("events_journal_lifecycle", 0)
    told = [r.getMessage() for r in caplog.records]
    assert len(told) == 1, told
    assert "2 event(s) could not be written" in told[0] and "Make room on its disk" in told[0]
    assert len(store) == 3  # still shown until the agent stops
    path.rmdir()
    raise_alarms(store, 1)
    with caplog.at_level(logging.WARNING, logger="twin.service.event_journal"):
        assert journal.flush()
    assert "written again, after 2 failed write(s); 3 event(s)" in caplog.records[-1].getMessage()
    journal.close()
    assert [e.id for e in EventJournal(path).load()] == [4]
    # Over: a failure after the recovery is told at once, within the minute of the last line.
    path.unlink()
    path.mkdir()
    raise_alarms(store, 1)
    emit(store, 2)  # the status events' file is written: only the alarm is counted
    with caplog.at_level(logging.ERROR, logger="twin.service.event_journal"):
        assert not journal.flush()
    assert "1 event(s) could not be written" in caplog.records[-1].getMessage()
    assert (journal.written, journal.not_written) == (3, 4)


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full, a file every write fills")
def test_a_full_disk_is_told_once_a_minute_not_once_per_flush(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A full disk opens the file and then fails the write, leaving the events in the file's buffer; closing
    # it fails on them again. The directory case above fails at the open, so it never reaches that close.
    path = tmp_path / "events.jsonl"
    path.symlink_to("/dev/full")
    clock = Clock()
    store, journal = EventStore(wall_clock=clock), EventJournal(path, clock=clock)
    store.subscribe(journal.add)
    with caplog.at_level(logging.WARNING, logger="twin.service.event_journal"):
        for _ in range(5):
            raise_alarms(store, 1)
            assert not journal.flush()
    assert journal.not_written == 5
    told = [r.getMessage() for r in caplog.records]
    assert len(told) == 1 and "No space left on device" in told[0], told


def test_what_waits_for_a_flush_is_bounded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    store, journal = journaled_store(tmp_path / "events.jsonl", max_pending=10)
    emit(store, 15)
    assert journal.pending == 10 and journal.not_written == 5
    journal.close()
    assert [e.id for e in EventJournal(tmp_path / "events.jsonl").load()] == list(range(6, 16))


def test_a_flood_of_status_events_on_a_failing_disk_leaves_the_alarms_waiting_with_it(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    # One queue held both pairs' events: while the disk failed, a flood of status events pushed the alarms
    # waiting for the next flush out of it, and the failure's log line named the alarms' file either way.
    path = tmp_path / "events.jsonl"
    path.mkdir()  # both pairs' files fail to open, as on a full or read-only disk
    bulk_path(path).mkdir()
    store, journal = journaled_store(path, max_pending=10)
    raise_alarms(store, 2)
    emit(store, 5)
    with caplog.at_level(logging.ERROR, logger="twin.service.event_journal"):
        assert not journal.flush()
    # One line per file that failed, each naming it and its own events.
    told = {r.getMessage().split(" (")[0] for r in caplog.records}
    assert len(caplog.records) == 2 and told == {
        f"2 event(s) could not be written to the event journal {path}",
        f"5 event(s) could not be written to the event journal {bulk_path(path)}",
    }, told
    waiting = raise_alarms(store, 3)
    flood = emit(store, 25)  # past max_pending before the next flush
    path.rmdir()
    bulk_path(path).rmdir()
    assert journal.flush()
    journal.close()
    assert EventJournal(path).load(None) == [*waiting, *flood[-10:]]
    kept, bulk, _ = journal.sinks()
    assert (kept.delivered, kept.dropped, kept.errors, kept.pending) == (3, 2, 1, 0)
    assert (bulk.delivered, bulk.dropped, bulk.errors, bulk.pending) == (10, 5 + 15, 1, 0)


def test_a_flood_of_status_events_behind_a_slow_disk_leaves_the_alarms_waiting_with_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The supervisor's flush held in a write (a slow disk) while the store kept adding: the status events
    # queued during it pushed out the alarms queued with them before any was written.
    held, release = threading.Event(), threading.Event()
    write = event_journal._Files.write

    def slow_write(files: event_journal._Files, batch: list[Event]) -> None:
        if not held.is_set():  # the first write only
            held.set()
            assert release.wait(30), "the test did not release the write"
        write(files, batch)

    monkeypatch.setattr(event_journal._Files, "write", slow_write)
    path = tmp_path / "events.jsonl"
    store, journal = journaled_store(path, max_pending=10)
    first = raise_alarms(store, 1)
    flushing = threading.Thread(target=journal.flush, name="flush-held")
    flushing.start()
    try:
        assert held.wait(30), "the flush never reached its write"
        waiting = raise_alarms(store, 3)
        flood = emit(store, 25)
        assert journal.pending == 3 + 10
    finally:
        release.set()
        flushing.join(30)
    assert not flushing.is_alive()
    assert journal.flush()
    journal.close()
    assert EventJournal(path).load(None) == [*first, *waiting, *flood[-10:]]
    kept, bulk, _ = journal.sinks()
    assert (kept.delivered, kept.dropped, bulk.delivered, bulk.dropped) == (4, 0, 10, 15)


def _agent_events(agent: object) -> list[Event]:
    return agent.events(EventQuery(limit=10_000))  # type: ignore[attr-defined]


@pytest.mark.slow
def test_the_agent_reads_its_events_back_and_says_how_its_run_before_ended(tmp_path: Path) -> None:
    events_file = tmp_path / "events.jsonl"
    devices = ["arm-001", "arm-002", "arm-003"]
    agent = unbrokered_agent(tmp_path, 1, **{"twin.events_file": str(events_file)})
    try:
        rng = random.Random(6)
        for device in devices:
            agent.feed(f"dt/lerobot/{device}/telemetry", encode(make_payload(device, 0.0, "ticks", rng)))
        arrived = EventQuery(kinds=frozenset({EventKind.STATUS.value}), text="first message")
        wait_for(lambda: len(agent.events(arrived)) == 3, 30, "the arrivals collected")

        # Written as the supervisor collects them; its figures are an output's in /state.
        def journal() -> tuple[SinkStats, SinkStats]:
            names = ("events_journal_lifecycle", "events_journal_bulk")
            bulk, lifecycle = [s for s in agent.state().agent.sinks if s.name in names]
            return lifecycle, bulk

        # The started event to the lifecycle pair, the arrivals (status events) to the bulk pair.
        wait_for(
            lambda: [s.delivered >= n for s, n in zip(journal(), (1, 3), strict=True)] == [True, True],
            30,
            "the started event and the arrivals written",
        )
        lifecycle = event_journal.lifecycle_path(events_file)
        written = lifecycle.read_text() + event_journal.bulk_path(events_file).read_text()
        assert [s.dropped for s in journal()] == [0, 0] and written.count("\n") >= 4
    finally:
        agent.stop()
    first_run = _agent_events(agent)
    assert first_run[0].message == "the agent started" and first_run[-1].message == "the agent stopped"
    assert first_run[-1].data["action"] == "stopped"

    # Stopped cleanly: the next start has the same events, with their ids, and says nothing is missing.
    agent = unbrokered_agent(tmp_path, 1, **{"twin.events_file": str(events_file)})
    agent.stop()
    second_run = _agent_events(agent)
    assert second_run[: len(first_run)] == first_run
    started = second_run[len(first_run)]
    assert (started.id, started.level, started.data["previous"]) == (first_run[-1].id + 1, "info", "stopped")
    assert started.message == "the agent started; its run before stopped"

    # A run that did not reach its stop (killed) wrote no `agent stopped`, and its state file says it had
    # not stopped: the next start warns.
    lines = lifecycle.read_bytes().splitlines(keepends=True)
    lifecycle.write_bytes(b"".join(lines[:-1]))
    state_says(tmp_path / "state.json", stopped=False)
    agent = unbrokered_agent(tmp_path, 1, **{"twin.events_file": str(events_file)})
    agent.stop()
    third_run = _agent_events(agent)
    warned = third_run[len(second_run) - 1]
    assert warned.kind == "agent" and warned.level == "warning", warned
    assert "did not record a stop" in warned.message and warned.data["previous"] == "did not stop"

    # A walk: a run without an events file was killed after one with it stopped. The journal's last event is
    # the older run's stop; the state file, which every run writes, says the last one did not stop.
    state_says(tmp_path / "state.json", stopped=False)
    agent = unbrokered_agent(tmp_path, 1, **{"twin.events_file": str(events_file)})
    agent.stop()
    fourth_run = _agent_events(agent)
    assert fourth_run[len(third_run)].data["previous"] == "did not stop", fourth_run[len(third_run)]

    # An older agent's state file says nothing of its stop: written after the journal's last event, a run
    # that kept no journal came between, and the start claims nothing about how it ended.
    state_says(tmp_path / "state.json", stopped=None)
    agent = unbrokered_agent(tmp_path, 1, **{"twin.events_file": str(events_file)})
    agent.stop()
    fifth_run = _agent_events(agent)
    assert fifth_run[len(fourth_run)].message == "the agent started", fifth_run[len(fourth_run)]


def test_a_start_after_runs_that_kept_no_events_says_their_events_are_not_here(tmp_path: Path) -> None:
    """An upgrade walk: the runs before kept no events file, and the Events page began with "the agent
    started" as if nothing had happened before."""
    for _ in range(2):
        agent = unbrokered_agent(tmp_path, 1)  # its state file, no events file
        agent.stop()
    (started, _) = _agent_events(agent)
    assert started.data["previous"] == "stopped" and "were not kept ([twin] events_file" in started.message
    agent = unbrokered_agent(tmp_path, 1, **{"twin.events_file": str(tmp_path / "events.jsonl")})
    agent.stop()
    (started, _) = _agent_events(agent)
    assert started.message == (
        "the agent started; its run before stopped; the events of the runs before it were not kept "
        "([twin] events_file keeps them over a restart)"
    )
    agent = unbrokered_agent(tmp_path, 1, **{"twin.events_file": str(tmp_path / "events.jsonl")})
    agent.stop()
    assert _agent_events(agent)[2].message == "the agent started; its run before stopped"


def state_says(path: Path, *, stopped: bool | None) -> None:
    """Rewrite the state file as a run that ended so would have left it (None: an older agent's, without
    `stopped`), written a minute after now."""
    document = json.loads(path.read_text())
    document.pop("stopped")
    if stopped is not None:
        document["stopped"] = stopped
    document["written_at"] = time.time() + 60.0
    path.write_text(json.dumps(document))


def test_a_restart_keeps_the_alarms_a_flood_of_status_events_came_after(tmp_path: Path) -> None:
    # The newest `capacity` lines of the journal were statuses only: reading back just those lost the raises
    # (and the Sessions page's counts) that the store itself had kept through the flood.
    events_file = tmp_path / "events.jsonl"
    store, journal = journaled_store(events_file)
    raised = {"action": "raised", "alarm_id": "arm-001/elbow_flex/over_temperature"}
    alarm = store.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-001", data=raised)
    emit(store, 300)
    assert journal.flush()
    journal.close()
    agent = unbrokered_agent(
        tmp_path, 1, **{"twin.events_file": str(events_file), "twin.events_capacity": 100}
    )
    agent.stop()
    assert agent.events(EventQuery(kinds=frozenset({"alarm"}))) == [alarm]
    assert len(_agent_events(agent)) <= 100


def test_a_flood_of_status_events_past_the_files_size_leaves_the_alarms_before_it_in_them(
    tmp_path: Path,
) -> None:
    # Two files held every kind: a flood bigger than both rotated the alarms before it out of them, and a
    # restart lost them though the store had kept them through the flood.
    path = tmp_path / "events.jsonl"
    store, journal = journaled_store(path, max_bytes=20_000)
    alarms = raise_alarms(store, 5)
    for _ in range(40):  # about 150,000 bytes of status events: seven times the two files
        emit(store, 50)
        assert journal.flush()
    later = raise_alarms(store, 2)
    journal.close()
    assert all(p.stat().st_size < 20_000 + 10_000 for p in tmp_path.iterdir())  # each within a flush of it
    assert len(list(tmp_path.iterdir())) <= 4
    again = EventStore(100, wall_clock=Clock())
    again.restore(EventJournal(path).load(again.capacity))
    assert again.query(EventQuery(kinds=frozenset({"alarm"}))) == alarms + later
    held = again.after(0)
    assert [e.id for e in held] == sorted({e.id for e in held}) and len(held) == 100  # id order, once each
    assert held[-1] == later[-1] and held[: len(alarms)] == alarms


def test_an_alarm_flood_past_the_files_size_leaves_the_restarts_before_it_in_theirs(tmp_path: Path) -> None:
    """The alarms and the lifecycle kinds shared a pair: an alarm flood longer than its files rotated the
    agent's starts, worker restarts and calibrations before it out, which the store had kept in a reserve of
    their own, and a restart lost them. Each part has its own pair now."""
    path = tmp_path / "events.jsonl"
    store, journal = journaled_store(path, max_bytes=20_000)
    started = store.emit(EventKind.AGENT, EventLevel.INFO, "the agent started")
    restarted = store.emit(EventKind.WORKER, EventLevel.WARNING, "worker 0 exited (exit code -9)")
    for _ in range(40):  # about 100,000 bytes of alarm events: five times the alarms' files
        raise_alarms(store, 10)
        assert journal.flush()
    journal.close()
    assert path.with_name(path.name + ".1").exists()  # the alarms' pair rotated
    again = EventStore(100, wall_clock=Clock())
    again.restore(EventJournal(path).load(again.capacity))
    assert [started, restarted] == again.query(EventQuery(kinds=frozenset({"agent", "worker"})))
    assert [started, restarted] == [e for e in store.after(0) if e.kind in ("agent", "worker")]


def test_a_journal_from_before_the_bulk_kinds_had_files_of_their_own_is_read(tmp_path: Path) -> None:
    # Its one pair holds every kind, in id order; the new events go to two pairs; a start reads all four.
    path = tmp_path / "events.jsonl"
    old = EventStore(wall_clock=Clock())
    made = [*raise_alarms(old, 2), *emit(old, 3), *raise_alarms(old, 1)]
    encoded = [msgspec.json.encode(e) + b"\n" for e in made]
    (tmp_path / "events.jsonl.1").write_bytes(b"".join(encoded[:3]))
    path.write_bytes(b"".join(encoded[3:]))
    assert EventJournal(path).load() == made
    store, journal = journaled_store(path)
    assert store.restore(EventJournal(path).load()) == len(made)
    new = [*emit(store, 2), *raise_alarms(store, 1)]
    journal.close()
    assert bulk_path(path).read_text().count("\n") == 2
    assert EventJournal(path).load() == made + new


def test_a_start_reads_the_newest_of_each_part_however_big_the_files(tmp_path: Path) -> None:
    path = tmp_path / "events.jsonl"
    store, journal = journaled_store(path)
    started = store.emit(EventKind.AGENT, EventLevel.INFO, "the agent started")
    alarms = raise_alarms(store, 30)
    statuses = emit(store, 500)
    journal.close()
    assert EventJournal(path).load(10) == [started, *alarms[-10:], *statuses[-10:]]
    assert len(EventJournal(path).load(None)) == 531


def mismatch_raise(device: str, joint: str, k: int) -> AlarmEvent:
    """A raise as the alarm engine makes it, with its text: an alarm event's line at its real size."""
    servo = so101.servo_name(joint)
    return AlarmEvent(
        alarm_id=f"{device}/{joint}/{AlarmKind.MODEL_MISMATCH}",
        device=device,
        joint=joint,
        kind=AlarmKind.MODEL_MISMATCH,
        severity=Severity.WARNING,
        previous=AlarmState.NORMAL,
        state=AlarmState.ACTIVE,
        action="raised",
        value=30.0 + k % 10,
        threshold=15.0,
        at=float(k),
        message=f"{servo} load differs from the model's holding load (12.5 %) by {30.0 + k % 10:.1f} points "
        "while still (alarm at 15): contact, a payload or a failing servo",
    )


@pytest.mark.parametrize("capacity", [100, DEFAULT_CAPACITY])
def test_a_store_full_of_alarms_comes_back_whole_after_a_restart_just_after_a_rotation(
    tmp_path: Path, capacity: int
) -> None:
    # A walk: an alarm flood at the default capacity left the store 20,000 alarms of about 600 bytes, and
    # each file was renamed away at 8 MiB: a restart just after a rename gave back 16,600 of them.
    path = tmp_path / "events.jsonl"
    store = EventStore(capacity, wall_clock=Clock())
    journal = EventJournal(path, capacity=capacity)
    store.subscribe(journal.add)
    watch = FleetWatch(store)
    devices = [f"so101-cell-{c:02d}-arm-{a:04d}" for c in range(4) for a in range(25)]

    def raise_alarm(k: int) -> None:
        watch.alarm(mismatch_raise(devices[k % len(devices)], so101.JOINT_NAMES[k % 6], k))

    flood_until_renamed(store, journal, path, raise_alarm, every=10)
    journal.close()
    held = store.after(0)
    assert len(held) == capacity and {e.kind for e in held} == {"alarm"}
    # Lines of their real size: more than the 8 MiB files gave each of a default store's events.
    assert min(len(msgspec.json.encode(e)) for e in held) > 8 * 2**20 / DEFAULT_CAPACITY
    again = EventStore(capacity, wall_clock=Clock())
    again.restore(EventJournal(path, capacity=capacity).load(capacity))
    assert again.after(0) == held


def test_an_event_longer_than_its_line_comes_back_cut_and_says_so(tmp_path: Path) -> None:
    """Bulk files are sized for lines of BULK_LINE_BYTES: rejections with a long detail were written whole,
    so the files held fewer events than the store and a restart just after a rename gave back fewer. Each
    line is cut to fit now, and the event says it was cut and from what size."""
    capacity = 50
    path = tmp_path / "events.jsonl"
    store = EventStore(capacity, wall_clock=Clock())
    journal = EventJournal(path, capacity=capacity)
    store.subscribe(journal.add)
    bulk = bulk_path(path)
    detail = "field 'positions' holds " + "[1.5, 2.5, 3.5] " * 40  # a message of about 700 bytes

    def reject(k: int) -> None:
        store.emit(
            EventKind.REJECTED,
            EventLevel.WARNING,
            f"telemetry from arm-{k:03d} rejected: bad_payload: {detail}",
            device=f"arm-{k:03d}",
            data={"reason": "bad_payload", "count": 1},
        )

    flood_until_renamed(store, journal, bulk, reject, every=1)
    journal.close()
    held = store.after(0)
    assert len(held) == capacity and all(len(msgspec.json.encode(e)) > 600 for e in held)
    back = EventJournal(path, capacity=capacity).load(capacity)
    assert [e.id for e in back] == [e.id for e in held]
    for whole, cut in zip(held, back, strict=True):
        assert len(msgspec.json.encode(cut)) < event_journal.BULK_LINE_BYTES
        assert cut.message.endswith(event_journal.CUT_MARK)
        assert whole.message.startswith(cut.message.removesuffix(event_journal.CUT_MARK))
        assert cut.data == {**whole.data, "cut_from_bytes": str(len(msgspec.json.encode(whole)) + 1)}
        assert (cut.kind, cut.device, cut.time, cut.level) == (
            whole.kind,
            whole.device,
            whole.time,
            whole.level,
        )


def test_data_too_long_for_a_line_is_cut_too_and_a_short_line_is_left_whole(tmp_path: Path) -> None:
    """A message that fits once the data values are cut is kept whole: it lost its last character to a
    cut mark ("short ms… [cut]"), though `cut_from_bytes` already says the line was cut."""
    path = tmp_path / "events.jsonl"
    store, journal = journaled_store(path)
    long_data = store.emit(
        EventKind.STATUS, EventLevel.INFO, "x" * 50, device="arm-1", data={"why": "y" * 900}
    )
    short = store.emit(EventKind.STATUS, EventLevel.INFO, "arm-1 is ONLINE", device="arm-1")
    journal.close()
    cut, whole = EventJournal(path).load()
    assert whole == short
    assert len(msgspec.json.encode(cut)) < event_journal.BULK_LINE_BYTES and cut.id == long_data.id
    assert cut.data["why"] == "y" * event_journal.CUT_DATA_CHARS and cut.message == "x" * 50
    assert cut.data[event_journal.CUT_KEY] == str(len(msgspec.json.encode(long_data)) + 1)


def test_the_agents_journal_files_are_sized_by_its_events_capacity(tmp_path: Path) -> None:
    # A store of 100 events keeps at most 100 of its lifecycle kinds: its journal's lifecycle file is renamed
    # away past 100 of their longest lines (100,000 bytes), not at a size made for the default 20,000.
    path = tmp_path / "events.jsonl"
    lifecycle = event_journal.lifecycle_path(path)
    store, journal = journaled_store(path)
    for i in range(2_000):  # a run before that restarted its workers often
        store.emit(EventKind.WORKER, EventLevel.WARNING, f"worker 0 exited (exit code -9), {i}")
    journal.close()
    assert 100 * event_journal.KEPT_LINE_BYTES < lifecycle.stat().st_size < 2**20
    agent = unbrokered_agent(tmp_path, 1, **{"twin.events_file": str(path), "twin.events_capacity": 100})
    agent.stop()  # its start and stop events are written after the lines before: the file is past its size
    assert lifecycle.with_name(lifecycle.name + ".1").exists()
    assert EventJournal(path).load(None)[-1].data["action"] == "stopped"


def test_what_waits_for_a_flush_is_a_store_of_the_agents_capacity(tmp_path: Path) -> None:
    """Each pair's queue holds a store's worth of events: at `[twin] events_capacity` 100, the 101st waiting
    for a flush pushes the oldest out, counted (a fixed 20,000 held 200 stores)."""
    store, journal = journaled_store(tmp_path / "events.jsonl", capacity=100)
    emit(store, 101)
    assert journal.pending == 100 and journal.not_written == 1
    journal.close()


def flood_until_renamed(
    store: EventStore, journal: EventJournal, file: Path, emit: Callable[[int], None], *, every: int
) -> None:
    """emit(k) for k = 0, 1, ... (flushing every `every`) until `file` was just renamed away, with the store
    full: its pair then holds the least it ever does."""
    capacity = store.capacity
    for k in range(4 * capacity):
        emit(k)
        if k % every == every - 1:
            assert journal.flush()
            if len(store) == capacity and not file.exists() and file.with_name(file.name + ".1").exists():
                return
    pytest.fail(f"the flood never renamed {file.name} away")
