"""The fault matrix: each fault for real against a live agent, and the counters accounting for every message.

One private mosquitto for the module (the broker case restarts it); each case starts its own agent, runs a
few seconds of a small fleet through its fault, and checks the same things:

- every message the agent accepted (its broker connections delivered) is counted: against its arm (received
  = decoded + rejected, decoded = applied + stale + coalesced), as a rejection of no arm, or as dropped with
  a reason (a full queue), and nothing is still pending;
- what the fleet published and the agent did not receive is what its loss estimate says is missing;
- and what the case is about: history's rows are in the table or counted as dropped, the arms keep their
  twins through a worker's death, the junk takes no place, ...

The cases: the broker killed and restarted; a worker SIGKILLed; the S3 endpoint (moto's server, not AWS)
stopped for longer than history's buffer; a full disk (a 2 MiB tmpfs) under history and the USD recording;
edge clocks skewed by an hour either way; a 10x burst; a flood of junk topics.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import threading
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
from conftest import Publisher, get_metrics, metric, wait_for
from moto_s3 import MotoS3
from test_emf import validate_emf_line
from twin.bench.harness import collect, start_publisher
from twin.bench.wire import WirePublisher, publish_packet, topic_field
from twin.core.topics import telemetry_topic
from twin.edge.payload import encode, make_payload
from twin.rig.local import LocalRig, RigError
from twin.service.agent import AgentService
from twin.service.shards import WorkerPlan
from twin.service.state import AgentState
from twin.transport.broker import new_client_id

pytestmark = pytest.mark.slow

PREFIX = "dt/lerobot"
# How long a wait for the agent's progress may take. Each needs a second or two of the fleet's messages; a
# loaded machine stretches that by how long it keeps the agent or the fleet off the CPU, so the bound is a
# hang's, not a speed's (a wait returns as soon as its condition holds).
PROGRESS_S = 60.0


@pytest.fixture(scope="module")
def matrix_rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalRig]:
    try:
        rig = LocalRig(workdir=tmp_path_factory.mktemp("matrix"))
    except RigError as exc:
        pytest.fail(str(exc))
    with rig:
        yield rig


@pytest.fixture(scope="module")
def matrix_publisher(matrix_rig: LocalRig) -> Iterator[Publisher]:
    publisher = Publisher(matrix_rig.broker.url)
    yield publisher
    publisher.close()


class Fleet:
    """Arms publishing ticks telemetry at `rate_hz` in a thread, stamped on their sampling grid (plus
    `skew_ms` per arm, an edge clock that is off), through the awscrt client, which reconnects after a
    broker restart. `generated` counts every sample by arm, `failed` those the client refused."""

    def __init__(
        self,
        publisher: Publisher,
        devices: Sequence[str],
        rate_hz: float = 10.0,
        skew_ms: dict[str, int] | None = None,
    ) -> None:
        self.publisher = publisher
        self.devices = list(devices)
        self.period = 1.0 / rate_hz
        self.skew_ms = skew_ms or {}
        self.generated: Counter[str] = Counter()
        self.failed = 0
        self._rng = random.Random(5)
        self._start_wall = time.time()
        self._k = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        start_mono = time.monotonic()
        while not self._stop.is_set():
            due = start_mono + self._k * self.period
            self._stop.wait(max(0.0, due - time.monotonic()))
            self._publish_round()

    def _publish_round(self) -> dict[str, int]:
        """One sample of every arm at the next grid step; their edge stamps."""
        k = self._k
        stamp = int((self._start_wall + k * self.period) * 1000)
        stamps = {}
        for device in self.devices:
            stamps[device] = stamp + self.skew_ms.get(device, 0)
            payload = make_payload(device, k * self.period, "ticks", self._rng, timestamp_ms=stamps[device])
            self.generated[device] += 1
            try:
                self.publisher.publish(device, encode(payload))
            except Exception:
                self.failed += 1  # the broker is down: an edge loses QoS 0 messages too
        self._k = k + 1
        return stamps

    def stop(self) -> None:
        self._stop.set()
        # Joined before anyone reads `generated` or publishes the tail: a round still running would race them.
        self._thread.join(PROGRESS_S)
        assert not self._thread.is_alive(), "the fleet's thread did not stop"

    def close_tail(self, agent: AgentService, timeout: float = PROGRESS_S) -> None:
        """After `stop`: one last sample of every arm, waited for at the agent. One connection keeps its
        messages in order, so once each arm's last sample is there, everything before it that was going to
        arrive has, and a sample lost at the end shows as a hole before the last one (a loss estimate cannot
        see past an arm's last message)."""
        last = self._publish_round()

        def arrived() -> bool:
            devices = agent.state().devices
            return all(d in devices and devices[d].health.last_timestamp_ms == last[d] for d in last)

        wait_for(arrived, timeout, "each arm's last sample at the agent", interval=0.1)


def settled(agent: AgentService, timeout: float = PROGRESS_S, *, expect: int = 0) -> AgentState:
    """The state once every message the agent accepted is counted or dropped and nothing is pending (and,
    with `expect`, it accepted at least that many: the last ones may still be on their way)."""

    def done() -> AgentState | None:
        state = agent.state()
        counted = sum(d.health.counters.received for d in state.devices.values())
        counted += sum(state.untracked_rejected.values())
        accepted = state.agent.broker.messages
        # The mirror counts a batch's messages against their arms stage by stage and adds the batch to
        # `processed` once its last stage is done: a reader in between sees them counted, not yet processed.
        quiet = (
            state.agent.mailbox.pending == 0
            and counted + state.agent.mailbox.overwritten_total == accepted
            and state.agent.worker.processed == counted
        )
        last[:] = [accepted, counted, state.agent.mailbox.overwritten_total, state.agent.worker.processed]
        return state if quiet and accepted >= expect else None

    last: list[int] = []
    try:
        return wait_for(done, timeout, "every accepted message counted or dropped", interval=0.1)
    except AssertionError as exc:
        # What was short, for the next person: the agent behind, or messages that never reached it.
        raise AssertionError(
            f"{exc}: accepted, counted, overwritten, processed = {last}; expected at least {expect} accepted"
        ) from None


def check_accounts(state: AgentState) -> None:
    """Every accepted message is counted once: against its arm, as a rejection of no arm, or as dropped."""
    counted = sum(d.health.counters.received for d in state.devices.values())
    untracked = sum(state.untracked_rejected.values())
    assert counted + untracked + state.agent.mailbox.overwritten_total == state.agent.broker.messages
    assert state.agent.worker.processed == counted + untracked
    for device, d in state.devices.items():
        c = d.health.counters
        assert c.received == c.decoded + c.rejected_total, device
        assert c.decoded == c.applied + c.ignored_stale + c.coalesced, device
        assert c.errors == 0, device


def test_broker_killed_and_restarted(matrix_rig: LocalRig, matrix_publisher: Publisher) -> None:
    devices = ["brk-1", "brk-2", "brk-3"]
    agent = matrix_rig.start_agent({"telemetry.devices": devices, "telemetry.units": "ticks"})
    fleet = Fleet(matrix_publisher, devices)
    try:
        wait_for(
            lambda: all(d.health.counters.applied > 10 for d in agent.state().devices.values()),
            PROGRESS_S,
            "mirroring",
        )
        subscribes = agent.state().agent.broker.subscribes
        matrix_rig.broker.restart(hard=True)  # SIGKILL: no clean close
        wait_for(
            lambda: agent.state().agent.broker.subscribes > subscribes,
            PROGRESS_S,
            "the agent to subscribe again",
        )
        after = agent.state()
        wait_for(
            lambda: all(
                agent.state().devices[d].health.counters.applied
                > after.devices[d].health.counters.applied + 10
                for d in devices
            ),
            PROGRESS_S,
            "mirroring again",
        )
    finally:
        fleet.stop()
    fleet.close_tail(agent)
    state = settled(agent)
    agent.stop()
    check_accounts(state)
    assert state.agent.broker.disconnections >= 1
    # What the agent did not get (lost with the broker, or refused while it was down; the client may also
    # have held them and sent them after it reconnected) is what it estimates lost.
    for device in devices:
        d = state.devices[device]
        missing = fleet.generated[device] - d.health.counters.received
        assert abs(missing - d.loss.lost) <= 1, (device, missing, d.loss)


def test_a_worker_sigkilled(matrix_rig: LocalRig, matrix_publisher: Publisher) -> None:
    devices = ["wk-1", "wk-2", "wk-3", "wk-4"]
    plan = WorkerPlan(2, devices)
    agent = matrix_rig.start_agent({"telemetry.devices": devices, "telemetry.units": "ticks"}, workers=2)
    fleet = Fleet(matrix_publisher, devices)
    try:
        wait_for(lambda: len(agent.state().devices) == 4, PROGRESS_S, "all arms mirrored")
        wait_for(lambda: agent._shards[1].checkpoint is not None, PROGRESS_S, "worker 1's checkpoint")
        victim = agent.state().agent.workers[1]
        os.kill(victim.pid, signal.SIGKILL)
        wait_for(
            lambda: agent.state().agent.workers[1].alive and agent.state().agent.workers[1].restarts == 1,
            60,
            "worker 1 running again",
            interval=0.1,
        )
        before = agent.state()
        wait_for(
            lambda: all(
                agent.state().devices[d].health.counters.applied
                > before.devices[d].health.counters.applied + 5
                for d in plan.devices_of(1)
            ),
            PROGRESS_S,
            "its arms mirrored again",
        )
    finally:
        fleet.stop()
    state = settled(agent, expect=sum(fleet.generated.values()))
    agent.stop()
    check_accounts(state)
    # Nothing was lost with the worker: the agent sent it again what its last checkpoint did not count.
    assert state.agent.mailbox.overwritten_total == 0 and state.agent.workers[1].dropped == 0
    for device in devices:
        assert state.devices[device].health.counters.received == fleet.generated[device]
        assert state.devices[device].loss.lost == 0


def _table_rows(uri: str, options: dict[str, str] | None = None) -> int:
    from deltalake import DeltaTable

    return int(DeltaTable(f"{uri}/telemetry", storage_options=options).to_pyarrow_dataset().count_rows())


def test_s3_stopped_longer_than_the_history_buffer(
    matrix_rig: LocalRig, matrix_publisher: Publisher, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """S3 is moto's server mode on loopback, not AWS. The outage outlasts history's buffer: rows are dropped
    and counted, the EMF lines carry the drops and the lag (the stack alarms on both), and once S3 is back
    every decoded message is a row in the table or one counted as dropped."""
    s3 = MotoS3()
    try:
        options = s3.storage_options()
        for key, value in options.items():
            if key.startswith("AWS_"):
                monkeypatch.setenv(key, value)
        uri = f"s3://{s3.bucket}/history"
        devices = [f"s3-{i}" for i in range(10)]
        emf = tmp_path / "emf.log"
        agent = _start_with_s3_history(matrix_rig, devices, uri, emf)
        fleet = Fleet(matrix_publisher, devices)
        try:
            wait_for(
                lambda: (agent.state().agent.history.commits or 0) >= 2, PROGRESS_S, "history committing"
            )
            s3.stop()
            _wait_for_the_outage_to_show(agent, emf)
            s3.start()
        finally:
            fleet.stop()
        # Waited for until every sample the fleet published is counted: one still on its way when the count
        # was read would become a table row the count does not have.
        state = settled(agent, expect=sum(fleet.generated.values()) - fleet.failed)
        decoded = sum(d.health.counters.decoded for d in state.devices.values())
        # Waited for until the writer has committed or dropped every row with S3 back, not left to the stop:
        # a writer starved by a busy machine is killed at the stop's budget, and the rows it held reach
        # HistoryRowsDropped (the last EMF line) but not the writer's own rows_dropped compared with it below.
        wait_for(lambda: _caught_up(agent, decoded), PROGRESS_S, "the writer to catch up with S3 back")
        agent.stop()
        check_accounts(state)
        _check_every_row_written_or_dropped(agent, emf, _table_rows(uri, options), decoded)
    finally:
        s3.close()


def _start_with_s3_history(rig: LocalRig, devices: list[str], uri: str, emf: Path) -> AgentService:
    """An agent writing history to `uri` with a buffer an outage soon outlasts, and EMF every half second."""
    return rig.start_agent(
        {
            "telemetry.devices": devices,
            "telemetry.units": "ticks",
            "history.uri": uri,
            "history.commit_every_s": 0.5,
            "history.commit_every_rows": 50,
            "history.max_buffer_rows": 300,
            "cloudwatch.emf_file": str(emf),
            "cloudwatch.agent_name": "matrix",
            "cloudwatch.interval_s": 0.5,
        }
    )


def _wait_for_the_outage_to_show(agent: AgentService, emf: Path) -> None:
    """With S3 stopped: rows dropped, and the EMF lines CloudWatch gets carry the drops, the lag growing while
    the outage lasts, and that commits are failing (the stack alarms on each); /metrics shows the lag too."""
    wait_for(lambda: agent.state().agent.history.rows_dropped > 0, 60, "the buffer to overflow", interval=0.2)
    wait_for(
        lambda: any(d.get("HistoryRowsDropped", 0) > 0 for d in _emf(emf)), PROGRESS_S, "the drops in EMF"
    )
    wait_for(
        lambda: any(d.get("HistoryLagSeconds", 0.0) > 2.0 for d in _emf(emf)), PROGRESS_S, "the lag in EMF"
    )
    # The HistoryCommitFailures alarm pages on this gauge.
    wait_for(
        lambda: any(d.get("HistoryCommitsFailing") == 1 for d in _emf(emf)),
        PROGRESS_S,
        "commits failing in EMF",
    )
    # A commit in flight when S3 stopped may still have landed, which starts the lag again from the rows
    # after it: it grows from there while the outage lasts.
    wait_for(
        lambda: metric(get_metrics(agent.http_url), "twin_history_lag_seconds") > 2.0,
        PROGRESS_S,
        "the lag in /metrics",
        interval=0.2,
    )


def _check_every_row_written_or_dropped(
    agent: AgentService, emf: Path, table_rows: int, decoded: int
) -> None:
    """After the stop, with S3 back: the EMF lines told the drops and commit failures and cleared the alarm,
    and every decoded message is one of the table's `table_rows` or counted as dropped."""
    report = agent.stop_reports[0]
    assert report is not None and "history_rows" not in report.unwritten
    # The writer's figures once it stopped (a failed commit's rows may be dropped after the fleet stops).
    history = agent.state().agent.history
    assert history is not None
    lines = _emf(emf)
    # Each line counts its interval's drops (the last interval's may come after the agent stopped).
    assert 0 < sum(d.get("HistoryRowsDropped", 0) for d in lines) <= history.rows_dropped
    assert sum(d.get("HistoryCommitFailures", 0) for d in lines) > 0
    # Storage back and every row written: the last line clears the alarm.
    assert [d["HistoryCommitsFailing"] for d in lines if "HistoryCommitsFailing" in d][-1] == 0
    assert table_rows + history.rows_dropped == decoded


def _caught_up(agent: AgentService, decoded: int) -> bool:
    """The writer has read every decoded row and committed or dropped each one, with its storage back."""
    history = agent.state().agent.history
    assert history is not None
    done = history.rows_committed + history.rows_dropped + history.rows_lost
    return history.storage_ok and history.rows_buffered == 0 and history.rows_received >= decoded == done


def _emf(path: Path) -> list[dict[str, Any]]:
    return [validate_emf_line(line) for line in path.read_text().splitlines()]


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A real filesystem that really fills: an 8 MiB tmpfs (the tests run as root, as `make setup` does)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mount)], check=True)
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_full_disk_under_history_and_the_recording(
    matrix_rig: LocalRig, matrix_publisher: Publisher, small_disk: Path
) -> None:
    devices = ["disk-1", "disk-2", "disk-3", "disk-4"]
    agent = matrix_rig.start_agent(
        {
            "telemetry.devices": devices,
            "telemetry.units": "ticks",
            "history.uri": str(small_disk / "history"),
            "history.commit_every_s": 0.5,
            "history.commit_every_rows": 50,
            "history.max_buffer_rows": 200,
            "twin.record_dir": str(small_disk / "usd"),
            "twin.record_flush_s": 0.5,
            "twin.record_max_mb": 1.0,
            "twin.record_budget_mb": 2.0,
        }
    )
    fleet = Fleet(matrix_publisher, devices)
    filler = small_disk / "filler"
    try:
        wait_for(lambda: (agent.state().agent.history.commits or 0) >= 1, PROGRESS_S, "history committing")
        # Fill what is left, so the next commits and saves meet ENOSPC.
        try:
            with filler.open("wb") as fh:
                while True:
                    fh.write(b"\0" * 65536)
                    fh.flush()
        except OSError:
            pass
        wait_for(
            lambda: agent.state().agent.history.rows_dropped > 0, 60, "history to drop rows", interval=0.2
        )
        # The buffer may overflow while the commit that meets the full disk is still on its way.
        state = wait_for(
            lambda: (
                (s := agent.state()).agent.history is not None
                and not s.agent.history.storage_ok
                and "disk is full" in s.agent.history.last_error
                and s
            ),
            60,
            "a commit failing on the full disk, said so",
            interval=0.2,
        )
        applied = sum(d.health.counters.applied for d in state.devices.values())
        # The twin goes on mirroring whatever the disk does.
        wait_for(
            lambda: sum(d.health.counters.applied for d in agent.state().devices.values()) > applied + 40,
            PROGRESS_S,
            "the twin to keep mirroring",
        )
        filler.unlink()  # space again: writing resumes, and the recording goes on in a new session
        rotations = agent.state().agent.recording.rotations
        wait_for(lambda: agent.state().agent.history.storage_ok, 60, "history writing again", interval=0.2)
        wait_for(
            lambda: agent.state().agent.recording.rotations > rotations,
            PROGRESS_S,
            "a new session",
            interval=0.2,
        )
    finally:
        fleet.stop()
    state = settled(agent, expect=sum(fleet.generated.values()))
    agent.stop()
    check_accounts(state)
    final = agent.state().agent
    # The failed saves are counted; the session they broke was set aside (writing to it again would crash
    # usd-core), and the samples meanwhile counted as dropped by the recording.
    assert final.recording is not None and final.recording.flush_errors > 0
    assert final.recording.samples_dropped > 0
    assert final.history is not None
    decoded = sum(d.health.counters.decoded for d in state.devices.values())
    assert _table_rows(str(small_disk / "history")) + final.history.rows_dropped == decoded


