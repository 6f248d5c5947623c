"""Each arm's own LeRobot calibration: the store (a directory, or S3 with moto standing in for it: AWS cannot
be reached from here), the watcher that picks files up without a restart, `twin calibration`, and the agent
decoding each arm with its own, flagging the arms that have none."""

from __future__ import annotations

import errno
import json
import os
import shlex
import signal
import threading
import time
from multiprocessing import Pipe
from pathlib import Path
from typing import Any

import boto3
import pytest
from conftest import AWS_TEST_REGION, NO_BROKER, http_get, wait_for
from moto import mock_aws
from twin.cli import main
from twin.cli.commands import calibration as cmd
from twin.core.health import HELD_REASON, MAX_UNHEARD
from twin.core.units import Units
from twin.edge.payload import encode
from twin.robot import so101
from twin.robot.calibration import load_calibration
from twin.service import calibrations, console
from twin.service.admission import DeviceBudget
from twin.service.agent import AgentService
from twin.service.calibrations import (
    STACK_PREFIX,
    CalibrationBook,
    CalibrationStoreError,
    CalibrationWatcher,
    DirectoryStore,
    S3Store,
    device_of,
    open_store,
    scan_of,
)
from twin.service.config import ConfigError, load_config
from twin.service.events import EventQuery
from twin.service.mirror import Mirror, PipeInbox
from twin.service.shards import AlarmsRequest, CalibrationsRequest

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "robots" / "so101" / "calibration" / "so101_follower_example.json"
RAD_PER_TICK = 2 * 3.141592653589793 / 4095


def shifted(ticks: int) -> bytes:
    """The example calibration with every range `ticks` higher: each joint's middle moves by as much."""
    data = json.loads(EXAMPLE.read_text())
    for motor in data.values():
        motor["range_min"] += ticks
        motor["range_max"] += ticks
    return json.dumps(data).encode()


def ticks_message(
    device: str, ts: int, positions: tuple[int, ...] = (2048, 1800, 2200, 2100, 2048, 2500)
) -> bytes:
    joints = {name: {"position": p} for name, p in zip(so101.JOINT_NAMES, positions, strict=True)}
    return json.dumps({"device_id": device, "timestamp": ts, "joints": joints}).encode()


def pan_angle(calibration_bytes: bytes | None, position: int = 2048) -> float:
    """shoulder_pan's angle for `position` ticks: (position - middle of its calibrated range) * K."""
    if calibration_bytes is None:
        return (position - so101.TICK_HOME) * RAD_PER_TICK
    pan = json.loads(calibration_bytes)["shoulder_pan"]
    return (position - (pan["range_min"] + pan["range_max"]) / 2) * RAD_PER_TICK


# --- the store and the watcher ---------------------------------------------------------------------------


def test_file_names_are_device_ids() -> None:
    assert device_of("arm-001.json") == "arm-001"
    assert device_of("arm-001.txt") is None
    assert device_of("+.json") is None and device_of(".json") is None


def test_a_scan_sorts_the_arms_the_kept_and_the_files_no_arm_reads() -> None:
    found = scan_of(
        [
            ("arm-001.json", "v1"),
            ("arm-001.json.previous", "k1"),
            ("arm-002.json.previous", "k2"),
            ("arm 9.json", "x"),  # a space: no device id
            ("ARM-003.JSON", "x"),  # the suffix is lower case
            ("arm.4.json.previous", "x"),  # a dot is a device id's: arm.4's kept one
            (".arm-5.json", "x"),  # a hidden file: no device id starts with '.'
            ("notes.txt", "x"),  # not a calibration at all: not reported
        ]
    )
    assert found.calibrations == {"arm-001": "v1"} and set(found.kept) == {"arm-001", "arm-002", "arm.4"}
    assert found.ignored == (".arm-5.json", "ARM-003.JSON", "arm 9.json")


