"""Edge simulator: the edge's payloads and motion, fault injection as counted, schedule accuracy, the CLI."""

from __future__ import annotations

import itertools
import json
import math
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import NO_BROKER, wait_for
from twin.cli import main
from twin.core.telemetry import (
    MAX_PAYLOAD_BYTES,
    DecoderConfig,
    RejectReason,
    TelemetryDecoder,
    TelemetryRejected,
    Units,
)
from twin.core.topics import POLICY_DEVICE_ID_RULE, device_from_topic, topic_filters
from twin.edge.payload import (
    MALFORMED_KINDS,
    device_ids,
    encode,
    make_malformed,
    make_payload,
    mock_motion_ticks,
    mock_ticks,
    sign_magnitude,
)
from twin.edge.simulator import EdgeSimConfig, EdgeSimulator, FaultConfig, clock_skews_ms
from twin.rig.mosquitto import MosquittoBroker
from twin.robot import so101
from twin.transport.broker import BrokerConfig
from twin.transport.subscriber import TelemetrySubscriber

PREFIX = "dt/lerobot"


def test_mock_ticks_match_the_edge_formula() -> None:
    # Hand-derived oracle (the formula's one definition is twin.edge.payload): at t = 0 joint i reads
    # 2048 + 500 sin(i pi/3) = 2048, 2481.0, 2481.0, 2048, 1614.9, 1614.9, truncated toward zero.
    assert mock_ticks(0.0) == [2048, 2481, 2481, 2048, 1614, 1614]
    # shoulder_pan at t = pi s: sin(0.5 pi) = 1; elbow_flex (i = 2) at t = pi: sin(0.7 pi + 2 pi/3).
    assert mock_ticks(math.pi)[0] == 2548
    assert mock_motion_ticks(math.pi)[2] == pytest.approx(
        2048 + 500 * math.sin(0.7 * math.pi + 2 * math.pi / 3)
    )
    assert mock_ticks(1.3) == [int(v) for v in mock_motion_ticks(1.3)]
    for t in (0.0, 1.3, 17.0, 1234.5):
        ticks = mock_ticks(t)
        assert len(ticks) == len(so101.JOINT_NAMES)
        assert all(1548 <= v <= 2548 for v in ticks)


@pytest.mark.parametrize(("value", "raw"), [(0, 0), (7, 7), (-1, 32769), (-10, 32778)])
def test_velocity_sign_magnitude(value: int, raw: int) -> None:
    assert sign_magnitude(value, 1 << 15) == raw


def test_ticks_payload_is_raw_registers() -> None:
    rng = random.Random(0)
    payload = make_payload("arm-007", 2.5, "ticks", rng, timestamp_ms=1706000000000)
    assert payload["device_id"] == "arm-007"
    assert payload["timestamp"] == 1706000000000
    assert list(payload["joints"]) == list(so101.JOINT_NAMES)
    assert [j["position"] for j in payload["joints"].values()] == mock_ticks(2.5)
    seen_negative = False
    for _ in range(50):
        for joint in make_payload("arm-007", 2.5, "ticks", rng)["joints"].values():
            assert all(type(v) is int for v in joint.values())
            velocity = joint["velocity"]
            assert 0 <= velocity <= 10 or 32769 <= velocity <= 32778
            seen_negative |= velocity >= 32768
            assert 5 <= joint["load"] <= 50
            assert 30 <= joint["temp"] <= 40
            assert 80 <= joint["current"] <= 300
    assert seen_negative
    signed = [
        j["load"]
        for _ in range(20)
        for j in make_payload("a", 0, "ticks", rng, load_sign=True)["joints"].values()
    ]
    assert any(v >= 1024 for v in signed) and any(v < 1024 for v in signed)
    assert all(5 <= (v & 1023) <= 50 for v in signed)


def test_degrees_payload_follows_the_same_motion() -> None:
    rng = random.Random(1)
    for t in (0.0, 3.3, 40.0):
        ticks = mock_ticks(t)
        joints = make_payload("arm-001", t, "degrees", rng)["joints"]
        positions = [j["position"] for j in joints.values()]
        assert all(isinstance(v, float) for j in joints.values() for v in j.values())
        expected = [(v - 2047) * 360 / 4095 for v in ticks[:5]]
        assert positions[:5] == pytest.approx(expected, abs=1e-3)
        assert 0.0 <= positions[5] <= 100.0
        assert all(-10 <= j["velocity"] <= 10 for j in joints.values())
    # The gripper sweeps its whole calibrated range over the motion.
    grip = [make_payload("a", t / 10, "degrees", rng)["joints"]["gripper"]["position"] for t in range(400)]
    assert min(grip) < 1.0 and max(grip) > 99.0


