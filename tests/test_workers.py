"""`twin run --workers N`: the receiving process and its worker processes (twin.service.shards).

The plan and the merge are pure and tested here with hand-built inputs. The rest runs for real: worker
processes (spawned, as the CLI spawns them) behind a real mosquitto, some through the quota proxy, with the
edge simulator publishing.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections import Counter
from multiprocessing import Pipe
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import psutil
import pytest
from awscrt import mqtt5
from conftest import (
    NO_BROKER,
    Publisher,
    get_metrics,
    get_state,
    metric,
    run_twin,
    signal_and_await_restart,
    unbrokered_agent,
    wait_for,
    wait_handled,
)
from test_restarts import running
from test_servo_alarms_e2e import alarms, post
from twin.bench.worker import _feed, _fleet
from twin.core.alarms import AlarmKind, AlarmRecord, AlarmState
from twin.core.health import DeviceCounters, DeviceStatus, HealthSnapshot
from twin.core.latency import LatencyHistogram
from twin.core.topics import DEFAULT_TOPIC_PREFIX
from twin.edge.payload import encode, make_payload
from twin.edge.servo_faults import ServoFault
from twin.rig.local import LocalRig, child_env
from twin.rig.quota_proxy import QuotaProxy
from twin.service import shards
from twin.service.admission import DeviceBudget
from twin.service.agent import AgentService
from twin.service.config import ConfigError, load_config
from twin.service.mirror import Mirror, MirrorBusyError, PipeInbox
from twin.service.persist import StateFile
from twin.service.shards import MirrorReport, WorkerPlan, merge_reports, worker_config
from twin.service.state import (
    AgentInfo,
    AgentState,
    AlarmsSummary,
    DeviceState,
    HistoryState,
    LossSnapshot,
    MailboxState,
    RecordingState,
    SinkStats,
    WorkerInfo,
    WorkerState,
)
from twin.service.workerstart import worker_count
from twin.transport.pipe import send_end

# --- the plan ---------------------------------------------------------------------------------------------


def test_a_listed_fleet_is_dealt_out_in_list_order() -> None:
    plan = WorkerPlan(3, ["d", "a", "c", "b"])
    assert [plan.worker_of(d) for d in ("d", "a", "c", "b")] == [0, 1, 2, 0]
    assert plan.devices_of(0) == ("d", "b") and plan.devices_of(2) == ("c",)


def test_any_other_device_has_the_same_worker_in_every_process() -> None:
    # Python's own hash() is salted per process; the plan must not be, or a restarted agent (or the test's
    # other interpreter) would send an arm to another worker.
    ids = [f"arm-{i:04d}" for i in range(300)]
    here = [WorkerPlan(4).worker_of(d) for d in ids]
    script = (
        "import json, sys; from twin.service.shards import WorkerPlan; "
        "print(json.dumps([WorkerPlan(4).worker_of(d) for d in json.loads(sys.argv[1])]))"
    )
    other = subprocess.run(
        [sys.executable, "-c", script, json.dumps(ids)],
        capture_output=True,
        text=True,
        check=True,
        env={**child_env(), "PYTHONHASHSEED": "12345"},
    )
    assert json.loads(other.stdout) == here
    # CRC-32 spreads the ids: each of 4 workers gets a quarter, give or take.
    assert all(50 <= n <= 100 for n in Counter(here).values()), Counter(here)


@pytest.mark.parametrize(
    ("overrides", "cores", "expected"),
    [
        ({"telemetry.devices": ["*"]}, 8, 8),  # the whole fleet: a worker per core
        ({"telemetry.devices": ["arm-001", "arm-002", "arm-003"]}, 8, 1),  # 30 msg/s: one process
        ({"telemetry.devices": [f"a{i}" for i in range(250)]}, 8, 3),  # 2,500 msg/s / 1,000 per worker
        ({"telemetry.devices": [f"a{i}" for i in range(5000)], "telemetry.max_devices": 6000}, 8, 8),
        ({"telemetry.devices": [f"a{i}" for i in range(250)], "health.expected_rate_hz": 30.0}, 8, 8),
        ({"telemetry.devices": ["*"], "twin.workers": 3}, 8, 3),  # asked for: as asked
        ({"telemetry.devices": ["*"], "rerun.save": "x.rrd"}, 8, 1),  # one Rerun stream, one process
    ],
)
def test_worker_count(overrides: dict[str, Any], cores: int, expected: int) -> None:
    assert worker_count(load_config(None, overrides), cores=cores) == expected


def test_a_workers_config_holds_its_share_and_leaves_cloudwatch_to_the_receiver() -> None:
    config = load_config(
        None,
        {
            "telemetry.devices": ["a", "b", "c"],
            "twin.workers": 2,
            "cloudwatch.emf_file": "/var/log/twin/emf.log",
        },
    )
    plan = WorkerPlan(2, config.telemetry.devices)
    first, second = (worker_config(config, plan, i) for i in (0, 1))
    assert (first.telemetry.devices, second.telemetry.devices) == (("a", "c"), ("b",))
    assert first.cloudwatch.emf_file == "" and first.twin.workers == 1
    assert first.broker == config.broker and first.history == config.history


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"twin.workers": -1}, "twin.workers = -1 is outside 0..64"),
        ({"twin.workers": 65}, "outside 0..64"),
        ({"twin.workers": 2, "rerun.save": "x.rrd"}, "set workers = 1"),
    ],
)
def test_bad_worker_settings_name_the_key_and_the_fix(overrides: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        load_config(None, overrides)


# --- the merge --------------------------------------------------------------------------------------------


def histogram(*seconds: float) -> LatencyHistogram:
    h = LatencyHistogram()
    for s in seconds:
        h.add(s)
    return h


def mirror_report(
    devices: dict[str, DeviceCounters],
    losses: dict[str, LossSnapshot] | None = None,
    *,
    internal: LatencyHistogram | None = None,
    end_to_end: LatencyHistogram | None = None,
    **parts: Any,
) -> MirrorReport:
    losses = losses or {}
    values: dict[str, Any] = {
        "mailbox": MailboxState(),
        "worker": WorkerState(alive=True),
        "recording": None,
        "history": None,
        "sinks": (),
        "alarms": AlarmsSummary(),
        **parts,
    }
    return MirrorReport(
        devices={
            d: DeviceState(
                device_id=d,
                health=HealthSnapshot(status=DeviceStatus.ONLINE, counters=c),
                loss=losses.get(d, LossSnapshot()),
            )
            for d, c in devices.items()
        },
        untracked_rejected={"not_json": 1},
        internal=internal or histogram(),
        end_to_end=end_to_end or histogram(),
        **values,
    )


def test_merged_state_sums_the_workers_and_adds_what_the_receiver_dropped() -> None:
    first = mirror_report(
        {"a": DeviceCounters(received=10, applied=9, overwritten=1)},
        {"a": LossSnapshot(received=10)},
        sinks=(SinkStats(name="history", delivered=10, dropped=0, errors=0, pending=2, last_error=""),),
        history=HistoryState(
            uri="out/h", rows_committed=8, commits=2, last_error="", log_entries_set_aside=1
        ),
        alarms=AlarmsSummary(present={"critical": 1}, raised_total={"over_current": 1}),
        internal=histogram(0.001, 0.002),
    )
    second = mirror_report(
        {"b": DeviceCounters(received=20, applied=20), "c": DeviceCounters(received=5, applied=5)},
        {"b": LossSnapshot(received=20, lost=5, losing=True), "c": LossSnapshot(received=5)},
        sinks=(SinkStats(name="history", delivered=25, dropped=1, errors=0, pending=0, last_error="full"),),
        history=HistoryState(uri="out/h", storage_ok=False, rows_committed=25, commits=3, last_error="full"),
        alarms=AlarmsSummary(present={"critical": 1, "warning": 2}, raised_total={"over_current": 2}),
        internal=histogram(0.004),
        end_to_end=histogram(0.01),
    )
    workers = (
        WorkerInfo(index=0, alive=True, queued=3),
        WorkerInfo(index=1, alive=True, queued=4),
    )
    state = merge_reports(
        AgentInfo(pid=1, running=True),
        [first, second],
        workers,
        dropped=Counter({"b": 3}),
    )
    assert list(state.devices) == ["a", "b", "c"]
    assert state.devices["a"].health.counters.overwritten == 1  # its worker's own
    assert state.devices["b"].health.counters.overwritten == 3  # dropped by the receiving process
    assert state.untracked_rejected == {"not_json": 2}
    agent = state.agent
    assert (agent.pid, agent.running, agent.workers) == (1, True, workers)
    assert agent.latency.internal_s.count == 3 and agent.latency.internal_s.max == pytest.approx(0.004)
    assert agent.latency.end_to_end_s.count == 1
    assert agent.mailbox.overwritten_total == 3 and agent.mailbox.pending == 7
    (sink,) = agent.sinks
    assert (sink.name, sink.delivered, sink.dropped, sink.pending, sink.last_error) == (
        "history",
        35,
        1,
        2,
        "full",
    )
    assert agent.history is not None
    assert (agent.history.rows_committed, agent.history.commits, agent.history.storage_ok) == (33, 5, False)
    assert agent.history.log_entries_set_aside == 1
    assert agent.alarms.present == {"critical": 2, "warning": 2}
    assert agent.alarms.raised_total == {"over_current": 3}
    assert (agent.loss.received, agent.loss.lost, agent.loss.devices_losing) == (35, 5, 1)
    assert agent.loss.loss_ratio == pytest.approx(5 / 40)
    # Still one state document: it survives its own JSON.
    assert AgentState.from_json(state.to_json()) == state


def ones(cls: type[Any], **fixed: Any) -> Any:
    """An instance of the dataclass `cls` whose every whole-number field is 1."""
    values = {f.name: 1 for f in dataclasses.fields(cls) if f.type in ("int", int)}
    return cls(**{**values, **fixed})


def test_every_count_of_the_recording_history_and_sinks_is_summed() -> None:
    # A count added to one of these states must be merged too: each whole-number field of two reports adds up.
    parts = {
        "recording": ones(RecordingState, path="a.usdc"),
        "history": ones(HistoryState, uri="out/h"),
        "sinks": (ones(SinkStats, name="history"),),
    }
    state = merge_reports(
        AgentInfo(), [mirror_report({}, **parts), mirror_report({}, **parts)], (), dropped=Counter()
    )
    merged = [state.agent.recording, state.agent.history, *state.agent.sinks]
    for item in merged:
        counts = {f.name: getattr(item, f.name) for f in dataclasses.fields(item) if f.type in ("int", int)}
        assert counts and set(counts.values()) == {2}, (type(item).__name__, counts)


def test_the_merged_recording_names_a_worker_session_that_was_kept() -> None:
    """Worker 0's session, given no arm, is removed at stop: the merged report named it all the same."""
    removed, kept = ones(RecordingState, path=""), ones(RecordingState, path="w1.usdc")
    reports = [mirror_report({}, recording=removed), mirror_report({}, recording=kept)]
    state = merge_reports(AgentInfo(), reports, (), dropped=Counter())
    assert state.agent.recording is not None and state.agent.recording.path == "w1.usdc"