def test_the_watcher_warns_once_of_a_file_no_arm_reads(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    (tmp_path / "cal" / "arm 9.json").write_bytes(EXAMPLE.read_bytes())  # copied in by hand
    watcher = CalibrationWatcher(store)

    def warnings() -> list[str]:
        return [r.getMessage() for r in caplog.records if getattr(r, "event", "") == "calibration_ignored"]

    with caplog.at_level("WARNING", logger="twin.service.calibrations"):
        assert watcher.poll() is True
        assert set(watcher.book.entries) == {"arm-001"}
        assert len(warnings()) == 1 and "arm 9.json" in warnings()[0], warnings()
        # A plain push would reach the stack's store, not this directory.
        assert f"twin calibration push ARM FILE --store {tmp_path / 'cal'}`" in warnings()[0], warnings()
        # A walk: the hint named a push that refuses the id; an arm with such an id has no fix but a new id.
        assert "rename the arm on the edge" in warnings()[0], warnings()
        watcher.poll()
        assert len(warnings()) == 1  # once, not every poll
    assert main(["calibration", "ls", "--store", str(tmp_path / "cal")]) == cmd.EXIT_OK
    listed = capsys.readouterr()
    assert listed.out == f"arm-001\t{tmp_path / 'cal' / 'arm-001.json'}\n"
    assert "ignored: arm 9.json (no arm reads it" in listed.err, listed.err
    assert f"twin calibration push ARM FILE --store {tmp_path / 'cal'}`" in listed.err, listed.err


def test_a_hidden_file_in_the_store_is_never_an_arms_and_its_notice_says_rename_or_remove(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    """Files an editor, a cut-short copy or a desktop leaves beside the arms' (`.arm-002.json`, macOS's
    `._arm-001.json`, `.DS_Store`) are no arm's calibration: an id cannot start with '.', so a push refuses
    one. Before, the notice for them gave the fix for a badly named arm (push under that id, or rename the arm
    on the edge); it now says it is a hidden file, to be renamed to the arm's <device id>.json or removed."""
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    for name in (".arm-002.json", "._arm-001.json", ".DS_Store"):
        (tmp_path / "cal" / name).write_bytes(EXAMPLE.read_bytes())
    watcher = CalibrationWatcher(store)
    with caplog.at_level("WARNING", logger="twin.service.calibrations"):
        assert watcher.poll() is True
    assert set(watcher.book.entries) == {"arm-001"} and not watcher.book.problems
    said = {getattr(r, "file", ""): r.getMessage() for r in caplog.records}
    assert set(said) == {".arm-002.json", "._arm-001.json"}, said  # .DS_Store names no calibration
    for name, message in said.items():
        assert f"{name} in {tmp_path / 'cal'} is ignored" in message, message
        assert "starts with '.', so it is a hidden file" in message and "else remove it" in message, message
        assert "rename the arm on the edge" not in message, message
    assert "rename it to <device id>.json (arm-002.json here)" in said[".arm-002.json"]
    assert "here)" not in said["._arm-001.json"]  # macOS's metadata of arm-001.json, not a calibration
    with pytest.raises(ValueError, match="not a device id"):
        store.write(".arm-002", EXAMPLE.read_bytes())
    assert main(["calibration", "ls", "--store", str(tmp_path / "cal")]) == cmd.EXIT_OK
    listed = capsys.readouterr()
    assert listed.out == f"arm-001\t{tmp_path / 'cal' / 'arm-001.json'}\n"
    assert "ignored: .arm-002.json (no arm reads it: its name starts with '.'" in listed.err, listed.err
    assert "DS_Store" not in listed.err, listed.err


def test_a_file_the_store_could_not_read_is_read_again_at_the_next_poll(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A review: a read that failed (S3 throttled, a network blip) refused the arm's file as a bad one and
    marked its version seen, so it was never read again: an arm held at the start stayed held until its
    file changed. It is read again at each poll, said once while it fails the same way."""
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-002", EXAMPLE.read_bytes())
    failing = [True]
    read = DirectoryStore.read

    def throttled(self: DirectoryStore, device: str) -> bytes:
        if failing[0]:
            raise CalibrationStoreError(f"cannot read {device}'s calibration: throttled (test)")
        return read(self, device)

    monkeypatch.setattr(DirectoryStore, "read", throttled)
    books: list[CalibrationBook] = []
    watcher = CalibrationWatcher(store, on_change=books.append)
    assert watcher.poll() is True and "throttled (test)" in books[-1].problems["arm-002"]
    assert watcher.poll() is False and len(books) == 1  # the same failure: not said again
    failing[0] = False
    assert watcher.poll() is True
    assert books[-1].problems == {} and books[-1].entries["arm-002"].calibration == load_calibration(EXAMPLE)


def test_the_watcher_picks_up_changes_refuses_bad_files_and_keeps_what_it_had(tmp_path: Path) -> None:
    store = DirectoryStore(tmp_path / "calibration")
    books: list[CalibrationBook] = []
    watcher = CalibrationWatcher(store, on_change=books.append)
    assert watcher.poll() is False and books == []  # no directory yet: nothing, and no error
    store.write("arm-001", EXAMPLE.read_bytes())
    store.write("arm-002", b'{"shoulder_pan": {}}')
    assert watcher.poll() is True
    book = books[-1]
    assert set(book.entries) == {"arm-001"}
    assert book.entries["arm-001"].source == str(tmp_path / "calibration" / "arm-001.json")
    assert "lacks id, drive_mode" in book.problems["arm-002"]
    assert [(c.device, c.action) for c in book.changes] == [("arm-001", "picked up"), ("arm-002", "refused")]
    # Nothing new: no second hand-over.
    assert watcher.poll() is False and len(books) == 1
    # A broken replacement keeps the arm's calibration; a good one for arm-002 is taken.
    (tmp_path / "calibration" / "arm-001.json").write_text("{not json")
    store.write("arm-002", shifted(100))
    assert watcher.poll() is True
    book = books[-1]
    assert book.entries["arm-001"].calibration == load_calibration(EXAMPLE)
    assert "not valid JSON" in book.problems["arm-001"]
    assert book.entries["arm-002"].calibration["shoulder_pan"].range_min == 762 + 100
    # Removing a file takes the arm back to the config's calibration.
    assert store.delete("arm-002") and not store.delete("arm-002")
    assert watcher.poll() is True
    assert set(books[-1].entries) == {"arm-001"}
    assert [(c.device, c.action) for c in books[-1].changes] == [("arm-002", "removed")]


def test_a_missing_directory_is_told_once_and_a_refusal_at_start_says_what_the_arm_uses(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A mistyped [telemetry] calibrations looked like an empty store: every arm decoded with the config's
    # calibration and nothing said why.
    store = DirectoryStore(tmp_path / "calibrations")
    watcher = CalibrationWatcher(store)
    with caplog.at_level("INFO", logger="twin.service.calibrations"):
        watcher.poll()
        watcher.poll()
        told = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
        assert len(told) == 1 and f"{tmp_path / 'calibrations'} does not exist" in told[0], told
        assert f"--store {tmp_path / 'calibrations'}`" in told[0]
        # The first file pushed makes the directory; a bad one, with no calibration in force before it,
        # holds the arm (not "the one it had", nor the config's: another arm's).
        store.write("arm-001", b"{not json")
        watcher.poll()
    said = [r.getMessage() for r in caplog.records]
    assert f"calibrations: {tmp_path / 'calibrations'} exists now; its files are read" in said, said
    (refused,) = [m for m in said if m.startswith("calibration of arm-001 refused")]
    assert "its twin holds still until a good file is pushed" in refused, refused


def test_the_log_says_which_arm_lost_its_calibration_and_how_to_put_a_refused_one_right(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A removal was logged without the device field a pick-up and a refusal carry, so a search of the log by
    # device missed it; a refusal while the agent ran named no fix, nor that its next start holds the arm.
    store = DirectoryStore(tmp_path / "calibration")
    watcher = CalibrationWatcher(store)
    store.write("arm-001", EXAMPLE.read_bytes())
    store.write("arm-002", EXAMPLE.read_bytes())
    watcher.poll()
    with caplog.at_level("INFO", logger="twin.service.calibrations"):
        store.delete("arm-001")
        (tmp_path / "calibration" / "arm-002.json").write_text("{not json")
        watcher.poll()
    by_event = {getattr(r, "event", ""): r for r in caplog.records}
    assert getattr(by_event["calibration_removed"], "device", "") == "arm-001"
    refused = by_event["calibration_refused"]
    assert getattr(refused, "device", "") == "arm-002"
    said = refused.getMessage()
    assert "keeps the one it had until the agent starts again" in said, said
    assert f"twin calibration push arm-002 FILE --store {tmp_path / 'calibration'}" in said, said


@pytest.mark.parametrize("fallback", ["", str(EXAMPLE)])
def test_a_removal_says_what_the_arm_decodes_with_now(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str], fallback: str
) -> None:
    # Both said "it decodes with the config's again", also for a config with no calibration key, where the
    # arm then decodes with the nominal SO-101 calibration and is flagged uncalibrated.
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    agent = agent_with_store(tmp_path / "cal", **{"telemetry.calibration": fallback})
    watcher = agent._calibrations
    assert watcher is not None
    watcher.poll()
    assert main(["calibration", "rm", "arm-001", "--store", store.uri]) == cmd.EXIT_OK
    said = capsys.readouterr().out
    assert "[telemetry] calibration, or, where that is not set, the nominal SO-101 calibration" in said, said
    with caplog.at_level("INFO", logger="twin.service.calibrations"):
        watcher.poll()
    (removed,) = [r.getMessage() for r in caplog.records if getattr(r, "event", "") == "calibration_removed"]
    if fallback:
        assert f"it decodes with the config's calibration ({fallback})" in removed, removed
    else:
        assert "it decodes with the nominal SO-101 calibration, and is flagged uncalibrated" in removed, (
            removed
        )
        assert "config's" not in removed, removed


def test_a_held_arm_is_offered_a_restore_only_when_a_calibration_is_kept_for_it(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The refusal named `twin calibration restore` with nothing kept, which then exits 1.
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-002", b"{not json")
    books: list[CalibrationBook] = []
    watcher = CalibrationWatcher(store, on_change=books.append)
    with caplog.at_level("WARNING", logger="twin.service.calibrations"):
        watcher.poll()
    (refused,) = [r.getMessage() for r in caplog.records if getattr(r, "event", "") == "calibration_refused"]
    assert "restore" not in refused and books[-1].restorable == frozenset(), refused
    # A kept one appears (a push over it kept one, or by hand): the held arm can be put back with it.
    store.write_kept("arm-002", EXAMPLE.read_bytes())
    assert watcher.poll() is True and books[-1].restorable == {"arm-002"}
    # Read once a version, as the arms' own files are: on S3 a GET per refused arm every poll otherwise.
    reads: list[str] = []
    read_kept = DirectoryStore.read_kept
    monkeypatch.setattr(DirectoryStore, "read_kept", lambda self, d: reads.append(d) or read_kept(self, d))
    assert watcher.poll() is False and reads == []
    monkeypatch.undo()
    store.delete_kept("arm-002")
    assert watcher.poll() is True and books[-1].restorable == frozenset()
    # A kept file that is no valid calibration either: restore would refuse it, so it is not offered.
    store.write_kept("arm-002", EXAMPLE.read_bytes()[:100])
    assert watcher.poll() is False and books[-1].restorable == frozenset()
    caplog.clear()
    store.write_kept("arm-002", EXAMPLE.read_bytes())
    with caplog.at_level("WARNING", logger="twin.service.calibrations"):
        store.write("arm-002", b"{still not json")
        watcher.poll()
    (refused,) = [r.getMessage() for r in caplog.records if getattr(r, "event", "") == "calibration_refused"]
    assert f"twin calibration restore arm-002 --store {store.uri}" in refused, refused


def test_an_unreadable_store_keeps_the_book_and_says_why(tmp_path: Path) -> None:
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    watcher = CalibrationWatcher(store)
    assert watcher.poll()
    # The store's path turns into a file: it cannot be listed (as root, permissions would not stop it).
    for child in (tmp_path / "cal").iterdir():
        child.unlink()
    (tmp_path / "cal").rmdir()
    (tmp_path / "cal").write_text("")
    assert watcher.poll() is False
    assert "is a file, not a store" in watcher.last_error and watcher.failures == 1
    assert set(watcher.book.entries) == {"arm-001"}


def test_a_store_under_a_file_is_not_called_a_file(tmp_path: Path) -> None:
    # `--store agent.toml/cal`: the listing's "Not a directory" is about agent.toml, and the store's own path
    # names nothing; calling it "a file" sends a person to look for one that is not there.
    (tmp_path / "agent.toml").write_text("")
    store = DirectoryStore(tmp_path / "agent.toml" / "cal")
    with pytest.raises(CalibrationStoreError) as raised:
        store.scan()
    assert "is a file" not in str(raised.value) and "Not a directory" in str(raised.value), raised.value


def test_a_file_gone_between_the_listing_and_its_size_is_passed_over(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A push renames its temporary file into place while a poll lists the directory: the poll saw the
    temporary file and its size then raised FileNotFoundError, and the whole round was skipped."""
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    pushing = tmp_path / "cal" / ".arm-002.json.k3j5x9q1.tmp"
    pushing.write_bytes(EXAMPLE.read_bytes())
    real_scandir = os.scandir

    def listed_then_renamed(path: Any) -> Any:
        entries = list(real_scandir(path))
        pushing.rename(tmp_path / "cal" / "arm-002.json")
        return iter(entries)

    monkeypatch.setattr(calibrations.os, "scandir", listed_then_renamed)
    watcher = CalibrationWatcher(store)
    assert watcher.poll() and watcher.failures == 0
    monkeypatch.undo()
    assert set(watcher.book.entries) == {"arm-001"}
    assert watcher.poll() and set(watcher.book.entries) == {"arm-001", "arm-002"}


def test_a_temporary_file_a_killed_push_left_is_removed_once_old(tmp_path: Path) -> None:
    """Nothing else removes the temporary file of a push killed before its rename: crash after crash they
    would fill the store. A young one may be a push under way, and is left alone."""
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    old, young = (tmp_path / "cal" / f".arm-001.json.{tag}.tmp" for tag in ("aaaaaaaa", "bbbbbbbb"))
    old.write_bytes(b"{")
    young.write_bytes(b"{")
    hour_ago = time.time() - 3600
    os.utime(old, (hour_ago, hour_ago))
    assert store.listing().keys() == {"arm-001"}
    assert not old.exists() and young.exists()
    assert (tmp_path / "cal" / "arm-001.json").read_bytes() == EXAMPLE.read_bytes()


@pytest.fixture
def s3(aws_env: None):
    with mock_aws():
        client = boto3.client("s3", region_name=AWS_TEST_REGION)
        client.create_bucket(Bucket="twin-bucket")
        yield client


def test_the_s3_store_lists_one_object_per_arm(s3: Any) -> None:
    store = open_store("s3://twin-bucket/calibration", s3_client=s3)
    assert isinstance(store, S3Store) and store.uri == "s3://twin-bucket/calibration"
    assert store.write("arm-003", EXAMPLE.read_bytes()) == "s3://twin-bucket/calibration/arm-003.json"
    # Not an arm's file: another prefix, a nested key, another suffix.
    s3.put_object(Bucket="twin-bucket", Key="history/arm-009.json", Body=b"{}")
    s3.put_object(Bucket="twin-bucket", Key="calibration/old/arm-004.json", Body=b"{}")
    s3.put_object(Bucket="twin-bucket", Key="calibration/notes.txt", Body=b"")
    listing = store.listing()
    assert list(listing) == ["arm-003"]
    # A calibration-like name right under the prefix that names no device is reported, not read.
    s3.put_object(Bucket="twin-bucket", Key="calibration/arm 9.json", Body=b"{}")
    assert store.scan().ignored == ("arm 9.json",) and list(store.listing()) == ["arm-003"]
    assert store.read("arm-003") == EXAMPLE.read_bytes()
    version = listing["arm-003"]
    store.write("arm-003", shifted(5))
    assert store.listing()["arm-003"] != version
    assert store.delete("arm-003") and store.listing() == {}


def test_an_s3_store_without_credentials_says_how_to_give_some(
    aws_env: None, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
        monkeypatch.delenv(name)
    # Exit 3, as the help says for no AWS credentials; not 1, which is the store's own error.
    assert main(["calibration", "ls", "--store", "s3://twin-bucket/calibration"]) == cmd.EXIT_SETUP
    err = capsys.readouterr().err
    assert "cannot list s3://twin-bucket/calibration" in err and "aws configure" in err, err


def test_the_stacks_prefix_is_the_one_a_plain_push_is_told_for() -> None:
    # The console tells the twin host's agent (s3://<bucket>/calibration) to push without --store.
    source = (REPO / "stacks" / "history_bucket.py").read_text()
    assert f'CALIBRATION_PREFIX = "{STACK_PREFIX}"' in source


def test_store_uris_are_checked() -> None:
    assert isinstance(open_store("out/calibration"), DirectoryStore)
    assert isinstance(open_store("file:///tmp/cal"), DirectoryStore)
    # "s3:/b/cal", a slash short, was a directory store: push made a local folder "s3:" and wrote there.
    for bad in ("s3://", "http://x/y", "s3:/b/cal", "S3:b"):
        with pytest.raises(ValueError, match=r"names no bucket|not a directory|lacks the '//'"):
            open_store(bad)
    for key, value, message in [
        ("telemetry.calibrations", "http://example.com/c", "not a directory or s3://"),
        ("telemetry.calibrations", "s3:///calibration", "names no bucket"),
        ("telemetry.calibrations", "s3:/b/calibration", "lacks the '//' after 's3:'"),
        ("telemetry.calibration_poll_s", 0.5, "outside 1..3600"),
    ]:
        with pytest.raises(ConfigError, match=message):
            load_config(None, {key: value})


# --- twin calibration ------------------------------------------------------------------------------------


def test_push_ls_rm_with_a_directory_store(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    store = str(tmp_path / "cal")
    assert main(["calibration", "push", "arm-001", str(EXAMPLE), "--store", store]) == cmd.EXIT_OK
    out = capsys.readouterr().out
    assert f"arm-001: {tmp_path / 'cal' / 'arm-001.json'}" in out and "shoulder_pan" in out
    assert (tmp_path / "cal" / "arm-001.json").read_bytes() == EXAMPLE.read_bytes()
    assert main(["calibration", "ls", "--store", store]) == cmd.EXIT_OK
    assert capsys.readouterr().out == f"arm-001\t{tmp_path / 'cal' / 'arm-001.json'}\n"
    assert main(["calibration", "rm", "arm-001", "--store", store]) == cmd.EXIT_OK
    assert main(["calibration", "rm", "arm-001", "--store", store]) == cmd.EXIT_STORE
    assert "arm-001 has no calibration" in capsys.readouterr().err


def test_ls_marks_a_file_the_agent_refuses_with_the_agents_reason(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A truncated file was listed like any other: an operator checking why an arm is held saw nothing wrong.
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    (tmp_path / "cal" / "arm-002.json").write_bytes(EXAMPLE.read_bytes()[:100])
    books: list[CalibrationBook] = []
    CalibrationWatcher(store, on_change=books.append).poll()
    why = books[-1].problems["arm-002"]
    assert main(["calibration", "ls", "--store", str(tmp_path / "cal")]) == cmd.EXIT_OK
    listed = capsys.readouterr()
    assert listed.out.splitlines() == [
        f"arm-001\t{store.uri_of('arm-001')}",
        f"arm-002\t{store.uri_of('arm-002')}\trefused: {why}",
    ], listed.out
    assert "not valid JSON" in why
    assert "refused: the agent does not use that file" in listed.err, listed.err


def test_a_push_or_rm_over_a_refused_file_keeps_it_but_offers_no_restore(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The broken file was kept with a hint to `restore`, which then refused it: "not valid JSON ...; nothing
    # restored", exit 1. It is still kept (nothing the user had is lost), and the output says what it is.
    store = DirectoryStore(tmp_path / "cal")
    broken = EXAMPLE.read_bytes()[:100]
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "arm-002.json").write_bytes(broken)
    kept = f"{store.uri_of('arm-002')}.previous"
    assert main(["calibration", "push", "arm-002", str(EXAMPLE), "--store", store.uri]) == cmd.EXIT_OK
    out = capsys.readouterr().out
    assert "twin calibration restore" not in out and store.read_kept("arm-002") == broken, out
    assert "the file it replaced was not a valid calibration (" in out and f"kept at {kept}" in out, out
    (tmp_path / "cal" / "arm-002.json").write_bytes(broken)
    assert main(["calibration", "rm", "arm-002", "--store", store.uri]) == cmd.EXIT_OK
    out = capsys.readouterr().out
    assert "twin calibration restore" not in out and store.read_kept("arm-002") == broken, out
    assert "the file it replaced was not a valid calibration (" in out and f"kept at {kept}" in out, out
    # A walk: ls listed the broken kept file like a good one, under the hint that restore swaps it back in,
    # and the restore then exited 1. It says what restore would say.
    assert main(["calibration", "ls", "--store", store.uri]) == cmd.EXIT_OK
    (line,) = capsys.readouterr().out.splitlines()
    assert line.startswith(f"arm-002\t(removed)\tkept: {kept} (refused, no restore: arm-002's kept "), line
    assert "is not valid JSON" in line, line


def test_a_restore_over_a_refused_file_offers_no_swap_back(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk: a restore over a hand-copied file with reversed ranges said "restore again to swap back",
    and that second restore refused the file it had kept, exit 1. It says what push and rm say instead."""
    store = DirectoryStore(tmp_path / "cal")
    reversed_ranges = json.loads(EXAMPLE.read_bytes())
    elbow = reversed_ranges["elbow_flex"]
    elbow["range_min"], elbow["range_max"] = elbow["range_max"], elbow["range_min"]
    broken = json.dumps(reversed_ranges).encode()
    store.write("arm-003", broken)
    store.write_kept("arm-003", EXAMPLE.read_bytes())
    assert main(["calibration", "restore", "arm-003", "--store", store.uri]) == cmd.EXIT_OK
    out = capsys.readouterr().out
    assert store.read("arm-003") == EXAMPLE.read_bytes() and store.read_kept("arm-003") == broken
    assert "swap back" not in out and "the file it replaced was not a valid calibration (" in out, out
    assert "range_min=3104 range_max=868" in out and f"kept at {store.uri_of('arm-003')}.previous" in out, out


def test_ls_of_a_directory_that_does_not_exist_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk: `ls --store` with a mistyped directory said "no calibration in ...", as for an empty store,
    where the agent's log and `twin config check` say the directory is not there."""
    assert main(["calibration", "ls", "--store", str(tmp_path / "calibratoin")]) == cmd.EXIT_OK
    out = capsys.readouterr().out
    missing = tmp_path / "calibratoin"
    assert out.startswith(f"no calibration in {missing}: that directory does not exist; "), out
    assert "[telemetry] calibrations" in out, out
    (tmp_path / "calibration").mkdir()
    assert main(["calibration", "ls", "--store", str(tmp_path / "calibration")]) == cmd.EXIT_OK
    assert capsys.readouterr().out == f"no calibration in {tmp_path / 'calibration'}\n"


def test_ls_stops_on_a_kept_file_it_cannot_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A review: a kept file `ls` could not read (S3 throttling, access denied) was marked "refused, no
    restore", telling the operator that a calibration which may be good cannot come back. A failed read
    stops `ls` with the store's error, as its other reads do."""
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-002", EXAMPLE.read_bytes())
    store.write_kept("arm-002", EXAMPLE.read_bytes())

    def denied(self: DirectoryStore, device: str) -> bytes:
        raise CalibrationStoreError(f"cannot read {device}'s kept file: access denied (test)")

    monkeypatch.setattr(DirectoryStore, "read_kept", denied)
    assert main(["calibration", "ls", "--store", store.uri]) == cmd.EXIT_STORE
    said = capsys.readouterr()
    assert "access denied (test)" in said.err and "refused" not in said.out, said
    # The same for the arm's own file: not "refused: ... push a good file" for one that may be good.
    monkeypatch.undo()
    monkeypatch.setattr(DirectoryStore, "read", denied)
    assert main(["calibration", "ls", "--store", store.uri]) == cmd.EXIT_STORE
    said = capsys.readouterr()
    assert "access denied (test)" in said.err and "refused" not in said.out, said


def test_a_broken_file_does_not_push_out_the_valid_calibration_kept_from_before(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # One kept slot per arm: a push (or rm) over a truncated upload kept the upload in place of the arm's
    # last good calibration, which was then gone. The good one stays, and the output says so.
    store = DirectoryStore(tmp_path / "cal")
    good = EXAMPLE.read_bytes()
    broken = good[:100]
    for command in (["push", "arm-002", str(EXAMPLE)], ["rm", "arm-002"]):
        store.write_kept("arm-002", good)
        (tmp_path / "cal" / "arm-002.json").write_bytes(broken)
        assert main(["calibration", *command, "--store", store.uri]) == cmd.EXIT_OK
        out = capsys.readouterr().out
        assert store.read_kept("arm-002") == good, command
        assert "not a valid calibration (" in out and "the valid one kept from before stays for" in out, out
        assert f"`twin calibration restore arm-002 --store {store.uri}`" in out, out


def test_push_refuses_what_is_not_a_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"shoulder_pan": {"id": 1}}))
    store = str(tmp_path / "cal")
    assert main(["calibration", "push", "arm-001", str(bad), "--store", store]) == cmd.EXIT_USAGE
    assert "lacks drive_mode" in capsys.readouterr().err
    assert main(["calibration", "push", "arm/1", str(EXAMPLE), "--store", store]) == cmd.EXIT_USAGE
    assert "not a device id" in capsys.readouterr().err
    assert main(["calibration", "push", "arm-001", str(tmp_path / "none.json"), "--store", store]) == 2
    assert "cannot read" in capsys.readouterr().err
    # The file first and the arm second: said so, with the command the right way round.
    assert main(["calibration", "push", str(EXAMPLE), "arm-001", "--store", store]) == cmd.EXIT_USAGE
    swapped = capsys.readouterr().err
    # ... the store flags kept: without them the command would go to the deployed stack's store.
    assert "the arm comes first" in swapped and f"push arm-001 {EXAMPLE} --store {store}`" in swapped, swapped
    # A file named in capitals (as a Windows export may be) is told the same way.
    upper = tmp_path / "ARM-001.JSON"
    upper.write_bytes(EXAMPLE.read_bytes())
    assert main(["calibration", "push", str(upper), "arm-001", "--store", store]) == cmd.EXIT_USAGE
    assert "the arm comes first" in capsys.readouterr().err
    assert not (tmp_path / "cal").exists()


@pytest.mark.parametrize(
    "device",
    ["arm 9", "a" * 65, "ärm", ".arm", "arm:9"],
    ids=["space", "65-chars", "non-ascii", "leading-dot", "colon"],
)
def test_push_and_rm_refuse_an_id_the_stack_would_not_mirror(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], device: str
) -> None:
    """The device id rule of docs/getting-started.md part 3 (twin.core.topics, the deployment's), for every
    store: refused as bad input, with the rule and the fix, and nothing written."""
    store = str(tmp_path / "cal")
    for argv in (["push", device, str(EXAMPLE)], ["rm", device]):
        assert main(["calibration", *argv, "--store", store]) == cmd.EXIT_USAGE
        err = capsys.readouterr().err
        assert f"ARM {device!r} is not a device id" in err, err
        assert "1..64 letters, digits, '-', '_' or '.'" in err and "deviceId" in err, err
    assert not (tmp_path / "cal").exists()
    # The longest id the rule allows is stored, and a file the rule refuses names no arm in a store.
    assert main(["calibration", "push", "a" * 64, str(EXAMPLE), "--store", store]) == cmd.EXIT_OK
    (tmp_path / "cal" / f"{device}.json").write_bytes(EXAMPLE.read_bytes())
    assert set(DirectoryStore(tmp_path / "cal").listing()) == {"a" * 64}


def test_an_id_with_dots_the_agent_mirrors_can_be_calibrated(
    tmp_path: Path, s3: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    """`twin run --devices so101.lab.7` mirrors the arm, so every store keeps its calibration and the
    console's hint gives the push that does it."""
    load_config(None, {"telemetry.devices": ["so101.lab.7"]})
    store = str(tmp_path / "cal")
    assert main(["calibration", "push", "so101.lab.7", str(EXAMPLE), "--store", store]) == cmd.EXIT_OK
    assert DirectoryStore(tmp_path / "cal").listing().keys() == {"so101.lab.7"}
    s3_store = open_store("s3://twin-bucket/calibration", s3_client=s3)
    s3_store.write("so101.lab.7", EXAMPLE.read_bytes())
    assert s3_store.listing().keys() == {"so101.lab.7"}
    for where in (store, s3_store.uri):
        hint = calibrations.push_hint("so101.lab.7", where)
        assert hint.command.startswith("twin calibration push so101.lab.7 FILE"), hint


@pytest.mark.parametrize("uri", ["directory", "s3://twin-bucket/calibration"])
def test_push_refuses_an_id_whose_store_holds_one_differing_in_case(
    tmp_path: Path, s3: Any, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, uri: str
) -> None:
    """ARM-001 and arm-001 are two arms to MQTT and S3 but one file to a Mac's directory store, and most
    often one arm typed two ways: the second push is refused, naming the first, whichever the store."""
    store = open_store(str(tmp_path / "cal") if uri == "directory" else uri, s3_client=s3)
    monkeypatch.setattr(cmd, "_store", lambda _args: (store, None))
    assert main(["calibration", "push", "ARM-001", str(EXAMPLE), "--store", store.uri]) == cmd.EXIT_OK
    assert main(["calibration", "push", "arm-001", str(EXAMPLE), "--store", store.uri]) == cmd.EXIT_USAGE
    err = capsys.readouterr().err
    assert "holds a calibration for ARM-001, which differs from arm-001 only in case" in err, err
    assert "twin calibration rm ARM-001" in err and "Nothing was stored" in err, err
    assert store.listing().keys() == {"ARM-001"} and store.read_kept("ARM-001") is None


@pytest.mark.parametrize("uri", ["directory", "s3://twin-bucket/calibration"])
def test_restore_refuses_an_id_whose_store_holds_one_differing_in_case(
    tmp_path: Path, s3: Any, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, uri: str
) -> None:
    """rm ARM-001 keeps its file, a push of arm-001 then finds no twin, and a restore of ARM-001 would put
    the kept file back beside arm-001's (on a Mac's directory store, over it): refused as the push is."""
    store = open_store(str(tmp_path / "cal") if uri == "directory" else uri, s3_client=s3)
    monkeypatch.setattr(cmd, "_store", lambda _args: (store, None))
    other = tmp_path / "other.json"
    other.write_bytes(shifted(40))
    assert main(["calibration", "push", "ARM-001", str(EXAMPLE), "--store", store.uri]) == cmd.EXIT_OK
    assert main(["calibration", "rm", "ARM-001", "--store", store.uri]) == cmd.EXIT_OK
    assert main(["calibration", "push", "arm-001", str(other), "--store", store.uri]) == cmd.EXIT_OK
    capsys.readouterr()
    assert main(["calibration", "restore", "ARM-001", "--store", store.uri]) == cmd.EXIT_USAGE
    err = capsys.readouterr().err
    assert "holds a calibration for arm-001, which differs from ARM-001 only in case" in err, err
    assert "twin calibration rm arm-001" in err and "Nothing was restored" in err, err
    assert store.listing().keys() == {"arm-001"} and store.read("arm-001") == other.read_bytes()
    assert store.read_kept("ARM-001") == EXAMPLE.read_bytes()  # still there to restore once arm-001 goes


def test_a_store_given_as_a_file_says_to_give_the_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # `--store` given the agent's config (or a calibration) said only "[Errno 20] Not a directory".
    config = tmp_path / "agent.toml"
    config.write_text('[telemetry]\ncalibrations = "cal"\n')
    for action in (["push", "arm-001", str(EXAMPLE)], ["ls"]):
        assert main(["calibration", *action, "--store", str(config)]) == cmd.EXIT_STORE
        err = capsys.readouterr().err
        assert f"{config} is a file, not a store: give the directory of the agent's" in err, err
    assert config.read_text() == '[telemetry]\ncalibrations = "cal"\n'


def test_push_refuses_a_leader_arms_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # LeRobot calibrates both arms of a teleoperation pair and keeps their files side by side, with the same
    # motor names; the edge reads the follower. A leader's file would decode the follower at wrong angles.
    leader = tmp_path / "calibration" / "teleoperators" / "so_leader" / "arm-001.json"
    leader.parent.mkdir(parents=True)
    leader.write_bytes(EXAMPLE.read_bytes())
    store = str(tmp_path / "cal")
    assert main(["calibration", "push", "arm-001", str(leader), "--store", store]) == cmd.EXIT_USAGE
    err = capsys.readouterr().err
    assert "a leader arm's calibration" in err and "robots/so_follower/<id>.json" in err, err
    assert not (tmp_path / "cal").exists()
    follower = tmp_path / "calibration" / "robots" / "so_follower" / "arm-001.json"
    follower.parent.mkdir(parents=True)
    follower.write_bytes(EXAMPLE.read_bytes())
    assert main(["calibration", "push", "arm-001", str(follower), "--store", store]) == cmd.EXIT_OK
    # Another robot type's follower (Koch) names its motors as the SO-101's: taken, it decoded at its angles.
    koch = tmp_path / "calibration" / "robots" / "koch_follower" / "arm-001.json"
    koch.parent.mkdir(parents=True)
    koch.write_bytes(EXAMPLE.read_bytes())
    assert main(["calibration", "push", "arm-001", str(koch), "--store", store]) == cmd.EXIT_USAGE
    err = capsys.readouterr().err
    assert "is a koch_follower robot's calibration" in err and "robots/so_follower/<id>.json" in err, err
    # A review: the rule is LeRobot's layout's, not a user's own folders ("left_follower" of their choosing).
    for parts in (
        ("robots", "so100_follower"),
        ("robots", "so101_follower"),
        ("robots", "bi_so100_follower"),
        ("robots", "SO101_follower"),
        ("mine", "left_follower"),
    ):
        other = tmp_path.joinpath("calibration", *parts, "arm-001.json")
        other.parent.mkdir(parents=True)
        other.write_bytes(EXAMPLE.read_bytes())
        assert main(["calibration", "push", "arm-001", str(other), "--store", store]) == cmd.EXIT_OK, parts


def test_decode_and_the_config_refuse_a_leader_arms_calibration_as_push_does(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The same file push refuses: it parses, but would decode the follower at a leader's angles.
    leader = tmp_path / "calibration" / "teleoperators" / "so_leader" / "arm-001.json"
    leader.parent.mkdir(parents=True)
    leader.write_bytes(EXAMPLE.read_bytes())
    payload = str(REPO / "examples" / "payload-ticks.json")
    assert main(["decode", payload, "--calibration", str(leader)]) == 1
    out, err = capsys.readouterr()
    assert out == "" and "a leader arm's calibration" in err and "robots/so_follower/<id>.json" in err, err
    config = tmp_path / "agent.toml"
    config.write_text(f"[telemetry]\ncalibration = {json.dumps(str(leader))}\n")
    with pytest.raises(ConfigError, match=r"telemetry\.calibration = .* is a leader arm's calibration"):
        load_config(config)
    assert main(["config", "check", str(config)]) == 2
    assert "robots/so_follower/<id>.json; give that one" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ('{"shoulder_pan": {"id": 1,', "is not valid JSON"),
        ('{"shoulder_pan": {}}', "to write a complete file"),
    ],
)
def test_config_check_refuses_a_calibration_file_the_agent_would_refuse(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, reason: str
) -> None:
    # `twin config check` called it valid and `twin run` then stopped with exit 2 after it had subscribed.
    bad = tmp_path / "arm-001.json"
    bad.write_text(text)
    config = tmp_path / "agent.toml"
    config.write_text(f"[telemetry]\ncalibration = {json.dumps(str(bad))}\n")
    with pytest.raises(ConfigError, match=r"telemetry\.calibration = .*: calibration file "):
        load_config(config)
    assert main(["config", "check", str(config)]) == 2
    assert reason in capsys.readouterr().err


def test_a_calibration_saved_with_a_utf8_bom_is_the_same_calibration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk: the arm's file copied on Windows (PowerShell's `Set-Content -Encoding UTF8`, an older Notepad)
    starts with a byte order mark, and every reader refused it with Python's hint to "decode using
    utf-8-sig", which no user can act on. The mark says only that the text is UTF-8."""
    marked = tmp_path / "arm-001.json"
    marked.write_bytes(b"\xef\xbb\xbf" + EXAMPLE.read_bytes())
    assert load_calibration(marked) == load_calibration(EXAMPLE)
    assert main(["calibration", "push", "arm-001", str(marked), "--store", str(tmp_path / "cal")]) == 0
    assert "BOM" not in capsys.readouterr().err
    books: list[Any] = []
    assert CalibrationWatcher(DirectoryStore(tmp_path / "cal"), on_change=books.append).poll() is True
    assert books[-1].problems == {} and books[-1].entries["arm-001"].calibration == load_calibration(EXAMPLE)
    # Windows PowerShell 5's `>` writes UTF-16: refused, with the way to UTF-8 (a review's finding).
    for encoding in ("utf-16", "utf-16-be"):
        marked.write_bytes(EXAMPLE.read_text().encode(encoding))
        if encoding == "utf-16-be":
            marked.write_bytes(b"\xfe\xff" + marked.read_bytes())
        with pytest.raises(ValueError, match=r"is UTF-16 text .*: save it as UTF-8 \(Out-File -Encoding"):
            load_calibration(marked)


def test_a_file_nested_too_deeply_is_refused_with_its_name_not_a_recursion_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk: 60 KB of nested brackets (under the size limit) crashed `push` and `decode` with a
    RecursionError traceback, and in the store it stopped `twin run` from starting ("maximum recursion
    depth exceeded", no file named) and each poll of a running agent. It is refused like any bad file."""
    deep = tmp_path / "arm-002.json"
    deep.write_text("[" * 30_000 + "]" * 30_000)
    with pytest.raises(ValueError, match=r"arm-002.json nests its JSON too deeply .*the right file\?"):
        load_calibration(deep)
    assert main(["calibration", "push", "arm-002", str(deep), "--store", str(tmp_path / "cal")]) == 2
    assert "nests its JSON too deeply" in capsys.readouterr().err
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    store.write("arm-002", deep.read_bytes())
    books: list[Any] = []
    assert CalibrationWatcher(store, on_change=books.append).poll() is True
    assert "nests its JSON too deeply" in books[-1].problems["arm-002"]
    assert books[-1].entries["arm-001"].calibration == load_calibration(EXAMPLE)


def test_config_check_notes_a_store_directory_that_is_not_there(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # A mistyped calibrations path was "a valid agent config" with no note, though `twin run` warns of it at
    # its start and every arm then decodes with the config's calibration.
    monkeypatch.chdir(tmp_path)
    config = tmp_path / "agent.toml"
    config.write_text('[telemetry]\ncalibrations = "out/calibratoin"\n')
    assert main(["config", "check", str(config)]) == 0
    out = capsys.readouterr().out
    missing = tmp_path / "out" / "calibratoin"
    assert f"note: [telemetry] calibrations = 'out/calibratoin': {missing} does not exist" in out, out
    assert f"`twin calibration push ARM FILE --store {missing}`" in out, out
    # The config sets no calibration: the arms decode with the nominal one, flagged, not "the config's".
    assert "each decodes with the nominal SO-101 calibration, and is flagged uncalibrated" in out, out
    # Once it is there (a push made it), nothing to note.
    missing.mkdir(parents=True)
    assert main(["config", "check", str(config)]) == 0
    assert "calibratoin" not in capsys.readouterr().out.split("a valid agent config", 1)[1]


def test_push_goes_to_the_stacks_calibration_uri(s3: Any, capsys: pytest.CaptureFixture[str]) -> None:
    template = {
        "Resources": {"Topic": {"Type": "AWS::SNS::Topic"}},
        "Outputs": {
            "InstanceId": {"Value": "i-0123456789abcdef0"},
            "DcvUrl": {"Value": "https://192.0.2.1:8443/#console"},
            "CalibrationUri": {"Value": "s3://twin-bucket/calibration"},
        },
    }
    boto3.client("cloudformation", region_name=AWS_TEST_REGION).create_stack(
        StackName="So101TwinStack", TemplateBody=json.dumps(template)
    )
    assert main(["calibration", "push", "arm-005", str(EXAMPLE)]) == cmd.EXIT_OK
    assert "s3://twin-bucket/calibration/arm-005.json" in capsys.readouterr().out
    body = s3.get_object(Bucket="twin-bucket", Key="calibration/arm-005.json")["Body"].read()
    assert body == EXAMPLE.read_bytes()
    assert main(["calibration", "ls", "--stack", "Missing"]) == cmd.EXIT_NO_STACK


def settings_output(devices: list[str]) -> dict[str, Any]:
    """The stack's Settings output for a deploy of `devices`, as the stack writes it."""
    from stacks.settings import resolve
    from stacks.settings_guard import settings_output as written

    file = {"clientCidr": "203.0.113.7/32", "devices": devices}
    return {"Value": written(resolve(lambda _key: None, file))}


@pytest.mark.parametrize(("devices", "warned"), [(["arm-001", "arm-002"], True), (["*"], False)])
def test_a_push_to_the_stack_for_an_arm_it_does_not_mirror_says_so(
    s3: Any, capsys: pytest.CaptureFixture[str], devices: list[str], warned: bool
) -> None:
    # moto stands in for CloudFormation and S3. A walk: arm-0O3's calibration went in without a word; only
    # the host's log said no twin would use it, as the host subscribes to the listed arms alone.
    create_stack("s3://twin-bucket/calibration", Settings=settings_output(devices))
    assert main(["calibration", "push", "arm-001", str(EXAMPLE)]) == cmd.EXIT_OK
    assert "mirrors" not in capsys.readouterr().err  # a listed arm: nothing to say
    assert main(["calibration", "push", "arm-0O3", str(EXAMPLE)]) == cmd.EXIT_OK
    err = capsys.readouterr().err
    if not warned:
        assert "mirrors" not in err, err  # the whole fleet: any arm's may come
        assert main(["calibration", "ls"]) == cmd.EXIT_OK
        assert "mirrored" not in "".join(capsys.readouterr())
        return
    assert "the stack mirrors arm-001, arm-002 (its devices setting), not arm-0O3" in err, err
    assert "add it to devices in twin.settings.toml" in err and "`twin calibration rm arm-0O3`" in err, err
    assert s3.get_object(Bucket="twin-bucket", Key="calibration/arm-0O3.json")  # stored, as asked
    # The same file again writes nothing, but says why no twin uses it: a walk's re-push said "nothing
    # written" alone, as if all were well.
    assert main(["calibration", "push", "arm-0O3", str(EXAMPLE)]) == cmd.EXIT_OK
    out, err = capsys.readouterr()
    assert "already holds this calibration; nothing written" in out, out
    assert "the stack mirrors arm-001, arm-002 (its devices setting), not arm-0O3" in err, err
    assert "It was stored before (if that was a slip: `twin calibration rm arm-0O3`)" in err, err
    # ls marks it too, long after the push's warning scrolled away.
    assert main(["calibration", "ls"]) == cmd.EXIT_OK
    out, err = capsys.readouterr()
    assert "arm-0O3\ts3://twin-bucket/calibration/arm-0O3.json\tnot mirrored\n" in out, out
    assert "arm-001\ts3://twin-bucket/calibration/arm-001.json\n" in out, out
    assert "the stack's devices (arm-001, arm-002) do not list arm-0O3" in err, err


def test_the_unmirrored_arm_warning_offers_the_listed_id_it_is_close_to(
    s3: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    # moto stands in for CloudFormation and S3. A stack of 20 arms: the warning named every one of them (up to
    # 150) and left the user to find the one meant among them.
    devices = [f"arm-{n:03d}" for n in range(1, 21)]
    create_stack("s3://twin-bucket/calibration", Settings=settings_output(devices))
    assert main(["calibration", "push", "arm-0O3", str(EXAMPLE)]) == cmd.EXIT_OK
    err = capsys.readouterr().err
    assert "mirrors arm-001, arm-002, arm-003, arm-004, arm-005, arm-006, arm-007, arm-008 and 12 more" in err
    assert "not arm-0O3 (did you mean arm-003?), so no twin" in err, err
    assert "arm-020" not in err, err
    assert main(["calibration", "push", "robot-x", str(EXAMPLE)]) == cmd.EXIT_OK
    err = capsys.readouterr().err
    assert "not robot-x, so no twin" in err and "did you mean" not in err, err


@pytest.mark.parametrize(
    ("arm", "hint"),
    [
        ("ARM-007", " (did you mean arm-007?)"),  # case
        ("arm-l07", " (did you mean arm-107?)"),  # a letter l for a one
        ("arm-151", " (did you mean arm-051 or arm-101 or arm-111, or 4 more as close?)"),
        ("arm-0007", " (did you mean arm-007?)"),  # one character too many (difflib)
        ("robot-x", ""),
        ("a1", ""),  # a short id one character off another: as likely an id of its own
        ("ARM1", " (did you mean arm1?)"),
    ],
)
def test_the_ids_offered_for_a_slip_are_the_closest_and_say_when_more_are(arm: str, hint: str) -> None:
    """A review: difflib alone offered ids as close as many others (arm-013 for arm-0O3) and cut the rest off
    without a word."""
    assert cmd._nearest(arm, (*(f"arm-{n:03d}" for n in range(1, 151)), "b1", "arm1")) == hint


def kept_cycle(store_arg: list[str], store: Any, capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """push over another calibration, rm and restore keep what they replace (one per arm), for `store`."""
    newer = tmp_path / "newer.json"
    newer.write_bytes(shifted(100))
    push = ["calibration", "push", "arm-001"]
    # Each command the output names reaches this store: without --store it would reach the stack's.
    again = " " + shlex.join(store_arg)
    assert main([*push, str(EXAMPLE), *store_arg]) == cmd.EXIT_OK
    assert "kept at" not in capsys.readouterr().out and store.read_kept("arm-001") is None
    # The same file again writes nothing (the agent has nothing to read again).
    assert main([*push, str(EXAMPLE), *store_arg]) == cmd.EXIT_OK
    assert "already holds this calibration; nothing written" in capsys.readouterr().out
    # Over another: the one it replaces is kept, and is no arm's in the listing.
    assert main([*push, str(newer), *store_arg]) == cmd.EXIT_OK
    out = capsys.readouterr().out
    assert "the one it replaced is kept at" in out and f"twin calibration restore arm-001{again}`" in out, out
    assert store.read("arm-001") == shifted(100) and store.read_kept("arm-001") == EXAMPLE.read_bytes()
    assert list(store.listing()) == ["arm-001"] and set(store.scan().kept) == {"arm-001"}
    # ls shows the kept one beside the arm's own, before anyone needs it.
    place = store.uri_of("arm-001")
    assert main(["calibration", "ls", *store_arg]) == cmd.EXIT_OK
    listed = capsys.readouterr()
    assert listed.out == f"arm-001\t{place}\tkept: {place}.previous\n", listed.out
    assert f"twin calibration restore ARM{again}`" in listed.err
    # restore swaps them, and again swaps back.
    restore = ["calibration", "restore", "arm-001", *store_arg]
    assert main(restore) == cmd.EXIT_OK
    assert store.read("arm-001") == EXAMPLE.read_bytes() and store.read_kept("arm-001") == shifted(100)
    assert main(restore) == cmd.EXIT_OK
    assert store.read("arm-001") == shifted(100) and store.read_kept("arm-001") == EXAMPLE.read_bytes()
    capsys.readouterr()
    # rm keeps what it removes; restore puts it back and then has nothing more to put back.
    assert main(["calibration", "rm", "arm-001", *store_arg]) == cmd.EXIT_OK
    assert f"twin calibration restore arm-001{again}`" in capsys.readouterr().out
    assert store.listing() == {} and store.read_kept("arm-001") == shifted(100)
    assert main(["calibration", "ls", *store_arg]) == cmd.EXIT_OK
    assert capsys.readouterr().out == f"arm-001\t(removed)\tkept: {place}.previous\n"
    assert main(restore) == cmd.EXIT_OK
    assert "holds the calibration rm removed again" in capsys.readouterr().out
    assert store.read("arm-001") == shifted(100) and store.read_kept("arm-001") is None
    assert not store.scan().kept
    assert main(["calibration", "ls", *store_arg]) == cmd.EXIT_OK
    assert capsys.readouterr().out == f"arm-001\t{place}\n"
    assert main(restore) == cmd.EXIT_STORE
    err = capsys.readouterr().err
    assert "arm-001 has no kept calibration" in err and f"`twin calibration rm arm-001{again}`" in err, err
    assert store.read("arm-001") == shifted(100)


def kept_removed(store_arg: list[str], store: Any, capsys: pytest.CaptureFixture[str]) -> None:
    """After kept_cycle (arm-001 has a calibration, nothing kept): rm --kept takes away only the kept one, so
    an arm removed by mistake long ago no longer stays in `ls` for good."""
    again = " " + shlex.join(store_arg)
    rm_kept = ["calibration", "rm", "--kept", "arm-001", *store_arg]
    assert main(rm_kept) == cmd.EXIT_STORE
    assert "arm-001 has no kept calibration" in capsys.readouterr().err
    assert main(["calibration", "push", "arm-001", str(EXAMPLE), *store_arg]) == cmd.EXIT_OK
    assert main(["calibration", "ls", *store_arg]) == cmd.EXIT_OK
    assert f"`twin calibration rm --kept ARM{again}` removes it" in capsys.readouterr().err
    assert main(rm_kept) == cmd.EXIT_OK
    out = capsys.readouterr().out
    assert f"removed {store.uri_of('arm-001')}.previous; its own calibration stays" in out, out
    assert store.read("arm-001") == EXAMPLE.read_bytes() and store.read_kept("arm-001") is None
    # An arm removed, then its kept one: gone from the listing.
    assert main(["calibration", "rm", "arm-001", *store_arg]) == cmd.EXIT_OK
    assert main(rm_kept) == cmd.EXIT_OK
    assert "it has no calibration in the store now" in capsys.readouterr().out
    assert not store.scan().kept and store.listing() == {}
    assert main(["calibration", "ls", *store_arg]) == cmd.EXIT_OK
    assert capsys.readouterr().out == f"no calibration in {store.uri}\n"


def test_a_directory_store_keeps_what_push_and_rm_replace(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    kept_cycle(["--store", str(tmp_path / "cal")], DirectoryStore(tmp_path / "cal"), capsys, tmp_path)
    assert sorted(p.name for p in (tmp_path / "cal").iterdir()) == ["arm-001.json"]
    kept_removed(["--store", str(tmp_path / "cal")], DirectoryStore(tmp_path / "cal"), capsys)
    assert list((tmp_path / "cal").iterdir()) == []


def test_the_stacks_store_keeps_what_push_and_rm_replace(
    s3: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # moto stands in for S3 (AWS cannot be reached from here); the stack's bucket keeps no versions.
    store = open_store("s3://twin-bucket/calibration", s3_client=s3)
    kept_cycle(["--store", "s3://twin-bucket/calibration"], store, capsys, tmp_path)
    keys = [o["Key"] for o in s3.list_objects_v2(Bucket="twin-bucket")["Contents"]]
    assert keys == ["calibration/arm-001.json"]
    kept_removed(["--store", "s3://twin-bucket/calibration"], store, capsys)
    assert "Contents" not in s3.list_objects_v2(Bucket="twin-bucket")


def _pushed_twice(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> list[str]:
    """A directory store under `tmp_path` whose arm-001 was pushed EXAMPLE, then a shifted one (so the first
    is kept for a restore); its `--store` arguments."""
    newer = tmp_path / "newer.json"
    newer.write_bytes(shifted(100))
    store = ["--store", str(tmp_path / "cal")]
    for file in (EXAMPLE, newer):
        assert main(["calibration", "push", "arm-001", str(file), *store]) == cmd.EXIT_OK
    capsys.readouterr()
    return store


def test_a_restore_that_fails_halfway_saves_the_kept_calibration_here(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """restore keeps the current calibration in the kept one's place first; when writing the kept one back
    then fails, it exists only in the command's memory, so it is saved in the working directory."""
    store = _pushed_twice(tmp_path, capsys)

    def refused(self: DirectoryStore, device: str, data: bytes) -> str:
        raise CalibrationStoreError(f"cannot write to {self.uri}: disk full")

    monkeypatch.setattr(DirectoryStore, "write", refused)
    monkeypatch.chdir(tmp_path)
    assert main(["calibration", "restore", "arm-001", *store]) == cmd.EXIT_STORE
    err = capsys.readouterr().err
    saved = tmp_path / "arm-001.json.previous"
    assert f"saved in {saved}" in err and "disk full" in err, err
    assert saved.read_bytes() == EXAMPLE.read_bytes()
    assert DirectoryStore(tmp_path / "cal").read("arm-001") == shifted(100)


def test_a_restores_rescue_copy_does_not_replace_one_made_before(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The copy a failed restore saves is the kept calibration's only one; so is one an earlier failed restore
    saved in the same directory, which the next one wrote over."""
    store = _pushed_twice(tmp_path, capsys)
    earlier = tmp_path / "arm-001.json.previous"
    earlier.write_bytes(b"an earlier rescue's only copy")

    def refused(self: DirectoryStore, device: str, data: bytes) -> str:
        raise CalibrationStoreError(f"cannot write to {self.uri}: disk full")

    monkeypatch.setattr(DirectoryStore, "write", refused)
    monkeypatch.chdir(tmp_path)
    assert main(["calibration", "restore", "arm-001", *store]) == cmd.EXIT_STORE
    saved = tmp_path / "arm-001.json.previous.1"
    assert f"saved in {saved}" in capsys.readouterr().err
    assert saved.read_bytes() == EXAMPLE.read_bytes()
    assert earlier.read_bytes() == b"an earlier rescue's only copy"


def test_a_directory_restore_the_disk_refuses_halfway_saves_the_kept_calibration_here(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """As above with the error a directory store really meets (the disk filled between the two writes): an
    OSError from the disk is the store's error, so the kept calibration is saved rather than lost."""
    store = _pushed_twice(tmp_path, capsys)
    real = calibrations.write_atomically

    def disk_fills(path: Path, data: bytes) -> None:
        if path.name == "arm-001.json":
            raise OSError(errno.ENOSPC, "No space left on device")
        real(path, data)

    monkeypatch.setattr(calibrations, "write_atomically", disk_fills)
    monkeypatch.chdir(tmp_path)
    assert main(["calibration", "restore", "arm-001", *store]) == cmd.EXIT_STORE
    err = capsys.readouterr().err
    assert "No space left on device" in err and "Traceback" not in err, err
    assert (tmp_path / "arm-001.json.previous").read_bytes() == EXAMPLE.read_bytes()
    assert DirectoryStore(tmp_path / "cal").read("arm-001") == shifted(100)


def test_a_directory_store_syncs_before_the_rename_and_a_failed_write_leaves_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A write reaches the disk before it replaces the arm's file (a power cut must not leave it empty), and
    a write the disk refuses is the store's error, leaving the old file and no temporary one."""
    store = DirectoryStore(tmp_path)
    store.write("arm-001", EXAMPLE.read_bytes())

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(CalibrationStoreError, match="No space left on device"):
        store.write("arm-001", shifted(100))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arm-001.json"]
    assert store.read("arm-001") == EXAMPLE.read_bytes()


def test_a_file_named_for_another_arm_is_stored_with_a_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # LeRobot names each file for the arm it calibrated: arm-002's file pushed as arm-003 is likely a slip.
    own = tmp_path / "arm-002.json"
    own.write_bytes(shifted(40))
    store = ["--store", str(tmp_path / "cal")]
    assert main(["calibration", "push", "arm-003", str(own), *store]) == cmd.EXIT_OK
    assert "warning" not in capsys.readouterr().err  # arm-002 has no calibration in the store
    assert main(["calibration", "push", "arm-002", str(own), *store]) == cmd.EXIT_OK
    assert main(["calibration", "push", "arm-004", str(own), *store]) == cmd.EXIT_OK
    err = capsys.readouterr().err
    assert "arm-002.json is named for arm-002, which has a calibration of its own" in err, err
    # arm-004 had none, so nothing was kept for restore: rm undoes it, in the store just written to.
    again = " " + shlex.join(store)
    assert "stored as arm-004's" in err and f"`twin calibration rm arm-004{again}`" in err, err
    assert DirectoryStore(tmp_path / "cal").read("arm-004") == shifted(40)
    # Over an arm's own calibration, push keeps it, so restore undoes the slip.
    assert main(["calibration", "push", "arm-003", str(EXAMPLE), *store]) == cmd.EXIT_OK
    assert main(["calibration", "push", "arm-003", str(own), *store]) == cmd.EXIT_OK
    assert f"`twin calibration restore arm-003{again}`" in capsys.readouterr().err
    assert main(["calibration", "restore", "arm-003", *store]) == cmd.EXIT_OK
    assert DirectoryStore(tmp_path / "cal").read("arm-003") == EXAMPLE.read_bytes()
    # An arm whose own was removed has it kept: rm would keep the slip in its place, so that is not the undo.
    assert main(["calibration", "rm", "arm-003", *store]) == cmd.EXIT_OK
    capsys.readouterr()
    assert main(["calibration", "push", "arm-003", str(own), *store]) == cmd.EXIT_OK
    err = capsys.readouterr().err
    assert "keeps it in place of the calibration kept from before" in err, err
    assert "save that one first" in err, err
    assert DirectoryStore(tmp_path / "cal").read_kept("arm-003") == EXAMPLE.read_bytes()
    # The same file again writes nothing, and warns of no slip.
    assert main(["calibration", "push", "arm-003", str(own), *store]) == cmd.EXIT_OK
    out, err = capsys.readouterr()
    assert "nothing written" in out and "warning" not in err, err


def test_the_calibration_another_arm_has_is_stored_with_a_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk: arm-001's file pushed as arm-002 too (a copy, under a name of no arm) was stored without a
    word, and arm-002's twin then took arm-001's angles."""
    store = ["--store", str(tmp_path / "cal")]
    first, other = tmp_path / "follower.json", tmp_path / "other.json"
    first.write_bytes(EXAMPLE.read_bytes())
    other.write_bytes(shifted(40))
    assert main(["calibration", "push", "arm-001", str(first), *store]) == cmd.EXIT_OK
    assert main(["calibration", "push", "arm-003", str(other), *store]) == cmd.EXIT_OK
    assert "warning" not in capsys.readouterr().err
    assert main(["calibration", "push", "arm-002", str(first), *store]) == cmd.EXIT_OK
    err = capsys.readouterr().err
    assert "follower.json is the calibration arm-001 already has in" in err, err
    assert "one of arm-002 and arm-001 has the other's" in err, err
    assert "`twin calibration rm arm-002 --store" in err, err
    assert DirectoryStore(tmp_path / "cal").read("arm-002") == EXAMPLE.read_bytes()  # stored, as asked
    # Two arms hold it now: the warning names both, as a sentence (it read "arm-001, arm-002 already has").
    assert main(["calibration", "push", "arm-004", str(first), *store]) == cmd.EXIT_OK
    err = capsys.readouterr().err
    assert "follower.json is the calibration arm-001 and arm-002 already have in" in err, err
    assert "one of arm-004, arm-001 and arm-002 has another's" in err, err


def test_pushing_an_arms_own_file_that_another_arm_holds_names_both_and_blames_neither(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # arm-002's file went to arm-003 by mistake; pushing it as arm-002's, where it belongs, was told to "push
    # arm-002's own file", the very one being pushed: the slip was arm-003's.
    store = ["--store", str(tmp_path / "cal")]
    own = tmp_path / "arm-002.json"
    own.write_bytes(shifted(40))
    assert main(["calibration", "push", "arm-003", str(own), *store]) == cmd.EXIT_OK
    capsys.readouterr()
    assert main(["calibration", "push", "arm-002", str(own), *store]) == cmd.EXIT_OK
    err = capsys.readouterr().err
    assert "push arm-002's own file" not in err, err
    assert "one of arm-002 and arm-003 has the other's" in err, err
    assert "arm-002.json is named for arm-002, so arm-003's may be the copy" in err, err


def test_pushing_the_example_calibration_says_it_was_measured_on_no_arm(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk: the example that comes with the model, pushed for a real arm, gave no word that it is no
    arm's (its README says so; the push did not). Laid out anew it is still the example."""
    store = ["--store", str(tmp_path / "cal")]
    relaid = tmp_path / "my-arm.json"
    relaid.write_text(json.dumps(json.loads(EXAMPLE.read_text()), indent=None, sort_keys=True))
    for file in (EXAMPLE, relaid):
        assert main(["calibration", "push", "arm-001", str(file), *store]) == cmd.EXIT_OK
        err = capsys.readouterr().err
        assert f"note: {file} holds the example calibration that comes with the model" in err, err
    own = tmp_path / "own.json"
    own.write_bytes(shifted(40))
    assert main(["calibration", "push", "arm-001", str(own), *store]) == cmd.EXIT_OK
    assert "example" not in capsys.readouterr().err


def test_without_aws_push_names_the_store_of_an_agent_on_this_machine(
    aws_env: None, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # A laptop without AWS: the user likelier means their own agent's store than the stack's.
    monkeypatch.delenv("AWS_DEFAULT_REGION")
    assert main(["calibration", "push", "arm-001", str(EXAMPLE)]) == cmd.EXIT_SETUP
    err = capsys.readouterr().err
    assert "no AWS region configured" in err and "--store DIR" in err, err
    assert "[telemetry] calibrations" in err, err


# --- the agent --------------------------------------------------------------------------------------------


def agent_with_store(store: Path | str, **overrides: Any) -> AgentService:
    config = load_config(
        None,
        {
            "broker.url": NO_BROKER,  # nobody answers: fed through feed()
            "http.listen": "127.0.0.1:0",
            "telemetry.devices": ["arm-001", "arm-002"],
            "telemetry.units": "ticks",
            "telemetry.calibrations": str(store),
            "telemetry.calibration_poll_s": 1.0,
            **overrides,
        },
    )
    return AgentService(config, workers=int(overrides.get("twin.workers", 1)))


def feed_until(agent: AgentService, device: str, expected_pan: float, ts: list[int]) -> None:
    """Feed `device` fresh ticks until its twin shows shoulder_pan at `expected_pan` (a poll may come
    between)."""

    def shown() -> bool:
        ts[0] += 100
        agent.feed(f"dt/lerobot/{device}/telemetry", ticks_message(device, ts[0]))
        joints = agent.state().devices.get(device)
        pan = (joints.joints_rad or {}).get("shoulder_pan") if joints else None
        return pan is not None and abs(pan - expected_pan) < 1e-9

    wait_for(shown, 60, f"{device}'s twin at shoulder_pan {expected_pan:.6f}", interval=0.1)


@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_each_arm_decodes_with_its_own_and_a_new_one_needs_no_restart(tmp_path: Path, workers: int) -> None:
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    agent = agent_with_store(tmp_path / "cal", **{"twin.workers": workers})
    agent.start()
    try:
        ts = [int(time.time() * 1000)]
        feed_until(agent, "arm-001", pan_angle(EXAMPLE.read_bytes()), ts)
        feed_until(agent, "arm-002", pan_angle(None), ts)
        devices = agent.state().devices
        assert devices["arm-001"].calibration == str(tmp_path / "cal" / "arm-001.json")
        assert not devices["arm-001"].uncalibrated
        assert devices["arm-002"].calibration == "" and devices["arm-002"].uncalibrated
        # A calibration for arm-002 arrives while the agent runs: picked up within a poll, no restart.
        store.write("arm-002", shifted(100))
        feed_until(agent, "arm-002", pan_angle(shifted(100)), ts)
        assert not agent.state().devices["arm-002"].uncalibrated
        # A broken upload is refused and said so; the arm keeps decoding with the one it had.
        (tmp_path / "cal" / "arm-002.json").write_text("{broken")
        wait_for(lambda: agent.state().devices["arm-002"].calibration_problem, 30, "the refusal in /state")
        feed_until(agent, "arm-002", pan_angle(shifted(100)), ts)
        kinds = {(e.device, e.data.get("action")) for e in agent.events(_calibration_events())}
        assert {("arm-001", "picked up"), ("arm-002", "picked up"), ("arm-002", "refused")} <= kinds
        (refused,) = [e for e in agent.events(_calibration_events()) if e.data.get("action") == "refused"]
        push = f"twin calibration push arm-002 FILE --store {tmp_path / 'cal'}"
        assert refused.message.endswith(f"; push a good file: {push}"), refused.message
        # Kept only until the agent starts again, which holds the arm: the page said only "kept".
        assert "it keeps the one it had until the agent starts again" in refused.message, refused.message
        # Its Fleet row says so (the row is its mirror's own, not cut from the whole state).
        rows = {row.device: row for row in agent.fleet_rows()}
        assert rows["arm-002"].calibration_refused and not rows["arm-001"].calibration_refused
        # Pushed under an id this agent does not mirror (a typo): picked up, but said to be of no use.
        store.write("arm-0O2", shifted(100))
        typo = wait_for(lambda: _picked_up(agent, "arm-0O2"), 30, "arm-0O2's calibration event")
        assert typo.level == "warning" and "not in this agent's telemetry.devices" in typo.message, typo
        assert "never used" in typo.message
        store.write("Arm-002", shifted(100))
        case = wait_for(lambda: _picked_up(agent, "Arm-002"), 30, "Arm-002's calibration event")
        assert "did you mean arm-002?" in case.message, case
        # The arms it mirrors and has heard picked theirs up with no such word.
        assert all(e.level == "info" for e in _picked_up_all(agent) if e.device not in ("arm-0O2", "Arm-002"))
    finally:
        agent.stop()


@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_an_arm_whose_file_is_bad_at_the_start_is_held_until_a_good_one_comes(
    tmp_path: Path, workers: int
) -> None:
    """A walk: a bad file copied over an arm's good one was refused while the agent ran, but after a restart
    the arm decoded with the config's calibration, another arm's: 22 degrees off, shown as live."""
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    (tmp_path / "cal" / "arm-002.json").write_text('{"shoulder_pan": {}}')
    # An arm this listed fleet leaves out: the Fleet page named it held, its messages "refused".
    (tmp_path / "cal" / "arm-009.json").write_text('{"shoulder_pan": {}}')
    agent = agent_with_store(tmp_path / "cal", **{"twin.workers": workers})
    agent.start()
    try:
        ts = [int(time.time() * 1000)]
        feed_until(agent, "arm-001", pan_angle(EXAMPLE.read_bytes()), ts)

        def held() -> bool:
            ts[0] += 100
            agent.feed("dt/lerobot/arm-002/telemetry", ticks_message("arm-002", ts[0]))
            arm = agent.state().devices.get("arm-002")
            return arm is not None and arm.health.counters.rejected.get("calibration_refused", 0) >= 3

        wait_for(held, 60, "arm-002's messages refused as calibration_refused", interval=0.1)
        arm = agent.state().devices["arm-002"]
        assert arm.joints_rad is None, arm.joints_rad  # never moved, to no pose at all
        assert arm.uncalibrated and "shoulder_pan" in arm.calibration_problem, arm.calibration_problem
        # A walk: with a card (this fleet is listed), its Arm page said it decodes with the nominal SO-101.
        assert "shoulder_pan" in agent.arm_view("arm-002").calibration_refused
        assert agent.arm_view("arm-001").calibration_refused == ""
        # The Fleet page names it (no card would, with the whole fleet subscribed); /healthz does not.
        # Each command it names reaches this agent's store: without --store, push writes to the stack's.
        option = f"--store {tmp_path / 'cal'}"
        (held_notice,) = [n for n in agent.notices() if n.startswith("arm-002's calibration")]
        assert not [n for n in agent.notices() if "arm-009" in n], agent.notices()
        assert f"twin calibration push arm-002 FILE {option}" in held_notice, held_notice
        # Its pose waits for a good file, its servos do not: the notice must not leave the operator thinking
        # the arm unwatched.
        assert "its servos' alarms are still checked" in held_notice, held_notice
        # Listed, its refusals are on its card: asked without the cards, the notice must not say nothing
        # came from it (a review), nor ask every worker for its rows.
        assert "nothing has been received" not in held_notice, held_notice
        rejected = EventQuery(kinds=frozenset({"rejected"}), device="arm-002")
        refused = wait_for(lambda: agent.events(rejected), 30, "arm-002's rejected event")
        # Nothing is kept for arm-002, so no restore is offered: it would only exit 1.
        assert f"twin calibration push arm-002 FILE {option}`" in refused[-1].message, refused
        assert "restore" not in refused[-1].message, refused
        # Once a calibration is kept for it, the refusal offers to put it back (the next poll hands it on).
        store.write_kept("arm-002", shifted(50))

        def offered() -> bool:
            ts[0] += 100
            agent.feed("dt/lerobot/arm-002/telemetry", ticks_message("arm-002", ts[0]))
            return any("twin calibration restore arm-002" in e.message for e in agent.events(rejected))

        wait_for(offered, 30, "arm-002's refusal offering a restore", interval=0.1)
        assert not [r for r in agent.healthz().reasons if "calibration" in r]
        # A good file, and the arm is mirrored with it, no restart.
        store.write("arm-002", shifted(100))
        feed_until(agent, "arm-002", pan_angle(shifted(100)), ts)
        assert not [n for n in agent.notices() if "calibration" in n]
    finally:
        agent.stop()


@pytest.mark.parametrize(
    ("workers", "units"), [(1, "ticks"), (2, "ticks"), (1, "auto")], ids=["in-process", "two-workers", "auto"]
)
def test_a_held_arms_servos_are_still_watched(tmp_path: Path, workers: int, units: str) -> None:
    """A walk: a held arm's elbow servo passed 65 C with no alarm while the other arm raised two: its servo
    readings were refused with its pose. They need no calibration: its alarms are raised and named as any
    arm's (log, /alarms, events), while its twin still holds still."""
    from test_alerts import hot

    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "arm-002.json").write_text('{"shoulder_pan": {}}')
    settings = {"twin.workers": workers, "telemetry.units": units, "alarms.temperature_raise_after_s": 0.0}
    agent = agent_with_store(tmp_path / "cal", **settings)
    agent.start()
    try:
        ts = [int(time.time() * 1000)]

        def refused(count: int) -> bool:
            arm = agent.state().devices.get("arm-002")
            return arm is not None and arm.health.counters.rejected.get("calibration_refused", 0) >= count

        # Readings older than the newest judged (a replayed backlog, a redelivery) raise nothing.
        agent.feed("dt/lerobot/arm-002/telemetry", hot("arm-002", ts[0], 35))
        wait_for(lambda: refused(1), 60, "arm-002's first message refused", interval=0.1)
        for back in (3, 2, 1):
            agent.feed("dt/lerobot/arm-002/telemetry", hot("arm-002", ts[0] - 100 * back, 68))
        wait_for(lambda: refused(4), 60, "arm-002's old messages refused", interval=0.1)
        assert not [a for a in agent.alarms() if a.device == "arm-002"], agent.alarms()

        def raised() -> list[Any] | None:
            ts[0] += 100
            agent.feed("dt/lerobot/arm-002/telemetry", hot("arm-002", ts[0], 68))
            found = [a for a in agent.alarms() if a.device == "arm-002" and a.state == "ACTIVE"]
            return found if len(found) == 2 else None

        alarms = wait_for(raised, 60, "arm-002's heat alarms", interval=0.1)
        kinds = {("elbow_flex", "over_temperature"), ("elbow_flex", "over_temperature_critical")}
        assert {(a.joint, a.kind) for a in alarms} == kinds, alarms
        arm = agent.state().devices.get("arm-002")
        assert arm is None or arm.joints_rad is None  # held: no pose, whatever its servos say
        # Listed, it has a card, which says "held" (a review: under auto it read "file refused").
        (row,) = [r for r in agent.fleet_rows() if r.device == "arm-002"]
        assert row.uncalibrated and row.calibration_refused, row
        # ... and is not also listed among the held arms with no card, whose alarms the counts add again.
        parts = console.fleet_parts(agent)
        assert "arm-002" in {r.device for r in parts.rows} and not parts.held, parts.held
        # On the Events page too (collected from the mirrors every half second), where alerts come from.
        told = EventQuery(kinds=frozenset({"alarm"}), device="arm-002")
        wait_for(lambda: [e for e in agent.events(told) if "elbow_flex" in e.message], 30, "its alarm events")
    finally:
        agent.stop()


@pytest.mark.parametrize("units", ["auto", "degrees"])
def test_an_arm_publishing_degrees_has_its_card_and_no_held_notice(tmp_path: Path, units: str) -> None:
    """Degrees use no calibration: such an arm with a refused file at the start decodes (the decoder's rule),
    and the Fleet page must not also say it is held, nor the Events page that its twin holds still."""
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "arm-002.json").write_text('{"shoulder_pan": {}}')
    agent = agent_with_store(tmp_path / "cal", **{"telemetry.units": units, "twin.workers": 1})
    agent.start()
    try:
        ts = [int(time.time() * 1000)]
        # Degrees (negative, so units=auto knows them), the gripper in 0..100 percent as LeRobot sends it.
        joints = {name: {"position": -12.5} for name in so101.JOINT_NAMES}
        joints["gripper"] = {"position": 40.0}

        def decoded() -> bool:
            ts[0] += 100
            message = {"device_id": "arm-002", "timestamp": ts[0], "joints": joints}
            agent.feed("dt/lerobot/arm-002/telemetry", json.dumps(message).encode())
            arm = agent.state().devices.get("arm-002")
            return arm is not None and arm.joints_rad is not None

        wait_for(decoded, 60, "arm-002's degrees decoded", interval=0.1)
        rows, notices, _, _ = console.fleet_parts(agent)
        assert "arm-002" in {row.device for row in rows}
        # Nor its page that the agent holds it (a review: it did, under auto, of a twin that moved).
        assert agent.arm_view("arm-002").calibration_refused == "", agent.arm_view("arm-002")
        assert not [n for n in notices if n.startswith("arm-002's calibration")], notices
        refused = EventQuery(kinds=frozenset({"calibration"}), device="arm-002")
        (event,) = wait_for(lambda: agent.events(refused), 30, "arm-002's refused calibration event")
        said = "which changes nothing" if units == "degrees" else "unless it publishes degrees"
        assert said in event.message, event.message
        # Asked without the page's cards: under auto the arm is named (its units are the message's to say),
        # with units = degrees no arm is ever held.
        named = [n for n in agent.notices() if n.startswith("arm-002's calibration")]
        assert len(named) == (0 if units == "degrees" else 1), named
    finally:
        agent.stop()


def _picked_up_all(agent: AgentService) -> list[Any]:
    return [e for e in agent.events(_calibration_events()) if e.data.get("action") == "picked up"]


def _picked_up(agent: AgentService, device: str) -> Any:
    return next((e for e in _picked_up_all(agent) if e.device == device), None)


def test_a_calibration_for_an_arm_not_heard_yet_says_so(tmp_path: Path) -> None:
    """With the whole fleet subscribed, a push under an id no message came from may be a new arm or a typo:
    the event says which ids the Fleet page knows; an arm heard before gets no such word."""
    store = DirectoryStore(tmp_path / "cal")
    agent = agent_with_store(tmp_path / "cal", **{"telemetry.devices": ["*"]})
    agent.start()
    try:
        ts = [int(time.time() * 1000)]
        feed_until(agent, "arm-001", pan_angle(None), ts)
        store.write("arm-001", shifted(100))
        store.write("arm-0O1", shifted(100))
        store.write("ARM-001", shifted(100))  # a walk: the arm publishes as arm-001, and nothing said so
        heard = wait_for(lambda: _picked_up(agent, "arm-001"), 30, "arm-001's calibration event")
        unheard = wait_for(lambda: _picked_up(agent, "arm-0O1"), 30, "arm-0O1's calibration event")
        upper = wait_for(lambda: _picked_up(agent, "ARM-001"), 30, "ARM-001's calibration event")
        assert heard.level == "info" and "no message" not in heard.message, heard
        assert unheard.level == "warning" and "no message from arm-0O1 yet" in unheard.message, unheard
        assert "case-sensitive" not in unheard.message, unheard
        assert "ids are case-sensitive: did you mean arm-001?" in upper.message, upper
    finally:
        agent.stop()


def test_one_rule_says_whose_card_is_held() -> None:
    """The mirror's rows and the rows read from a restarting worker's checkpoint had each their own copy of
    when a card's `uncalibrated` is on (with `calibration_refused`, "held"): one function now decides."""
    rule = console.card_uncalibrated
    assert rule(False, True, Units.TICKS) and rule(False, True, Units.AUTO) and rule(False, True, None)
    assert not rule(False, True, Units.DEGREES)  # degrees use no calibration: such an arm is not held
    assert rule(True, False, Units.TICKS) and rule(True, True, Units.DEGREES)  # /state's own flag stands
    assert not rule(False, False, Units.TICKS)


def test_a_held_arms_card_says_held_while_its_worker_is_started_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A held arm's card, drawn from its worker's checkpoint while the worker was started again, read "file
    refused, it keeps the one it had": with the config's calibration for every arm, /state's flag is off.
    It says held there too, as the running worker's row does. The new process waits here to be launched."""
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "arm-002.json").write_text('{"shoulder_pan": {}}')
    settings = {"twin.workers": 2, "telemetry.calibration": str(EXAMPLE)}
    agent = agent_with_store(tmp_path / "cal", **settings)
    release = threading.Event()
    agent.start()
    try:
        shard = agent._shards[agent.plan.worker_of("arm-002")]
        ts = [int(time.time() * 1000)]

        def refused_and_kept() -> bool:
            ts[0] += 100
            agent.feed("dt/lerobot/arm-002/telemetry", ticks_message("arm-002", ts[0]))
            arm = agent.state().devices.get("arm-002")
            checkpoint = shard.checkpoint
            held = arm is not None and arm.health.counters.rejected.get("calibration_refused", 0) >= 1
            return held and checkpoint is not None and "arm-002" in checkpoint.devices

        wait_for(refused_and_kept, 60, "arm-002 refused, in its worker's checkpoint", interval=0.1)
        assert _row(agent, "arm-002").uncalibrated  # the running worker's row: held
        launch = shard.launch

        def held_launch() -> None:
            release.wait(120)
            launch()

        monkeypatch.setattr(shard, "launch", held_launch)
        os.kill(shard.pid, signal.SIGKILL)
        wait_for(lambda: _row(agent, "arm-002").mirror == "restarting", 60, "arm-002 restarting")
        row = _row(agent, "arm-002")
        assert row.uncalibrated and row.calibration_refused, row
        release.set()
        wait_for(lambda: shard.restarts == 1 and shard.answering, 120, "the worker running again")
    finally:
        release.set()
        agent.stop()


def test_a_held_arms_refused_messages_stay_counted_when_its_worker_is_started_again(
    tmp_path: Path,
) -> None:
    """A held arm's refused messages are counted among the arms not tracked, and the Fleet page reads the
    count from its worker's checkpoint: a worker started again after a crash began with none, so the held
    arm's link said "none heard" though the count was in the checkpoint it was started from."""
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "arm-002.json").write_text('{"shoulder_pan": {}}')
    agent = agent_with_store(tmp_path / "cal", **{"twin.workers": 2, "telemetry.devices": ["*"]})
    agent.start()
    try:
        shard = agent._shards[agent.plan.worker_of("arm-002")]
        ts = int(time.time() * 1000)
        for step in range(5):
            agent.feed("dt/lerobot/arm-002/telemetry", ticks_message("arm-002", ts + 100 * step))

        def checkpointed(since: float = 0.0) -> int | None:
            checkpoint = shard.checkpoint
            if checkpoint is None or checkpoint.at <= since:
                return None
            return sum(a.rejected for a in checkpoint.unheard if a.device == "arm-002")

        # All five in the checkpoint: nothing is sent again to the new process, which starts from it alone.
        wait_for(lambda: checkpointed() == 5, 60, "all five refused in arm-002's worker's checkpoint")
        assert [h.refused for h in agent.held_arms()] == [5]
        os.kill(shard.pid, signal.SIGKILL)
        wait_for(lambda: shard.restarts == 1 and shard.answering, 120, "the worker running again")
        again = time.monotonic()  # worker processes share the host's monotonic clock
        wait_for(lambda: checkpointed(again) is not None, 60, "a checkpoint of the new process")
        assert checkpointed(again) == 5
        assert [h.refused for h in agent.held_arms()] == [5]
    finally:
        agent.stop()


def test_a_held_arm_nothing_was_received_from_is_not_said_to_have_its_messages_refused(
    tmp_path: Path,
) -> None:
    """A walk: a held arm switched off was said to have "its messages refused", in the Fleet page's notice
    and on its page, which sent the operator looking for refused messages. Said of it: nothing received
    yet; of one publishing, its messages refused, how many and when the last came (on its page)."""
    (tmp_path / "cal").mkdir()
    for device in ("arm-002", "arm-004"):
        (tmp_path / "cal" / f"{device}.json").write_text('{"shoulder_pan": {}}')
    agent = agent_with_store(tmp_path / "cal", **{"telemetry.devices": ["*"]})
    agent.start()
    try:
        ts = int(time.time() * 1000)
        for step in range(3):
            agent.feed("dt/lerobot/arm-002/telemetry", ticks_message("arm-002", ts + 100 * step))
        wait_for(lambda: agent.arm_view("arm-002").refused is not None, 60, "arm-002's refused messages")
        (fed,) = [n for n in agent.notices() if n.startswith("arm-002")]
        (silent,) = [n for n in agent.notices() if n.startswith("arm-004")]
        assert "so its messages are refused" in fed, fed
        assert "nothing has been received from it" in silent and "so its messages are" not in silent
        assert "twin calibration push arm-004 FILE" in silent, silent
        count, age_s = agent.arm_view("arm-002").refused or (0, 0.0)
        assert count == 3 and age_s >= 0.0
        assert agent.arm_view("arm-004").refused is None
        doc = json.loads(console.arm_document("arm-002", agent.arm_view("arm-002")))
        assert doc["refused"]["count"] == 3, doc["refused"]
        # Whether the broker limits each connection reaches the Arm page, which names a connection's quota
        # as a cause of steady gaps only then (a local broker has none, and the page blamed IoT Core's).
        assert doc["per_connection_limit"] is False, doc
        limited = agent_with_store(tmp_path / "cal", **{"broker.per_connection_limit": 100})
        assert limited.arm_view("arm-002").per_connection_limit is True
    finally:
        agent.stop()


def test_an_arm_no_longer_held_leaves_the_refused_ids_kept_beside_the_cap(tmp_path: Path) -> None:
    """A review: an id refused for its calibration was kept beside the 64 newest other refused ids for good,
    also once its file was removed. The mirror tells its fleet which ids are held now."""
    (tmp_path / "cal").mkdir()
    bad = tmp_path / "cal" / "arm-002.json"
    bad.write_text('{"shoulder_pan": {}}')
    agent = agent_with_store(tmp_path / "cal", **{"telemetry.devices": ["*"]})
    agent.start()
    try:
        agent.feed("dt/lerobot/arm-002/telemetry", ticks_message("arm-002", int(time.time() * 1000)))
        wait_for(lambda: agent.arm_view("arm-002").refused is not None, 60, "arm-002's refused message")
        bad.unlink()
        wait_for(lambda: agent.arm_view("arm-002").calibration_refused == "", 60, "arm-002 no longer held")
        for n in range(64):
            agent.feed(f"dt/lerobot/junk-{n:03d}/telemetry", b"not json")
        unheard = agent._unheard_arms  # type: ignore[attr-defined]
        ids = lambda: {a.device for a in unheard()}  # noqa: E731
        # hold() runs on the watcher thread after the held set the view reads is swapped: wait for both.
        wait_for(lambda: "junk-063" in ids() and "arm-002" not in ids(), 60, "arm-002 among the 64 others")
    finally:
        agent.stop()


def _row(agent: AgentService, device: str) -> console.FleetRow:
    (row,) = [r for r in agent.fleet_rows() if r.device == device]
    return row


def test_a_console_tick_asks_only_the_held_arms_mirror_for_their_alarms(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The Fleet page counts and links a held arm's alarms (it has no card): each tick, twice a second, asked
    every worker for all its alarms to find them. Only the held arm's worker is asked."""
    from test_alerts import hot

    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "arm-002.json").write_text('{"shoulder_pan": {}}')
    settings = {"twin.workers": 2, "telemetry.devices": ["*"], "alarms.temperature_raise_after_s": 0.0}
    agent = agent_with_store(tmp_path / "cal", **settings)
    agent.start()
    try:
        ts = [int(time.time() * 1000)]

        def raised() -> bool:
            ts[0] += 100
            agent.feed("dt/lerobot/arm-002/telemetry", hot("arm-002", ts[0], 68))
            return len([a for a in agent.alarms() if a.device == "arm-002"]) == 2

        wait_for(raised, 60, "arm-002's heat alarms", interval=0.1)
        asked: list[int] = []
        for shard in agent._shards:

            def counted(request: Any, shard: Any = shard, ask: Any = shard.request) -> Any:
                if isinstance(request, AlarmsRequest):
                    asked.append(shard.index)
                return ask(request)

            monkeypatch.setattr(shard, "request", counted)
        # Its refused messages counted, from its worker's checkpoint (within a second): "none heard" is for
        # a held arm that sent nothing.
        wait_for(lambda: agent.held_arms()[0].refused >= 1, 60, "arm-002's refused messages counted")
        asked.clear()
        (held,) = agent.held_arms()
        assert held.device == "arm-002" and held.unacknowledged == 2, held
        assert asked == [agent.plan.worker_of("arm-002")], asked
    finally:
        agent.stop()


@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_a_good_file_for_a_held_arm_does_not_say_it_was_never_heard(tmp_path: Path, workers: int) -> None:
    """A walk: with the whole fleet subscribed, an arm held by a bad file at the start has no card, and the
    good file pushed for it said "no message from arm-002 yet" while its refused messages were counted. A
    worker process tells its refused arms in its checkpoints (every second): within a second of an arm's
    first message the warning can still come, so the push waits for the agent to know the arm."""
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "arm-002.json").write_text('{"shoulder_pan": {}}')
    agent = agent_with_store(tmp_path / "cal", **{"telemetry.devices": ["*"], "twin.workers": workers})
    agent.start()
    try:
        ts = [int(time.time() * 1000)]

        def held() -> bool:
            ts[0] += 100
            agent.feed("dt/lerobot/arm-002/telemetry", ticks_message("arm-002", ts[0]))
            refused = agent.state().untracked_rejected.get("calibration_refused", 0) >= 3
            return refused and any(arm.device == "arm-002" for arm in agent._unheard_arms())

        wait_for(held, 60, "arm-002's messages refused as calibration_refused", interval=0.1)
        DirectoryStore(tmp_path / "cal").write("arm-002", shifted(100))
        event = wait_for(lambda: _picked_up(agent, "arm-002"), 30, "arm-002's calibration event")
        assert event.level == "info" and "no message" not in event.message, event
    finally:
        agent.stop()


@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_messages_that_arrive_while_the_mirrors_start_decode_with_the_arms_own(
    tmp_path: Path, workers: int
) -> None:
    """The broker connection starts before the mirrors are ready (a cold start overlaps them), so messages can
    arrive before the arm's calibration is read: they wait for it. Here they are queued before start()."""
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    agent = agent_with_store(tmp_path / "cal", **{"twin.workers": workers})
    ts = int(time.time() * 1000)
    for k in range(3):
        agent.feed("dt/lerobot/arm-001/telemetry", ticks_message("arm-001", ts + 100 * k))
    agent.start()
    try:
        state = wait_for(
            lambda: (
                (s := agent.state()).devices.get("arm-001")
                and s.devices["arm-001"].health.counters.applied == 3
                and s
            ),
            60,
            "arm-001's three queued messages applied",
            interval=0.05,
        )
        pan = (state.devices["arm-001"].joints_rad or {})["shoulder_pan"]
        assert abs(pan - pan_angle(EXAMPLE.read_bytes())) < 1e-9
        assert state.devices["arm-001"].calibration == str(tmp_path / "cal" / "arm-001.json")
    finally:
        agent.stop()


def create_stack(calibration_uri: str, **outputs: Any) -> None:
    """A stack in moto whose CalibrationUri output is `calibration_uri` (what a plain push writes to), with
    `outputs` besides."""
    template = {
        "Resources": {"Topic": {"Type": "AWS::SNS::Topic"}},
        "Outputs": {
            "InstanceId": {"Value": "i-0123456789abcdef0"},
            "DcvUrl": {"Value": "https://192.0.2.1:8443/#console"},
            "CalibrationUri": {"Value": calibration_uri},
            **outputs,
        },
    }
    boto3.client("cloudformation", region_name=AWS_TEST_REGION).create_stack(
        StackName="So101TwinStack", TemplateBody=json.dumps(template)
    )


def arm_flagged(agent: AgentService, device: str) -> bool:
    state = agent.state().devices.get(device)
    return state is not None and state.uncalibrated


def arm_document(agent: AgentService, device: str) -> dict[str, Any]:
    """GET /api/arm/<device> (what the console's Arm page reads) once the agent flags the arm uncalibrated."""
    agent.feed(f"dt/lerobot/{device}/telemetry", ticks_message(device, int(time.time() * 1000)))
    wait_for(
        lambda: (d := agent.state().devices.get(device)) and d.uncalibrated, 30, f"{device} uncalibrated"
    )
    status, _, body = http_get(f"{agent.http_url}/api/arm/{device}")
    assert status == 200, body
    return dict(json.loads(body))


@pytest.mark.parametrize("store", ["directory", "stack", "none"])
def test_the_arm_document_says_how_to_push_to_the_store_this_agent_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, request: pytest.FixtureRequest, store: str
) -> None:
    """The Arm page's hint is the command that gives the arm a calibration this very agent picks up: `--store`
    with the agent's own directory (absolute: the agent resolved it in its working directory), the plain
    command for the stack's bucket (it writes to the stack's CalibrationUri), and for an agent without a
    store, the setting to set first."""
    monkeypatch.chdir(tmp_path)
    setting = {"directory": "cal", "stack": "s3://twin-bucket/calibration", "none": ""}[store]
    if store == "stack":
        request.getfixturevalue("s3")
        create_stack(setting)
    agent = agent_with_store(setting)
    agent.start()
    try:
        push = arm_document(agent, "arm-002")["calibration_push"]
        expected = {
            "directory": f"twin calibration push arm-002 FILE --store {shlex.quote(str(tmp_path / 'cal'))}",
            "stack": "twin calibration push arm-002 FILE",
            "none": "twin calibration push arm-002 FILE --store DIR",
        }[store]
        assert push["command"] == expected and expected in push["text"], push
        assert push["store"] == {"directory": str(tmp_path / "cal"), "stack": setting, "none": ""}[store]
        assert agent.state().agent.calibration_store == push["store"]
        if store == "none":
            assert "reads no per-arm calibrations" in push["text"]
            assert '[telemetry] calibrations = "DIR"' in push["text"], push
            return
        # The command as the page shows it, run from elsewhere: the agent picks the file up, no restart.
        monkeypatch.chdir(tmp_path.parent)
        argv = [EXAMPLE.as_posix() if a == "FILE" else a for a in shlex.split(push["command"])]
        assert main(argv[1:]) == cmd.EXIT_OK
        feed_until(agent, "arm-002", pan_angle(EXAMPLE.read_bytes()), [int(time.time() * 1000) + 100])
        assert not agent.state().devices["arm-002"].uncalibrated
    finally:
        agent.stop()


def _calibration_events() -> Any:
    from twin.service.events import EventQuery

    return EventQuery(kinds=frozenset({"calibration"}))


def degrees_arm(store: Path) -> Any:
    """arm-001 as /state shows it, in an agent with units = degrees over `store`, once a message decoded."""
    agent = agent_with_store(store, **{"telemetry.units": "degrees"})
    agent.start()
    try:
        joints = {name: {"position": 1.5} for name in so101.JOINT_NAMES}
        agent.feed(
            "dt/lerobot/arm-001/telemetry",
            encode({"device_id": "arm-001", "timestamp": int(time.time() * 1000), "joints": joints}),
        )
        state = wait_for(lambda: agent.state().devices["arm-001"].joints_rad and agent.state(), 30, "arm-001")
        return state.devices["arm-001"]
    finally:
        agent.stop()


def test_degrees_need_no_calibration_so_they_are_not_flagged(tmp_path: Path) -> None:
    assert degrees_arm(tmp_path / "none").uncalibrated is False


def test_an_arm_publishing_degrees_shows_no_calibration_in_use(tmp_path: Path) -> None:
    # Its file in the store was shown as its `calibration` in /state, though degrees never use one.
    DirectoryStore(tmp_path / "cal").write("arm-001", EXAMPLE.read_bytes())
    arm = degrees_arm(tmp_path / "cal")
    assert arm.calibration == "" and arm.uncalibrated is False, arm.calibration


@pytest.mark.slow
def test_a_restarted_worker_decodes_with_the_arms_own_from_its_first_message(tmp_path: Path) -> None:
    """The new process is handed the arms' calibrations before the messages it is sent again and those that
    waited while it was down: not one of them decodes with the nominal arm's."""
    store = DirectoryStore(tmp_path / "cal")
    store.write("arm-001", EXAMPLE.read_bytes())
    agent = agent_with_store(tmp_path / "cal", **{"twin.workers": 2})
    agent.start()
    try:
        ts = [int(time.time() * 1000)]
        feed_until(agent, "arm-001", pan_angle(EXAMPLE.read_bytes()), ts)
        shard = agent._shards[agent.plan.worker_of("arm-001")]
        wait_for(
            lambda: shard.checkpoint is not None and "arm-001" in shard.checkpoint.devices, 30, "a checkpoint"
        )
        victim = agent.state().agent.workers[shard.index]
        os.kill(victim.pid, signal.SIGKILL)
        restarting = wait_for(
            lambda: (
                (d := agent.state().devices.get("arm-001")) is not None and d.mirror == "restarting" and d
            ),
            30,
            "arm-001 shown as restarting",
            interval=0.05,
        )
        assert restarting.calibration == str(tmp_path / "cal" / "arm-001.json")
        assert not restarting.uncalibrated
        # One message while its worker is down, then none: it is the first the new process decodes.
        applied = restarting.health.counters.applied
        ts[0] += 100
        agent.feed(
            "dt/lerobot/arm-001/telemetry",
            ticks_message("arm-001", ts[0], (2500, 1800, 2200, 2100, 2048, 2500)),
        )
        back = wait_for(
            lambda: (
                (d := agent.state().devices.get("arm-001")) is not None
                and d.mirror == "running"
                and d.health.counters.applied > applied
                and d
            ),
            60,
            "the worker running again with the message applied",
        )
        assert back.timestamp_ms == ts[0]
        assert back.joints_rad is not None
        assert abs(back.joints_rad["shoulder_pan"] - pan_angle(EXAMPLE.read_bytes(), 2500)) < 1e-9
    finally:
        agent.stop()


def test_a_newly_held_arms_first_refusal_finds_it_held_already() -> None:
    """The mirror tells its fleet which arms are held before the decoder holds them: a message the decoder
    refuses at once for its calibration, recorded before the fleet knew, was trimmed as one of the 64 other
    refused ids, and the held arm said to have sent nothing."""
    config = load_config(None, {"telemetry.devices": ["*"]})
    mirror = Mirror(config, inbox=PipeInbox(Pipe(duplex=False)[0]), budget=DeviceBudget(4))
    mirror.set_calibrations(CalibrationsRequest())  # none held: the fleet is told so, not left untold
    decoder_set = mirror._decoder.set_calibrations
    fleet = mirror._fleet

    def refuse_at_once(*args: Any, **kwargs: Any) -> None:
        # As a worker does between the decoder's swap and the rest: the held arm's message, then garbage.
        decoder_set(*args, **kwargs)
        fleet.record_rejected("arm-002", HELD_REASON)
        for n in range(MAX_UNHEARD):
            fleet.record_rejected(f"junk-{n:03d}", "invalid_json")

    mirror._decoder = type("Spy", (), {"set_calibrations": staticmethod(refuse_at_once)})()
    mirror.set_calibrations(CalibrationsRequest(problems=(("arm-002", "its file is not a calibration"),)))
    assert "arm-002" in {arm.device for arm in mirror.unheard()}
