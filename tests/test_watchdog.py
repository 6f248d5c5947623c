"""A stuck agent is started again: what `twin run` tells systemd (its notify protocol, which the host's unit
uses with `Type=notify` and `WatchdogSec=`), and an in-process mirror whose worker thread stopped turning.

systemd itself cannot run here: its side of the protocol is a unix datagram socket the test binds, as
systemd's is, and reads as systemd would (sd_notify(3): newline-separated `KEY=VALUE` lines a datagram).
"""

from __future__ import annotations

import logging
import os
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import one_arm_agent, wait_for
from test_catch_up import GateSink
from twin.rig.local import LocalRig
from twin.service import agent as agent_module
from twin.service import mirror as mirror_module
from twin.service.stall import StallWatch
from twin.service.systemd import Notifier

PAYLOAD = (
    b'{"device_id":"arm-001","timestamp":1760000000000,"joints":{"shoulder_pan":{"position":2048},'
    b'"shoulder_lift":{"position":2048},"elbow_flex":{"position":2048},"wrist_flex":{"position":2048},'
    b'"wrist_roll":{"position":2048},"gripper":{"position":2048}}}'
)


@pytest.fixture
def manager() -> Iterator[tuple[socket.socket, str]]:
    """systemd's end: a bound datagram socket, and its path (short: a unix socket's path has 108 bytes)."""
    directory = tempfile.mkdtemp(prefix="notify-", dir="/tmp")
    path = os.path.join(directory, "s")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    try:
        yield sock, path
    finally:
        sock.close()
        os.unlink(path)
        os.rmdir(directory)


def messages_until(sock: socket.socket, wanted: str, timeout: float) -> list[dict[str, str]]:
    """Every datagram received, parsed, up to and including the first that sets `wanted` (e.g. READY=1)."""
    got: list[dict[str, str]] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        try:
            data = sock.recv(4096)
        except TimeoutError:
            break
        got.append(dict(line.split("=", 1) for line in data.decode().splitlines()))
        key, value = wanted.split("=", 1)
        if got[-1].get(key) == value:
            return got
    raise AssertionError(f"no {wanted} within {timeout} s; received {got}")


