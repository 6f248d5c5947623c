"""End to end against a real mosquitto: publish edge telemetry, read the agent's HTTP state.

The agent runs in-process (AgentService) except in the SIGTERM test, which runs `twin run` as a subprocess to
prove the real signal path: exit code 0 and a flushed USD recording. The in-process agent runs on the test's
clock (ManualClock), which stands still until the test moves it: whether a device reads ONLINE, STALE or
OFFLINE is then the test's decision, not a matter of how quickly this busy machine answered.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import (
    ManualClock,
    Publisher,
    device_state,
    get_health,
    get_metrics,
    get_state,
    metric,
    run_twin,
    start_agent_on_clock,
    wait_for,
    wait_handled,
)
from twin.core.health import DeviceStatus
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, TelemetryRejected, Units
from twin.edge.payload import encode, make_payload
from twin.rig.local import LocalRig
from twin.robot import so101
from twin.service.agent import AgentService
from twin.service.mirror import Mirror
from twin.service.state import AgentState

pytestmark = pytest.mark.slow

# Fast health thresholds so STALE/OFFLINE show within a test: 20 Hz expected, STALE after 3 missed periods.
FAST_HEALTH = {
    "health.expected_rate_hz": 20.0,
    "health.stale_periods": 3,
    "health.offline_after_s": 1.0,
    "health.window_s": 2.0,
}


def start_agent(rig: LocalRig, clock: ManualClock, **overrides: Any) -> AgentService:
    values = {"telemetry.devices": ["arm-001", "arm-002"], "telemetry.units": "auto", **FAST_HEALTH}
    values.update(overrides)
    return start_agent_on_clock(rig, values, clock)


@pytest.fixture
def agent(rig: LocalRig, tmp_path: Path) -> Iterator[AgentService]:
    # The clock stands still: every device heard from stays ONLINE, its rates and latencies in the window.
    yield start_agent(rig, ManualClock(), **{"twin.record_dir": str(tmp_path / "sessions")})


def test_two_devices_both_variants_match_decode(agent: AgentService, publisher: Publisher) -> None:
    rng = random.Random(7)
    reference = TelemetryDecoder(DecoderConfig(units=Units.AUTO))
    variants = {"arm-001": "ticks", "arm-002": "degrees"}
    last: dict[str, Any] = {}
    t0_ms = int(time.time() * 1000)
    for i in range(12):
        for device, variant in variants.items():
            payload = encode(make_payload(device, 0.3 * i, variant, rng, timestamp_ms=t0_ms + 50 * i))
            publisher.publish(device, payload)
            try:
                last[device] = reference.decode(payload, topic_device=device)
            except TelemetryRejected as exc:
                # auto units: the first messages may wait for evidence, exactly as in the agent.
                assert exc.reason == "units_undecided"

    for device, variant in variants.items():
        expected = last[device]
        assert expected.units == variant
        state = wait_for(
            lambda d=device, e=expected: (
                (s := device_state(agent.http_url, d)).timestamp_ms == e.timestamp_ms and s
            ),
            30,
            f"{device} at the last timestamp",
        )
        # Wiring: the agent shows what the decoder under test makes of the last message (the decoder's own
        # hand-derived oracles are in test_telemetry.py).
        assert state.units == variant
        assert state.health.status is DeviceStatus.ONLINE
        assert state.joints_rad is not None and set(state.joints_rad) == set(so101.JOINT_NAMES)
        for joint in so101.JOINT_NAMES:
            assert abs(state.joints_rad[joint] - expected.angles_rad[joint]) <= 1e-9, (device, joint)
        assert state.health.counters.applied >= 1
        assert state.health.counters.rejected.get("units_undecided", 0) <= 3
        assert state.health.rate_hz > 0
        assert state.health.internal_latency_s.p50 is not None
        assert state.health.edge_clock_latency_s.samples > 0
        assert state.torques_nm is not None and set(state.torques_nm) == set(so101.JOINT_NAMES)

    samples = get_metrics(agent.http_url)
    assert metric(samples, "twin_device_status", device="arm-002", status="ONLINE") == 1
    status, health = get_health(agent.http_url)
    assert status == 200 and health["status"] == "ok"
    recording = wait_for(
        lambda: (r := agent.state().agent.recording) and r.samples_written > 0 and r,
        30,
        "the recording sink to write samples",
    )
    assert recording.path.endswith(".usdc")


def publish_ticks(publisher: Publisher, device: str, count: int, t0_ms: int, rate_hz: float = 20.0) -> None:
    """`count` messages stamped `rate_hz` apart from t0_ms (ages come from the agent's clock)."""
    rng = random.Random(1)
    for i in range(count):
        stamp = t0_ms + round(i * 1000 / rate_hz)
        publisher.publish(device, encode(make_payload(device, i / rate_hz, "ticks", rng, timestamp_ms=stamp)))


def test_stale_and_offline_appear_and_clear(rig: LocalRig, publisher: Publisher) -> None:
    clock = ManualClock()
    service = start_agent(rig, clock, **{"telemetry.devices": ["arm-001"], "telemetry.units": "ticks"})
    url = service.http_url

    def status() -> DeviceStatus:
        return device_state(url, "arm-001").health.status

    t0 = int(time.time() * 1000)
    publish_ticks(publisher, "arm-001", 12, t0)
    wait_handled(lambda: get_state(url), 12)
    # The clock stands at the messages' arrival: no silence yet.
    assert status() is DeviceStatus.ONLINE
    assert get_health(url)[0] == 200
    # Stale after 3 periods at 20 Hz (0.15 s), offline after 1 s of silence: STALE shows in between, and
    # OFFLINE not before the 1 s threshold.
    clock.advance(0.2)
    assert status() is DeviceStatus.STALE
    clock.advance(0.75)
    assert status() is DeviceStatus.STALE, "OFFLINE before 1 s of silence"
    clock.advance(0.1)
    assert status() is DeviceStatus.OFFLINE
    status_code, body = get_health(url)
    assert status_code == 503 and "device arm-001 is OFFLINE" in body["reasons"]
    assert metric(get_metrics(url), "twin_device_status", device="arm-001", status="OFFLINE") == 1

    publish_ticks(publisher, "arm-001", 6, t0 + 2000)
    wait_handled(lambda: get_state(url), 18)
    assert status() is DeviceStatus.ONLINE
    assert get_health(url)[0] == 200


def test_healthz_reads_the_statuses_without_building_the_state(
    rig: LocalRig, publisher: Publisher, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Health checks come often: /healthz asks each mirror for its arms' statuses, not for the report (at
    1,000 arms that took the workers over a second to build under load)."""
    clock = ManualClock()
    service = start_agent(rig, clock, **{"telemetry.devices": ["arm-001"], "telemetry.units": "ticks"})
    publish_ticks(publisher, "arm-001", 6, int(time.time() * 1000))
    wait_handled(lambda: get_state(service.http_url), 6)

    def no_report(self: Mirror) -> None:
        raise AssertionError("/healthz built a mirror report")

    monkeypatch.setattr(Mirror, "report", no_report)
    assert get_health(service.http_url) == (
        200,
        {
            "status": "ok",
            "running": True,
            "broker_connected": True,
            "devices": {"arm-001": "ONLINE"},
            "reasons": [],
        },
    )
    clock.advance(1.1)  # past FAST_HEALTH's offline time
    status_code, body = get_health(service.http_url)
    assert status_code == 503 and body["devices"] == {"arm-001": "OFFLINE"}
    assert body["reasons"] == ["device arm-001 is OFFLINE"]


def test_stream_follows_the_twin(agent: AgentService, publisher: Publisher) -> None:
    rng = random.Random(3)
    seen: list[int | None] = []
    t0 = int(time.time() * 1000)

    def reader() -> None:
        with urllib.request.urlopen(agent.http_url + "/stream", timeout=30) as resp:
            for raw in resp:
                if raw.startswith(b"data: "):
                    seen.append(AgentState.from_json(raw[6:]).devices["arm-001"].timestamp_ms)
                    if seen[-1] == t0 + 9:
                        return

    def publish(i: int) -> None:
        publisher.publish(
            "arm-001", encode(make_payload("arm-001", i * 0.1, "ticks", rng, timestamp_ms=t0 + i))
        )

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    wait_for(lambda: seen, 30, "the stream's first event")
    # The stream shows a pose from the first half (units=auto may turn the first messages away while it
    # gathers evidence) before the second half is sent, so it has two states to show in order however
    # slowly it is read.
    for i in range(5):
        publish(i)
    wait_for(lambda: any(s is not None for s in seen), 30, "the stream to show a pose")
    for i in range(5, 10):
        publish(i)
    thread.join(60)
    assert not thread.is_alive(), f"the stream never showed the last message: {seen[-5:]}"
    stamps = [s for s in seen if s is not None]
    assert stamps == sorted(stamps)
    assert stamps[0] < t0 + 5 and stamps[-1] == t0 + 9


def test_sigterm_flushes_the_recording_and_exits_zero(rig: LocalRig, tmp_path: Path) -> None:
    config = tmp_path / "agent.toml"
    config.write_text(
        f'[broker]\nurl = "{rig.broker.url}"\n[telemetry]\ndevices = ["arm-001"]\nunits = "ticks"\n'
        '[twin]\nrecord_flush_s = 60.0\n[http]\nlisten = "127.0.0.1:0"\n'
    )
    record_dir = tmp_path / "rec"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "twin.cli", "run", "--config", str(config), "--record-dir", str(record_dir)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        text=True,
    )
    lines: list[dict[str, Any]] = []

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(json.loads(line))  # every stdout line is a JSON object

    thread = threading.Thread(target=pump, daemon=True)
    thread.start()
    try:
        wait_for(lambda: any("subscribed" in ln["msg"] for ln in lines), 60, "the agent to subscribe", 0.1)
        base_url = wait_for(
            lambda: next((ln["url"] for ln in lines if ln["msg"] == "http listening"), None),
            60,
            "the agent's HTTP address in its log",
        )
        publisher = Publisher(rig.broker.url)
        try:
            rng = random.Random(5)
            t0 = int(time.time() * 1000)
            for i in range(20):
                publisher.publish(
                    "arm-001", encode(make_payload("arm-001", i * 0.1, "ticks", rng, timestamp_ms=t0 + i))
                )
                # The recording keeps at most 30 samples a second of receive time: 20 Hz arrivals are all
                # kept, and a busy agent receiving several at once still keeps the 5 the check needs.
                time.sleep(0.05)
        finally:
            publisher.close()
        wait_handled(lambda: get_state(base_url), 20)
        # record_flush_s = 60: nothing but the shutdown path can have saved these samples.
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0, proc.stderr.read() if proc.stderr else ""
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    thread.join(30)
    assert all({"ts", "level", "logger", "msg"} <= set(ln) for ln in lines)
    assert any(ln["msg"] == "agent stopped" for ln in lines)
    sessions = list(record_dir.glob("session-*.usdc"))  # the default format
    assert len(sessions) == 1
    from pxr import Usd

    stage = Usd.Stage.Open(str(sessions[0]))
    assert stage.GetEndTimeCode() > stage.GetStartTimeCode()
    samples = [
        len(attr.GetTimeSamples())
        for prim in stage.Traverse()
        for attr in prim.GetAttributes()
        if attr.GetName().endswith(":twin")
    ]
    assert samples and max(samples) >= 5


def test_bad_config_exits_2_with_the_reason(tmp_path: Path) -> None:
    config = tmp_path / "bad.toml"
    config.write_text("[health]\noffline_after = 3\n")
    proc = run_twin(["run", "--config", str(config)], os.environ, timeout=30)
    assert proc.returncode == 2
    assert "health.offline_after" in proc.stderr and "offline_after_s" in proc.stderr
    line = json.loads(proc.stdout.strip().splitlines()[-1])
    assert line["level"] == "ERROR" and "offline_after_s" in line["error"]
