"""TelemetrySubscriber and broker settings against a real mosquitto (plain and TLS) and the real awscrt.

AWS IoT Core is not reachable from here: the "iot" path is checked by building (never starting) the client
through the SDK's SigV4 WebSocket builder, and moto stands in for iot:DescribeEndpoint.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from awscrt import mqtt5
from awscrt.exceptions import AwsCrtError
from conftest import NO_BROKER, get_state, wait_for
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
from moto import mock_aws
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
from twin.core.topics import device_from_topic, topic_filters
from twin.edge.payload import device_ids, mock_ticks
from twin.edge.simulator import EdgeSimConfig, EdgeSimulator
from twin.rig.mosquitto import MosquittoBroker
from twin.service.agent import AgentService
from twin.service.config import load_config
from twin.transport import client as client_mod
from twin.transport.broker import (
    CLIENT_ID_PREFIX_MAX,
    NO_CREDENTIALS_HINT,
    BrokerConfig,
    BrokerConfigError,
    connack_hint,
    connect_hint,
    new_client_id,
)
from twin.transport.client import build_mqtt5_client, resolve_iot_endpoint
from twin.transport.mailbox import InboundQueue
from twin.transport.subscriber import TelemetrySubscriber

PREFIX = "dt/lerobot"


# -- settings and topics (pure) -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("url", "kind", "host", "port"),
    [
        ("iot", "iot", "", 443),
        ("mqtt://127.0.0.1:1883", "mqtt", "127.0.0.1", 1883),
        ("mqtt://broker.local", "mqtt", "broker.local", 1883),
        ("mqtts://broker.local", "mqtts", "broker.local", 8883),
        ("mqtts://10.0.0.5:9883", "mqtts", "10.0.0.5", 9883),
        (" mqtt://h:1 ", "mqtt", "h", 1),
    ],
)
def test_broker_url_parsing(url: str, kind: str, host: str, port: int) -> None:
    config = BrokerConfig(url=url)
    assert (config.kind, config.host, config.port) == (kind, host, port)


def test_default_backoff_meets_the_recovery_budget_and_the_connect_limit() -> None:
    config = BrokerConfig()
    # FULL jitter waits uniformly in [0, current delay]: once the broker is back, the next attempt comes at
    # most max_reconnect_delay_ms later, inside the 3 s "telemetry flows again" budget with ~1 s to connect.
    assert config.max_reconnect_delay_ms <= 2000
    # ... and at the cap the mean wait is max/2: at most one attempt per second on average, IoT Core's
    # CONNECT limit per client id.
    assert config.max_reconnect_delay_ms / 2 >= 1000
    assert 0 < config.min_reconnect_delay_ms <= config.max_reconnect_delay_ms
    # A silently dropped connection is noticed within a minute (1.5 keep-alives), inside IoT Core's 1200 s.
    assert 1.5 * config.keep_alive_s <= 60 and config.keep_alive_s <= 1200


@pytest.mark.parametrize(
    ("kwargs", "fix"),
    [
        ({"url": ""}, '"iot"'),
        ({"url": "http://h:1"}, "mqtts://host:port"),
        ({"url": "tcp://h"}, "mqtt://host:port"),
        ({"url": "mqtt://h:99999"}, "1..65535"),
        ({"url": "mqtt://h:1/path"}, "only mqtt"),
        ({"url": "mqtt://user:pw@h:1"}, "only mqtt"),
        ({"client_id_prefix": "bad prefix"}, "IAM policy"),
        ({"client_id_prefix": "x" * 101}, "1..100"),
        ({"url": "mqtt://h:1", "ca_file": "/etc/hostname"}, "only applies to mqtts"),
        ({"url": "mqtts://h:1", "ca_file": "/nonexistent/ca.pem"}, "PEM CA bundle"),
        ({"min_reconnect_delay_ms": 0}, "0 < min"),
        ({"min_reconnect_delay_ms": 3000, "max_reconnect_delay_ms": 1000}, "<= max"),
        ({"keep_alive_s": 5000}, "1200"),
    ],
)
def test_broker_config_errors_name_the_fix(kwargs: dict[str, Any], fix: str) -> None:
    with pytest.raises(BrokerConfigError, match=fix.replace("(", r"\(").replace("+", r"\+")):
        BrokerConfig(**kwargs)


def test_client_ids_are_unique_prefixed_and_fit_iot_core() -> None:
    prefix = "p" * CLIENT_ID_PREFIX_MAX  # the longest prefix the settings accept
    ids = {new_client_id(BrokerConfig(client_id_prefix=prefix).client_id_prefix) for _ in range(1000)}
    assert len(ids) == 1000  # two agents with one id would evict each other
    # The IAM policy scopes iot:Connect by prefix, and IoT Core refuses client ids over 128 bytes.
    assert all(i.startswith(prefix) and len(i.encode()) <= 128 for i in ids)
    config = BrokerConfig(url="mqtt://127.0.0.1:1", client_id_prefix="fleet-a-")
    a = TelemetrySubscriber(config, ["t/+/telemetry"], lambda *_: None)
    b = TelemetrySubscriber(config, ["t/+/telemetry"], lambda *_: None)
    assert a.client_id != b.client_id and a.client_id.startswith("fleet-a-")


# -- the "iot" path, built but never started ---------------------------------------------------------------


@pytest.fixture
def builder_calls(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """Record the arguments of the SDK's SigV4 builder; the real builder still constructs the client."""
    calls: list[dict[str, Any]] = []
    real = client_mod.mqtt5_client_builder.websockets_with_default_aws_signing

    def recording(**kwargs: Any) -> mqtt5.Client:
        calls.append(kwargs)
        return real(**kwargs)

    monkeypatch.setattr(client_mod.mqtt5_client_builder, "websockets_with_default_aws_signing", recording)
    return calls