def test_edge_clocks_an_hour_off_either_way(matrix_rig: LocalRig, matrix_publisher: Publisher) -> None:
    devices = ["ahead-1", "behind-1", "right-1"]
    skew = {"ahead-1": 3_600_000, "behind-1": -3_600_000}
    agent = matrix_rig.start_agent({"telemetry.devices": devices, "telemetry.units": "ticks"})
    fleet = Fleet(matrix_publisher, devices, skew_ms=skew)
    try:
        wait_for(
            lambda: all(d.health.counters.applied > 30 for d in agent.state().devices.values()),
            PROGRESS_S,
            "mirroring",
        )
    finally:
        fleet.stop()
    state = settled(agent, expect=sum(fleet.generated.values()))
    agent.stop()
    check_accounts(state)
    for device in devices:
        d = state.devices[device]
        # Every message decoded and applied (or coalesced, had the agent fallen behind for a moment), none
        # rejected for its time, no loss; the offset shows in the health figures.
        c = d.health.counters
        assert c.decoded == c.received == fleet.generated[device] and c.rejected_total == 0, (device, c)
        assert c.applied + c.coalesced == c.decoded, (device, c)
        assert d.loss.lost == 0
        offset = d.health.edge_clock_offset_s
        assert offset is not None and abs(offset + skew.get(device, 0) / 1000.0) < 5.0