def test_a_worker_that_does_not_answer_is_not_running_in_the_merged_state() -> None:
    report = mirror_report({"a": DeviceCounters(received=1)})
    state = merge_reports(
        AgentInfo(running=True),
        [report],
        (WorkerInfo(index=0, alive=True), WorkerInfo(index=1, alive=False)),
        dropped=Counter(),
    )
    assert state.agent.running is False and state.agent.worker.alive is False
    assert list(state.devices) == ["a"]


class _SilentWorker:
    """A worker process that lives and never answers, and a control pipe that records how long each wait
    on it was allowed to take."""

    def __init__(self) -> None:
        self.polled: list[float] = []

    def is_alive(self) -> bool:
        return True

    def send(self, message: Any) -> None:
        pass

    def poll(self, timeout: float) -> bool:
        self.polled.append(timeout)
        return False


def test_asking_every_worker_waits_out_one_timeout_for_all_not_one_each(
    monkeypatch: pytest.MonkeyPatch,
) -> None:

    now = [1000.0]
    monkeypatch.setattr(shards.time, "monotonic", lambda: now[0])
    config = load_config(None, {"telemetry.devices": ["*"]})
    silent = []
    for index in range(2):
        shard = shards.WorkerShard(index, config, DeviceBudget(10), context=None)  # type: ignore[arg-type]
        worker = _SilentWorker()
        shard.process, shard.control, shard.ready = worker, worker, True  # type: ignore[assignment]
        silent.append((shard, worker))
    # As the agent asks (AgentService._ask_all): every worker first, then each answer in turn.
    waits = [shard.request(shards.ReportRequest()) for shard, _ in silent]
    with pytest.raises(shards.WorkerError, match="did not answer"):
        waits[0]()
    assert silent[0][1].polled == [shards.ASK_TIMEOUT_S]
    now[0] += shards.ASK_TIMEOUT_S  # the first wait took its whole timeout
    with pytest.raises(shards.WorkerError, match="did not answer"):
        waits[1]()
    assert silent[1][1].polled == []  # no second timeout: the ask's own deadline had passed with the first