def test_iot_client_uses_sigv4_websockets(builder_calls: list[dict[str, Any]]) -> None:
    from awscrt import auth

    config = BrokerConfig(
        url="iot",
        region="eu-west-1",
        endpoint="abc123-ats.iot.eu-west-1.amazonaws.com",
        min_reconnect_delay_ms=300,
        max_reconnect_delay_ms=1900,
        keep_alive_s=45,
    )
    client_id = new_client_id(config.client_id_prefix)
    client = build_mqtt5_client(config, client_id)
    assert isinstance(client, mqtt5.Client)
    (kwargs,) = builder_calls
    assert kwargs["region"] == "eu-west-1"
    assert kwargs["endpoint"] == "abc123-ats.iot.eu-west-1.amazonaws.com"
    assert isinstance(kwargs["credentials_provider"], auth.AwsCredentialsProvider)
    assert kwargs["client_id"] == client_id
    # Clean session (the twin wants only the newest pose) and jittered backoff (a fleet of agents that lost
    # IoT Core together does not reconnect in lock step), with the configured figures passed through.
    assert kwargs["session_behavior"] == mqtt5.ClientSessionBehaviorType.CLEAN
    assert kwargs["retry_jitter_mode"] == mqtt5.ExponentialBackoffJitterMode.FULL
    assert (kwargs["min_reconnect_delay_ms"], kwargs["max_reconnect_delay_ms"]) == (300, 1900)
    assert kwargs["keep_alive_interval_sec"] == 45


def test_iot_endpoint_from_describe_endpoint(
    builder_calls: list[dict[str, Any]], monkeypatch: pytest.MonkeyPatch
) -> None:
    # IoT Core is not reachable here; moto answers iot:DescribeEndpoint in its place.
    for name, value in {
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_SESSION_TOKEN": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
    }.items():
        monkeypatch.setenv(name, value)
    with mock_aws():
        subscriber = TelemetrySubscriber(
            BrokerConfig(url="iot", region="us-east-1"), topic_filters(PREFIX, ["*"]), lambda *_: None
        )
        client = build_mqtt5_client(subscriber.config, subscriber.client_id)
    assert isinstance(client, mqtt5.Client)
    assert subscriber.config.endpoint == ""
    # The account-specific ATS data endpoint, as DescribeEndpoint(endpointType="iot:Data-ATS") returns it.
    assert re.fullmatch(r"[a-z0-9]+-ats\.iot\.us-east-1\.amazonaws\.com", builder_calls[0]["endpoint"])
    assert builder_calls[0]["client_id"] == subscriber.client_id


def test_iot_endpoint_lookup_failure_names_the_fix(monkeypatch: pytest.MonkeyPatch) -> None:
    import boto3

    def broken_client(*_args: Any, **_kwargs: Any) -> Any:
        raise RuntimeError("no credentials")

    monkeypatch.setattr(boto3, "client", broken_client)
    with pytest.raises(BrokerConfigError, match=r"set \[broker\] endpoint \(twin edge-sim: --endpoint\)"):
        resolve_iot_endpoint(BrokerConfig(url="iot", region="us-east-1"))


