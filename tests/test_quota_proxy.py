"""The quota proxy: MQTT framing, the token bucket, and the budget enforced both ways against a real mosquitto
and the real awscrt client (what the fleet tests and `twin bench quota` rely on)."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
from awscrt import mqtt5
from conftest import Publisher, wait_for
from twin.rig.mosquitto import MosquittoBroker
from twin.rig.quota_proxy import (
    ProxyError,
    QuotaProxy,
    TokenBucket,
    connect_client_id,
    parse_subscribe,
    split_packets,
    suback_with,
)
from twin.transport.subscriber import BrokerConfig, TelemetrySubscriber, build_mqtt5_client

# --- framing (pure) -----------------------------------------------------------------------------------------


def _packet(kind: int, body: bytes, flags: int = 0) -> bytes:
    length, encoded = len(body), bytearray()
    while True:
        byte, length = length & 0x7F, length >> 7
        encoded.append(byte | (0x80 if length else 0))
        if not length:
            break
    return bytes([kind << 4 | flags]) + bytes(encoded) + body


def test_split_packets_handles_fragments_and_long_lengths() -> None:
    small = _packet(3, b"x" * 5)
    large = _packet(3, b"y" * 20_000)  # a three-byte remaining length
    ping = _packet(12, b"")
    stream = small + large + ping
    for cut in (1, 2, 3, len(small) + 2, len(small) + 4, len(stream) - 1):
        buffer = bytearray(stream[:cut])
        first, used = split_packets(buffer)
        del buffer[:used]
        buffer += stream[cut:]
        rest, used2 = split_packets(buffer)
        assert [p for _, p in first + rest] == [small, large, ping]
        assert used2 == len(buffer)
    assert [k for k, _ in split_packets(bytearray(stream))[0]] == [3, 3, 12]


def test_split_packets_refuses_a_non_mqtt_stream() -> None:
    with pytest.raises(ValueError, match="not an MQTT stream"):
        split_packets(bytearray(b"\x30\xff\xff\xff\xff\x01"))


def _connect(level: int, client_id: str, properties: bytes = b"") -> bytes:
    body = b"\x00\x04MQTT" + bytes([level, 0x02]) + b"\x00\x3c"
    if level == 5:
        body += bytes([len(properties)]) + properties
    body += len(client_id).to_bytes(2, "big") + client_id.encode()
    return _packet(1, body)


def test_connect_client_id_of_both_protocol_versions() -> None:
    assert connect_client_id(_connect(4, "agent-311")) == "agent-311"
    # MQTT 5: a session-expiry property (0x11, four bytes) sits between the header and the payload.
    assert connect_client_id(_connect(5, "agent-5", b"\x11\x00\x00\x00\x3c")) == "agent-5"
    assert connect_client_id(b"\x10\x02\x00") == ""


def test_token_bucket_allows_the_budget_per_second() -> None:
    now = [0.0]
    bucket = TokenBucket(rate=100, capacity=100, clock=lambda: now[0])
    assert sum(bucket.take() for _ in range(150)) == 100  # a full bucket, then nothing
    now[0] = 0.5
    assert sum(bucket.take() for _ in range(150)) == 50
    now[0] = 10.0
    assert sum(bucket.take() for _ in range(500)) == 100  # never more than the capacity


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"upstream_host": "10.0.0.1"}, "not a loopback address"),
        ({"listen_host": "0.0.0.0"}, "not a loopback address"),
        ({"budget": 0}, "positive number"),
        ({"burst_s": 0}, "burst_s"),
    ],
)
def test_bad_settings_are_refused(kwargs: dict[str, Any], needle: str) -> None:
    args = {"upstream_host": "127.0.0.1", "upstream_port": 1883, **kwargs}
    with pytest.raises(ProxyError, match=needle):
        QuotaProxy(args.pop("upstream_host"), args.pop("upstream_port"), **args)


# --- against mosquitto --------------------------------------------------------------------------------------

TOPIC = "dt/lerobot/arm-001/telemetry"
BUDGET = 100  # the proxy's budget in these tests, a second; its bucket holds one second's worth (burst_s 1)
QOS_0 = mqtt5.QoS.AT_MOST_ONCE


class _Publisher:
    """One connection publishing QoS 0 through the real awscrt client: one proxy connection, one bucket."""

    def __init__(self, url: str) -> None:
        self._connected, self._stopped = threading.Event(), threading.Event()
        self._client = build_mqtt5_client(
            BrokerConfig(url=url, client_id_prefix="proxy-test-pub-"),
            "proxy-test-pub",
            on_connection_success=lambda _d: self._connected.set(),
            on_stopped=lambda _d: self._stopped.set(),
        )
        self._client.start()
        assert self._connected.wait(30)
        self._sent = 0

    def send(self, count: int, rate: float | None = None) -> None:
        """`count` publishes, at `rate` per second if given; returns once all are on the socket."""
        start = time.monotonic()
        sent = []
        for i in range(count):
            delay = start + i / rate - time.monotonic() if rate else 0.0
            if delay > 0:
                time.sleep(delay)  # the rate under test, not synchronisation
            payload = b"%d" % (self._sent + i)
            sent.append(self._client.publish(mqtt5.PublishPacket(topic=TOPIC, payload=payload, qos=QOS_0)))
        for future in sent:
            future.result(30)  # a QoS 0 publish completes once it is written to the socket
        self._sent += count

    def close(self) -> None:
        self._client.stop()
        self._stopped.wait(30)


def _publish(url: str, count: int, rate: float) -> None:
    publisher = _Publisher(url)
    try:
        publisher.send(count, rate)
    finally:
        publisher.close()


def _subscriber(url: str) -> tuple[TelemetrySubscriber, list[bytes]]:
    received: list[bytes] = []
    sub = TelemetrySubscriber(
        BrokerConfig(url=url, client_id_prefix="proxy-test-sub-"),
        [TOPIC],
        lambda _t, payload, _r: received.append(payload),
        client_id="proxy-test-sub",
    )
    sub.start()
    assert sub.wait_subscribed(30)
    return sub, received


def _passed(proxy: QuotaProxy, to_broker: bool) -> tuple[int, int]:
    """(forwarded, dropped) PUBLISH packets so far in one direction, over all connections."""
    conns = proxy.connections()
    if to_broker:
        return sum(c.forwarded_to_broker for c in conns), sum(c.dropped_to_broker for c in conns)
    return sum(c.forwarded_to_client for c in conns), sum(c.dropped_to_client for c in conns)


def _counted(proxy: QuotaProxy, to_broker: bool, total: int) -> int:
    """Forwarded packets in one direction once the proxy has counted `total` (forwarded or dropped)."""
    direction = "to the broker" if to_broker else "to the client"
    wait_for(lambda: sum(_passed(proxy, to_broker)) >= total, 60, f"{total} packets {direction}")
    return _passed(proxy, to_broker)[0]


class _Clock:
    """The proxy's clock, moved only by the test: what passes is the bucket's arithmetic, however slowly
    this machine delivers the packets (on the real clock a stall of the publisher or the proxy turned the
    burst into one, and fewer passed than the burst's two seconds allow)."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


# Bursts of a publisher over budget and the proxy's time before each: the full bucket (BUDGET), then a
# second's refill (BUDGET), then half a second's (BUDGET / 2), each burst more than the bucket holds.
BURSTS = ((0.0, 300), (1.0, 200), (0.5, 100))
PASSING = BUDGET + BUDGET + BUDGET // 2


def _over_budget(proxy: QuotaProxy, clock: _Clock, publisher_url: str, to_broker: bool) -> int:
    """The bursts published, each counted by the proxy before its clock moves on; what it forwarded."""
    publisher = _Publisher(publisher_url)
    try:
        total = 0
        for advance, count in BURSTS:
            clock.now += advance
            publisher.send(count)
            total += count
            forwarded = _counted(proxy, to_broker=to_broker, total=total)
    finally:
        publisher.close()
    return forwarded


@pytest.mark.slow
def test_a_publisher_over_budget_loses_the_excess(mosquitto: MosquittoBroker) -> None:
    clock = _Clock()
    with QuotaProxy("127.0.0.1", mosquitto.port, budget=BUDGET, clock=clock) as proxy:
        sub, received = _subscriber(mosquitto.url)  # directly on the broker: sees what got through
        try:
            forwarded = _over_budget(proxy, clock, proxy.url, to_broker=True)
            wait_for(lambda: len(received) >= forwarded, 60, f"the {forwarded} forwarded messages")
        finally:
            sub.stop()
        totals = proxy.totals()
    (conn,) = totals["per_connection"]
    assert conn["client_id"] == "proxy-test-pub"
    assert conn["forwarded_to_broker"] + conn["dropped_to_broker"] == 600
    assert conn["forwarded_to_broker"] == len(received) == PASSING
    assert conn["dropped_to_client"] == 0


@pytest.mark.slow
def test_a_subscriber_over_budget_receives_at_most_its_budget(mosquitto: MosquittoBroker) -> None:
    clock = _Clock()
    with QuotaProxy("127.0.0.1", mosquitto.port, budget=BUDGET, clock=clock) as proxy:
        sub, received = _subscriber(proxy.url)  # the subscriber's inbound direction is metered too
        try:
            forwarded = _over_budget(proxy, clock, mosquitto.url, to_broker=False)
            wait_for(lambda: len(received) >= forwarded, 60, f"the {forwarded} forwarded messages")
        finally:
            sub.stop()
        totals = proxy.totals()
    (conn,) = totals["per_connection"]
    assert conn["client_id"] == "proxy-test-sub"
    assert conn["forwarded_to_client"] == len(received) == PASSING
    assert conn["forwarded_to_client"] + conn["dropped_to_client"] == 600
    assert totals["dropped"] == conn["dropped_to_client"]


@pytest.mark.slow
def test_under_budget_everything_passes_and_unlimited_is_a_plain_proxy(mosquitto: MosquittoBroker) -> None:
    for budget in (BUDGET, None):
        count = 90 if budget else 900
        with QuotaProxy("127.0.0.1", mosquitto.port, budget=budget) as proxy:
            sub, received = _subscriber(proxy.url)
            try:
                _publish(proxy.url, count=count, rate=90.0 if budget else 900.0)
                # Through the proxy to the broker, back through it to the subscriber.
                to_broker = _counted(proxy, to_broker=True, total=count)
                to_client = _counted(proxy, to_broker=False, total=to_broker)
                wait_for(lambda n=to_client, got=received: len(got) >= n, 60, f"the {to_client} messages")
            finally:
                sub.stop()
            totals = proxy.totals()
        assert totals["dropped"] == 0
        assert len(received) == count
        assert totals["connections"] == 2


# --- the policy stand-in: a SUBSCRIBE refused per filter, as IoT Core refuses what a policy does not allow -


def test_a_subscribe_is_taken_apart_and_its_suback_gets_the_failures_back_in_order() -> None:
    entries = [(name, len(name).to_bytes(2, "big") + name.encode() + b"\x00") for name in ("a/b", "c", "d/+")]
    for level, props in ((5, b"\x00"), (4, b"")):
        subscribe = _packet(8, b"\x12\x34" + props + b"".join(e for _, e in entries), flags=2)
        parsed = parse_subscribe(subscribe, level)
        assert (parsed.packet_id, parsed.head) == (0x1234, b"\x12\x34" + props)
        assert parsed.entries == tuple(entries)
        # The broker granted the two filters it was sent (QoS 0 and 1); the first one was denied.
        suback = _packet(9, b"\x12\x34" + props + b"\x00\x01")
        assert suback_with(suback, level, {0: 0x87}) == _packet(9, b"\x12\x34" + props + b"\x87\x00\x01")
        assert suback_with(suback, level, {1: 0x80}) == _packet(9, b"\x12\x34" + props + b"\x00\x80\x01")
    with pytest.raises(ValueError, match="runs past its end"):
        parse_subscribe(_packet(8, b"\x00\x01\x00\x00\x09ab", flags=2), 5)


def _subscribe(client: mqtt5.Client, *filters: str) -> list[mqtt5.SubackReasonCode]:
    packet = mqtt5.SubscribePacket(
        subscriptions=[mqtt5.Subscription(topic_filter=f, qos=mqtt5.QoS.AT_MOST_ONCE) for f in filters]
    )
    return list(client.subscribe(packet).result(30).reason_codes)


@pytest.mark.slow
def test_denied_filters_are_refused_as_iot_core_refuses_them_and_allow_lifts_it(
    mosquitto: MosquittoBroker,
) -> None:
    denied, other = TOPIC, "dt/lerobot/arm-002/telemetry"
    received: list[str] = []
    connected = threading.Event()
    publisher = Publisher(mosquitto.url)
    with QuotaProxy("127.0.0.1", mosquitto.port, budget=None, denied_filters=[denied]) as proxy:
        client = build_mqtt5_client(
            BrokerConfig(url=proxy.url, client_id_prefix="proxy-test-policy-"),
            "proxy-test-policy",
            on_publish_received=lambda d: received.append(d.publish_packet.topic),
            on_connection_success=lambda _d: connected.set(),
        )
        client.start()
        try:
            assert connected.wait(30)
            granted = mqtt5.SubackReasonCode.GRANTED_QOS_0
            refused = mqtt5.SubackReasonCode.NOT_AUTHORIZED
            # Both in one SUBSCRIBE: the denied one refused, the other granted, in the client's order.
            assert _subscribe(client, denied, other) == [refused, granted]
            # Alone: refused without reaching the broker.
            assert _subscribe(client, denied) == [refused]
            # The broker holds only the granted subscription: of one publisher's messages on the two topics,
            # in this order, the one on the granted topic arrives and the one before it does not.
            publisher.publish("arm-001", b"1")
            publisher.publish("arm-002", b"2")
            wait_for(lambda: other in received, 30, "the message on the granted topic")
            assert denied not in received
            proxy.allow(denied)  # the policy corrected: the same SUBSCRIBE now goes through
            assert _subscribe(client, denied) == [granted]
            publisher.publish("arm-001", b"3")
            wait_for(lambda: denied in received, 30, "the message on the topic allowed since")
        finally:
            client.stop()
            publisher.close()
        (conn,) = proxy.connections()
    assert conn.level == 5 and conn.subscriptions_denied == 2