@pytest.mark.parametrize("variant", ["ticks", "degrees"])
def test_payloads_decode_and_agree(variant: str) -> None:
    """Both variants of one instant decode to the same arm pose (gripper aside: its scale differs)."""
    rng = random.Random(2)
    ticks_decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    decoder = TelemetryDecoder(DecoderConfig(units=Units(variant)))
    for t in (0.0, 5.0, 9.9):
        reference = ticks_decoder.decode(encode(make_payload("arm-001", t, "ticks", rng)))
        telemetry = decoder.decode(encode(make_payload("arm-001", t, variant, rng)), topic_device="arm-001")
        for joint in so101.ARM_JOINTS:
            assert telemetry.angles_rad[joint] == pytest.approx(reference.angles_rad[joint], abs=0.01)


@pytest.mark.parametrize("kind", MALFORMED_KINDS)
@pytest.mark.parametrize("variant", ["ticks", "degrees"])
def test_malformed_messages_are_rejected_by_the_decoder(kind: str, variant: str) -> None:
    # A seed from the parameters themselves (not hash(), which is salted per process): every run replays.
    rng = random.Random(f"{kind}/{variant}")
    decoder = TelemetryDecoder(DecoderConfig(units=Units(variant)))
    for _ in range(15):  # each kind has random sub-forms
        data = make_malformed(kind, make_payload("arm-001", rng.random() * 10, variant, rng), rng)
        with pytest.raises(TelemetryRejected) as excinfo:
            decoder.decode(data, topic_device="arm-001")
        # Named as the agent counts it: edge-sim --json's counts and the agent's read one-to-one.
        assert excinfo.value.reason == RejectReason(kind), data[:200]
    if kind == "too_large":
        assert len(data) > MAX_PAYLOAD_BYTES


def test_config_validation() -> None:
    broker = BrokerConfig(url="mqtt://127.0.0.1:1")
    with pytest.raises(ValueError, match="variant"):
        EdgeSimConfig(broker=broker, variant="radians")
    with pytest.raises(ValueError, match="MQTT topic character"):
        EdgeSimConfig(broker=broker, devices=["arm/1"])
    with pytest.raises(ValueError, match="rate"):
        EdgeSimConfig(broker=broker, rate_hz=0)
    with pytest.raises(ValueError, match="--drop"):
        FaultConfig(drop=1.5)
    with pytest.raises(ValueError, match="at least 1"):
        device_ids(0)
    assert device_ids(3) == ["arm-001", "arm-002", "arm-003"]
    assert clock_skews_ms(device_ids(4), 400) == {
        "arm-001": 100,
        "arm-002": 200,
        "arm-003": 300,
        "arm-004": 400,
    }
    assert clock_skews_ms(["a"], -250) == {"a": -250}


def test_iot_spreads_devices_over_connections(caplog: pytest.LogCaptureFixture) -> None:
    # IoT Core discards publishes beyond 100/s per connection; nothing connects here.
    config = EdgeSimConfig(
        broker=BrokerConfig(url="iot", region="us-east-1", endpoint="x-ats.iot.us-east-1.amazonaws.com"),
        devices=device_ids(3),
        rate_hz=50,
    )
    assert EdgeSimulator(config)._connections_needed() == 2
    assert "spreading them over 2 connections" in caplog.text
    local = EdgeSimConfig(broker=BrokerConfig(url="mqtt://127.0.0.1:1"), devices=device_ids(3), rate_hz=50)
    assert EdgeSimulator(local)._connections_needed() == 1


# -- against a real broker ---------------------------------------------------------------------------------


class Received:
    def __init__(self) -> None:
        self.items: list[tuple[str, bytes, float]] = []

    def __call__(self, topic: str, payload: bytes, received: float) -> None:
        self.items.append((topic, payload, received))

    def wait_for(self, count: int, timeout: float = 60.0) -> None:
        wait_for(lambda: len(self.items) >= count, timeout, f"{count} messages at the subscriber")
        # A quiet period for the exact-count checks: a message beyond `count` would show up now.
        time.sleep(0.1)


def _subscribe(url: str, received: Received) -> TelemetrySubscriber:
    sub = TelemetrySubscriber(BrokerConfig(url=url), topic_filters(PREFIX, ["*"]), received)
    sub.start()
    assert sub.wait_subscribed(30)
    return sub


def _run(url: str, **kwargs: Any) -> Any:
    broker = BrokerConfig(url=url, client_id_prefix="so101-edge-sim-")
    return EdgeSimulator(EdgeSimConfig(broker=broker, **kwargs)).run()


