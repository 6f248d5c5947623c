"""EMF lines against the CloudWatch "Specification: Embedded metric format" (CloudWatch user guide).

The spec is expressed twice here: as a JSON Schema for the shape (its required members, types, lengths and
the unit names it allows), and as checks for the rules a schema cannot say (every directive's names must be
root members; metric targets are numbers or arrays of at most 100 numbers; dimension targets are strings of
at most 1024 characters; a directive defines at most 100 metrics; an event is at most 1 MB). The validator is
itself tested on documents that break each rule, so it cannot pass everything.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import math
import threading
import time
import types
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import jsonschema
import pytest
from conftest import wait_for
from twin.core.health import DeviceStatus, HealthSnapshot
from twin.core.loss import LossSnapshot
from twin.output.emf import (
    AGENT_DIMENSION,
    CLOCK_STEP_TELL_EVERY_S,
    LOSS_METRICS,
    NAMESPACE,
    UNSENT_FILE_BYTES,
    UNSENT_TELL_EVERY_S,
    EmfFileWriter,
    EmfPublisher,
    FleetMetrics,
    FleetTotals,
    Metric,
    UnsentCount,
    emf_document,
    fleet_documents,
    next_slot,
    realigned_slot,
    unsent_path,
)
from twin.service.agent import AgentService, fleet_totals
from twin.service.state import (
    AgentInfo,
    AgentState,
    BrokerState,
    ConnectionState,
    DeviceState,
    HistoryState,
)

CLOUDWATCH_UNITS = (
    "Seconds|Microseconds|Milliseconds|Bytes|Kilobytes|Megabytes|Gigabytes|Terabytes|Bits|Kilobits|Megabits|"
    "Gigabits|Terabits|Percent|Count|Bytes/Second|Kilobytes/Second|Megabytes/Second|Gigabytes/Second|"
    "Terabytes/Second|Bits/Second|Kilobits/Second|Megabits/Second|Gigabits/Second|Terabits/Second|"
    "Count/Second|None"
)
NAME = {"type": "string", "minLength": 1, "maxLength": 1024}
EMF_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["_aws"],
    "properties": {
        "_aws": {
            "type": "object",
            "required": ["Timestamp", "CloudWatchMetrics"],
            "properties": {
                "Timestamp": {"type": "integer", "minimum": 0},
                "CloudWatchMetrics": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "required": ["Namespace", "Dimensions", "Metrics"],
                        "additionalProperties": False,
                        "properties": {
                            "Namespace": NAME,
                            "Dimensions": {
                                "type": "array",
                                "minItems": 1,
                                "items": {
                                    "type": "array",
                                    "maxItems": 30,
                                    "items": {"type": "string", "minLength": 1, "maxLength": 250},
                                },
                            },
                            "Metrics": {
                                "type": "array",
                                "maxItems": 100,
                                "items": {
                                    "type": "object",
                                    "required": ["Name"],
                                    "additionalProperties": False,
                                    "properties": {
                                        "Name": NAME,
                                        "Unit": {"type": "string", "pattern": f"^({CLOUDWATCH_UNITS})$"},
                                        "StorageResolution": {"enum": [1, 60]},
                                    },
                                },
                            },
                        },
                    },
                },
            },
        }
    },
}


def validate_emf_line(line: str) -> dict[str, Any]:
    """Raises (jsonschema.ValidationError or AssertionError) unless `line` is one valid EMF log event."""
    assert len(line.encode()) <= 1024 * 1024, "an EMF event is at most 1 MB"
    assert line == line.strip() and "\n" not in line, "one event per line, nothing around the JSON object"
    doc = json.loads(line, parse_constant=lambda token: pytest.fail(f"{token} is not JSON"))
    jsonschema.validate(doc, EMF_SCHEMA)
    for directive in doc["_aws"]["CloudWatchMetrics"]:
        for dimension_set in directive["Dimensions"]:
            for key in dimension_set:
                assert key in doc, f"dimension {key} is not a member of the root node"
                value = doc[key]
                assert isinstance(value, str) and len(value) <= 1024, f"dimension {key} must be a string"
        for definition in directive["Metrics"]:
            name = definition["Name"]
            assert name in doc, f"metric {name} is not a member of the root node"
            value = doc[name]
            values = value if isinstance(value, list) else [value]
            assert len(values) <= 100, f"metric {name} has more than 100 values"
            for v in values:
                assert isinstance(v, int | float) and not isinstance(v, bool), (
                    f"metric {name} is not a number"
                )
                assert math.isfinite(v), f"metric {name} is not finite"
    return doc


FLEET = FleetMetrics(
    messages_per_s=29.8,
    rejects=3,
    loss_percent=0.7,
    worst_arm_loss_percent=33.0,
    devices_online=3,
    devices_stale=1,
    devices_offline=0,
    internal_latency_p99_ms=1.9,
    active_alarms={"critical": 1, "warning": 2},
)


def test_fleet_lines_written_to_the_file_are_valid_emf(tmp_path: Path) -> None:
    writer = EmfFileWriter(tmp_path / "emf" / "metrics.log")
    writer.write(fleet_documents(FLEET, "so101-twin", 1_764_000_000_000))
    lines = writer.path.read_text().splitlines()
    assert len(lines) == 3 and writer.lines_written == 3
    docs = [validate_emf_line(line) for line in lines]
    fleet, critical, warning = docs
    assert fleet[AGENT_DIMENSION] == "so101-twin"
    assert fleet["_aws"]["Timestamp"] == 1_764_000_000_000
    assert fleet["_aws"]["CloudWatchMetrics"][0]["Namespace"] == NAMESPACE
    assert {m["Name"]: m["Unit"] for m in fleet["_aws"]["CloudWatchMetrics"][0]["Metrics"]} == {
        "AgentUp": "Count",
        "MessagesPerSecond": "Count/Second",
        "Rejects": "Count",
        "LossPercent": "Percent",
        "WorstArmLossPercent": "Percent",
        "DevicesOnline": "Count",
        "DevicesStale": "Count",
        "DevicesOffline": "Count",
        "InternalLatencyP99": "Milliseconds",
        "MessagesDropped": "Count",
        "SinkDrops": "Count",
        "WorkerRestarts": "Count",
        "SubscriptionsRefused": "Count",
        "BrokerDisconnected": "Count",
        "DeviceLimitRefusals": "Count",
        "AlertPublishFailures": "Count",
        "EmfWriteFailures": "Count",
    }
    assert (fleet["MessagesPerSecond"], fleet["DevicesStale"], fleet["InternalLatencyP99"]) == (29.8, 1, 1.9)
    assert (fleet["LossPercent"], fleet["WorstArmLossPercent"]) == (0.7, 33.0)
    assert (critical["Severity"], critical["ActiveAlarms"]) == ("critical", 1)
    assert (warning["Severity"], warning["ActiveAlarms"]) == ("warning", 2)
    assert critical["_aws"]["CloudWatchMetrics"][0]["Dimensions"] == [["Agent", "Severity"]]


def test_the_arm_losing_most_is_its_own_figure_and_an_offline_arm_is_not_it() -> None:
    """LossPercent averages the arms' shortfall, so one arm losing 40 % of its messages among ten reads 4;
    WorstArmLossPercent reads its 40 (an OFFLINE arm's old window is not counted: AgentSilent and ArmsStale
    speak for it)."""

    def arm(name: str, recent: float, status: DeviceStatus = DeviceStatus.ONLINE) -> DeviceState:
        health = HealthSnapshot(status=status, rate_hz=10.0 * (1.0 - recent))
        return DeviceState(device_id=name, health=health, loss=LossSnapshot(recent_loss_ratio=recent))

    arms = [arm(f"arm-{i}", 0.0) for i in range(9)]
    arms += [arm("weak", 0.4), arm("gone", 1.0, DeviceStatus.OFFLINE)]
    state = AgentState(agent=AgentInfo(running=True), devices={d.device_id: d for d in arms})
    totals = fleet_totals(state, 10.0)
    assert round(totals.loss_percent or 0.0, 6) == 4.0
    assert round(totals.worst_arm_loss_percent, 6) == 40.0
    # An arm read from a restarting worker's checkpoint has no rate known: not counted as 100 % loss.
    restarting = DeviceState(
        device_id="restarting", health=HealthSnapshot(rate_hz=None, status=DeviceStatus.ONLINE)
    )
    state = AgentState(agent=AgentInfo(running=True), devices={d.device_id: d for d in [*arms, restarting]})
    assert round(fleet_totals(state, 10.0).loss_percent or 0.0, 6) == 4.0


def test_loss_percent_is_left_out_while_no_delivering_arms_rate_is_known(tmp_path: Path) -> None:
    """A one-worker fleet while its worker restarts: every arm is read from its checkpoint, with no rate
    known, and LossPercent read 0 %, an all-clear no one measured. It is left out of the document (the
    MessagesLost alarm takes a minute without it as not breaching); the other figures are still sent."""
    # Built without a rate, a snapshot knows none (as refused_rate_hz): 0.0 there read as 100 % loss.
    restarting = DeviceState(device_id="restarting", health=HealthSnapshot(status=DeviceStatus.ONLINE))
    totals = fleet_totals(AgentState(agent=AgentInfo(running=True), devices={"restarting": restarting}), 10.0)
    assert totals.loss_percent is None
    docs = [d for d in _three_intervals(tmp_path, totals) if "AgentUp" in d]
    assert len(docs) == 3 and not [d for d in docs if "LossPercent" in d], docs
    assert [d["DevicesOnline"] for d in docs] == [1, 1, 1]


def test_no_loss_is_sent_while_every_arm_is_offline(tmp_path: Path) -> None:
    """Nothing is expected of an OFFLINE arm, so nothing of it is measured: with every arm OFFLINE (or none
    at all) LossPercent and WorstArmLossPercent read 0 %, which the dashboard drew as an all-clear beside a
    fleet all offline. They are left out, as when no rate is known (the loss alarms take a minute without
    them as not breaching); the arms' count says why."""
    gone = {"arm-1": DeviceState("arm-1", HealthSnapshot(status=DeviceStatus.OFFLINE, rate_hz=0.0))}
    for devices in (gone, {}):
        totals = fleet_totals(AgentState(agent=AgentInfo(running=True), devices=devices), 10.0)
        assert (totals.loss_percent, totals.worst_arm_loss_percent) == (None, None), devices
        (where := tmp_path / f"arms-{len(devices)}").mkdir()
        docs = [d for d in _three_intervals(where, totals) if "AgentUp" in d]
        assert len(docs) == 3, docs
        assert not [d for d in docs if "LossPercent" in d or "WorstArmLossPercent" in d], docs
        assert [d["DevicesOffline"] for d in docs] == [len(devices)] * 3
    # One arm STALE beside it is measured: its figures are sent, 0 % included.
    stale = DeviceState("arm-2", HealthSnapshot(status=DeviceStatus.STALE, rate_hz=10.0))
    totals = fleet_totals(AgentState(agent=AgentInfo(running=True), devices={**gone, "arm-2": stale}), 10.0)
    assert (totals.loss_percent, totals.worst_arm_loss_percent) == (0.0, 0.0)


