"""The agent's state file (twin.service.persist): the alarms a restart must not forget, written atomically,
read back on another process's clock, and a broken file set aside instead of stopping the agent."""

from __future__ import annotations

import errno
import json
import logging
import os
from pathlib import Path

import pytest
from twin.core.alarms import AlarmKind, AlarmRecord, AlarmState
from twin.service.persist import StateFile, StateFileError, adopt_file, parse, write_atomically


def _record(state: AlarmState, joint: str = "elbow_flex", since: float = 100.0) -> AlarmRecord:
    return AlarmRecord(
        device="arm-001",
        joint=joint,
        kind=AlarmKind.OVER_TEMPERATURE,
        state=state,
        since=since,
        present=state is not AlarmState.LATCHED,
        raised=2,
        value=63.0,
        message="elbow_flex servo at 63 C",
    )


def test_kept_alarms_are_written_and_read_back_on_a_new_clock(tmp_path: Path) -> None:
    path = tmp_path / "state" / "state.json"
    store = StateFile(path)
    records = [
        _record(AlarmState.ACKNOWLEDGED),
        _record(AlarmState.LATCHED, joint="wrist_flex", since=90.0),
        _record(AlarmState.NORMAL, joint="gripper"),  # never kept
    ]
    # Written at monotonic 110 s = wall 1,000,010 s: the elbow changed 10 s before, the wrist 20 s.
    assert store.save(records, now_mono=110.0, now_wall=1_000_010.0)
    assert not store.save(records, now_mono=111.0, now_wall=1_000_011.0)  # unchanged: not written again
    document = json.loads(path.read_text())
    assert document["version"] == 1 and [a["state"] for a in document["alarms"]] == [
        "ACKNOWLEDGED",
        "LATCHED",
    ]
    assert not list(path.parent.glob(".state.json.*"))  # no temporary file left behind

    # A reboot later: a new monotonic clock (5 s since boot), wall time 1,000,060.
    back = StateFile(path).load(now_mono=5.0, now_wall=1_000_060.0)
    by_joint = {r.joint: r for r in back}
    assert by_joint["elbow_flex"].state is AlarmState.ACKNOWLEDGED and by_joint["elbow_flex"].present
    assert by_joint["elbow_flex"].since == pytest.approx(5.0 - 60.0)
    assert by_joint["wrist_flex"].state is AlarmState.LATCHED and not by_joint["wrist_flex"].present
    assert by_joint["wrist_flex"].raised == 2 and by_joint["wrist_flex"].message.startswith("elbow_flex")