@pytest.mark.slow
def test_rate_is_kept_without_drift(mosquitto: MosquittoBroker) -> None:
    received = Received()
    sub = _subscribe(mosquitto.url, received)
    try:
        report = _run(mosquitto.url, rate_hz=50, seconds=1.0)
        received.wait_for(report.published)
    finally:
        sub.stop(30)
    # Every tick of the 50 is published or, if the machine stalled the loop over a second, skipped (a
    # loaded machine does that; the checks below hold either way).
    assert report.ticks == report.published == len(received.items)
    assert report.ticks + report.skipped_ticks == 50
    # The schedule is absolute: the 50th tick is due 0.98 s after the start and never sent early (a
    # skipped one ends the run later still). How late it ended is this machine's load, not the simulator's:
    # speed belongs to `twin bench`.
    assert report.elapsed_s >= 0.98
    # Timestamps follow the absolute schedule exactly: each on the 20 ms grid (1 ms for rounding), no
    # accumulated drift; a gap in the grid is only ever ticks the report counts as skipped.
    stamps = [json.loads(p)["timestamp"] for _, p, _ in received.items]
    grid = [round((s - stamps[0]) / 20) for s in stamps]
    assert all(abs(s - stamps[0] - 20 * n) <= 1 for s, n in zip(stamps, grid, strict=True)), stamps
    assert all(b > a for a, b in itertools.pairwise(grid)), grid
    assert not grid or grid[-1] + 1 - len(grid) <= report.skipped_ticks, grid
    if report.skipped_ticks == 0:
        assert grid == list(range(50)), grid


@pytest.mark.slow
def test_faults_are_produced_as_counted(mosquitto: MosquittoBroker) -> None:
    received = Received()
    sub = _subscribe(mosquitto.url, received)
    try:
        before_ms = time.time() * 1000
        report = _run(
            mosquitto.url,
            devices=device_ids(2),
            rate_hz=100,
            seconds=1.0,
            seed=7,
            faults=FaultConfig(drop=0.1, duplicate=0.1, reorder=0.1, clock_skew_ms=60_000),
        )
        after_ms = time.time() * 1000
        received.wait_for(report.published)
    finally:
        sub.stop(30)
    # Every tick of the 100 is built or, if the machine stalled the loop over a second, skipped (by design:
    # a loaded machine does that). Each fault showing up needs the whole run; the counts below hold either
    # way.
    assert report.ticks + report.skipped_ticks == 100
    assert report.generated == 2 * report.ticks
    if report.skipped_ticks == 0:
        assert report.dropped > 0 and report.duplicated > 0 and report.reordered > 0
    assert report.published == report.generated - report.dropped + report.duplicated
    assert len(received.items) == report.published  # loopback QoS 0 loses nothing
    by_device: dict[str, list[dict[str, Any]]] = {}
    for topic, payload, _ in received.items:
        device = device_from_topic(topic, PREFIX)
        assert device is not None
        by_device.setdefault(device, []).append(json.loads(payload))
    assert {d: len(m) for d, m in by_device.items()} == report.per_device
    inversions = duplicates = 0
    for device, messages in by_device.items():
        stamps = [m["timestamp"] for m in messages]
        duplicates += sum(1 for a, b in itertools.pairwise(messages) if a == b)
        inversions += sum(1 for a, b in itertools.pairwise(stamps) if b < a)
        # Skew: arm-001 runs 30 s ahead, arm-002 60 s ahead of the wall clock (during the run; 1 ms for
        # rounding).
        skew = {"arm-001": 30_000, "arm-002": 60_000}[device]
        assert before_ms + skew - 1 <= stamps[-1] <= after_ms + skew + 1
    assert duplicates == report.duplicated
    assert inversions == report.reordered
    total_unique = sum(len({m["timestamp"] for m in ms}) for ms in by_device.values())
    assert total_unique == report.generated - report.dropped


@pytest.mark.slow
def test_malformed_fault_reaches_the_consumer_and_is_rejected(mosquitto: MosquittoBroker) -> None:
    received = Received()
    sub = _subscribe(mosquitto.url, received)
    try:
        report = _run(mosquitto.url, rate_hz=100, seconds=1.0, seed=11, faults=FaultConfig(malformed=0.5))
        received.wait_for(report.published)
    finally:
        sub.stop(30)
    # A stall over a second skips ticks (by design); the kinds' variety needs the whole run, the counts of
    # what was sent below hold either way.
    assert report.ticks + report.skipped_ticks == 100
    if report.skipped_ticks == 0:
        assert report.malformed_total > 20
        assert sum(1 for v in report.malformed.values() if v) >= 6  # several kinds, not one
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    rejected: dict[str, int] = {}
    accepted = 0
    for topic, payload, _ in received.items:
        try:
            decoder.decode(payload, topic_device=device_from_topic(topic, PREFIX))
            accepted += 1
        except TelemetryRejected as exc:
            rejected[str(exc.reason)] = rejected.get(str(exc.reason), 0) + 1
    assert sum(rejected.values()) == report.malformed_total
    assert accepted == report.published - report.malformed_total
    for kind, count in report.malformed.items():
        assert rejected.get(kind, 0) >= count  # each kind is named as the agent's reason


