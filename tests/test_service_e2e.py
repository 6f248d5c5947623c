"""End to end against a real mosquitto: publish edge telemetry, read the agent's HTTP state.

The agent runs in-process (AgentService) except in the SIGTERM test, which runs `twin run` as a subprocess to
prove the real signal path: exit code 0 and a flushed USD recording.
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
from conftest import Publisher, device_state, get_health, get_metrics, metric, wait_for
from twin.core.health import DeviceStatus
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, TelemetryRejected, Units
from twin.edge.payload import encode, make_payload
from twin.rig.local import LocalRig
from twin.robot import so101
from twin.service.agent import AgentService
from twin.service.state import AgentState

pytestmark = pytest.mark.slow

# Fast health thresholds so STALE/OFFLINE show within a test: 20 Hz expected, STALE after 3 missed periods.
FAST_HEALTH = {
    "health.expected_rate_hz": 20.0,
    "health.stale_periods": 3,
    "health.offline_after_s": 1.0,
    "health.window_s": 2.0,
}


def start_agent(rig: LocalRig, **overrides: Any) -> AgentService:
    values = {"telemetry.devices": ["arm-001", "arm-002"], "telemetry.units": "auto", **FAST_HEALTH}
    values.update(overrides)
    return rig.start_agent(values)


@pytest.fixture
def agent(rig: LocalRig, tmp_path: Path) -> Iterator[AgentService]:
    yield start_agent(rig, **{"twin.record_dir": str(tmp_path / "sessions")})


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
        time.sleep(0.05)

    for device, variant in variants.items():
        expected = last[device]
        assert expected.units == variant
        state = wait_for(
            lambda d=device, e=expected: (
                (s := device_state(agent.http_url, d)).timestamp_ms == e.timestamp_ms and s
            ),
            5,
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
        5,
        "the recording sink to write samples",
    )
    assert recording.path.endswith(".usdc")


def publish_for(publisher: Publisher, device: str, seconds: float, rate_hz: float = 20.0) -> int:
    rng = random.Random(1)
    n = int(seconds * rate_hz)
    for _ in range(n):
        payload = make_payload(device, time.monotonic(), "ticks", rng)
        publisher.publish(device, encode(payload))
        time.sleep(1.0 / rate_hz)
    return n


def test_stale_and_offline_appear_and_clear(rig: LocalRig, publisher: Publisher) -> None:
    service = start_agent(rig, **{"telemetry.devices": ["arm-001"], "telemetry.units": "ticks"})
    url = service.http_url
    publish_for(publisher, "arm-001", 0.6)
    t_stop = time.monotonic()  # the last message went out one period (50 ms) before this
    assert device_state(url, "arm-001").health.status is DeviceStatus.ONLINE
    assert get_health(url)[0] == 200
    # Stale after 3 periods at 20 Hz (0.15 s), offline after 1 s of silence: STALE must show in between.
    wait_for(
        lambda: device_state(url, "arm-001").health.status is DeviceStatus.STALE, 0.9, "STALE before 1 s"
    )
    wait_for(lambda: device_state(url, "arm-001").health.status is DeviceStatus.OFFLINE, 2.0, "OFFLINE")
    # OFFLINE comes from the 1 s threshold, so it cannot show earlier than that after the last message.
    assert time.monotonic() - t_stop >= 1.0 - 0.05
    status, body = get_health(url)
    assert status == 503 and "device arm-001 is OFFLINE" in body["reasons"]
    assert metric(get_metrics(url), "twin_device_status", device="arm-001", status="OFFLINE") == 1

    publish_for(publisher, "arm-001", 0.3)
    assert device_state(url, "arm-001").health.status is DeviceStatus.ONLINE
    assert get_health(url)[0] == 200


def test_stream_follows_the_twin(agent: AgentService, publisher: Publisher) -> None:
    rng = random.Random(3)
    seen: list[int | None] = []

    def reader() -> None:
        with urllib.request.urlopen(agent.http_url + "/stream", timeout=5) as resp:
            for raw in resp:
                if raw.startswith(b"data: "):
                    seen.append(AgentState.from_json(raw[6:]).devices["arm-001"].timestamp_ms)
                    if len(seen) >= 15:
                        return

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    t0 = int(time.time() * 1000)
    for i in range(10):
        publisher.publish(
            "arm-001", encode(make_payload("arm-001", i * 0.1, "ticks", rng, timestamp_ms=t0 + i))
        )
        time.sleep(0.03)
    thread.join(5)
    stamps = [s for s in seen if s is not None]
    assert stamps and stamps == sorted(stamps)
    assert stamps[-1] > stamps[0]


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
        wait_for(lambda: any("subscribed" in ln["msg"] for ln in lines), 20, "the agent to subscribe", 0.1)
        publisher = Publisher(rig.broker.url)
        try:
            rng = random.Random(5)
            t0 = int(time.time() * 1000)
            for i in range(10):
                publisher.publish(
                    "arm-001", encode(make_payload("arm-001", i * 0.1, "ticks", rng, timestamp_ms=t0 + i))
                )
                time.sleep(0.05)
        finally:
            publisher.close()
        # record_flush_s = 60: nothing but the shutdown path can have saved these samples.
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(20) == 0, proc.stderr.read() if proc.stderr else ""
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    thread.join(5)
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
    proc = subprocess.run(
        [sys.executable, "-m", "twin.cli", "run", "--config", str(config)],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert proc.returncode == 2
    assert "health.offline_after" in proc.stderr and "offline_after_s" in proc.stderr
    line = json.loads(proc.stdout.strip().splitlines()[-1])
    assert line["level"] == "ERROR" and "offline_after_s" in line["error"]