class _StuckMirrorWorker(_SilentWorker):
    """A worker process whose control thread answers each call at once, as its mirror thread would have it
    (`replies` by kind: "stuck" refuses it as the thread not getting to it, "answer" answers)."""

    def __init__(self, replies: list[str]) -> None:
        super().__init__()
        self.replies, self.calls, self.killed = replies, [], False
        self.pending: list[Any] = []

    def send(self, message: Any) -> None:
        kind = self.replies.pop(0)
        if kind == "stuck":
            text = "the mirror's worker did not take its checkpoint within 10 s"
            self.pending.append(shards.Refused(message.call_id, shards.Refusal.STUCK, text))
        elif kind == "busy":
            text = (
                "the mirror's worker did not take its checkpoint within 10 s; it handled 40 batches meanwhile"
            )
            self.pending.append(shards.Refused(message.call_id, shards.Refusal.BUSY, text))
        else:
            self.pending.append(shards.Answer(message.call_id, 0))

    def poll(self, timeout: float) -> bool:
        return bool(self.pending)

    def recv(self) -> Any:
        return self.pending.pop(0)

    def kill(self) -> None:
        self.killed = True

    def join(self, timeout: float) -> None:
        pass


def test_a_mirror_thread_that_never_gets_to_a_request_counts_as_hung() -> None:
    """The process answers, but only to say its mirror thread did not get to the request: a mirror thread
    stuck for good looks so, and is killed like a process that answers nothing. An answer in between
    starts the count again."""
    assert shards.HUNG_AFTER_ASKS == 3
    config = load_config(None, {"telemetry.devices": ["*"]})
    shard = shards.WorkerShard(0, config, DeviceBudget(10), context=None)  # type: ignore[arg-type]
    replies = ["stuck", "stuck", "answer", "stuck", "stuck", "stuck"]
    worker = _StuckMirrorWorker(list(replies))
    shard.process, shard.control, shard.ready = worker, worker, True  # type: ignore[assignment]

    def ask(kind: str) -> None:
        if kind == "answer":
            assert shard.request(shards.StatusesRequest())() == 0
            return
        with pytest.raises(shards.WorkerError, match="did not take its checkpoint"):
            shard.request(shards.StatusesRequest())()

    for kind in replies[:4]:
        ask(kind)
    shard.supervise()
    assert not worker.killed  # two stuck, an answer, one stuck: busy, not hung
    for kind in replies[4:]:
        ask(kind)
    shard.supervise()
    assert worker.killed


def test_a_mirror_thread_that_handles_batches_but_misses_the_timeout_is_busy_not_hung() -> None:
    """A starved host slows a checkpoint taken over many batches past the ask's timeout while the mirror
    thread keeps handling messages: counted as hung, three such asks killed a working worker, and its
    restart's replay added to the load that slowed it. BUSY answers, so the count starts again."""
    config = load_config(None, {"telemetry.devices": ["*"]})
    shard = shards.WorkerShard(0, config, DeviceBudget(10), context=None)  # type: ignore[arg-type]
    replies = ["stuck", "stuck", "busy", "stuck", "stuck", "busy", "busy", "busy", "busy"]
    worker = _StuckMirrorWorker(list(replies))
    shard.process, shard.control, shard.ready = worker, worker, True  # type: ignore[assignment]
    for kind in replies:
        with pytest.raises(shards.WorkerError, match="did not take its checkpoint"):
            shard.request(shards.StatusesRequest())()
        shard.supervise()
        assert not worker.killed, kind