def test_history_commits_failing_is_told_while_the_last_commit_failed(tmp_path: Path) -> None:
    """The gauge HistoryCommitFailures pages on: between two backed-off retries no commit fails, yet storage
    is still out; in every interval until a commit works, and never while history is off."""
    history: list[HistoryState | None] = [HistoryState(storage_ok=False, commit_failures=3)]

    def totals() -> FleetTotals:
        return fleet_totals(AgentState(agent=AgentInfo(running=True, history=history[-1]), devices={}), 10.0)

    writer = EmfFileWriter(tmp_path / "emf.log")
    publisher = EmfPublisher(writer, "a", totals)
    assert [publisher.publish_once().history_commits_failing for _ in range(2)] == [1, 1]
    history.append(HistoryState(storage_ok=True, commit_failures=3))
    assert publisher.publish_once().history_commits_failing == 0
    history.append(None)
    publisher.publish_once()
    docs = [validate_emf_line(line) for line in writer.path.read_text().splitlines()]
    assert [d.get("HistoryCommitsFailing") for d in docs] == [1, 1, 0, None]


def test_no_latency_figure_when_nothing_was_applied() -> None:
    quiet = FleetMetrics(0.0, 0, 0.0, 0, 0, 1, None, {})
    (doc,) = fleet_documents(quiet, "so101-twin", 1)
    validate_emf_line(json.dumps(doc))
    assert "InternalLatencyP99" not in doc


