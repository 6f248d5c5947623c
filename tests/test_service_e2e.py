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
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from awscrt import mqtt5
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, TelemetryRejected, Units
from twin.robot import so101
from twin.service.agent import AgentService
from twin.service.config import load_config
from twin.tools.edge_sim import encode, make_payload
from twin.tools.mosquitto import MosquittoBroker
from twin.transport.subscriber import BrokerConfig, build_mqtt5_client, new_client_id, topic_for

pytestmark = pytest.mark.slow

PREFIX = "dt/lerobot"


class Publisher:
    """A plain awscrt MQTT5 publisher (QoS 0, like the edge); reconnects by itself after broker restarts."""

    def __init__(self, url: str) -> None:
        self.connected = threading.Event()
        self.stopped = threading.Event()
        self.client = build_mqtt5_client(
            BrokerConfig(url=url, min_reconnect_delay_ms=100, max_reconnect_delay_ms=500),
            new_client_id("test-pub-"),
            on_connection_success=lambda _d: self.connected.set(),
            on_disconnection=lambda _d: self.connected.clear(),
            on_stopped=lambda _d: self.stopped.set(),
        )
        self.client.start()
        assert self.connected.wait(10), "test publisher could not connect"

    def publish(self, device: str, payload: bytes) -> None:
        self.client.publish(
            mqtt5.PublishPacket(topic=topic_for(PREFIX, device), payload=payload, qos=mqtt5.QoS.AT_MOST_ONCE)
        ).result(5)

    def close(self) -> None:
        self.client.stop()
        self.stopped.wait(5)


def agent_config(broker_url: str, **overrides: Any):
    values = {
        "broker.url": broker_url,
        "http.listen": "127.0.0.1:0",
        "telemetry.devices": ["arm-001", "arm-002"],
        "telemetry.units": "auto",
        "health.expected_rate_hz": 20.0,
        "health.stale_periods": 3,
        "health.offline_after_s": 1.0,
        "health.window_s": 2.0,
    }
    values.update(overrides)
    return load_config(None, values)


def start_agent(broker_url: str, **overrides: Any) -> AgentService:
    service = AgentService(agent_config(broker_url, **overrides))
    service.start()
    assert service.wait_subscribed(10), "agent did not subscribe"
    return service


def http_get(url: str) -> tuple[int, Any]:
    try:
        with urllib.request.urlopen(url, timeout=5) as resp:
            body = resp.read().decode()
            status = resp.status
    except urllib.error.HTTPError as err:
        body, status = err.read().decode(), err.code
    return status, json.loads(body) if body.startswith(("{", "[")) else body


def wait_for(predicate: Callable[[], Any], timeout: float, what: str, interval: float = 0.02) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


def device_state(service: AgentService, device: str) -> dict[str, Any]:
    return http_get(service.http_url + "/state")[1]["devices"][device]


@pytest.fixture
def publisher(mosquitto: MosquittoBroker) -> Iterator[Publisher]:
    pub = Publisher(mosquitto.url)
    yield pub
    pub.close()


@pytest.fixture
def agent(mosquitto: MosquittoBroker, tmp_path: Path) -> Iterator[AgentService]:
    service = start_agent(mosquitto.url, **{"twin.record_dir": str(tmp_path / "sessions")})
    yield service
    service.stop()


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
                (s := device_state(agent, d))["timestamp_ms"] == e.timestamp_ms and s
            ),
            5,
            f"{device} at the last timestamp",
        )
        assert state["units"] == variant
        assert state["status"] == "ONLINE"
        assert set(state["joints_rad"]) == set(so101.JOINT_NAMES)
        for joint in so101.JOINT_NAMES:
            assert abs(state["joints_rad"][joint] - expected.angles_rad[joint]) <= 1e-9, (device, joint)
        assert state["counters"]["applied"] >= 1
        assert state["counters"]["rejected"].get("units_undecided", 0) <= 3
        assert state["rate_hz"] > 0
        assert state["internal_latency_s"]["p50"] is not None
        assert state["edge_clock_latency_s"]["samples"] > 0
        assert set(state["torques_nm"]) == set(so101.JOINT_NAMES)

    status, metrics = http_get(agent.http_url + "/metrics")
    assert status == 200
    assert 'twin_device_status{device="arm-002",status="ONLINE"} 1' in metrics
    status, health = http_get(agent.http_url + "/healthz")
    assert status == 200 and health["status"] == "ok"
    assert agent.state()["agent"]["recording"]["samples_written"] > 0


def publish_for(publisher: Publisher, device: str, seconds: float, rate_hz: float = 20.0) -> int:
    rng = random.Random(1)
    n = int(seconds * rate_hz)
    for _ in range(n):
        payload = make_payload(device, time.monotonic(), "ticks", rng)
        publisher.publish(device, encode(payload))
        time.sleep(1.0 / rate_hz)
    return n


def test_stale_and_offline_appear_and_clear(mosquitto: MosquittoBroker, publisher: Publisher) -> None:
    service = start_agent(mosquitto.url, **{"telemetry.devices": ["arm-001"], "telemetry.units": "ticks"})
    try:
        publish_for(publisher, "arm-001", 0.6)
        t_stop = time.monotonic()  # the last message went out one period (50 ms) before this
        assert device_state(service, "arm-001")["status"] == "ONLINE"
        assert http_get(service.http_url + "/healthz")[0] == 200
        # Stale after 3 periods at 20 Hz (0.15 s), offline after 1 s of silence.
        wait_for(lambda: device_state(service, "arm-001")["status"] == "STALE", 1.0, "STALE")
        assert time.monotonic() - t_stop < 1.0
        wait_for(lambda: device_state(service, "arm-001")["status"] == "OFFLINE", 2.0, "OFFLINE")
        assert time.monotonic() - t_stop >= 1.0 - 0.05
        status, body = http_get(service.http_url + "/healthz")
        assert status == 503 and "device arm-001 is OFFLINE" in body["reasons"]
        metrics = http_get(service.http_url + "/metrics")[1]
        assert 'twin_device_status{device="arm-001",status="OFFLINE"} 1' in metrics

        publish_for(publisher, "arm-001", 0.3)
        assert device_state(service, "arm-001")["status"] == "ONLINE"
        assert http_get(service.http_url + "/healthz")[0] == 200
    finally:
        service.stop()


def test_stream_follows_the_twin(agent: AgentService, publisher: Publisher) -> None:
    rng = random.Random(3)
    seen: list[int | None] = []

    def reader() -> None:
        with urllib.request.urlopen(agent.http_url + "/stream", timeout=5) as resp:
            for raw in resp:
                if raw.startswith(b"data: "):
                    seen.append(json.loads(raw[6:])["devices"]["arm-001"]["timestamp_ms"])
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


def test_sigterm_flushes_the_recording_and_exits_zero(mosquitto: MosquittoBroker, tmp_path: Path) -> None:
    config = tmp_path / "agent.toml"
    config.write_text(
        f'[broker]\nurl = "{mosquitto.url}"\n[telemetry]\ndevices = ["arm-001"]\nunits = "ticks"\n'
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
        publisher = Publisher(mosquitto.url)
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