class _HungWorker(_SilentWorker):
    """A worker process that runs and answers nothing until killed, after which it is dead with `ended`
    (SIGKILL's code; another if it exited or crashed by itself just before the kill reached it)."""

    def __init__(self, ended: int | None = -signal.SIGKILL) -> None:
        super().__init__()
        self.pid, self.exitcode, self.alive, self.ended = 4242, None, True, ended

    def is_alive(self) -> bool:
        return self.alive

    def kill(self) -> None:
        self.alive, self.exitcode = False, self.ended

    def join(self, timeout: float) -> None:
        pass


_KILLED_AS_HUNG = "answered no request for 15 s (hung) and was killed by the supervisor with SIGKILL"


@pytest.mark.parametrize(
    ("ended", "how", "data"),
    [
        (-signal.SIGKILL, _KILLED_AS_HUNG, {"exit_code": -9, "hung_s": 15}),
        (None, _KILLED_AS_HUNG, {"exit_code": None, "hung_s": 15}),
        (255, _KILLED_AS_HUNG, {"exit_code": 255, "hung_s": 15}),
        (1, "exited, exit code 1, while found hung", {"exit_code": 1}),
        (-signal.SIGSEGV, "exited, killed by SIGSEGV (signal 11), while found hung", {"exit_code": -11}),
    ],
)
def test_a_hung_worker_the_supervisor_killed_is_said_to_be_so_in_the_log_and_on_the_events_page(
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    ended: int | None,
    how: str,
    data: dict[str, Any],
) -> None:
    """A worker that ran but answered nothing was told as "exited, exit code unknown" or as killed by
    SIGKILL, as if it had crashed: now as hung for so long and killed by the supervisor, in one wording in
    the log line and the event. One that exited or crashed by itself just before the kill keeps its own
    exit code (a review: it was told as killed by the supervisor while the data said exit code 1 or -11)."""
    now = [1000.0]
    monkeypatch.setattr(shards.time, "monotonic", lambda: now[0])
    monkeypatch.setattr(shards, "_still_runs", lambda pid: False)  # 255: the fork server gone, pid 4242 too
    config = load_config(None, {"telemetry.devices": ["*"]})
    shard = shards.WorkerShard(0, config, DeviceBudget(10), context=None)  # type: ignore[arg-type]
    worker = _HungWorker(ended)
    shard.process, shard.control, shard.ready = worker, worker, True  # type: ignore[assignment]
    shard.pid, shard.started_at = worker.pid, now[0]
    for _ in range(shards.HUNG_AFTER_ASKS):
        with pytest.raises(shards.WorkerError, match="did not answer"):
            shard.request(shards.ReportRequest())()
        now[0] += 5.0  # the silent pipe's poll returns at once, as at the end of its wait
    with caplog.at_level(logging.ERROR, logger="twin.service.shards"):
        shard.supervise()  # finds it hung and kills it
        shard.supervise()  # finds it dead; started again after a pause (it died young)
    killing, found = [r.getMessage() for r in caplog.records]
    assert "nothing for 15 s): it is hung; killing it (SIGKILL)" in killing
    assert found == f"worker 0 (pid 4242) {how}; starting it again in 1 s"
    events: list[tuple[str, dict[str, Any]]] = []
    emit = lambda _kind, _level, message, data: events.append((message, data))  # noqa: E731
    watcher = SimpleNamespace(_workers_seen={}, _events=SimpleNamespace(emit=emit))
    AgentService._watch_worker(watcher, shard)  # type: ignore[arg-type]
    assert events == [
        (
            f"worker 0 (pid 4242) {how}; it is started again from its last checkpoint, its arms kept",
            {"worker": 0, "pid": 4242} | data,
        )
    ]


class _ServerLostWorker:
    """A worker process as multiprocessing shows it once its fork server is killed: not alive, exit code
    255, while the process of that pid (`child`) still runs."""

    def __init__(self, child: subprocess.Popen[bytes]) -> None:
        self.pid, self.exitcode = child.pid, 255

    def is_alive(self) -> bool:
        return False