def test_no_file_is_no_alarms_and_a_broken_one_is_set_aside(tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    assert StateFile(path).load(0.0, 0.0) == []
    path.write_text('{"version": 1, "alarms": [{"device": "arm-001"}]}')
    assert StateFile(path).load(0.0, 0.0) == []
    assert not path.exists() and (tmp_path / "state.json.bad").exists()
    with pytest.raises(ValueError, match="never keeps"):
        parse(
            json.dumps(
                {
                    "version": 1,
                    "alarms": [
                        {
                            "device": "a",
                            "joint": "gripper",
                            "kind": "overload",
                            "state": "NORMAL",
                            "changed_at": 0,
                        }
                    ],
                }
            ),
            0.0,
            0.0,
        )


def test_a_file_that_cannot_be_read_is_set_aside_not_replaced_by_the_first_write(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A file the agent may not read (another user's, an I/O error) is as unusable as a broken one, and the
    first check's write would replace it, acknowledgements and all: it is set aside as a broken one is."""
    path = tmp_path / "state.json"
    StateFile(path).save([_record(AlarmState.ACKNOWLEDGED)], 200.0, 1000.0)
    kept = path.read_bytes()
    real = Path.read_bytes

    def refused(self: Path) -> bytes:
        if self == path:
            raise PermissionError(13, "Permission denied", str(self))
        return real(self)

    monkeypatch.setattr(Path, "read_bytes", refused)
    state = StateFile(path)
    assert state.previous_run() is None
    with caplog.at_level(logging.ERROR, logger="twin.service.persist"):
        assert state.load(0.0, 0.0) == []
    assert "Permission denied" in caplog.text and "state.json.bad" in caplog.text, caplog.text
    assert state.stats().dropped == 1
    assert state.save([], 0.0, 0.0)
    assert (tmp_path / "state.json.bad").read_bytes() == kept


def test_a_file_in_a_directory_the_agent_cannot_search_is_reported_and_the_agent_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A state directory the agent may not search (its mode or owner changed by hand): the file cannot be
    read, and moving it to a `.bad` name raises the same PermissionError (a link or a look there). The
    agent starts without the file, reported and counted, rather than not at all."""
    path = tmp_path / "state.json"
    path.write_text("{}")
    real_read, real_stat = Path.read_bytes, os.stat

    def refused(name: str) -> PermissionError:
        return PermissionError(13, "Permission denied", name)

    def read_bytes(self: Path) -> bytes:
        if self == path:
            raise refused(str(self))
        return real_read(self)

    def stat(name: os.PathLike[str] | str, *args: object, **kwargs: object) -> os.stat_result:
        if os.fspath(name).startswith(str(path)):
            raise refused(os.fspath(name))
        return real_stat(name, *args, **kwargs)  # type: ignore[arg-type]

    def link(src: object, dst: os.PathLike[str] | str, *args: object, **kwargs: object) -> None:
        raise refused(os.fspath(dst))

    monkeypatch.setattr(Path, "read_bytes", read_bytes)
    monkeypatch.setattr(os, "stat", stat)
    monkeypatch.setattr(os, "link", link)
    state = StateFile(path)
    with caplog.at_level(logging.ERROR, logger="twin.service.persist"):
        assert state.load(0.0, 0.0) == []
    assert "could not be moved aside" in caplog.text, caplog.text
    assert state.stats().dropped == 1
    monkeypatch.undo()
    assert path.read_text() == "{}"


def test_a_file_set_aside_before_is_not_replaced_by_the_next(tmp_path: Path) -> None:
    """The first `.bad` may hold every acknowledgement (a rollback's, docs/deploy.md): a file found broken at
    a later start (cut to nothing by a power cut) is set aside beside it, not over it."""
    path = tmp_path / "state.json"
    path.write_text('{"version": 1, "alarms": [{"device": "arm-001"}]}')
    first = path.read_bytes()
    assert StateFile(path).load(0.0, 0.0) == []
    path.write_bytes(b"")
    assert StateFile(path).load(0.0, 0.0) == []
    path.write_bytes(b"\x00garbage")
    assert StateFile(path).load(0.0, 0.0) == []
    assert (tmp_path / "state.json.bad").read_bytes() == first
    assert (tmp_path / "state.json.bad.1").read_bytes() == b""
    assert (tmp_path / "state.json.bad.2").read_bytes() == b"\x00garbage"


def test_a_file_of_bytes_that_are_not_text_is_set_aside_and_not_adopted(tmp_path: Path) -> None:
    """A failing disk leaves bytes that are not UTF-8: reading them as text raised past the start's checks
    and the agent did not start; they are a broken file like any other, and no host adopts them."""
    path = tmp_path / "state.json"
    path.write_bytes(b"\xff\xfe\x00garbage")
    state = StateFile(path)
    assert state.previous_run() is None
    assert state.stats().dropped == 0
    assert state.load(0.0, 0.0) == []
    assert (tmp_path / "state.json.bad").read_bytes() == b"\xff\xfe\x00garbage"
    # Its alarms are lost to this run: counted where SinkDrops reads, with the way to bring them back.
    assert state.stats().dropped == state.stats().errors == 1
    assert "move it back to state.json" in state.stats().last_error, state.stats().last_error
    (tmp_path / "other.json").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(StateFileError, match="not JSON"):
        adopt_file(str(tmp_path / "other.json"), str(tmp_path / "adopted.json"))
    assert not (tmp_path / "adopted.json").exists()


def test_a_file_nested_too_deeply_is_set_aside_and_not_adopted(tmp_path: Path) -> None:
    """A walk: 60 KB of nested brackets in the state file stopped `twin run` at its start ("cannot start:
    maximum recursion depth exceeded", naming no file); it is a broken file like any other."""
    deep = b"[" * 30_000 + b"]" * 30_000
    path = tmp_path / "state.json"
    path.write_bytes(deep)
    state = StateFile(path)
    assert state.load(0.0, 0.0) == []
    assert (tmp_path / "state.json.bad").read_bytes() == deep
    assert "nested too deeply" in state.stats().last_error, state.stats().last_error
    with pytest.raises(StateFileError, match="nested too deeply"):
        adopt_file(str(tmp_path / "state.json.bad"), str(tmp_path / "adopted.json"))
    assert not (tmp_path / "adopted.json").exists()


def test_an_unknown_kind_alarm_nested_near_the_parsers_limit_is_dropped_alone(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An alarm of an unknown kind is carried and written back as read: nested hundreds of levels deep, under
    json.loads' limit, the file loaded, and every save from a thread a little deeper in its stack raised
    RecursionError in json.dumps. That alarm alone is dropped, said; the acknowledgement is kept."""
    path = tmp_path / "state.json"
    store = StateFile(path)
    assert store.save([_record(AlarmState.ACKNOWLEDGED)], 110.0, 1e6)
    document = json.loads(path.read_text())
    odd = {**document["alarms"][0], "kind": "a_future_kind", "extra": "@"}
    text = json.dumps({**document, "alarms": [*document["alarms"], odd]})
    deep = text.replace('"@"', "[" * 900 + "]" * 900)
    path.write_text(deep)
    later = StateFile(path)
    with caplog.at_level(logging.WARNING, logger="twin.service.persist"):
        back = later.load(5.0, 1e6 + 60)
    assert [r.state for r in back] == [AlarmState.ACKNOWLEDGED]
    assert not (tmp_path / "state.json.bad").exists()
    assert "nested more than 32 levels deep" in caplog.text and "other alarms are kept" in caplog.text
    assert later.save(back, 6.0, 1e6 + 61)
    assert [a["kind"] for a in json.loads(path.read_text())["alarms"]] == [document["alarms"][0]["kind"]]


def test_a_file_written_whole_keeps_its_mode_and_a_new_one_gets_the_umasks(tmp_path: Path) -> None:
    """The temporary file is 0600: renamed as it was, a calibration root pushed into a directory store was
    one the agent's own user could no longer read (its next read: Permission denied)."""
    old = os.umask(0o022)
    try:
        write_atomically(tmp_path / "new.json", "{}")
    finally:
        os.umask(old)
    assert (tmp_path / "new.json").stat().st_mode & 0o777 == 0o644
    kept = tmp_path / "kept.json"
    kept.write_text("{}")
    kept.chmod(0o640)
    write_atomically(kept, b"[]")
    assert kept.stat().st_mode & 0o777 == 0o640 and kept.read_bytes() == b"[]"


def test_a_refused_chmod_still_writes_the_file_and_leaks_no_descriptor(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A filesystem that refuses a mode change (vfat, some network shares) wrote these files before the mode
    was kept, and still does; the state file is written every second, so no try may leak a descriptor."""

    def refused(fd: int, mode: int) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "fchmod", refused)
    before = len(os.listdir("/proc/self/fd"))
    for i in range(20):
        write_atomically(tmp_path / "state.json", f"{{{i}}}")
    assert len(os.listdir("/proc/self/fd")) <= before + 5
    assert [p.name for p in tmp_path.iterdir()] == ["state.json"]
    assert (tmp_path / "state.json").read_text() == "{19}"


def test_a_failed_write_leaves_the_previous_file_whole(tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    write_atomically(path, "old\n")
    with pytest.raises(TypeError):
        write_atomically(path, None)  # type: ignore[arg-type]  # fails mid-write
    assert path.read_text() == "old\n" and [p.name for p in tmp_path.iterdir()] == ["state.json"]


def test_failed_writes_are_counted_told_once_a_minute_and_the_recovery_is_told(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A full disk failed the write at every check, a second apart, with an error line each time (52 in
    70 s in a walk) and no count anywhere. Now one line a minute, each saying how many it stands for, a
    count in the file's output figures (SinkDrops), and a line when it is written again."""
    from twin.service import persist

    state = StateFile(tmp_path / "state.json")
    monkeypatch.setattr(persist, "write_atomically", _disk_full)
    caplog.set_level(logging.WARNING, logger="twin.service.persist")
    for second in range(130):
        assert not state.save([_record(AlarmState.ACTIVE, since=float(second))], float(second), 1e9 + second)
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 3, errors  # at 0, 60 and 120 s
    assert "(60 failed writes since the last line)" in errors[1] and "free space in" in errors[0]
    stats = state.stats()
    assert (stats.name, stats.dropped, stats.pending) == ("state_file", 130, 1)
    assert stats.last_error == "OSError: [Errno 28] No space left on device"
    monkeypatch.setattr(persist, "write_atomically", write_atomically)
    assert state.save([_record(AlarmState.ACKNOWLEDGED)], 131.0, 1e9 + 131)
    assert "written again, after 130 failed writes" in caplog.records[-1].getMessage()
    assert (state.stats().pending, state.stats().delivered) == (0, 1)


def test_a_stop_the_file_cannot_record_is_told_at_the_stop_and_named_at_the_next_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A SIGTERM on a full disk: the stop's write failed within the minute of the last error line, so
    nothing said so, and the next start told the operator the run was killed or crashed and to look in the
    kernel's OOM log. The stop's failed write is told at once, and the next start names that cause too."""
    from twin.service import persist

    path = tmp_path / "state.json"
    run = StateFile(path)
    assert run.save([_record(AlarmState.LATCHED)], 10.0, 1e9 + 10)  # the run's first check
    monkeypatch.setattr(persist, "write_atomically", _disk_full)
    caplog.set_level(logging.WARNING, logger="twin.service.persist")
    assert not run.save([_record(AlarmState.ACTIVE)], 11.0, 1e9 + 11)  # told: the minute's line
    assert not run.save([_record(AlarmState.ACTIVE)], 12.0, 1e9 + 12, stopped=True)
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 2 and "could not record this stop" in errors[1], errors
    monkeypatch.setattr(persist, "write_atomically", write_atomically)
    caplog.clear()
    StateFile(path).load(5.0, 1e9 + 60)
    (warning,) = _warnings_of_an_unclean_stop(caplog)
    assert "its stop could not be written here" in warning.getMessage()


def _disk_full(path: Path, text: str) -> None:
    raise OSError(28, "No space left on device")


def _warnings_of_an_unclean_stop(caplog: pytest.LogCaptureFixture) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.levelno == logging.WARNING and "did not stop" in r.getMessage()]


def test_a_file_left_by_a_run_that_never_stopped_says_so_at_the_next_start(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A `kill -9` (or an OOM kill, a power cut) leaves no line in the log; the state file is what the next
    # start has of the run before it, so it must tell a run that stopped from one that did not.
    path = tmp_path / "state.json"
    run = StateFile(path)
    latched = [_record(AlarmState.LATCHED)]
    assert run.save(latched, now_mono=110.0, now_wall=1_000_010.0)  # the run's first check
    caplog.set_level(logging.INFO, logger="twin.service.persist")
    assert [r.state for r in StateFile(path).load(5.0, 1_000_060.0)] == [AlarmState.LATCHED]
    (warning,) = _warnings_of_an_unclean_stop(caplog)
    assert warning.previous_pid == os.getpid()  # type: ignore[attr-defined]
    assert "lost without a count" in warning.getMessage()

    # The same run's stop is written even though its alarms did not change, and then nothing is reported.
    assert run.save(latched, now_mono=111.0, now_wall=1_000_011.0, stopped=True)
    assert not run.save(latched, now_mono=112.0, now_wall=1_000_012.0, stopped=True)
    caplog.clear()
    assert len(StateFile(path).load(5.0, 1_000_060.0)) == 1
    assert not _warnings_of_an_unclean_stop(caplog)

    # A time no clock can show only words the warning: the start goes on with the alarms.
    document = json.loads(path.read_text())
    path.write_text(json.dumps(document | {"stopped": False, "written_at": 1e300}))
    assert len(StateFile(path).load(5.0, 1_000_060.0)) == 1
    assert "an unknown time" in _warnings_of_an_unclean_stop(caplog)[0].getMessage()
    caplog.clear()

    # An older agent's file, which does not say: nothing either.
    del document["stopped"]
    path.write_text(json.dumps(document))
    assert len(StateFile(path).load(5.0, 1_000_060.0)) == 1
    assert not _warnings_of_an_unclean_stop(caplog)


def test_temporary_files_of_writes_a_kill_cut_short_are_removed_at_the_start(tmp_path: Path) -> None:
    # write_atomically removes its temporary file when the write fails, but a SIGKILL between mkstemp and the
    # rename leaves it, as large as the state file, and each such crash added one.
    path = tmp_path / "state.json"
    assert StateFile(path).save([_record(AlarmState.LATCHED)], 110.0, 1_000_010.0)
    left = [tmp_path / ".state.json.k1ll3d_1.tmp", tmp_path / ".state.json.k1ll3d_2.tmp"]
    for leftover in left:
        leftover.write_text('{"version": 1, "al')
    others = [tmp_path / ".other.json.abc.tmp", tmp_path / "state.json.bad"]
    for other in others:
        other.write_text("not ours to remove")
    assert len(StateFile(path).load(5.0, 1_000_060.0)) == 1
    assert not [p for p in left if p.exists()]
    assert all(p.exists() for p in others)


def test_another_hosts_file_is_adopted_with_its_alarms_and_no_word_on_how_its_run_ended(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A replacement host starts with the replaced host's copy, written while that host still ran
    # (`stopped` false): its alarms come back, and no unclean stop of this host's own is reported.
    theirs = tmp_path / "theirs.json"
    StateFile(theirs).save(
        [_record(AlarmState.LATCHED), _record(AlarmState.ACKNOWLEDGED, "wrist_flex")], 110.0, 1e6
    )
    assert json.loads(theirs.read_text())["stopped"] is False
    ours = tmp_path / "agent" / "state.json"
    assert adopt_file(str(theirs), str(ours)) == 2
    assert "stopped" not in json.loads(ours.read_text())
    caplog.set_level(logging.INFO, logger="twin.service.persist")
    back = StateFile(ours).load(5.0, 1_000_060.0)
    assert sorted(str(r.state) for r in back) == ["ACKNOWLEDGED", "LATCHED"]
    assert not _warnings_of_an_unclean_stop(caplog)

    # A copy that is not a state file is refused, and nothing is put in place.
    theirs.write_text('{"version": 1, "alarms": [{"state": "NORMAL"}]}')
    elsewhere = tmp_path / "other" / "state.json"
    with pytest.raises(StateFileError):
        adopt_file(str(theirs), str(elsewhere))
    assert not elsewhere.exists()


def test_alarms_of_a_kind_only_a_newer_agent_knows_are_kept_aside_not_the_whole_file(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A rollback: the file of an agent that knows a kind this one does not. Refusing the whole file would
    # drop the acknowledgements and latched alarms of the kinds this agent knows as well.
    path = tmp_path / "state.json"
    store = StateFile(path)
    assert store.save(
        [_record(AlarmState.ACKNOWLEDGED), _record(AlarmState.LATCHED, joint="wrist_flex")], 110.0, 1e6
    )
    document = json.loads(path.read_text())
    newer = [
        {
            **document["alarms"][0],
            "alarm_id": f"{device}/gripper/a_future_kind",
            "device": device,
            "joint": "gripper",
            "kind": "a_future_kind",
            "state": "ACTIVE",
        }
        for device in ("arm-001", "arm-002")
    ]
    path.write_text(json.dumps({**document, "alarms": document["alarms"] + newer}))

    later = StateFile(path)
    with caplog.at_level(logging.WARNING, logger="twin.service.persist"):
        back = later.load(5.0, 1e6 + 60)
    assert sorted((r.joint, r.state) for r in back) == [
        ("elbow_flex", AlarmState.ACKNOWLEDGED),
        ("wrist_flex", AlarmState.LATCHED),
    ]
    assert not path.with_name("state.json.bad").exists()
    assert "arm-001/gripper/a_future_kind" in caplog.text and "newer version" in caplog.text

    # Written back as they were, so rolling forward again finds them; a forgotten arm's go with it.
    assert later.save(back, 6.0, 1e6 + 61)
    assert [a for a in json.loads(path.read_text())["alarms"] if a["kind"] == "a_future_kind"] == newer
    later.forget("arm-001")
    assert later.save(back, 7.0, 1e6 + 62)
    kinds = [(a["device"], a["kind"]) for a in json.loads(path.read_text())["alarms"]]
    assert ("arm-002", "a_future_kind") in kinds and ("arm-001", "a_future_kind") not in kinds


def test_a_name_taken_while_a_file_is_set_aside_is_not_replaced(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another process (a second agent started by mistake, a person's copy) may make `state.json.bad` between
    the look for a free name and the move: its file must survive, and the broken one go to the next name."""
    path = tmp_path / "state.json"
    path.write_bytes(b"broken")
    competitor = tmp_path / "state.json.bad"
    real_link, real_replace = os.link, os.replace

    def first_make_competitor(real):  # type: ignore[no-untyped-def]
        def call(src, dst, *args, **kwargs):  # type: ignore[no-untyped-def]
            if not competitor.exists():
                competitor.write_bytes(b"the other one")
            return real(src, dst, *args, **kwargs)

        return call

    monkeypatch.setattr(os, "link", first_make_competitor(real_link))
    monkeypatch.setattr(os, "replace", first_make_competitor(real_replace))
    assert StateFile(path).load(0.0, 0.0) == []
    monkeypatch.undo()
    assert competitor.read_bytes() == b"the other one"
    assert (tmp_path / "state.json.bad.1").read_bytes() == b"broken"
    assert not path.exists()


def test_a_filesystem_without_hard_links_still_sets_a_file_aside(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """vfat and some network shares refuse a hard link (EPERM): the file is still moved, beside the first."""
    path = tmp_path / "state.json"
    (tmp_path / "state.json.bad").write_bytes(b"first")
    path.write_bytes(b"broken")

    def refuse(src: object, dst: object, *args: object, **kwargs: object) -> None:
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "link", refuse)
    state = StateFile(path)
    assert state.load(0.0, 0.0) == []
    monkeypatch.undo()
    assert (tmp_path / "state.json.bad").read_bytes() == b"first"
    assert (tmp_path / "state.json.bad.1").read_bytes() == b"broken"
    assert "moved to state.json.bad.1" in state.stats().last_error


def test_a_file_linked_but_not_removable_is_not_left_with_two_names(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A sticky directory may let the link be made and refuse the removal: the new name goes again, so no
    start leaves one more `.bad` beside a file still in place, and the agent starts, having said so."""
    path = tmp_path / "state.json"
    path.write_bytes(b"broken")
    real_unlink = os.unlink

    def refuse_the_original(name: object, *args: object, **kwargs: object) -> None:
        if os.fspath(name) == str(path):  # type: ignore[arg-type]
            raise PermissionError(errno.EPERM, "Operation not permitted", str(name))
        real_unlink(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(os, "unlink", refuse_the_original)
    state = StateFile(path)
    assert state.load(0.0, 0.0) == []
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]
    assert "could not be moved aside" in state.stats().last_error, state.stats().last_error