@pytest.mark.slow
def test_cli_runs_and_reports(mosquitto: MosquittoBroker, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(
        [
            *("edge-sim", "--broker", mosquitto.url, "--devices", "2", "--rate", "20", "--seconds", "0.5"),
            *(
                "--variant",
                "degrees",
                "--malformed",
                "0.3",
                "--seed",
                "5",
                "--json",
                "--log-level",
                "WARNING",
            ),
        ]
    )
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    # 10 ticks, each built or (a stall over a second, by design) skipped.
    assert report["ticks"] + report["skipped_ticks"] == 10
    assert report["generated"] == 2 * report["ticks"] == sum(report["per_device"].values())
    assert report["per_device"].keys() == {"arm-001", "arm-002"} or report["skipped_ticks"]
    assert report["malformed_total"] == sum(report["malformed"].values())
    assert report["malformed_total"] > 0 or report["skipped_ticks"]
    assert main(["edge-sim", "--broker", "ftp://x", "--seconds", "1"]) == 2
    assert "mqtts://host:port" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_stops_on_sigterm(mosquitto: MosquittoBroker) -> None:
    received = Received()
    sub = _subscribe(mosquitto.url, received)
    twin = Path(sys.executable).with_name("twin")
    proc = subprocess.Popen(
        [str(twin), "edge-sim", "--broker", mosquitto.url, "--device", "arm-042", "--rate", "20"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for(lambda: received.items, 60, "the simulator to publish")
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        sub.stop(30)
    assert proc.returncode == 0, err
    assert "published" in out
    assert device_from_topic(received.items[0][0], PREFIX) == "arm-042"


@pytest.mark.slow
def test_stop_event_ends_a_forever_run(mosquitto: MosquittoBroker) -> None:
    stop = threading.Event()
    config = EdgeSimConfig(broker=BrokerConfig(url=mosquitto.url), rate_hz=10)
    simulator = EdgeSimulator(config)
    ticks_at_stop: list[int] = []

    def stop_after_three_ticks() -> None:
        wait_for(lambda: simulator.report.ticks >= 3, 60, "three ticks")
        stop.set()
        ticks_at_stop.append(simulator.report.ticks)

    stopper = threading.Thread(target=stop_after_three_ticks, daemon=True)
    stopper.start()
    report = simulator.run(stop)  # returns: a run without `seconds` ends on the event
    stopper.join(30)
    assert ticks_at_stop, "the run ended before the stop event was set"
    # Once the event is set no new tick starts; at most the one under way when it was set finishes.
    assert ticks_at_stop[0] <= report.ticks <= ticks_at_stop[0] + 1


def test_a_device_id_the_stack_refuses_is_refused_at_argument_time(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # The rule twin calibration keeps: "bad id" would have been published as dt/lerobot/bad id/telemetry.
    with pytest.raises(SystemExit) as exited:
        main(
            ["edge-sim", "--broker", NO_BROKER, "--device", "arm-001", "--device", "bad id", "--seconds", "1"]
        )
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert "argument --device: 'bad id' is not a device id" in err, err
    assert POLICY_DEVICE_ID_RULE in err and "pass --device such an id (as the arm's edge publishes)" in err, (
        err
    )


def test_a_refused_connection_names_the_broker_and_what_to_check(caplog: pytest.LogCaptureFixture) -> None:
    # Nothing listens on NO_BROKER's port: the simulator gives up at its connect timeout with the last error
    # and the hint (is a broker there, else the URL), in its log line and in what it raises, so a user who
    # started it before the broker sees what to do.
    config = EdgeSimConfig(broker=BrokerConfig(url=NO_BROKER), seconds=1.0, connect_timeout_s=3.0)
    with caplog.at_level("WARNING", logger="twin.edge"), pytest.raises(ConnectionError) as raised:
        EdgeSimulator(config).run()
    message = str(raised.value)
    assert message.startswith(f"edge-sim could not connect to {NO_BROKER} within 3 s: "), message
    assert "Is a broker listening on 127.0.0.1 port 1 (a local one: `mosquitto -p 1`)?" in message, message
    assert "Else fix the URL in --broker" in message, message
    lines = [r.getMessage() for r in caplog.records if "could not connect to" in r.getMessage()]
    assert lines and "Is a broker listening on 127.0.0.1 port 1" in lines[0], lines