def test_no_aws_credentials_says_how_to_give_them(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A laptop without AWS credentials: the endpoint lookup, and every failed connect after it, say where
    credentials come from, not only that the lookup failed (nothing is sent: boto3 finds none first)."""
    for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_PROFILE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(tmp_path / "no-credentials"))
    monkeypatch.setenv("AWS_CONFIG_FILE", str(tmp_path / "no-config"))
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")
    with pytest.raises(BrokerConfigError) as caught:
        resolve_iot_endpoint(BrokerConfig(url="iot", region="us-east-1"))
    assert str(caught.value).startswith(
        "could not look up the IoT Core endpoint: No AWS credentials were found"
    )
    assert "`aws configure`" in str(caught.value) and "AWS_PROFILE" in str(caught.value)
    # With an endpoint given, awscrt signs each connect and fails each one with this error.
    no_credentials = AwsCrtError(code=6153, name="AWS_AUTH_SIGNING_NO_CREDENTIALS", message="no credentials")
    assert connect_hint(BrokerConfig(url="iot"), no_credentials) == NO_CREDENTIALS_HINT
    assert connect_hint(BrokerConfig(url="mqtt://127.0.0.1:1883"), no_credentials) == ""


# -- against a real broker ---------------------------------------------------------------------------------


class Collector:
    """on_message that records (topic, payload, received) and never blocks."""

    def __init__(self) -> None:
        self.messages: list[tuple[str, bytes, float]] = []
        self.threads: set[str] = set()

    def __call__(self, topic: str, payload: bytes, received: float) -> None:
        self.threads.add(threading.current_thread().name)
        self.messages.append((topic, payload, received))

    def wait_for(self, count: int, timeout: float = 60.0) -> bool:
        return wait_for(lambda: len(self.messages) >= count, timeout, f"{count} messages")


def _sim(url: str, **kwargs: Any) -> EdgeSimulator:
    broker = BrokerConfig(url=url, client_id_prefix="so101-edge-sim-", ca_file=kwargs.pop("ca_file", ""))
    return EdgeSimulator(EdgeSimConfig(broker=broker, **kwargs))


@pytest.mark.slow
@pytest.mark.parametrize("variant", ["ticks", "degrees"])
def test_receives_edge_sim_variants(mosquitto: MosquittoBroker, variant: str) -> None:
    collector = Collector()
    sub = TelemetrySubscriber(BrokerConfig(url=mosquitto.url), topic_filters(PREFIX, ["arm-001"]), collector)
    sub.start()
    try:
        assert sub.wait_subscribed(30), sub.stats
        assert sub.connected
        report = _sim(mosquitto.url, variant=variant, rate_hz=50, seconds=0.4, seed=1).run()
        assert collector.wait_for(report.published)
    finally:
        assert sub.stop(30)
    assert report.published == report.ticks == 20
    assert len(collector.messages) == 20
    # awscrt calls on_message on its event-loop thread, never the caller's.
    assert "MainThread" not in collector.threads
    decoder = TelemetryDecoder(DecoderConfig(units=Units(variant)))
    for k, (topic, payload, received) in enumerate(collector.messages):
        assert device_from_topic(topic, PREFIX) == "arm-001"
        assert received <= time.monotonic()
        message = json.loads(payload)
        positions = [joint["position"] for joint in message["joints"].values()]
        ticks = mock_ticks(k / 50)
        if variant == "ticks":
            assert positions == ticks
        else:
            assert positions[:5] == pytest.approx([(t - 2047) * 360 / 4095 for t in ticks[:5]], abs=1e-3)
            assert 0.0 <= positions[5] <= 100.0
        telemetry = decoder.decode(payload, topic_device="arm-001")
        assert telemetry.device_id == "arm-001"
    stats = sub.stats
    assert stats.messages_received == 20
    assert stats.connection_successes == 1 and stats.subscribes_acked == 1
    assert not sub.connected


@pytest.mark.slow
def test_two_devices_with_wildcard(mosquitto: MosquittoBroker) -> None:
    collector = Collector()
    sub = TelemetrySubscriber(BrokerConfig(url=mosquitto.url), topic_filters(PREFIX, ["*"]), collector)
    sub.start()
    try:
        assert sub.wait_subscribed(30)
        report = _sim(mosquitto.url, devices=device_ids(2), rate_hz=40, seconds=0.5, seed=2).run()
        assert collector.wait_for(report.published)
    finally:
        sub.stop(30)
    per_device: dict[str, int] = {}
    for topic, payload, _ in collector.messages:
        device = device_from_topic(topic, PREFIX)
        assert device is not None and json.loads(payload)["device_id"] == device
        per_device[device] = per_device.get(device, 0) + 1
    assert per_device == {"arm-001": 20, "arm-002": 20} == report.per_device


@pytest.mark.slow
def test_on_message_errors_are_counted_not_raised(mosquitto: MosquittoBroker) -> None:
    def broken(_topic: str, _payload: bytes, _received: float) -> None:
        raise RuntimeError("handler bug")

    sub = TelemetrySubscriber(BrokerConfig(url=mosquitto.url), topic_filters(PREFIX, ["*"]), broken)
    sub.start()
    try:
        assert sub.wait_subscribed(30)
        _sim(mosquitto.url, rate_hz=50, seconds=0.2).run()
        wait_for(lambda: sub.stats.callback_errors >= 10, 30, "10 callback errors")
        assert sub.connected  # the client survived its handler raising
    finally:
        sub.stop(30)
    assert sub.stats.callback_errors == sub.stats.messages_received == 10


# -- TLS with a private CA ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def private_ca(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A throwaway CA and a server certificate for 127.0.0.1 signed by it, made in Python (cryptography)."""
    folder = tmp_path_factory.mktemp("pki")
    now = datetime.datetime.now(datetime.UTC)
    valid = {
        "not_valid_before": now - datetime.timedelta(minutes=5),
        "not_valid_after": now + datetime.timedelta(days=2),
    }
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "so101 test CA")])
    ca_cert = (
        x509.CertificateBuilder(subject_name=ca_name, issuer_name=ca_name, **valid)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True, crl_sign=True,
                encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )  # fmt: skip
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder(
            subject_name=x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")]),
            issuer_name=ca_name,
            **valid,
        )
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .add_extension(
            x509.SubjectAlternativeName(
                [x509.IPAddress(ipaddress.ip_address("127.0.0.1")), x509.DNSName("localhost")]
            ),
            critical=False,
        )
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    paths = {"ca": folder / "ca.crt", "cert": folder / "server.crt", "key": folder / "server.key"}
    paths["ca"].write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))
    paths["cert"].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    paths["key"].write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    return paths