def test_a_10x_burst(matrix_rig: LocalRig) -> None:
    arms, rate = 50, 10.0
    devices = [f"arm-{i:04d}" for i in range(1, arms + 1)]
    agent = matrix_rig.start_agent({"telemetry.devices": ["*"], "telemetry.units": "ticks"})
    url = matrix_rig.broker.url
    sent = 0
    # Steady, then ten times the rate (every arm at 100 Hz), then steady again: three publisher processes in
    # turn, each writing its packets straight to the broker's socket.
    for phase_rate, seconds in ((rate, 2.0), (10 * rate, 2.0), (rate, 2.0)):
        sent += collect([start_publisher(url, 1, arms, phase_rate, seconds)], timeout=60)["sent"]
    state = settled(agent, expect=sent)
    agent.stop()
    check_accounts(state)
    assert state.agent.broker.messages == sent
    assert set(state.devices) == set(devices)


def test_a_flood_of_junk_topics(matrix_rig: LocalRig, matrix_publisher: Publisher) -> None:
    good = ["good-1", "good-2"]
    agent = matrix_rig.start_agent(
        {"telemetry.devices": ["*"], "telemetry.units": "ticks", "telemetry.max_devices": 50}
    )
    fleet = Fleet(matrix_publisher, good)
    junk = WirePublisher(matrix_rig.broker.url, new_client_id("junk-"))
    junk.connect()
    flooded = 0
    try:
        wait_for(lambda: all(d in agent.state().devices for d in good), PROGRESS_S, "the good arms mirrored")
        rng = random.Random(9)
        for batch in range(20):
            packets = []
            for i in range(1000):
                n = batch * 1000 + i
                topic = telemetry_topic(PREFIX, f"junk-{n:05d}")
                body = b"{not json" if n % 3 else encode(make_payload(f"junk-{n:05d}", 0.0, "ticks", rng))
                packets.append(publish_packet(topic_field(topic), body))
            junk.send(packets)
            flooded += len(packets)
    finally:
        junk.close()
        fleet.stop()
    state = settled(agent, timeout=60, expect=flooded + sum(fleet.generated.values()))
    agent.stop()
    check_accounts(state)
    assert state.agent.broker.messages >= flooded
    # The good arms lost nothing to the flood: every sample was received and decoded (one the agent, behind
    # for a moment, coalesced is counted and in history, only not shown); the junk took at most the places
    # left under max_devices.
    for device in good:
        c = state.devices[device].health.counters
        assert c.decoded == c.applied + c.coalesced == fleet.generated[device], (device, c)
    assert len(state.devices) <= 50
    assert sum(state.untracked_rejected.values()) > 0