@pytest.mark.parametrize(
    ("metrics", "dimensions", "match"),
    [
        ([], {"Agent": "a"}, "at least one metric"),
        ([Metric("x", float("nan"))], {"Agent": "a"}, "finite"),
        ([Metric("x", 1, "Furlongs")], {"Agent": "a"}, "unit 'Furlongs'"),
        ([Metric("Agent", 1)], {"Agent": "a"}, "collides"),
        ([Metric("x", 1)], {"Agent": ""}, "non-empty string"),
        ([Metric(f"m{i}", i) for i in range(101)], {"Agent": "a"}, "100"),
    ],
)
def test_documents_the_spec_forbids_are_refused(
    metrics: list[Metric], dimensions: dict[str, str], match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        emf_document(metrics, dimensions, 0)


def good() -> dict[str, Any]:
    return emf_document([Metric("Latency", 2.5, "Milliseconds")], {"Agent": "a"}, 1_764_000_000_000)


def broken(change: str) -> dict[str, Any]:
    doc = good()
    aws = doc["_aws"]
    directive = aws["CloudWatchMetrics"][0]
    if change == "no timestamp":
        del aws["Timestamp"]
    elif change == "timestamp in seconds as a string":
        aws["Timestamp"] = "1764000000"
    elif change == "no namespace":
        del directive["Namespace"]
    elif change == "no dimensions":
        directive["Dimensions"] = []
    elif change == "too many dimension keys":
        directive["Dimensions"] = [[f"d{i}" for i in range(31)]]
    elif change == "dimension not on the root":
        directive["Dimensions"] = [["Region"]]
    elif change == "numeric dimension":
        doc["Agent"] = 7
    elif change == "metric not on the root":
        directive["Metrics"].append({"Name": "Missing"})
    elif change == "nested metric":
        doc["Latency"] = {"value": 2.5}
    elif change == "string metric":
        doc["Latency"] = "2.5"
    elif change == "101 values":
        doc["Latency"] = list(range(101))
    elif change == "bad unit":
        directive["Metrics"][0]["Unit"] = "ms"
    elif change == "extra directive member":
        directive["Region"] = "eu-west-1"
    elif change == "storage resolution 30":
        directive["Metrics"][0]["StorageResolution"] = 30
    return doc


@pytest.mark.parametrize(
    "change",
    [
        "no timestamp",
        "timestamp in seconds as a string",
        "no namespace",
        "no dimensions",
        "too many dimension keys",
        "dimension not on the root",
        "numeric dimension",
        "metric not on the root",
        "nested metric",
        "string metric",
        "101 values",
        "bad unit",
        "extra directive member",
        "storage resolution 30",
    ],
)
def test_the_validator_catches_each_broken_rule(change: str) -> None:
    validate_emf_line(json.dumps(good()))
    with pytest.raises((jsonschema.ValidationError, AssertionError)):
        validate_emf_line(json.dumps(broken(change)))


def test_the_specifications_own_example_passes() -> None:
    example = {
        "_aws": {
            "Timestamp": 1574109732004,
            "CloudWatchMetrics": [
                {
                    "Namespace": "lambda-function-metrics",
                    "Dimensions": [["functionVersion"]],
                    "Metrics": [{"Name": "time", "Unit": "Milliseconds", "StorageResolution": 60}],
                }
            ],
        },
        "functionVersion": "$LATEST",
        "time": 100,
        "requestId": "989ffbf8-9ace-4817-a57c-e4dd734019ee",
    }
    validate_emf_line(json.dumps(example))


def test_the_file_rotates_at_its_bound(tmp_path: Path) -> None:
    writer = EmfFileWriter(tmp_path / "metrics.log", max_bytes=1024 * 1024)
    doc = fleet_documents(FLEET, "x" * 1000, 1)
    per_call = sum(len(json.dumps(d, separators=(",", ":"))) + 1 for d in doc)
    for _ in range(1024 * 1024 // per_call + 2):  # just past 1 MiB: one rotation
        writer.write(doc)
    rotated = tmp_path / "metrics.log.1"
    assert writer.rotations == 1 and rotated.exists()
    assert rotated.stat().st_size <= 1024 * 1024
    for line in (rotated.read_text() + writer.path.read_text()).splitlines():
        assert json.loads(line)["_aws"]["Timestamp"] == 1
    with pytest.raises(ValueError, match="at least one EMF event"):
        EmfFileWriter(tmp_path / "small.log", max_bytes=100)


def test_a_line_a_full_disk_cut_short_does_not_take_the_next_document_with_it(tmp_path: Path) -> None:
    """A write the disk could not take leaves part of a line (a walk filled a tmpfs under the file); once
    there is room again, the next interval's documents each begin a line of their own and parse."""
    writer = EmfFileWriter(tmp_path / "emf.log")
    writer.write(fleet_documents(FLEET, "a", 1))
    with writer.path.open("a", encoding="utf-8") as fh:
        fh.write('{"Agent":"a","AgentUp":1,"_aws":{"Timest')
    writer.write(fleet_documents(FLEET, "a", 2))
    lines = writer.path.read_text().splitlines()
    whole = [json.loads(line)["_aws"]["Timestamp"] for line in lines if line.endswith("}")]
    assert whole == [1] * 3 + [2] * 3
    assert sum(not line.endswith("}") for line in lines) == 1


def test_an_interval_the_disk_could_not_take_is_counted_in_the_next(tmp_path: Path) -> None:
    """The counts are differences of running totals: an interval whose document could not be written (a
    walk's full disk) must not take its losses with it, or MessagesDropped never pages for them."""
    clock = [0.0]
    totals = [FleetTotals(0, 0, 1, 0, 0, 0.0, None, {}, messages_dropped=0)]
    writer = EmfFileWriter(tmp_path / "emf.log")
    publisher = EmfPublisher(writer, "a", lambda: totals[-1], clock=lambda: clock[0], wall=lambda: 1.0)
    publisher.publish_once()
    write = writer.write

    def full(_documents: Any) -> None:
        raise OSError(28, "No space left on device")

    writer.write = full  # type: ignore[method-assign]
    clock[0] = 60.0
    totals.append(dataclasses.replace(totals[-1], messages_dropped=7))
    with pytest.raises(OSError):
        publisher.publish_once()
    writer.write = write  # type: ignore[method-assign]
    clock[0] = 120.0
    totals.append(dataclasses.replace(totals[-1], messages_dropped=9))
    assert publisher.publish_once().messages_dropped == 9
    docs = [validate_emf_line(line) for line in writer.path.read_text().splitlines()]
    assert [d["MessagesDropped"] for d in docs if "AgentUp" in d] == [0, 9]
    # A review: the disk full inside the severity lines, after the counts were in the file. The counts are
    # not sent again in the next interval.
    written: list[Any] = []

    def counts_then_full(documents: Any) -> None:
        if written:
            raise OSError(28, "No space left on device")
        written.append(documents)
        write(documents)

    writer.write = counts_then_full  # type: ignore[method-assign]
    clock[0] = 180.0
    totals.append(dataclasses.replace(totals[-1], messages_dropped=16, active_alarms={"critical": 1}))
    with pytest.raises(OSError):
        publisher.publish_once()
    writer.write = write  # type: ignore[method-assign]
    clock[0] = 240.0
    assert publisher.publish_once().messages_dropped == 0
    docs = [validate_emf_line(line) for line in writer.path.read_text().splitlines()]
    assert [d["MessagesDropped"] for d in docs if "AgentUp" in d] == [0, 9, 7, 0]


def test_publisher_turns_totals_into_interval_figures(tmp_path: Path) -> None:
    clock = [100.0]
    totals = [FleetTotals(0, 0, 0, 0, 1, 100.0, None, {"critical": 0, "warning": 0})]
    writer = EmfFileWriter(tmp_path / "emf.log")
    publisher = EmfPublisher(
        writer,
        "so101-twin",
        lambda: totals[-1],
        interval_s=60.0,
        clock=lambda: clock[0],
        wall=lambda: 1_764.5,
    )
    first = publisher.publish_once()
    assert (first.messages_per_s, first.rejects, first.devices_offline) == (0.0, 0, 1)
    clock[0] = 160.0
    totals.append(FleetTotals(600, 4, 1, 0, 0, 0.0, 2.5, {"critical": 1, "warning": 0}))
    second = publisher.publish_once()
    assert (second.messages_per_s, second.rejects) == (10.0, 4)  # 600 messages over 60 s
    clock[0] = 190.0  # a shorter interval (a stop flushes early): the rate is over the real span
    totals.append(FleetTotals(750, 4, 1, 0, 0, 0.0, 2.5, {"critical": 0, "warning": 0}))
    assert publisher.publish_once().messages_per_s == 5.0
    docs = [validate_emf_line(line) for line in writer.path.read_text().splitlines()]
    assert len(docs) == 9 and publisher.published == 3
    assert {d["_aws"]["Timestamp"] for d in docs} == {1_764_500}
    assert [d["ActiveAlarms"] for d in docs if d.get("Severity") == "critical"] == [0, 1, 0]
    with pytest.raises(ValueError, match="positive"):
        EmfPublisher(writer, "x", lambda: totals[0], interval_s=0)


def test_writes_the_disk_refused_are_counted_where_a_person_looks(tmp_path: Path) -> None:
    """A full disk's failed writes were only logged: now /state and /metrics count them (the `emf` output)
    and the first document written after them says how many intervals CloudWatch did not get."""
    writer = EmfFileWriter(tmp_path / "emf.log")
    write = writer.write
    disk_full = threading.Event()
    disk_full.set()

    def full_or_not(documents: Any) -> None:
        if disk_full.is_set():
            raise OSError(28, "No space left on device")
        write(documents)

    writer.write = full_or_not  # type: ignore[method-assign]
    totals = FleetTotals(0, 0, 1, 0, 0, 0.0, 1.0, {})
    publisher = EmfPublisher(writer, "so101-twin", lambda: totals, interval_s=0.05)
    publisher.start()
    try:
        wait_for(lambda: publisher.errors >= 3, 30, "three writes refused")
        disk_full.clear()
        wait_for(lambda: publisher.published >= 2, 30, "two documents written once the disk has room")
    finally:
        publisher.stop()
    stats = publisher.sink_stats()
    assert (stats.name, stats.errors, stats.delivered) == ("emf", publisher.errors, publisher.published)
    assert "No space left on device" in stats.last_error
    told = [validate_emf_line(line)["EmfWriteFailures"] for line in writer.path.read_text().splitlines()]
    # Each failure told once, in the first document written after it.
    assert told[0] >= 3 and sum(told) == publisher.errors and told[1:] == [0] * (len(told) - 1)


def test_publisher_thread_writes_until_stopped(tmp_path: Path) -> None:
    writer = EmfFileWriter(tmp_path / "emf.log")
    totals = FleetTotals(0, 0, 1, 0, 0, 0.0, 1.0, {"critical": 0, "warning": 0})
    publisher = EmfPublisher(writer, "so101-twin", lambda: totals, interval_s=0.05)
    publisher.start()
    wait_for(lambda: publisher.published >= 2, 30, "two intervals published")
    publisher.stop()
    count = publisher.published
    assert count >= 2 and publisher.errors == 0
    time.sleep(0.15)  # three intervals of quiet: a thread still running would have published again
    assert publisher.published == count


def test_losses_are_counted_per_interval_and_history_only_when_it_is_on(tmp_path: Path) -> None:
    clock = [0.0]
    base = FleetTotals(0, 0, 1, 0, 0, 0.0, None, {})
    totals = [dataclasses.replace(base, history_rows_dropped=0, history_commit_failures=0, history_lag_s=0.5)]
    writer = EmfFileWriter(tmp_path / "emf.log")
    publisher = EmfPublisher(writer, "a", lambda: totals[-1], clock=lambda: clock[0], wall=lambda: 1.0)
    publisher.publish_once()
    clock[0] = 60.0
    totals.append(
        dataclasses.replace(
            totals[-1],
            messages_dropped=7,
            sink_drops=3,
            worker_restarts=1,
            history_rows_dropped=5000,
            history_commit_failures=4,
            history_lag_s=75.0,
        )
    )
    second = publisher.publish_once()
    assert (second.messages_dropped, second.sink_drops, second.worker_restarts) == (7, 3, 1)
    assert (second.history_rows_dropped, second.history_commit_failures, second.history_lag_s) == (
        5000,
        4,
        75.0,
    )
    clock[0] = 120.0
    # The history writer process was started again: its commit failures count from zero again, so a lower
    # total is all new.
    totals.append(dataclasses.replace(totals[-1], history_rows_dropped=200, history_commit_failures=4))
    third = publisher.publish_once()
    assert (third.history_rows_dropped, third.history_commit_failures, third.sink_drops) == (200, 0, 0)
    docs = [validate_emf_line(line) for line in writer.path.read_text().splitlines()]
    assert [d["HistoryRowsDropped"] for d in docs] == [0, 5000, 200]
    assert [d["HistoryLagSeconds"] for d in docs] == [0.5, 75.0, 75.0]
    assert {m["Name"]: m["Unit"] for m in docs[1]["_aws"]["CloudWatchMetrics"][0]["Metrics"]}[
        "HistoryLagSeconds"
    ] == "Seconds"
    # History off: no history metric at all (the stack's alarms treat that as no loss).
    off = fleet_documents(dataclasses.replace(FLEET), "a", 1)
    assert not set(LOSS_METRICS[3:]) & set(off[0])


def test_refused_subscriptions_are_reported_as_they_are_not_as_an_increase(tmp_path: Path) -> None:
    """SubscriptionsRefused is a state (filters refused now), so the stack's alarm sees 2 in every interval
    the refusal lasts, not 2 once and then 0."""
    docs = _three_intervals(tmp_path, FleetTotals(0, 0, 1, 0, 0, 0.0, None, {}, subscriptions_refused=2))
    assert [d["SubscriptionsRefused"] for d in docs] == [2, 2, 2]


def _three_intervals(tmp_path: Path, totals: FleetTotals) -> list[dict[str, Any]]:
    """The EMF documents of three intervals a minute apart, each with the same `totals`."""
    clock = [0.0]
    writer = EmfFileWriter(tmp_path / "emf.log")
    publisher = EmfPublisher(writer, "a", lambda: totals, clock=lambda: clock[0], wall=lambda: 1.0)
    for _ in range(3):
        publisher.publish_once()
        clock[0] += 60.0
    return [validate_emf_line(line) for line in writer.path.read_text().splitlines()]


def test_arms_kept_out_by_the_device_limit_are_counted_per_interval(tmp_path: Path) -> None:
    """The messages refused for telemetry.max_devices (untracked, so no arm's counter holds them): the
    stack pages on them, and garbage on invented topics does not count."""
    rejected = {"too_many_devices": 40, "not_json": 9}
    state = AgentState(agent=AgentInfo(running=True), devices={}, untracked_rejected=rejected)
    clock = [0.0]
    totals = [fleet_totals(state, 10.0)]
    assert totals[0].device_limit_refusals == 40
    writer = EmfFileWriter(tmp_path / "emf.log")
    publisher = EmfPublisher(writer, "a", lambda: totals[-1], clock=lambda: clock[0], wall=lambda: 1.0)
    publisher.publish_once()
    clock[0] = 60.0
    totals.append(dataclasses.replace(totals[-1], device_limit_refusals=100))
    publisher.publish_once()
    clock[0] = 120.0
    publisher.publish_once()
    docs = [validate_emf_line(line) for line in writer.path.read_text().splitlines()]
    assert [d["DeviceLimitRefusals"] for d in docs] == [40, 60, 0]


def test_a_broker_connection_down_is_reported_in_every_interval_it_lasts(tmp_path: Path) -> None:
    """With the broker out of reach every arm reads OFFLINE and the loss figures leave OFFLINE arms out, so
    the connections down now are the figure the stack pages on (a walk: the agent sent AgentUp and nothing
    else told of it). A refused filter is a connection that is up."""
    connections = tuple(
        ConnectionState(index=i, state=s) for i, s in enumerate(("connected", "connecting", "refused"))
    )
    offline = {"arm-1": DeviceState("arm-1", HealthSnapshot(status=DeviceStatus.OFFLINE))}
    info = AgentInfo(running=True, broker=BrokerState(connected=False, connections=connections))
    totals = fleet_totals(AgentState(agent=info, devices=offline), 10.0)
    assert (totals.broker_disconnected, totals.loss_percent) == (1, None)
    docs = _three_intervals(tmp_path, totals)
    assert [d["BrokerDisconnected"] for d in docs if "AgentUp" in d] == [1, 1, 1]


def _scheduled_documents(tmp_path: Path, sample_s: float, documents: int) -> list[int]:
    """The minute (of the wall clock, here the same as the monotonic one) of each document that the
    publisher's own loop writes, every 60 s, started 0.5 s into the first minute, when each sample takes
    `sample_s` (the agent asks every worker for its state, up to ASK_TIMEOUT_S)."""
    clock = [0.5]
    writer = EmfFileWriter(tmp_path / "emf.log")

    def slow_sample() -> FleetTotals:
        clock[0] += sample_s
        return FleetTotals(0, 0, 1, 0, 0, 0.0, None, {})

    def wait(seconds: float) -> bool:
        clock[0] += seconds
        return publisher.published >= documents

    publisher = EmfPublisher(
        writer, "a", slow_sample, clock=lambda: clock[0], wall=lambda: clock[0], wait=wait
    )
    publisher.run()
    stamps = [validate_emf_line(line)["_aws"]["Timestamp"] for line in writer.path.read_text().splitlines()]
    return [stamp // 60_000 for stamp in stamps]


def test_documents_are_written_on_a_fixed_grid_however_long_sampling_takes(tmp_path: Path) -> None:
    """Waiting the interval after each write put documents an interval plus the sample's time apart, so
    some minutes had none and the sustained alarms (5 of 5 minutes) cleared mid-outage and paged again."""
    assert _scheduled_documents(tmp_path, 10.0, 12) == list(range(1, 13))


def test_a_publish_longer_than_the_interval_skips_the_slots_it_missed(tmp_path: Path) -> None:
    """Not written at once afterwards (two in one minute and none later): the next slot still ahead."""
    assert _scheduled_documents(tmp_path, 70.0, 3) == [1, 3, 5]
    assert next_slot(60.0, 60.0, 60.0) == 120.0
    assert next_slot(60.0, 200.0, 60.0) == 240.0
    assert next_slot(60.0, 119.0, 60.0) == 120.0


@pytest.mark.parametrize(("interval_s", "phase"), [(60.0, 30.0), (10.0, 5.0)])
def test_slots_lie_mid_minute_by_the_wall_clock_and_keep_to_the_monotonic_one(
    tmp_path: Path, interval_s: float, phase: float
) -> None:
    """Slots were an interval apart from the start, wherever that fell in the wall minute: one a few ms
    from a minute boundary could leave a minute empty and break the 5-of-5 alarms. The first is lined up
    with the middle of a wall minute; the rest stay on the monotonic clock (a wall clock moved against it by
    less than clock_step_tolerance, read noise, moves none of them). The two clocks differ here, so
    scheduling on the wrong one shows."""
    mono, wall = [500.0], [1_000_000_012.3]  # 52.3 s into a wall minute, 20 s into a monotonic one
    started = (mono[0], wall[0])
    published: list[tuple[float, float]] = []
    writer = EmfFileWriter(tmp_path / "emf.log")

    def sample() -> FleetTotals:
        published.append((mono[0], wall[0]))
        return FleetTotals(0, 0, 1, 0, 0, 0.0, None, {})

    moved = []

    def wait(seconds: float) -> bool:
        mono[0] += seconds
        wall[0] += seconds
        if len(published) == 1 and not moved:  # once, after the first: less than the step tolerance
            wall[0] += 0.9
            moved.append(True)
        return len(published) >= 4

    publisher = EmfPublisher(
        writer, "a", sample, interval_s=interval_s, clock=lambda: mono[0], wall=lambda: wall[0], wait=wait
    )
    publisher.run()
    (first_mono, first_wall), *_ = published
    assert interval_s <= first_mono - started[0] < 2 * interval_s
    assert first_wall % interval_s == pytest.approx(phase, abs=1e-5)
    gaps = [b[0] - a[0] for a, b in itertools.pairwise(published)]
    assert gaps == pytest.approx([interval_s] * 3)


def _around_a_step(
    step_s: float, late_s: float, at_slot: bool = False, interval_s: float = 60.0, stall_s: float = 0.0
) -> tuple[list[float], EmfPublisher]:
    """The wall times of six documents the publisher's own loop writes when the wall clock is stepped by
    `step_s` once after the first (at the first wait, or at the wait that reaches the next slot if
    `at_slot`), every wait returning `late_s` late, and the publisher. With `stall_s`, the first read of the
    wall clock after the first document takes that long (the thread stalled)."""
    mono, wall = [500.0], [1_000_000_012.3]
    published: list[tuple[float, float]] = []
    stepped: list[bool] = []
    stalled: list[bool] = []

    def sample() -> FleetTotals:
        published.append((mono[0], wall[0]))
        return FleetTotals(0, 0, 1, 0, 0, 0.0, None, {})

    def wait(seconds: float) -> bool:
        mono[0] += seconds + late_s
        wall[0] += seconds + late_s
        due = len(published) == 1 and (not at_slot or mono[0] >= published[0][0] + interval_s)
        if due and not stepped:
            wall[0] += step_s
            stepped.append(True)
        return len(published) >= 6

    def read_wall() -> float:
        if stall_s and len(published) == 1 and not stalled:
            stalled.append(True)
            mono[0] += stall_s
            wall[0] += stall_s
        return wall[0]

    writer = types.SimpleNamespace(write=lambda documents: None, path="memory")
    publisher = EmfPublisher(
        writer,  # type: ignore[arg-type]
        "a",
        sample,
        interval_s=interval_s,
        clock=lambda: mono[0],
        wall=read_wall,
        wait=wait,
    )
    publisher.run()
    return [w for _, w in published], publisher


def _minutes(walls: list[float]) -> list[int]:
    """How many documents each wall minute from the first document's to the last one's got."""
    counts = Counter(int(w // 60.0) for w in walls)
    return [counts[m] for m in range(min(counts), max(counts) + 1)]


@pytest.mark.parametrize(
    ("step_s", "late_s"),
    [
        (30.0, 0.0),
        (-30.0, 0.0),
        (29.9, 0.2),
        (-30.5, 0.6),
        (29.0, 0.0),
        (-29.0, 0.0),
        (7.0, 0.3),
        (-40.0, 0.0),
    ],
)
def test_a_wall_clock_stepped_between_two_documents_leaves_each_minute_one(
    caplog: pytest.LogCaptureFixture, step_s: float, late_s: float
) -> None:
    """The grid was lined up with the wall clock once, at the start: a wall clock stepped later (chrony at
    first boot) left every document at its old place in the wall minute, up to a minute boundary. Then a
    step was seen only after the next document was written at the old place (stepped +30 s: documents at
    :30, :00.0, :30, a minute with none and one with two), and the grid moved to the place nearest the old
    one, not to the minute after the last document's. Now the step is seen before that document: each
    wall minute, the ones either side of the step too, gets exactly one, mid-minute, and the step is
    counted and logged once."""
    with caplog.at_level(logging.WARNING, logger="twin.output.emf"):
        walls, publisher = _around_a_step(step_s, late_s)
    assert _minutes(walls) == [1] * 6
    assert all(30.0 - 1e-5 <= w % 60.0 <= 30.0 + late_s + 1e-5 for w in walls), walls
    assert publisher.clock_steps == 1
    assert len([r for r in caplog.records if "wall clock moved" in r.getMessage()]) == 1


@pytest.mark.parametrize(("step_s", "minutes"), [(30.0, [1, 0, 1, 1, 1, 1, 1]), (-30.5, [1] * 6)])
def test_a_step_seen_only_at_the_slot_is_followed_before_the_document(
    step_s: float, minutes: list[int]
) -> None:
    """A step just as the slot is reached was followed only after a document at the old place: stepped
    forward past the slot's place, the next document is at the next one (the minute the clock jumped over
    gets none, no minute two); stepped back, at the place of the minute after the last document's."""
    walls, _ = _around_a_step(step_s, 0.6, at_slot=True)
    assert _minutes(walls) == minutes
    assert all(30.0 - 1e-5 <= w % 60.0 <= 30.6 + 1e-5 for w in walls), walls


def test_a_forward_step_of_an_hour_skips_the_minutes_jumped_over_and_writes_none_twice() -> None:
    """Not a whole number of minutes (a review: a step of exactly an hour left every slot's place in the
    minute as it was, so the test passed with the step ignored)."""
    walls, publisher = _around_a_step(3620.0, 0.0)
    assert max(Counter(int(w // 60.0) for w in walls).values()) == 1
    assert [w % 60.0 for w in walls] == pytest.approx([30.0] * 6, abs=1e-5)
    assert publisher.clock_steps == 1


def test_a_backward_step_of_an_hour_waits_no_more_than_two_intervals() -> None:
    """Waiting for the wall clock to come round to the minute after the last document's would leave an
    hour without metrics: the next document is at most two intervals on, in a minute written before the
    step."""
    walls, _ = _around_a_step(-3600.0, 0.0)
    assert 0.0 < walls[1] - (walls[0] - 3600.0) <= 120.0
    assert _minutes(walls[1:]) == [1] * 5
    assert 160.0 < realigned_slot(160.0, 100.0, 101.0, -3600.0, 60.0) <= 220.0


def test_a_step_of_two_fifths_of_a_short_interval_lines_the_grid_up_again() -> None:
    """A fixed 1 s tolerance let a 0.9 s step stand with a 2 s interval: slots 0.1 s from a boundary."""
    walls, publisher = _around_a_step(0.9, 0.0, interval_s=2.0)
    assert [w % 2.0 for w in walls] == pytest.approx([1.0] * 6, abs=1e-5)
    assert publisher.clock_steps == 1


def test_a_thread_stalled_between_the_clock_reads_is_not_a_step(caplog: pytest.LogCaptureFixture) -> None:
    """The monotonic and the wall clock were read one after the other: a thread stalled between the two
    read as a step of the wall clock, moved the grid and warned (and again, back, at the next read)."""
    with caplog.at_level(logging.WARNING, logger="twin.output.emf"):
        walls, publisher = _around_a_step(0.0, 0.0, stall_s=3.0)
    assert publisher.clock_steps == 0 and not caplog.records
    assert [w % 60.0 for w in walls] == pytest.approx([30.0] * 6, abs=1e-5)


def _under_a_moving_clock(
    wall_of: Callable[[float], float],
    waits: int,
    read_stalls: int = 0,
    *,
    stall_s: float | tuple[float, ...] = 3.0,
    stall_after: bool = False,
) -> tuple[list[float], EmfPublisher, float]:
    """The monotonic times of the documents the publisher's own loop writes (60 s interval) in `waits` waits
    when the wall clock reads `wall_of(monotonic)`, the publisher, and the monotonic time at the end. With
    `read_stalls`, that many of the first reads of the wall clock stall `stall_s` before they read it (after
    it, before the call returns, with `stall_after`); a tuple gives each of them its own stall."""
    mono, published, count = [500.0], [], [0]

    def sample() -> FleetTotals:
        published.append(mono[0])
        return FleetTotals(0, 0, 1, 0, 0, 0.0, None, {})

    def wait(seconds: float) -> bool:
        mono[0] += seconds
        count[0] += 1
        return count[0] >= waits

    def read_wall() -> float:
        wall = wall_of(mono[0])
        if count[0] < read_stalls:
            mono[0] += stall_s if isinstance(stall_s, float) else stall_s[count[0]]
            count[0] += 1  # a stall counts as a wait, so stalls at every read still end
        return wall if stall_after else wall_of(mono[0])

    writer: Any = types.SimpleNamespace(write=lambda documents: None, path="memory")
    publisher = EmfPublisher(writer, "a", sample, clock=lambda: mono[0], wall=read_wall, wait=wait)
    publisher.run()
    return published, publisher, mono[0]


@pytest.mark.parametrize(
    "wall_of",
    [
        lambda mono: 1e9,  # frozen
        lambda mono: 1e9 + 2.0 * mono,  # running at twice the rate
        lambda mono: 1e9 + mono + 3.0 * (mono // 1.5),  # stepped +3 s every 1.5 s
        lambda mono: 1e9 + mono + 1.5 * ((mono // 2.0) % 2),  # flapping by 1.5 s every 2 s
    ],
    ids=["frozen", "twice-as-fast", "stepping", "flapping"],
)
def test_a_wall_clock_that_keeps_moving_stops_no_document(
    caplog: pytest.LogCaptureFixture, wall_of: Callable[[float], float]
) -> None:
    """A review: each step moved the slot, and a wall clock that kept moving moved it on before every
    publish: no document in 20,000 waits, so the AgentUp heartbeat stopped and AgentSilent paged on a live
    agent, with a warning every other second. A slot is moved once at most: documents keep coming, at most
    two intervals apart on the monotonic clock; every step is counted, and told once then every 10 minutes."""
    with caplog.at_level(logging.WARNING, logger="twin.output.emf"):
        published, publisher, end = _under_a_moving_clock(wall_of, 20_000)
    gaps = [b - a for a, b in itertools.pairwise([500.0, *published, end])]
    assert len(published) > 20 and max(gaps) <= 120.0 + 1e-6, gaps
    lines = [r.getMessage() for r in caplog.records if "wall clock moved" in r.getMessage()]
    assert publisher.clock_steps > 1000
    assert 1 <= len(lines) <= 1 + (end - 500.0) / CLOCK_STEP_TELL_EVERY_S, len(lines)
    assert "1 step(s) since the last" in lines[0] and "1 step(s)" not in lines[-1]


def test_two_steps_before_one_slot_are_both_followed() -> None:
    """Moving a slot once at most must not leave the second of two steps standing: the grid would keep the
    place it had in the minute, up to a boundary, for good. It moves the next slot instead."""

    def wall_of(mono: float) -> float:
        return 1_000_000_000.0 + mono + (30.0 if mono >= 600.0 else 0.0) - (20.0 if mono >= 610.0 else 0.0)

    published, _, _ = _under_a_moving_clock(wall_of, 2000)
    walls = [wall_of(m) for m in published]
    assert [w % 60.0 for w in walls[2:]] == pytest.approx([30.0] * len(walls[2:]), abs=1e-5), walls
    assert max(Counter(int(w // 60.0) for w in walls).values()) == 1


@pytest.mark.parametrize("stall_after", [False, True], ids=["stall-before-the-wall-read", "stall-after-it"])
@pytest.mark.parametrize(("stalls", "stall_s"), [(2, 3.0), (10, 1.6)], ids=["retried", "every-try"])
def test_a_first_clock_read_that_stalls_is_retried_then_the_least_stalled_taken(
    stalls: int, stall_s: float, stall_after: bool
) -> None:
    """The first slot is lined up with a read of both clocks: two stalled reads are read again, and ten
    (every try) still start the grid. The last try read the monotonic clock once, before or after the wall
    one, so a stall on one side or the other landed in the offset in full and a 1.6 s one was counted as a
    step later: the offset is taken against the middle of two monotonic reads, off by half a stall at most."""
    published, publisher, _ = _under_a_moving_clock(
        lambda mono: 1_000_000_000.0 + mono, 1000, stalls, stall_s=stall_s, stall_after=stall_after
    )
    assert publisher.clock_steps == 0
    off = 0.0 if stalls == 2 else stall_s / 2.0  # a loose read within the tolerance leaves the grid there
    phases = [(1_000_000_000.0 + m) % 60.0 for m in published]
    assert phases == pytest.approx([30.0] * len(published), abs=off + 1e-5)


@pytest.mark.parametrize("stall_after", [False, True], ids=["stall-before-the-wall-read", "stall-after-it"])
def test_of_three_stalled_first_clock_reads_the_least_stalled_is_taken(stall_after: bool) -> None:
    """Three tries that all stall, the middle one least: the grid takes that one's offset, off by half its
    0.6 s, not the first's or the last's (off by 0.8 s, within the step tolerance, so it would stay)."""
    published, publisher, _ = _under_a_moving_clock(
        lambda mono: 1_000_000_000.0 + mono, 1000, 3, stall_s=(1.6, 0.6, 1.6), stall_after=stall_after
    )
    assert publisher.clock_steps == 0
    phases = [(1_000_000_000.0 + m) % 60.0 for m in published]
    assert phases == pytest.approx([30.0] * len(published), abs=0.3 + 1e-5)


@pytest.mark.parametrize("stall_after", [False, True], ids=["stall-before-the-wall-read", "stall-after-it"])
def test_three_first_clock_reads_that_stall_over_two_seconds_count_no_step(
    caplog: pytest.LogCaptureFixture, stall_after: bool
) -> None:
    """Every first try stalled 3 s: the offset taken was off by 1.5 s, over the 1 s tolerance, and the first
    clean read later counted (and warned of) a step of a wall clock nobody moved. The grid still moves to
    the clean read, so the documents sit mid-minute; nothing is counted or told."""
    with caplog.at_level(logging.WARNING, logger="twin.output.emf"):
        published, publisher, _ = _under_a_moving_clock(
            lambda mono: 1_000_000_000.0 + mono, 1000, 3, stall_s=3.0, stall_after=stall_after
        )
    assert publisher.clock_steps == 0 and not caplog.records
    phases = [(1_000_000_000.0 + m) % 60.0 for m in published]
    assert len(published) > 5 and phases == pytest.approx([30.0] * len(published), abs=1e-5)


def test_a_step_after_first_clock_reads_that_stalled_is_still_counted() -> None:
    """Only the first read's own error is forgiven: a step of the clock after it is counted as ever."""

    def wall_of(mono: float) -> float:
        return 1_000_000_000.0 + mono + (20.0 if mono >= 900.0 else 0.0)

    published, publisher, _ = _under_a_moving_clock(wall_of, 2000, 3, stall_s=3.0)
    assert publisher.clock_steps == 1
    assert [wall_of(m) % 60.0 for m in published] == pytest.approx([30.0] * len(published), abs=1e-5)


def test_a_sample_that_raises_is_logged_as_a_failed_publish(caplog: pytest.LogCaptureFixture) -> None:
    """Any error in a publish is counted and logged, not only a write: the log line said "writing" when
    reading the twin's state raised, and sent a reader to the disk."""
    clock = [0.0]

    def sample() -> FleetTotals:
        raise RuntimeError("worker 2 did not answer")

    def wait(seconds: float) -> bool:
        clock[0] += seconds
        return publisher.errors >= 1

    writer: Any = types.SimpleNamespace(write=lambda documents: None, path="memory")
    publisher = EmfPublisher(writer, "a", sample, clock=lambda: clock[0], wall=lambda: clock[0], wait=wait)
    with caplog.at_level(logging.ERROR, logger="twin.output.emf"):
        publisher.run()
    assert [r.getMessage() for r in caplog.records] == ["publishing CloudWatch metrics to memory failed"]
    assert publisher.last_error == "RuntimeError: worker 2 did not answer"


def test_the_first_documents_rate_is_over_the_time_since_the_start(tmp_path: Path) -> None:
    """A review: the first slot lies one to two intervals after the start (mid-minute), but its totals were
    divided by one interval, overstating MessagesPerSecond up to twice."""
    mono = [100.0]
    publisher = EmfPublisher(EmfFileWriter(tmp_path / "emf.log"), "a", lambda: None, clock=lambda: mono[0])
    mono[0] += 90.0  # the first slot, 1.5 intervals on
    fleet = publisher.publish_once(FleetTotals(900, 0, 1, 0, 0, 0.0, None, {}))
    assert fleet.messages_per_s == pytest.approx(10.0)
    mono[0] += 60.0
    assert publisher.publish_once(FleetTotals(1500, 0, 1, 0, 0, 0.0, None, {})).messages_per_s == 10.0


def test_severity_lines_the_disk_refused_after_the_counts_are_a_write_failure(tmp_path: Path) -> None:
    """docs/servo-health.md: EmfWriteFailures counts an interval whose per-severity ActiveAlarms were lost
    too (the counts got through), since those figures are missing from CloudWatch and the disk is full."""
    clock = [0.0]
    writer = EmfFileWriter(tmp_path / "emf.log")
    write, calls = writer.write, [0]

    def second_severity_lines_refused(documents: Any) -> None:
        calls[0] += 1
        if calls[0] == 4:  # the second interval's severity lines, after its counts
            raise OSError(28, "No space left on device")
        write(documents)

    def wait(seconds: float) -> bool:
        clock[0] += seconds
        return publisher.published + publisher.errors >= 3

    writer.write = second_severity_lines_refused  # type: ignore[method-assign]
    totals = FleetTotals(0, 0, 1, 0, 0, 0.0, None, {"critical": 1})
    publisher = EmfPublisher(
        writer, "a", lambda: totals, clock=lambda: clock[0], wall=lambda: clock[0], wait=wait
    )
    publisher.run()
    docs = [validate_emf_line(line) for line in writer.path.read_text().splitlines()]
    assert [d["EmfWriteFailures"] for d in docs if "AgentUp" in d] == [0, 0, 1]
    assert [d.get("ActiveAlarms") for d in docs if "AgentUp" not in d] == [1, 1]
    assert publisher.sink_stats().errors == 1


def test_the_last_document_at_a_stop_tells_the_failed_publishes_no_document_told(tmp_path: Path) -> None:
    """A clean stop tells the count in its last document, without waiting for the next run (which tells only
    what a crash or a stop that could not write that document left: the test after the next)."""
    writer = EmfFileWriter(tmp_path / "emf.log")
    publisher = EmfPublisher(writer, "a", lambda: totals, clock=lambda: 60.0, wall=lambda: 60.0)
    totals = FleetTotals(0, 0, 1, 0, 0, 0.0, None, {})
    publisher.failed(OSError(28, "No space left on device"))
    publisher.failed(OSError(28, "No space left on device"))
    holder = SimpleNamespace(_emf=publisher, _history=None)
    AgentService._publish_last(holder, totals, Counter())  # type: ignore[arg-type]
    docs = [validate_emf_line(line) for line in writer.path.read_text().splitlines()]
    assert [d["EmfWriteFailures"] for d in docs if "AgentUp" in d] == [2]


def _publish_on_a_full_disk(publisher: EmfPublisher, times: int) -> None:
    """`times` publishes the full disk refuses, each counted as the publisher's own loop does (run)."""
    write = publisher.writer.write

    def full(_documents: Any) -> None:
        raise OSError(28, "No space left on device")

    publisher.writer.write = full  # type: ignore[method-assign]
    for _ in range(times):
        try:
            publisher.publish_once()
        except OSError as exc:
            publisher.failed(exc)
    publisher.writer.write = write  # type: ignore[method-assign]


def test_failed_publishes_outlive_a_crash_and_the_next_run_tells_them(tmp_path: Path) -> None:
    """The count travelled only in the file that refused it, and in memory: an agent that crashed (or was
    killed) while the disk stayed full took it along, and EmfWriteFailures never fired for those minutes.
    It is kept in a file of its own, written in place (its size and inode stay: a full disk takes that), and
    the next run's first document written tells it, once."""
    emf = tmp_path / "emf.log"
    totals = FleetTotals(0, 0, 1, 0, 0, 0.0, None, {})

    def run() -> EmfPublisher:
        unsent = UnsentCount(unsent_path(emf))
        return EmfPublisher(EmfFileWriter(emf), "a", lambda: totals, clock=lambda: 60.0, unsent=unsent)

    crashed = run()
    made = unsent_path(emf).stat()
    _publish_on_a_full_disk(crashed, 3)
    assert crashed.errors == 3 and not emf.exists()  # then the agent dies: no stop, no last document
    kept = unsent_path(emf).stat()
    assert (kept.st_ino, kept.st_size) == (made.st_ino, made.st_size) == (made.st_ino, UNSENT_FILE_BYTES)
    assert sorted(p.name for p in tmp_path.iterdir()) == [unsent_path(emf).name]
    assert run().publish_once().emf_write_failures == 3
    assert run().publish_once().emf_write_failures == 0  # told once, not again by the run after
    docs = [validate_emf_line(line) for line in emf.read_text().splitlines()]
    assert [d["EmfWriteFailures"] for d in docs if "AgentUp" in d] == [3, 0]


def test_a_save_of_the_unsent_count_cut_short_leaves_the_one_before(tmp_path: Path) -> None:
    """Written in place, a save a crash cut short would leave a count that is neither: two slots in turn,
    each with its checksum, so the other slot still holds the save before it."""
    path = tmp_path / ".emf.log.unsent"
    count = UnsentCount(path)
    assert count.load() == 0
    assert count.save(5) and count.save(7) and UnsentCount(path).load() == 7
    data = bytearray(path.read_bytes())
    data[9] ^= 0xFF  # the count of the last save (the second: slot 0) is torn
    path.write_bytes(bytes(data))
    again = UnsentCount(path)
    assert again.load() == 5
    assert again.save(6) and UnsentCount(path).load() == 6  # the torn slot is the one written next
    path.write_bytes(b"not a count")
    assert UnsentCount(path).load() == 0


def test_a_save_of_the_unsent_count_that_keeps_failing_says_how_many_failed_in_each_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A save fails at each failed publish, told once per 10 minutes: each line says how many failed since
    the one before, so the held-back ones are not lost from the log."""
    now = [0.0]
    count = UnsentCount(tmp_path / ".emf.log.unsent", clock=lambda: now[0])  # never loaded: no file
    caplog.set_level(logging.ERROR, logger="twin.output.emf")
    for at in (0.0, 1.0, 2.0, UNSENT_TELL_EVERY_S + 1.0):
        now[0] = at
        assert not count.save(1)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2, said
    assert "1 failure(s) since the last such line" in said[0]
    assert "3 failure(s) since the last such line" in said[1]


def test_an_unsent_count_file_that_cannot_be_made_says_so_and_what_to_check(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A directory the file cannot be made in (here: missing; on a host, one the agent's user cannot write)
    was logged as a file that 'could not be read', with nothing to do about it."""
    where = tmp_path / "gone"
    caplog.set_level(logging.ERROR, logger="twin.output.emf")
    assert UnsentCount(where / ".emf.log.unsent").load() == 0
    [said] = [r.getMessage() for r in caplog.records]
    assert "could not be opened or created" in said
    assert f"the agent's user can write {where}" in said and f"df -h {where}" in said


def test_the_last_document_counts_what_each_sink_still_held_at_the_stop_as_sink_drops() -> None:
    """A stop report names a sink's unwritten items `<sink>_items` (tests/test_sinks.py pins the mirror's
    side); the agent must add them to the last SinkDrops, or a loss at the stop never reaches CloudWatch."""
    published: list[FleetTotals] = []
    holder = SimpleNamespace(_emf=SimpleNamespace(publish_once=published.append), _history=None)
    unwritten = Counter({"rerun_items": 4, "usd_items": 2, "history_rows": 9})
    totals = dataclasses.replace(FleetTotals(0, 0, 1, 0, 0, 0.0, None, {}), sink_drops=1)
    AgentService._publish_last(holder, totals, unwritten)  # type: ignore[arg-type]
    assert [t.sink_drops for t in published] == [1 + 4 + 2]