@pytest.mark.slow
def test_mqtts_with_custom_ca(private_ca: dict[str, Path], tmp_path: Path) -> None:
    with MosquittoBroker(
        workdir=tmp_path / "tls", tls_certfile=private_ca["cert"], tls_keyfile=private_ca["key"]
    ) as broker:
        assert broker.url.startswith("mqtts://127.0.0.1:")
        collector = Collector()
        config = BrokerConfig(url=broker.url, ca_file=str(private_ca["ca"]))
        sub = TelemetrySubscriber(config, topic_filters(PREFIX, ["*"]), collector)
        sub.start()
        try:
            assert sub.wait_subscribed(30), sub.stats
            report = _sim(broker.url, ca_file=str(private_ca["ca"]), rate_hz=50, seconds=0.2).run()
            assert collector.wait_for(report.published)
        finally:
            sub.stop(30)
        assert len(collector.messages) == report.published == 10

        # Without the private CA the system trust store must refuse the broker: TLS really verifies. s2n
        # reports the failed handshake only after its 10-30 s anti-timing "blinding" delay, so the check runs
        # in a child process that waits for the first attempt, gives it 2 s to (wrongly) succeed, reports and
        # exits without waiting for the CRT.
        script = (
            "import os, sys, time\n"
            "from twin.transport.broker import BrokerConfig\n"
            "from twin.transport.subscriber import TelemetrySubscriber\n"
            "s = TelemetrySubscriber(BrokerConfig(url=sys.argv[1]), ['dt/+/telemetry'], lambda *a: None)\n"
            "s.start(); deadline = time.monotonic() + 60\n"
            "while s.stats.connection_attempts == 0 and time.monotonic() < deadline: time.sleep(0.05)\n"
            "time.sleep(2.0); st = s.stats\n"
            "print(st.connection_attempts, st.connection_successes, flush=True); os._exit(0)\n"
        )
        child = subprocess.run(
            [sys.executable, "-c", script, broker.url],
            check=True,
            capture_output=True,
            text=True,
            timeout=120,
        )
        attempts, successes = map(int, child.stdout.split())
        assert attempts >= 1 and successes == 0, child.stderr


# -- broker outages ----------------------------------------------------------------------------------------


