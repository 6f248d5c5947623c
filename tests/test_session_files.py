"""The console's session files stay within `[http] session_files_mb` (twin.service.session_files).

The cache's rule on a test clock first; then through the agent's HTTP server, with a catalog that makes
files of a known size in place of history's (the real catalog, which rebuilds them from a Delta table, is
tested in tests/test_console.py; here only the size matters)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest
from conftest import http_get
from test_http_api import StubSource
from twin.output import scratch
from twin.service import http_api, session_files
from twin.service.config import ConfigError, HttpSection, load_config
from twin.service.console import SessionInfo
from twin.service.events import Event, EventKind, EventLevel, EventQuery, EventStore
from twin.service.http_api import AgentHttpServer
from twin.service.session_files import KEEP_S, PREFIX, SessionFiles

MB = 2**20


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def made(files: SessionFiles, name: str, size: int) -> Path:
    path = files.directory / name
    path.write_bytes(b"x" * size)
    files.used(path)
    return path


def test_the_files_used_longest_ago_go_first_once_over_the_bound() -> None:
    clock = Clock()
    files = SessionFiles(3 * MB, clock=clock)
    try:
        for name in ("a.csv", "b.csv", "c.csv"):
            made(files, name, MB)
            clock.now += KEEP_S + 1
        assert files.trim() == []  # 3 MB: within the bound
        files.used(files.directory / "a.csv")  # served again: now the newest
        (files.directory / "d.csv.part").write_bytes(b"x" * MB)  # being written: not counted or removed
        made(files, "d.csv", MB)
        assert files.trim() == ["b.csv"]
        assert sorted(p.name for p in files.directory.iterdir()) == [
            ".owner",  # the directory's lock (output.scratch): never the cache's to remove
            "a.csv",
            "c.csv",
            "d.csv",
            "d.csv.part",
        ]
        assert files.removed == 1
        # A file not served yet is being made while it is young (a plot's name of its own): kept; once old
        # (a leftover), it goes first.
        making = files.directory / "e.png.png"
        making.write_bytes(b"x" * MB)
        clock.now += KEEP_S + 1
        assert files.trim() == ["c.csv"]  # 4 MB: the oldest served one goes, the young one stays
        old = time.time() - KEEP_S - 1
        os.utime(making, (old, old))
        made(files, "f.csv", MB)
        assert files.trim() == ["e.png.png"]
    finally:
        directory = files.directory
        files.close()
    assert not directory.exists()


def test_a_file_used_within_keep_s_is_kept_over_the_bound() -> None:
    """Its download may still be reading it: the bound waits, and is kept once the file is old enough."""
    clock = Clock()
    files = SessionFiles(1 * MB, clock=clock)
    try:
        made(files, "a.usd", MB)
        clock.now += 10
        made(files, "b.usd", MB)
        assert files.trim() == []  # both used within KEEP_S
        clock.now += KEEP_S - 5  # a.usd is past KEEP_S, b.usd not yet
        assert files.trim() == ["a.usd"]
        clock.now += 10
        assert files.trim() == []  # b.usd alone fits
    finally:
        files.close()


def test_the_bound_is_a_setting_with_a_range() -> None:
    assert load_config(None, {}).http.session_files_mb == 1024
    assert load_config(None, {"http.session_files_mb": 5}).http.session_files_mb == 5
    with pytest.raises(ConfigError, match=r"session_files_mb = 0 is outside 1\.\.1000000"):
        load_config(None, {"http.session_files_mb": 0})


class SizedCatalog:
    """Completed sessions whose every file is `size` bytes; counts what it makes."""

    def __init__(self, sessions: Sequence[SessionInfo], size: int) -> None:
        self._sessions = list(sessions)
        self.size = size
        self.made: Counter[str] = Counter()

    def sessions(self, gap_s: float) -> Sequence[SessionInfo]:
        return self._sessions

    def session_file(self, session: SessionInfo, kind: str, directory: Path) -> Path:
        path = directory / f"{session.device}-{session.key}.{kind}"
        path.write_bytes(b"x" * self.size)
        self.made[session.device] += 1
        return path


def test_the_servers_session_files_stay_within_the_bound(monkeypatch: pytest.MonkeyPatch) -> None:
    # Files count as old at once here, so each request past the bound removes what it can.
    monkeypatch.setattr(session_files, "KEEP_S", 0.0)
    arms = [SessionInfo(f"arm-00{i}", start=1_000.0 + i, end=1_010.0 + i, messages=100) for i in range(3)]
    catalog = SizedCatalog(arms, 600 * 1024)
    server = AgentHttpServer(
        StubSource(), "127.0.0.1", 0, settings=HttpSection(session_files_mb=1), sessions=catalog
    )
    server.start()
    try:
        url = f"http://127.0.0.1:{server.port}/api/sessions"

        def fetch(session: SessionInfo) -> None:
            status, _, body = http_get(f"{url}/{session.device}/{session.key}/parquet")
            assert status == 200 and len(body) == catalog.size

        fetch(arms[0])
        fetch(arms[0])
        assert catalog.made == {"arm-000": 1}  # a completed session's file is made once
        fetch(arms[1])  # 1.2 MB: arm-000's, used longest ago, goes
        fetch(arms[2])  # and then arm-001's
        directory = server._session_files.directory
        assert sorted(p.name for p in directory.iterdir()) == [".owner", f"arm-002-{arms[2].key}.parquet"]
        fetch(arms[0])  # removed, so made again
        assert catalog.made == {"arm-000": 2, "arm-001": 1, "arm-002": 1}
        assert sum(p.stat().st_size for p in directory.iterdir()) <= MB
    finally:
        server.stop()
    assert not directory.exists()


def test_a_killed_agents_session_files_go_when_the_next_server_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The directory is named for its agent's process (output.scratch): the next agent's server removes
    the one a `kill -9` left (its owner is gone) as it starts, and never one whose owner runs."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], check=True, capture_output=True, text=True
    )
    dead = tmp_path / f"{PREFIX}{int(gone.stdout)}-1-abcd1234"
    (dead / "arm-001-1.usd").parent.mkdir()
    (dead / "arm-001-1.usd").write_bytes(b"x" * 1024)
    own = SessionFiles(MB)
    live = own.directory  # this process's: it runs
    assert live.name.startswith(f"{PREFIX}{os.getpid()}-{scratch._start_time(os.getpid())}-")
    server = AgentHttpServer(StubSource(), "127.0.0.1", 0)
    server.start()
    try:
        assert not dead.exists() and live.is_dir()
    finally:
        server.stop()
        own.close()


class EventsOnlySource(StubSource):
    """A source with the events `store` holds, which does not say from when its alarms are complete."""

    def __init__(self, store: EventStore) -> None:
        super().__init__()
        self.store = store

    def events(self, query: EventQuery) -> list[Event]:
        return self.store.query(query)


class EventfulSource(EventsOnlySource):
    """A source with the events `store` holds (the agent's EventSource)."""

    def alarms_complete_from(self) -> float | None:
        return self.store.alarms_complete_from()


def test_a_sessions_alarm_count_is_unknown_before_its_alarms_are_all_held() -> None:
    """Its alarms are counted from the time the agent holds every raise from: a session that began before it
    (an agent started since, with no events file, or events pushed out of the store) used to read 0 alarms
    raised whatever it had. It reads null now, and the answer says from when the counts hold."""
    store = EventStore(10)
    store.emit(EventKind.AGENT, EventLevel.INFO, "the agent started", at=2_000.0)
    for at in (2_050.0, 2_055.0, 3_020.0):
        raised = {"action": "raised", "alarm_id": "arm-002/wrist_roll/over_temperature"}
        store.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-002", data=raised, at=at)
    store.emit(EventKind.ALARM, EventLevel.INFO, "cleared", device="arm-002", data={"action": "cleared"})
    sessions = [
        SessionInfo("arm-001", start=1_900.0, end=2_100.0, messages=2_000),  # began before the events
        SessionInfo("arm-002", start=2_010.0, end=2_200.0, messages=1_900),  # two raised in it
        SessionInfo("arm-003", start=2_001.0, end=2_300.0, messages=2_990),  # none
    ]
    answer = sessions_answer(store, sessions)
    counts = {s["device"]: s["alarms_raised"] for s in answer["sessions"]}
    assert counts == {"arm-001": None, "arm-002": 2, "arm-003": 0}
    assert answer["alarms_known_since"] == 2_000.0


def test_a_history_that_cannot_be_read_is_said_not_listed_as_empty() -> None:
    """A walk damaged a data file of the agent's history: GET /api/sessions answered an empty list and the
    page "no session yet", as of a history holding nothing; the reason was in the agent's log only."""
    catalog = SizedCatalog([], 1)
    answer = sessions_answer(EventStore(10), [], catalog)
    assert answer["sessions"] == [] and answer["unreadable"] is None
    said = "cannot read history at h/telemetry: a data file its log names is missing"
    catalog.unreadable = said  # type: ignore[attr-defined]
    assert sessions_answer(EventStore(10), [], catalog)["unreadable"] == said


def sessions_answer(
    source: EventStore | Any, sessions: list[SessionInfo], catalog: Any = None
) -> dict[str, Any]:
    """GET /api/sessions of a server over `source` (an EventStore: served as the agent serves its own)."""
    source = EventfulSource(source) if isinstance(source, EventStore) else source
    server = AgentHttpServer(source, "127.0.0.1", 0, sessions=catalog or SizedCatalog(sessions, 1))
    server.start()
    try:
        status, _, body = http_get(f"http://127.0.0.1:{server.port}/api/sessions")
    finally:
        server.stop()
    assert status == 200
    answer: dict[str, Any] = json.loads(body)
    return answer


def test_a_flood_of_status_events_leaves_the_sessions_alarm_counts_known() -> None:
    """300 arms going STALE and ONLINE on a loaded host pushed the raises out of the store, and with them the
    oldest events: every session read "not known". The raises are kept now, and counted."""
    store = EventStore(100)
    store.emit(EventKind.AGENT, EventLevel.INFO, "the agent started", at=2_000.0)
    for at in (2_050.0, 2_055.0):
        raised = {"action": "raised", "alarm_id": "arm-002/wrist_roll/over_temperature"}
        store.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-002", data=raised, at=at)
    for i in range(3 * store.capacity):
        device = f"arm-{i % 300:03d}"
        store.emit(
            EventKind.STATUS, EventLevel.WARNING, f"{device} went STALE", device=device, at=2_060.0 + i
        )
    assert len(store) == store.capacity
    sessions = [
        SessionInfo("arm-002", start=2_010.0, end=2_200.0, messages=1_900),  # two raised in it
        SessionInfo("arm-003", start=2_001.0, end=2_300.0, messages=2_990),  # none
    ]
    answer = sessions_answer(store, sessions)
    assert {s["device"]: s["alarms_raised"] for s in answer["sessions"]} == {"arm-002": 2, "arm-003": 0}
    assert answer["alarms_known_since"] == 2_000.0


def test_alarm_counts_are_known_from_the_oldest_alarm_kept_not_an_older_status_event() -> None:
    # The alarms' part of the store let go of its oldest while an older status event stayed: the counts
    # hold from the oldest alarm kept, not from that status event.
    store = EventStore(100)
    store.emit(EventKind.STATUS, EventLevel.INFO, "arm-001 is ONLINE", device="arm-001", at=1_000.0)
    raised = {"action": "raised", "alarm_id": "arm-002/wrist_roll/over_temperature"}
    for i in range(store.capacity):
        store.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-002", data=raised, at=2_000.0 + i)
    oldest_alarm = min(e.time for e in store.query(EventQuery(kinds=frozenset({"alarm"}))))
    assert oldest_alarm > 2_000.0 and store.query(EventQuery(kinds=frozenset({"status"})))
    sessions = [SessionInfo("arm-002", start=1_500.0, end=2_500.0, messages=1_900)]  # raises went from it
    answer = sessions_answer(store, sessions)
    assert [s["alarms_raised"] for s in answer["sessions"]] == [None]
    assert answer["alarms_known_since"] == oldest_alarm


def test_alarm_counts_are_not_known_from_an_agent_event_older_than_the_alarms_a_flood_pushed_out() -> None:
    # The agent's start stays through an alarm flood (the lifecycle kinds' reserve), older than the raises
    # let go of: the counts hold after the newest raise let go of, not from that start.
    store = EventStore(100)
    store.emit(EventKind.AGENT, EventLevel.INFO, "the agent started", at=1_000.0)
    raised = {"action": "raised", "alarm_id": "arm-002/wrist_roll/over_temperature"}
    for i in range(3 * store.capacity):
        store.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-002", data=raised, at=2_000.0 + i)
    assert store.query(EventQuery(kinds=frozenset({"agent"})))
    oldest_alarm = min(e.time for e in store.query(EventQuery(kinds=frozenset({"alarm"}))))
    sessions = [
        SessionInfo("arm-002", start=1_500.0, end=2_500.0, messages=1_900),  # raises went from it
        SessionInfo("arm-003", start=oldest_alarm, end=oldest_alarm + 10, messages=100),  # all held
    ]
    answer = sessions_answer(store, sessions)
    assert [s["alarms_raised"] for s in answer["sessions"]] == [None, 0]
    assert answer["alarms_known_since"] == oldest_alarm - 1


def test_alarm_counts_hold_only_from_the_oldest_alarm_the_read_took(monkeypatch: pytest.MonkeyPatch) -> None:
    # The page reads at most EVENTS_READ_FOR_SESSIONS alarm events: when more are held, the older ones are
    # not counted, so a session that began before the oldest read is not known, whatever the store holds.
    monkeypatch.setattr(http_api, "EVENTS_READ_FOR_SESSIONS", 5)
    store = EventStore(100)
    store.emit(EventKind.AGENT, EventLevel.INFO, "the agent started", at=1_000.0)
    raised = {"action": "raised", "alarm_id": "arm-002/wrist_roll/over_temperature"}
    for i in range(10):
        store.emit(EventKind.ALARM, EventLevel.WARNING, "hot", device="arm-002", data=raised, at=2_000.0 + i)
    assert store.alarms_complete_from() == 1_000.0
    sessions = [
        SessionInfo("arm-002", start=1_500.0, end=2_100.0, messages=1_900),  # 10 raised, 5 read
        SessionInfo("arm-002", start=2_005.0, end=2_100.0, messages=900),  # the 5 read
    ]
    answer = sessions_answer(store, sessions)
    assert [s["alarms_raised"] for s in answer["sessions"]] == [None, 5]
    assert answer["alarms_known_since"] == 2_005.0


def test_a_source_that_does_not_say_from_when_its_alarms_are_complete_has_no_counts() -> None:
    # The counts' time is the store's to tell (EventStore.alarms_complete_from): a source with events but
    # without it is not guessed at from the kinds of its events.
    store = EventStore(100)
    store.emit(EventKind.AGENT, EventLevel.INFO, "the agent started", at=1_000.0)
    sessions = [SessionInfo("arm-002", start=1_500.0, end=2_100.0, messages=1_900)]
    answer = sessions_answer(EventsOnlySource(store), sessions)
    assert [s["alarms_raised"] for s in answer["sessions"]] == [None]
    assert answer["alarms_known_since"] is None


def test_without_events_no_sessions_alarm_count_is_known() -> None:
    answer = sessions_answer(
        StubSource(), [SessionInfo("arm-001", start=1_900.0, end=2_100.0, messages=2_000)]
    )
    assert [s["alarms_raised"] for s in answer["sessions"]] == [None]
    assert answer["alarms_known_since"] is None