def test_a_worker_its_lost_fork_server_left_running_is_not_said_to_have_exited_once_it_does(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The agent's Events page asks `last_exit` after the supervisor found the worker dead. Judged again
    then, a worker that still ran when its fork server was killed, and exited since (its pipes closed for
    the restart), read as "exited, exit code 255"."""
    now = [1000.0]
    monkeypatch.setattr(shards.time, "monotonic", lambda: now[0])
    config = load_config(None, {"telemetry.devices": ["*"]})
    shard = shards.WorkerShard(0, config, DeviceBudget(10), context=None)  # type: ignore[arg-type]
    child = subprocess.Popen(["sleep", "600"])
    try:
        shard.process = _ServerLostWorker(child)  # type: ignore[assignment]
        shard.pid, shard.started_at = child.pid, now[0]
        shard.supervise()  # found dead; a quick death, so started again only after a pause
        assert shard.restarting
    finally:
        child.kill()
        child.wait()
    ended = shard.last_exit()
    assert ended is not None and ended.pid == child.pid and ended.server_lost, ended


def test_the_worker_answers_busy_when_its_mirror_thread_worked_through_the_wait() -> None:
    """What the worker's control thread answers when a wait for its mirror thread runs out: BUSY when the
    thread handled batches meanwhile (mirror.MirrorBusyError), STUCK when it handled none."""
    reader, writer = Pipe(duplex=False)
    config = load_config(None, {"telemetry.devices": ["*"], "telemetry.units": "ticks"})
    mirror = Mirror(config, inbox=PipeInbox(reader), budget=DeviceBudget(64))
    mirror.start()
    never = dataclasses.make_dataclass("NeverTaken", [("done", threading.Event)])(threading.Event())
    try:
        before = mirror.batches
        _feed(mirror, writer, _fleet(4, 3))
        with pytest.raises(MirrorBusyError, match="busy, not stuck"):
            mirror._captured(never, time.monotonic(), before)  # type: ignore[arg-type]
        with pytest.raises(TimeoutError) as stuck:
            mirror._captured(never, time.monotonic(), mirror.batches)  # type: ignore[arg-type]
        assert not isinstance(stuck.value, MirrorBusyError)
    finally:
        send_end(writer)
        mirror.stop(timeout=30.0)
    # The control thread maps each to its refusal.
    errors = [MirrorBusyError("slow"), TimeoutError("stuck")]

    class Refusing:
        def answer(self, _request: object) -> None:
            raise errors.pop(0)

    ours, theirs = Pipe()
    serving = threading.Thread(target=shards._serve_control, args=(Refusing(), theirs), daemon=True)
    serving.start()
    answered = []
    for call_id in (1, 2):
        ours.send(shards.Call(call_id, shards.StatusesRequest()))
        answered.append(ours.recv().refusal)
    ours.close()
    serving.join(30)
    assert answered == [shards.Refusal.BUSY, shards.Refusal.STUCK]


def _messages(first: int, count: int) -> list[tuple[str, tuple[str, bytes, float, float]]]:
    return [
        (f"arm-{i % 3}", (f"dt/lerobot/arm-{i % 3}/telemetry", b'{"n": %d}' % i, 10.0 + i, 1.7e9 + i))
        for i in range(first, first + count)
    ]


def test_a_restarted_worker_is_sent_again_exactly_what_its_checkpoint_did_not_count(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The shard keeps what it handed over as the bytes it sent; the checkpoint can fall inside one of those
    pipe messages, and the new worker gets the rest of it, then the later ones, then what was held."""
    import multiprocessing

    from twin.transport.pipe import messages_of

    monkeypatch.setattr(shards, "MAX_UNCONFIRMED", 250)
    config = load_config(None, {"telemetry.devices": ["*"]})
    shard = shards.WorkerShard(0, config, DeviceBudget(10), context=None)  # type: ignore[arg-type]
    theirs, ours = multiprocessing.Pipe(duplex=False)
    shard.data, shard.ready = ours, True
    for first in range(0, 300, 100):  # three pipe messages of 100: 0-99, 100-199, 200-299
        shard._hand_over(_messages(first, 100))
    # Beyond the bound the oldest pipe message goes whole: 200 kept, and 0-99 no longer.
    assert [(start, count) for start, count, _ in shard._unconfirmed] == [(100, 100), (200, 100)]
    assert all(isinstance(raw, bytes) for _, _, raw in shard._unconfirmed)
    sent = [messages_of(theirs.recv_bytes()) for _ in range(3)]
    assert sent == [_messages(0, 100), _messages(100, 100), _messages(200, 100)]

    # The worker counted 150 when it checkpointed: the first kept message is only partly counted, so kept.
    assert shard.confirm(shards.MirrorCheckpoint(taken=150), restarts=0)
    # One asked of a process that died as it answered (a restart began since): not the restart point.
    shard.restarts = 1
    assert not shard.confirm(shards.MirrorCheckpoint(taken=280), restarts=0)
    assert shard.checkpoint is not None and shard.checkpoint.taken == 150
    assert [(start, count) for start, count, _ in shard._unconfirmed] == [(100, 100), (200, 100)]
    # It died; two messages came in meanwhile (held), then the new process is sent the rest.
    shard.ready = False
    shard._hand_over(_messages(300, 2))
    assert shard._replay(shard.checkpoint) == 152
    again = []
    while theirs.poll(0):
        again.extend(messages_of(theirs.recv_bytes()))
    assert again == _messages(150, 152)
    # Sent again and kept again, counted from the checkpoint: a checkpoint that counts them all frees them.
    assert [(start, count) for start, count, _ in shard._unconfirmed] == [(150, 152)]
    shard.confirm(shards.MirrorCheckpoint(taken=302))
    assert not shard._unconfirmed and shard._unconfirmed_count == 0
    assert shard.dropped_total == 0


# --- for real ---------------------------------------------------------------------------------------------

FLEET = [f"arm-{i:03d}" for i in range(1, 31)]


@pytest.mark.slow
def test_a_sharded_agent_mirrors_a_listed_fleet_through_the_quota(rig: LocalRig) -> None:
    with QuotaProxy("127.0.0.1", rig.broker.port, budget=100) as proxy:
        agent = rig.start_agent(
            {
                "broker.url": proxy.url,
                "broker.per_connection_limit": 100,
                "telemetry.devices": FLEET,
                "telemetry.units": "ticks",
                "telemetry.max_devices": 100,
            },
            workers=3,
        )
        report = rig.start_edge(FLEET, seconds=4.0, rate_hz=10.0).join(30)
        state = wait_handled(agent.state, report.published)
        assert proxy.totals()["dropped"] == 0
        with urllib.request.urlopen(agent.http_url + "/healthz", timeout=30) as resp:
            assert json.loads(resp.read())["status"] == "ok"
    # Every device on its worker (dealt out in list order), every message applied once, nothing lost. (A
    # worker that falls behind, as one may on a busy machine, applies each batch's newest message and counts
    # the others as coalesced: they reached the twin's worker all the same.)
    assert [w.devices for w in state.agent.workers] == [10, 10, 10]
    assert all(w.alive and w.pid not in (0, os.getpid()) for w in state.agent.workers)
    for device in FLEET:
        counters = state.devices[device].health.counters
        assert counters.applied + counters.coalesced == report.per_device[device], device
        assert counters.ignored_stale == counters.overwritten == 0
    assert state.agent.loss.lost == 0 and state.agent.loss.received == report.published
    applied = {device: d.health.counters.applied for device, d in state.devices.items()}
    assert state.agent.latency.internal_s.count == sum(applied.values())
    assert len(state.agent.broker.connections) == 4  # the pool is the receiving process's, as before
    metrics = get_metrics(agent.http_url)
    assert metric(metrics, "twin_messages_applied_total", device="arm-030") == applied["arm-030"]
    assert [metric(metrics, "twin_worker_devices", worker=str(i)) for i in range(3)] == [10.0] * 3


# Above 60 C from about 1.6 s to 5.4 s: 1.7 s more than the 2 s the alarm waits, so a worker that falls
# behind on a busy host (and coalesces) still sees the condition last.
FAULTS = (ServoFault("heat", "wrist_roll", 0.5, 6.0),)


@pytest.mark.slow
def test_a_sharded_wildcard_fleet_keeps_history_and_routes_acknowledgements(
    rig: LocalRig, tmp_path: Path
) -> None:
    devices = FLEET[:6]
    plan = WorkerPlan(2)
    assert {plan.worker_of(d) for d in devices} == {0, 1}  # both workers get arms (and alarms)
    history = tmp_path / "history"
    agent = rig.start_agent(
        {"telemetry.units": "ticks", "history.uri": str(history), "history.commit_every_s": 1.0}, workers=2
    )
    edge = rig.start_edge(devices, rate_hz=10.0, servo_faults=FAULTS, seconds=8.0)
    url = agent.http_url

    def raised() -> set[str] | None:
        seen = {a.device for a in alarms(url).alarms if a.kind == "over_temperature"}
        return seen if seen == set(devices) else None

    wait_for(raised, 60, "an over-temperature alarm on every arm", interval=0.2)
    # Each acknowledgement goes to the worker that owns the arm; twice is a conflict, an unknown id 404.
    for device in devices:
        status, body = post(f"{url}/alarms/{device}/wrist_roll/over_temperature/ack")
        assert status == 200 and body["alarms"][0]["state"] == "ACKNOWLEDGED", body
    status, body = post(f"{url}/alarms/{devices[0]}/wrist_roll/over_temperature/ack")
    assert status == 409 and body["error"] == "nothing_to_acknowledge"
    status, _ = post(f"{url}/alarms/arm-999/wrist_roll/over_temperature/ack")
    assert status == 404
    report = edge.join(30)
    wait_for(
        lambda: sum(d.health.counters.decoded for d in agent.state().devices.values()) >= report.published,
        60,
        "every message decoded",
    )
    agent.stop()  # both workers commit what they hold
    import polars as pl

    rows = pl.read_delta(str(history / "telemetry")).group_by("device_id").len()
    assert dict(rows.iter_rows()) == report.per_device


@pytest.mark.slow
def test_twin_run_with_workers_stops_them_all_on_sigterm(rig: LocalRig) -> None:
    with rig.agent_process(devices="*", extra_args=("--workers", "2", "--units", "ticks")) as (proc, base):

        def up() -> AgentState | None:
            try:
                with urllib.request.urlopen(base + "/state", timeout=30) as resp:
                    state = AgentState.from_json(resp.read())
            except OSError:
                return None
            return state if state.agent.broker.subscribes and len(state.agent.workers) == 2 else None

        state = wait_for(up, 60, "the agent and its 2 workers", interval=0.2)
        pids = [w.pid for w in state.agent.workers]
        children = {p.pid for p in psutil.Process(proc.pid).children(recursive=True)}
        assert set(pids) <= children
        report = rig.start_edge(["arm-001", "arm-002", "arm-003"], seconds=2.0).join(30)
        wait_handled(lambda: get_state(base), report.published)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0
    # No worker outlives the agent: systemd's stop leaves nothing behind. (It joins its workers before it
    # exits, so they are gone already, not on their way out.)
    assert not [
        p for p in pids if psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE
    ]
    log_lines = [
        json.loads(line) for line in rig.workdir.glob("agent-*.log").__next__().read_text().splitlines()
    ]
    workers_seen = {line.get("worker") for line in log_lines if line.get("msg") == "worker stopped"}
    assert workers_seen == {0, 1}
    stopped = [line for line in log_lines if line.get("msg") == "agent stopped"]
    assert [line.get("worker") for line in stopped] == [None]  # the receiving process's own line, once


@pytest.mark.slow
def test_a_killed_fork_server_is_named_and_its_workers_run_again(rig: LocalRig) -> None:
    # The workers' exit codes come through their fork server: with it killed, multiprocessing reports 255
    # for workers that still run. The log said each "exited (code 255)", and nothing of the fork server.
    fleet = ["arm-001", "arm-002", "arm-003", "arm-004"]
    extra = ("--workers", "2", "--units", "ticks")
    with rig.agent_process(devices=",".join(fleet), extra_args=extra, log_name="forkserver") as (proc, base):

        def workers() -> list[Any]:
            try:
                return list(get_state(base).agent.workers)
            except OSError:
                return []

        def both(restarts: int) -> list[Any] | None:
            now = workers()
            ok = len(now) == 2 and all(w.alive and w.restarts == restarts for w in now)
            return now if ok else None

        first = wait_for(lambda: both(0), 60, "2 workers")
        (server,) = [p for p in psutil.Process(proc.pid).children() if "forkserver" in " ".join(p.cmdline())]
        old = [psutil.Process(w.pid) for w in first]
        server.kill()
        wait_for(lambda: both(1), 60, "both workers running again", interval=0.1)
        wait_for(lambda: not running(old), 30, "the old workers to stop", interval=0.1)
        lines = [
            json.loads(t)
            for t in rig.agent_log(base.rsplit(":", 1)[1], "forkserver").read_text().splitlines()
            if t.startswith("{")
        ]
    errors = [ln for ln in lines if ln["level"] == "ERROR"]
    # Each worker's line names the fork server; none blames a worker that did not exit.
    named = [ln for ln in errors if "the fork server that started it is gone" in ln["msg"]]
    assert sorted(ln["worker"] for ln in named) == [0, 1], errors
    assert not [ln for ln in errors if "exited (code 255)" in ln["msg"]], errors


@pytest.mark.slow
def test_a_worker_that_runs_but_answers_nothing_is_killed_and_started_again(
    rig: LocalRig, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A worker process stuck for good (here stopped with SIGSTOP: a native call holding the GIL looks the
    same from outside) kept its arms' messages queued, with nothing to say so until the queue overflowed.
    After HUNG_AFTER_ASKS unanswered asks it is killed and started again from its checkpoint, as after a
    crash. The asks' timeout is cut to a second here; the agent's is ten."""
    monkeypatch.setattr(shards, "ASK_TIMEOUT_S", 1.0)
    agent = rig.start_agent({"telemetry.units": "ticks"}, workers=2)
    fleet = ["arm-001", "arm-002", "arm-003", "arm-004"]
    shard = agent._shards[agent.plan.worker_of("arm-001")]
    assert isinstance(shard, shards.WorkerShard)
    victim = shard.pid
    edge = rig.start_edge(fleet, rate_hz=10.0)
    try:
        wait_for(lambda: set(fleet) <= set(agent.state().devices), 60, "every arm")
        # Stopped, not killed: the agent must find it hung, kill it and start it again.
        signal_and_await_restart(shard, signal.SIGSTOP, timeout=120)

        def received() -> int:
            # The new worker lists the arm once it has taken its checkpoint and the messages since back.
            arm = agent.state().devices.get("arm-001")
            return arm.health.counters.received if arm is not None else 0

        before = wait_for(received, 60, "arm-001 back")
        wait_for(lambda: received() > before, 60, "arm-001 counted again")
        assert not psutil.pid_exists(victim) or psutil.Process(victim).status() == psutil.STATUS_ZOMBIE
        # Any of the lines: on a machine busy enough that the other worker also answered three asks late (a
        # one-second timeout here), it may have been restarted first, and that is not what this checks.
        hung = [r.getMessage() for r in caplog.records if "it is hung" in r.getMessage()]
        assert any(f"worker {shard.index} (pid {victim})" in line for line in hung), hung
    finally:
        edge.stop()
        with contextlib.suppress(ProcessLookupError):
            os.kill(victim, signal.SIGCONT)


# Junk that must take no place in the device budget: garbage on invented devices' topics (on both workers),
# JSON that is not telemetry, a valid message on another device's topic, and a topic that names no device.
JUNK_DEVICES = [f"junk-{i}" for i in range(8)] + [f"ghost-{i}" for i in range(8)]


@pytest.mark.slow
def test_junk_takes_no_place_and_the_device_limit_holds_across_workers(rig: LocalRig) -> None:
    plan = WorkerPlan(2)
    assert {plan.worker_of(d) for d in JUNK_DEVICES} == {0, 1}
    # arm-001 is on worker 1, arm-004 and arm-005 on worker 0: the three places are taken on both workers.
    order = ("arm-001", "arm-004", "arm-005", "arm-002", "arm-006")
    assert [plan.worker_of(d) for d in order] == [1, 0, 0, 1, 0]
    config = '[telemetry]\nmax_devices = 3\nunits = "ticks"\n'
    with rig.agent_process(devices="*", config_text=config, extra_args=("--workers", "2")) as (_proc, base):

        def up() -> AgentState | None:
            try:
                state = get_state(base)
            except OSError:
                return None
            workers = state.agent.workers
            ready = state.agent.broker.subscribes and len(workers) == 2 and all(w.alive for w in workers)
            return state if ready else None

        wait_for(up, 60, "the agent and its 2 workers", interval=0.2)
        publisher = Publisher(rig.broker.url)
        try:
            rng = random.Random(7)
            for device in JUNK_DEVICES[:8]:
                publisher.publish(device, b"not json")
            for device in JUNK_DEVICES[8:]:
                publisher.publish(device, json.dumps({"device_id": device}).encode())
            publisher.publish("ghost-9", encode(make_payload("arm-009", 0.0, "ticks", rng)))
            nameless = f"{DEFAULT_TOPIC_PREFIX}/{'x' * 129}/telemetry"  # longer than a device id may be
            publisher.client.publish(
                mqtt5.PublishPacket(topic=nameless, payload=b"{}", qos=mqtt5.QoS.AT_MOST_ONCE)
            ).result(30)
        finally:
            publisher.close()
        sent = len(JUNK_DEVICES) + 2

        def counted() -> AgentState | None:
            state = get_state(base)
            return state if sum(state.untracked_rejected.values()) >= sent else None

        state = wait_for(counted, 60, f"the {sent} junk messages rejected")
        assert sum(state.untracked_rejected.values()) == sent, state.untracked_rejected
        assert "too_many_devices" not in state.untracked_rejected
        assert state.devices == {}

        # Three arms, one after another: each is admitted and mirrored, whichever worker it lands on.
        for arms in (["arm-001"], ["arm-004", "arm-005"]):
            report = rig.start_edge(arms, seconds=1.5, rate_hz=10.0).join(30)

            def mirrored(arms: list[str] = arms, report: Any = report) -> bool:
                # Every message reached the arm's twin: applied, or coalesced by a worker behind.
                devices = get_state(base).devices
                return all(
                    d in devices
                    and (c := devices[d].health.counters).applied + c.coalesced == report.per_device[d]
                    for d in arms
                )

            wait_for(mirrored, 60, f"{arms} mirrored")

        # The budget is spent across both workers: a fourth and fifth arm are refused, each on its own worker.
        report = rig.start_edge(["arm-002", "arm-006"], seconds=1.5, rate_hz=10.0).join(30)

        def refused() -> AgentState | None:
            state = get_state(base)
            return state if state.untracked_rejected.get("too_many_devices") == report.published else None

        state = wait_for(refused, 60, "every message of the fourth and fifth arm refused")
        assert sorted(state.devices) == ["arm-001", "arm-004", "arm-005"]
        assert [w.devices for w in state.agent.workers] == [2, 1]


@pytest.mark.slow
def test_a_setting_only_a_worker_can_check_stops_twin_run_with_exit_code_2(tmp_path: Path) -> None:
    # The calibration file exists (the config loads), but only a mirror reads it: in a worker process here.
    calibration = tmp_path / "arm.json"
    calibration.write_text("{not a calibration")
    config = tmp_path / "agent.toml"
    config.write_text(f'[telemetry]\ncalibration = "{calibration}"\n')
    broker = NO_BROKER  # never reached: the workers fail before the pool starts
    run = ["run", "--config", str(config), "--workers", "2", "--broker", broker, "--http", "127.0.0.1:0"]
    done = run_twin(run, child_env())
    assert done.returncode == 2, done.stderr
    assert "configuration error: telemetry.calibration" in done.stderr
    assert str(calibration) in done.stderr


@pytest.mark.slow
@pytest.mark.parametrize("failure", ["http_address_taken", "no_aws_region"])
def test_a_start_that_fails_reports_only_the_stop_it_made(tmp_path: Path, failure: str) -> None:
    # `twin run` that cannot start exits 1 (docs/agent.md, "Exit codes"). It used to stop its workers twice:
    # the second stop found their pipes closed, logged an ERROR that both were killed at the 60 s budget with
    # what they held lost, and saved an empty state file over the alarms it kept. Here the workers start and
    # stop cleanly (HTTP address taken), or are never launched (no region for IoT Core).
    state_file = tmp_path / "state.json"
    latched = AlarmRecord(
        device="arm-001",
        joint="elbow_flex",
        kind=AlarmKind.OVER_TEMPERATURE,
        state=AlarmState.LATCHED,
        since=time.monotonic(),
        present=False,
        raised=1,
        value=63.0,
        message="elbow_flex servo at 63 C",
    )
    assert StateFile(state_file).save([latched], time.monotonic(), time.time())
    config = tmp_path / "agent.toml"
    config.write_text(f'[twin]\nstate_file = "{state_file}"\n')
    env = child_env()
    # A broker port bound but not listening, held for the test: refused, and no other process can take it.
    with socket.socket() as taken, socket.socket() as no_broker:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        no_broker.bind(("127.0.0.1", 0))
        if failure == "http_address_taken":
            broker = f"mqtt://127.0.0.1:{no_broker.getsockname()[1]}"
            http = f"127.0.0.1:{taken.getsockname()[1]}"
        else:
            broker, http = "iot", "127.0.0.1:0"
            empty = tmp_path / "aws-config"
            empty.write_text("")
            env = {k: v for k, v in env.items() if k not in ("AWS_REGION", "AWS_DEFAULT_REGION")}
            env |= {"AWS_CONFIG_FILE": str(empty), "AWS_SHARED_CREDENTIALS_FILE": str(empty)}
        run = ["run", "--config", str(config), "--workers", "2", "--broker", broker, "--http", http]
        done = run_twin(run, env)
    assert done.returncode == 1, done.stderr
    assert "cannot start" in done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    stopped = [
        (line["level"], line["workers_killed"], line["unwritten"])
        for line in lines
        if line["logger"] == "twin.service.agent" and line["msg"].startswith("agent stopped")
    ]
    assert stopped == [("INFO", [], {})], done.stdout
    assert [line["msg"] for line in lines if line["level"] == "ERROR"] == ["cannot start"], done.stdout
    kept = StateFile(state_file).load(time.monotonic(), time.time())
    assert [(r.alarm_id, r.state) for r in kept] == [(latched.alarm_id, AlarmState.LATCHED)]


@pytest.mark.parametrize("workers", [1, 2])
def test_the_started_line_counts_the_mirrors_and_names_each_process(
    tmp_path: Path, workers: int, caplog: pytest.LogCaptureFixture
) -> None:
    """A walk: `--workers 1` logged "workers": 0, as its one mirror runs in the agent's own process, which
    read as no mirror at all."""
    caplog.set_level(logging.INFO, logger="twin.service.agent")
    agent = unbrokered_agent(tmp_path, workers=workers)
    try:
        [started] = [r for r in caplog.records if r.getMessage() == "agent started"]
        assert started.workers == workers
        assert len(started.worker_pids) == (0 if workers == 1 else workers)
    finally:
        agent.stop()