@pytest.mark.slow
def test_survives_broker_restarts(
    mosquitto: MosquittoBroker, record_property: Callable[[str, object], None]
) -> None:
    """Kill/stop and restart the broker 5 times under load; telemetry must flow again each time, after at
    most the client's reconnect backoff (broker.max_reconnect_delay_ms) and the reconnect itself."""
    mailbox: InboundQueue[tuple[bytes, float]] = InboundQueue()
    arrivals: list[float] = []

    def on_message(topic: str, payload: bytes, received: float) -> None:
        arrivals.append(received)
        mailbox.put(device_from_topic(topic, PREFIX) or "?", (payload, received))

    sub = TelemetrySubscriber(BrokerConfig(url=mosquitto.url), topic_filters(PREFIX, ["*"]), on_message)
    sub.start()
    assert sub.wait_subscribed(30)
    stop = threading.Event()
    sim = _sim(mosquitto.url, devices=device_ids(2), rate_hz=20, seed=3)
    sim_errors: list[BaseException] = []

    def run_sim() -> None:
        try:
            sim.run(stop)
        except BaseException as exc:
            sim_errors.append(exc)

    publisher = threading.Thread(target=run_sim, name="edge-sim")
    publisher.start()
    recoveries: list[float] = []
    try:
        assert mailbox.take_all(timeout=60), "no telemetry before the first outage"
        for cycle in range(5):
            time.sleep(0.3)  # telemetry flows for a while between outages
            if cycle % 2 == 0:
                mosquitto.kill()  # crash: no DISCONNECT, sockets reset
            else:
                mosquitto.stop()  # clean shutdown
            time.sleep(0.2 + 0.3 * cycle)  # the outage; longer ones grow the client's backoff
            mailbox.take_all(timeout=0)
            mosquitto.restart()
            back = time.monotonic()
            items = mailbox.take_all(timeout=60)
            while items and all(received < back for _, (_, received) in items):
                items = mailbox.take_all(timeout=60)
            assert items, f"cycle {cycle}: no telemetry within 60 s of the broker's return; {sub.stats}"
            first = min(received for _, (_, received) in items if received >= back)
            recoveries.append(first - back)
    finally:
        stop.set()
        publisher.join(30)
        stopped = sub.stop(30)
    assert not sim_errors
    assert stopped
    record_property("recovery_seconds", [round(r, 3) for r in recoveries])
    # The next attempt comes at most max_reconnect_delay_ms after the broker is back; the connect, subscribe
    # and first message take milliseconds here, but up to seconds when every core is busy with other runs.
    backoff_s = BrokerConfig(url=mosquitto.url).max_reconnect_delay_ms / 1000
    assert all(r < backoff_s + 10.0 for r in recoveries), recoveries
    stats = sub.stats
    assert stats.connection_successes == 6
    assert stats.disconnects == 5
    assert stats.subscribes_acked >= 6
    assert stats.callback_errors == 0
    # Publishes during the outages fail (QoS 0 is not queued offline) and are counted, not raised.
    assert sim.report.publish_failures > 0
    assert sim.report.published > sim.report.publish_failures
    # Messages flowed after the last restart too, for both devices.
    assert any(t > back for t in arrivals)


def test_a_long_outage_is_told_a_few_times_then_once_a_minute(caplog: pytest.LogCaptureFixture) -> None:
    """A walk's 30 s broker outage made 15 lines; a day's would make tens of thousands. The first three
    failures are each told, then one line a minute with the running count; a connection starts it over."""
    from types import SimpleNamespace

    from twin.transport import subscriber as module

    now = [0.0]
    sub = TelemetrySubscriber(
        BrokerConfig(url=NO_BROKER), ["t/+/telemetry"], lambda *_: None, clock=lambda: now[0]
    )
    refused = SimpleNamespace(
        exception=AwsCrtError(code=1047, name="AWS_IO_SOCKET_CONNECTION_REFUSED", message="refused")
    )
    caplog.set_level("WARNING", logger="twin.transport")

    def told() -> list[str]:
        return [r.getMessage() for r in caplog.records if " could not connect to " in r.getMessage()]

    for _ in range(60):  # two minutes of failures, one every 2 s
        sub._on_connection_failure(refused)  # awscrt's callback, driven by the test's clock
        now[0] += 2.0
    lines = told()
    assert [int(re.search(r"failure #(\d+)", line)[1]) for line in lines] == [1, 2, 3, 33], lines
    assert "told once a minute from now on" in lines[2]
    assert sub.stats.connection_failures == 60
    assert module.FAILURES_TOLD_EACH == 3
    sub._on_connection_success(SimpleNamespace())
    sub._on_connection_failure(refused)  # a new outage: told at once again
    assert len(told()) == 5