def test_twin_run_says_it_is_ready_once_it_serves_pings_the_watchdog_and_says_it_stops(
    rig: LocalRig, manager: tuple[socket.socket, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    sock, path = manager
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    # 2 s: the agent pings on every turn of its loop, every second.
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    with rig.agent_process(devices="arm-001", config_text="[twin]\nworkers = 1\n") as (proc, url):
        before = messages_until(sock, "READY=1", 60)
        # Ready once it serves: the console's address it names answers.
        assert not any("WATCHDOG" in m for m in before), before
        assert before[-1]["STATUS"].endswith(f"console {url}"), before
        assert "dt/lerobot/arm-001/telemetry" in before[-1]["STATUS"]
        for _ in range(2):
            messages_until(sock, "WATCHDOG=1", 30)
        assert proc.poll() is None
    assert proc.returncode == 0
    said = messages_until(sock, "STOPPING=1", 5)
    assert said[-1]["STATUS"] == "stopping (SIGTERM)", said


def test_no_watchdog_for_another_process_and_none_without_systemd(
    manager: tuple[socket.socket, str],
) -> None:
    _, path = manager
    ours = Notifier.from_env({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "60000000"})
    assert ours.enabled and ours.watchdog_s == 60.0
    mine = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "60000000", "WATCHDOG_PID": str(os.getpid())}
    assert Notifier.from_env(mine).watchdog_s == 60.0
    # systemd sets WATCHDOG_PID to its main process: a child that inherited the variables is not watched.
    other = Notifier.from_env({**mine, "WATCHDOG_PID": str(os.getpid() + 1)})
    assert other.enabled and other.watchdog_s is None
    outside = Notifier.from_env({})
    assert not outside.enabled and outside.watchdog_s is None
    outside.ready("up")  # nothing to tell, nothing raised
    outside.watchdog()


def test_an_abstract_socket_is_reached_and_a_vsock_one_is_refused_with_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    name = f"so101-twin-test-{os.getpid()}-{time.monotonic_ns()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        notifier = Notifier.from_env({"NOTIFY_SOCKET": "@" + name})
        notifier.ready("up")
        notifier.close()
        assert messages_until(sock, "READY=1", 5)[-1]["STATUS"] == "up"
    with caplog.at_level(logging.WARNING, logger="twin.service.systemd"):
        vsock = Notifier.from_env({"NOTIFY_SOCKET": "vsock:2:1234"})
    assert not vsock.enabled
    assert "not a unix socket" in caplog.text


def test_a_manager_that_went_away_is_logged_once_and_never_raises(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    notifier = Notifier.from_env({"NOTIFY_SOCKET": str(tmp_path / "gone"), "WATCHDOG_USEC": "4"})
    with caplog.at_level(logging.ERROR, logger="twin.service.systemd"):
        notifier.ready("up")
        notifier.stopping("down")
    assert [r.getMessage().split(":")[0] for r in caplog.records] == [
        f"cannot notify systemd at {tmp_path}/gone"
    ]


def test_a_stuck_in_process_mirror_fails_the_agent_and_the_log_says_where_it_waits(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A worker process that stops answering is killed and started again; the one mirror of an agent with
    `workers = 1` (the default for a small listed fleet) runs in the agent's own process, where nothing can
    start it again: stuck, it fails the agent, so `twin run` exits and systemd starts it again."""
    # Many of the supervisor's half-second turns: shorter, its looks on a loaded machine could read as the
    # process paused (a gap of half the window), each starting the window again.
    monkeypatch.setattr(mirror_module, "STALL_AFTER_S", 6.0)
    # Held in its first sample, as a stuck native call would hold it, until the test lets go.
    sink = GateSink(hold_s=120)
    service = one_arm_agent([sink])
    # Whether the agent still ran when the stall was logged: the reason must be in the log before anyone
    # sees the agent fail (a final check read the log the moment it failed, and the line was not there yet).
    running_when_told: list[bool] = []

    class Told(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if "is stuck" in record.getMessage():
                running_when_told.append(service.running)

    told = Told()
    logging.getLogger("twin.service.mirror").addHandler(told)
    try:
        with caplog.at_level(logging.ERROR, logger="twin.service.mirror"):
            service.feed("dt/lerobot/arm-001/telemetry", PAYLOAD)
            assert sink.entered.wait(30)
            wait_for(lambda: not service.running, 90, "the agent to count its stuck mirror as failed")
        assert running_when_told == [True]
        (record,) = [r for r in caplog.records if "is stuck" in r.getMessage()]
        said = record.getMessage()
        assert said.startswith("the mirror's worker thread has not turned for "), said
        # Where it waits: the sink's frame.
        assert "in applied" in said and "test_catch_up.py" in said and "self.release.wait" in said, said
        # Its stop waits a few seconds for it, not the whole shutdown budget: it will not finish its batch.
        with caplog.at_level(logging.ERROR, logger="twin.service.mirror"):
            service.stop()
        assert f"twin worker did not finish within {mirror_module.STALLED_STOP_S:.1f} s" in caplog.text
    finally:
        logging.getLogger("twin.service.mirror").removeHandler(told)
        sink.release.set()
        service.stop()


def test_an_idle_in_process_mirror_is_not_taken_for_a_stuck_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """Its worker thread turns its loop while nothing arrives (every IDLE_WAKE_S), and the supervisor its
    own (every SUPERVISE_EVERY_S): no message for many times either window is no stall."""
    monkeypatch.setattr(mirror_module, "STALL_AFTER_S", 4.0)
    monkeypatch.setattr(agent_module, "SUPERVISOR_STUCK_S", 4.0)
    service = one_arm_agent()
    try:
        (shard,) = service._shards
        start, turns = time.monotonic(), shard.mirror.turns
        # Asked as `twin run`'s main thread asks it, all along: the supervisor's watch judges on each ask.
        stopped_running: list[float] = []

        def three_windows_passed() -> bool:
            if not service.running:
                stopped_running.append(time.monotonic() - start)
            idle_turns = shard.mirror.turns - turns
            return idle_turns > 12 / mirror_module.IDLE_WAKE_S and time.monotonic() - start > 12

        # Past three stall windows by the mirror's own turns, each seen by the supervisor (every 0.5 s).
        wait_for(three_windows_passed, 60, "three stall windows of idle turns")
        assert not stopped_running and service.running
    finally:
        service.stop()


def test_a_stuck_supervisor_fails_the_agent_and_the_log_says_where_it_waits(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The agent's supervisor starts dead workers again, keeps the state file and collects events; the main
    thread tells systemd's watchdog all is well. A supervisor stuck in one step (here its event collection,
    standing in for a lock a stuck thread holds or a disk that hangs) fails the agent, so `twin run` exits
    and systemd starts it again; the log says where it waits."""
    monkeypatch.setattr(agent_module, "SUPERVISOR_STUCK_S", 6.0)
    service = one_arm_agent()
    hang, entered = threading.Event(), threading.Event()

    def collect_hangs() -> None:
        entered.set()
        hang.wait(120)

    monkeypatch.setattr(service, "_collect_events", collect_hangs)
    try:
        with caplog.at_level(logging.ERROR, logger="twin.service.agent"):
            assert entered.wait(30)
            assert service.running  # not yet: a step may take a while
            wait_for(lambda: not service.running, 90, "the agent to count its stuck supervisor as failed")
        (record,) = [r for r in caplog.records if "supervisor has got past no step" in r.getMessage()]
        said = record.getMessage()
        assert "in collect_hangs" in said and "hang.wait(120)" in said, said
    finally:
        hang.set()
        service.stop()


def test_a_supervisor_that_fails_fails_the_agent_at_once_with_its_traceback(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A supervisor ended by an error it did not expect would start no worker again, keep no state and
    collect no event: the agent fails at once (not a stuck window later), its log holding the traceback."""
    monkeypatch.setattr(agent_module, "SUPERVISOR_STUCK_S", 3600.0)
    service = one_arm_agent()

    def collect_fails() -> None:
        raise RuntimeError("a fault the supervisor did not expect")

    try:
        with caplog.at_level(logging.ERROR, logger="twin.service.agent"):
            monkeypatch.setattr(service, "_collect_events", collect_fails)
            wait_for(lambda: not service.running, 30, "the agent to count its failed supervisor")
        (record,) = [r for r in caplog.records if "supervisor failed" in r.getMessage()]
        assert record.exc_info is not None and "did not expect" in str(record.exc_info[1])
    finally:
        service.stop()


def test_only_the_supervisors_own_steps_count_as_its_turns() -> None:
    """An acknowledgement writes the state file on an HTTP thread through the supervisor's own helpers:
    those steps must not pass for the supervisor's, or a stuck one would be hidden while people click."""
    service = one_arm_agent()
    try:
        before = service._supervisor_turns
        service._turned()  # this thread is not the supervisor
        assert service._supervisor_turns == before
        wait_for(lambda: service._supervisor_turns > before, 30, "the supervisor to turn")
    finally:
        service.stop()


def test_the_stall_watch_judges_a_thread_by_its_turns_not_by_a_pause_of_the_whole_process() -> None:
    """Looked at every half second (the agent's supervisor): a thread that turns is never stuck; one that has
    not turned for STALL_AFTER_S is, and the watch says for how long. A gap between two looks (a process
    paused by SIGSTOP, a suspended VM) starts the window again; a thread that waits longer than that between
    two turns when idle (a slow physics rate) gets three of its waits."""
    stall = mirror_module.STALL_AFTER_S
    watch = StallWatch(stall)
    looks = [0.5 * i for i in range(int(3 * stall))]
    assert [watch.look(i, t, 0.2) for i, t in enumerate(looks)] == [None] * len(looks)

    stuck = StallWatch(stall)
    said = [stuck.look(7, t, 0.2) for t in looks]
    first = said.index(stall)
    assert said[:first] == [None] * first and said[first:] == [t for t in looks[first:]]

    paused = StallWatch(stall)
    assert paused.look(7, 0.0, 0.2) is None
    # The whole process stopped for longer than a stall, then the supervisor looked before the thread ran:
    # a stall only once it has not turned for a whole window of regular looks after that.
    after = [2 * stall + 0.5 * i for i in range(int(2 * stall) + 1)]
    said = [paused.look(7, t, 0.2) for t in after]
    assert said == [None] * (len(after) - 1) + [stall], said

    slow = StallWatch(stall)
    wait = stall  # a physics step a minute apart
    times = [0.5 * i for i in range(int(8 * stall))]
    verdicts = [slow.look(7, t, wait) for t in times]
    due = times.index(3 * wait)
    assert verdicts[:due] == [None] * due and verdicts[due] == 3 * wait


def test_a_manager_that_stops_reading_never_blocks_the_main_thread(
    manager: tuple[socket.socket, str], caplog: pytest.LogCaptureFixture
) -> None:
    """A unix datagram queue holds a few messages (net.unix.max_dgram_qlen, 10 here): a manager that does
    not read them (a hung PID 1) would stop a blocking sender on the next one, the main thread with it."""
    sock, path = manager
    notifier = Notifier.from_env({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "60000000"})
    pinged = threading.Event()

    def ping() -> None:
        for _ in range(200):
            notifier.watchdog()
        pinged.set()

    with caplog.at_level(logging.ERROR, logger="twin.service.systemd"):
        thread = threading.Thread(target=ping, daemon=True)
        thread.start()
        assert pinged.wait(30), "the notifier blocked on a full queue"
    notifier.close()
    assert [r.getMessage().split(": ", 1)[0] for r in caplog.records] == [f"cannot notify systemd at {path}"]
    assert messages_until(sock, "WATCHDOG=1", 5)  # what the queue held is systemd's to read