def test_a_refused_connection_says_what_to_check(caplog: pytest.LogCaptureFixture) -> None:
    # A real agent pointed at a closed loopback port: awscrt's own words name the error, not the fix.
    caplog.set_level("WARNING", logger="twin.transport")
    agent = AgentService(load_config(None, {"broker.url": NO_BROKER, "http.listen": "127.0.0.1:0"}))
    agent.start()
    try:

        def failures() -> list[str]:
            return [r.getMessage() for r in caplog.records if " could not connect to " in r.getMessage()]

        lines = wait_for(lambda: failures()[1:] and failures(), 60, "two connection failures logged")
    finally:
        agent.stop()
    assert all("CONNECTION_REFUSED" in line for line in lines), lines
    # awscrt's message ends with a full stop: inside a sentence it made "refused.; retrying".
    assert not [line for line in lines if ".;" in line or ".." in line], lines
    for line in lines:  # the hint rides on each failure's line, once
        assert line.count("Is a broker listening on 127.0.0.1 port 1") == 1, line
        assert "`mosquitto -p 1`" in line and "--broker or [broker] url" in line, line


@pytest.mark.slow
def test_a_broker_that_refuses_the_client_is_named_with_its_reason(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """awscrt's error says only that the CONNACK was unsuccessful; its reason code says why, and on IoT Core a
    refused connect is the role not allowing the client id: a local file planning more connections than the
    stack's settings (a walk found the log naming neither)."""
    caplog.set_level("WARNING", logger="twin.transport")
    # mosquitto answers an anonymous client it does not admit with CONNACK 135, Not authorized.
    with MosquittoBroker(workdir=tmp_path / "closed", extra_config="allow_anonymous false") as broker:
        sub = TelemetrySubscriber(BrokerConfig(url=broker.url), topic_filters(PREFIX, ["*"]), Collector())
        sub.start()
        try:
            wait_for(lambda: sub.stats.connection_failures >= 1, 60, "a refused connect")
        finally:
            sub.stop(30)
    assert not sub.connected
    assert sub.stats.last_error.endswith("(CONNACK reason 135: not authorized)"), sub.stats.last_error
    lines = [r.getMessage() for r in caplog.records if "could not connect" in r.getMessage()]
    assert lines and all(
        "the broker refused the connection (not authorized, CONNACK reason 135)" in x for x in lines
    )
    # On IoT Core the same refusal names what plans the connections the role allows.
    iot = connack_hint(BrokerConfig(url="iot"), 135)
    assert "role does not allow this client id" in iot and "maxConnections" in iot
    assert "agent.local.toml" in iot
    assert connack_hint(BrokerConfig(url="iot"), 136) == ""  # server unavailable: not the client's fault


@pytest.mark.slow
def test_the_broker_error_after_a_reconnect_says_when_it_was(mosquitto: MosquittoBroker) -> None:
    """/state kept a lost connection's error after the connection came back, with nothing to tell it from a
    current one: a walk read "disconnect: socket is closed" beside `connected: true` as a problem now. The
    error is kept (the "connection lost" event reads it after a quick reconnect) and says when it was."""
    agent = AgentService(
        load_config(None, {"broker.url": mosquitto.url, "http.listen": "127.0.0.1:0", "twin.workers": 1})
    )
    agent.start()
    try:
        wait_for(lambda: get_state(agent.http_url).agent.broker.connected, 60, "the agent connected")
        first = get_state(agent.http_url).agent.broker
        assert first.last_error == "" and first.last_error_at is None
        mosquitto.kill()
        wait_for(lambda: not get_state(agent.http_url).agent.broker.connected, 60, "the connection lost")
        mosquitto.restart()
        wait_for(lambda: get_state(agent.http_url).agent.broker.connected, 60, "the agent reconnected")
        broker = get_state(agent.http_url).agent.broker
    finally:
        agent.stop()
    assert broker.connection_successes == 2
    # The lost connection's error, or a reconnect refused while the broker was down (when one was tried).
    assert broker.last_error.startswith(("disconnect: ", "connect: ")), broker
    (connection,) = broker.connections
    assert broker.last_error_at is not None and connection.connected_at is not None, broker
    # The error came before the reconnect: past, as its time says.
    assert connection.last_error_at == broker.last_error_at <= connection.connected_at, broker
