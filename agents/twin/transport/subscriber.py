"""MQTT5 transport for the twin: broker settings, topic filters and the telemetry subscriber.

One awscrt MQTT5 client code path serves AWS IoT Core (WebSocket + SigV4), a TLS broker with a private CA and
a plain local mosquitto, so tests and the demo exercise the same reconnect and re-subscribe logic as
production. awscrt calls every callback here on its event-loop thread: they only count, log and hand data
on, and never wait for anything (a blocking callback deadlocks the client).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import re
import secrets
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

# awscrt is this module's reason to exist (~70 ms to import); commands import this module lazily, so
# `twin --help` does not pay for it. boto3 stays lazy below: only the "iot" path needs it.
from awscrt import auth, io, mqtt5
from awsiot import mqtt5_client_builder

if TYPE_CHECKING:
    from concurrent.futures import Future

log = logging.getLogger(__name__)

DEFAULT_TOPIC_PREFIX = "dt/lerobot"
TELEMETRY_SUFFIX = "telemetry"
# IoT Core refuses client ids over 128 bytes; the random suffix takes 13.
_MAX_PREFIX_LEN = 100
_CLIENT_ID_PREFIX_RE = re.compile(r"^[A-Za-z0-9_.:-]*$")
# IoT Core takes at most 8 topic filters per SUBSCRIBE packet (aws-facts.md section 3).
_FILTERS_PER_SUBSCRIBE = 8


class BrokerConfigError(ValueError):
    """A broker setting is invalid; the message names the setting and the fix."""


@dataclass
class BrokerConfig:
    """Where and how to connect. `url`: "iot" (AWS IoT Core), "mqtt://host:port" or "mqtts://host:port"."""

    url: str = "iot"
    region: str = ""
    endpoint: str = ""
    client_id_prefix: str = "so101-twin-"
    ca_file: str = ""
    # Reconnect backoff. awscrt doubles the delay after each failed attempt up to the maximum, and FULL
    # jitter waits a uniform random time in [0, current delay]. So once a broker is back, the next attempt
    # comes at most max_reconnect_delay_ms later: 2000 ms keeps "telemetry flows again within 3 s of the
    # broker's return" true even after a long outage, while averaging one attempt per second per agent,
    # which is IoT Core's CONNECT limit per client id. 250 ms minimum: a blip (broker restart) costs little.
    min_reconnect_delay_ms: int = 250
    max_reconnect_delay_ms: int = 2000
    # The builder default is 1200 s; a NAT or network cut that drops packets silently would then go unnoticed
    # for up to half an hour. 30 s detects it within ~45 s for a negligible ping cost.
    keep_alive_s: int = 30

    def __post_init__(self) -> None:
        self.url = (self.url or "").strip()
        if not self.url:
            raise BrokerConfigError(
                'broker url is empty: use "iot" (AWS IoT Core), "mqtt://host:port" or "mqtts://host:port"'
            )
        if self.url != "iot":
            parts = urlsplit(self.url)
            if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname:
                raise BrokerConfigError(
                    f'broker url {self.url!r} is not understood: use "iot" (AWS IoT Core), '
                    '"mqtt://host:port" (plain TCP) or "mqtts://host:port" (TLS)'
                )
            if parts.path not in ("", "/") or parts.query or parts.username:
                raise BrokerConfigError(
                    f"broker url {self.url!r} has a path, query or credentials; give only mqtt[s]://host:port"
                )
            try:
                _ = parts.port
            except ValueError as exc:
                raise BrokerConfigError(
                    f"broker url {self.url!r} has a bad port; use a number 1..65535"
                ) from exc
        if len(self.client_id_prefix) > _MAX_PREFIX_LEN or not _CLIENT_ID_PREFIX_RE.match(
            self.client_id_prefix
        ):
            raise BrokerConfigError(
                f"client_id_prefix {self.client_id_prefix!r} must be at most {_MAX_PREFIX_LEN} characters of "
                "letters, digits and _ . : - (the IAM policy matches client ids by this prefix)"
            )
        if self.ca_file and self.kind != "mqtts":
            raise BrokerConfigError(
                f"ca_file is set but the broker url is {self.url!r}: a custom CA only applies to mqtts:// "
                "(IoT Core uses the system trust store); clear ca_file or use mqtts://"
            )
        if self.ca_file and not Path(self.ca_file).is_file():
            raise BrokerConfigError(f"ca_file {self.ca_file!r} does not exist; give the PEM CA bundle path")
        if not 0 < self.min_reconnect_delay_ms <= self.max_reconnect_delay_ms:
            raise BrokerConfigError(
                f"reconnect delays must satisfy 0 < min ({self.min_reconnect_delay_ms} ms) <= max "
                f"({self.max_reconnect_delay_ms} ms)"
            )
        if not 5 <= self.keep_alive_s <= 1200:
            raise BrokerConfigError(
                f"keep_alive_s {self.keep_alive_s} is outside 5..1200 (IoT Core allows at most 1200 s)"
            )

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> BrokerConfig:
        """From the [broker] table of the agent config; unknown keys are an error naming the valid ones."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise BrokerConfigError(f"unknown [broker] setting(s) {unknown}; valid: {sorted(names)}")
        return cls(**dict(values))

    @property
    def kind(self) -> str:
        """ "iot", "mqtt" or "mqtts"."""
        return "iot" if self.url == "iot" else urlsplit(self.url).scheme

    @property
    def host(self) -> str:
        if self.kind == "iot":
            return self.endpoint
        return urlsplit(self.url).hostname or ""

    @property
    def port(self) -> int:
        if self.kind == "iot":
            return 443
        parts = urlsplit(self.url)
        return parts.port or (8883 if parts.scheme == "mqtts" else 1883)


def new_client_id(prefix: str) -> str:
    """prefix + 12 random hex digits: unique per process, since two clients with one id evict each other."""
    return f"{prefix}{secrets.token_hex(6)}"


def _check_topic_part(what: str, value: str) -> None:
    if not value or any(ch in value for ch in "/+#") or "\x00" in value:
        raise ValueError(
            f"{what} {value!r} must be non-empty and contain no '/', '+', '#' (MQTT topic level separators "
            "and wildcards); use '*' in devices for the whole fleet"
        )


def topic_filters(prefix: str, devices: Sequence[str]) -> list[str]:
    """MQTT topic filters for `devices` under `prefix` ("*" alone = every device via a '+' wildcard)."""
    prefix = prefix.strip("/")
    if not prefix or "+" in prefix or "#" in prefix:
        raise ValueError(
            f"topic prefix {prefix!r} must be non-empty and without wildcards, e.g. 'dt/lerobot'"
        )
    devices = list(devices)
    if not devices:
        raise ValueError('devices is empty: list device ids (e.g. ["arm-001"]) or ["*"] for the fleet')
    if "*" in devices:
        if len(devices) > 1:
            raise ValueError(f'devices {devices} mixes "*" with ids; "*" alone already covers the fleet')
        return [f"{prefix}/+/{TELEMETRY_SUFFIX}"]
    for device in devices:
        _check_topic_part("device id", device)
    return [f"{prefix}/{device}/{TELEMETRY_SUFFIX}" for device in dict.fromkeys(devices)]


def device_from_topic(topic: str, prefix: str) -> str | None:
    """The device id of `{prefix}/{device}/telemetry`, or None for any other topic."""
    head = prefix.strip("/") + "/"
    if not topic.startswith(head) or not topic.endswith("/" + TELEMETRY_SUFFIX):
        return None
    device = topic[len(head) : -len(TELEMETRY_SUFFIX) - 1]
    if not device or "/" in device:
        return None
    return device


def topic_for(prefix: str, device_id: str) -> str:
    _check_topic_part("device id", device_id)
    return f"{prefix.strip('/')}/{device_id}/{TELEMETRY_SUFFIX}"


def resolve_iot_endpoint(config: BrokerConfig) -> str:
    """The account's IoT data endpoint: from the config, else iot:DescribeEndpoint (iot:Data-ATS)."""
    if config.endpoint:
        return config.endpoint
    import boto3  # noqa: PLC0415 - slow to import; only the "iot" path needs it

    kwargs = {"region_name": config.region} if config.region else {}
    try:
        client = boto3.client("iot", **kwargs)
        response = client.describe_endpoint(endpointType="iot:Data-ATS")
    except Exception as exc:
        raise BrokerConfigError(
            f"could not look up the IoT Core endpoint ({exc}); set [broker] endpoint to the account's "
            "xxxx-ats.iot.<region>.amazonaws.com, or give the instance role iot:DescribeEndpoint"
        ) from exc
    return str(response["endpointAddress"])


def _region(config: BrokerConfig) -> str:
    if config.region:
        return config.region
    import boto3  # noqa: PLC0415 - see resolve_iot_endpoint

    region = boto3.session.Session().region_name
    if not region:
        raise BrokerConfigError(
            "no AWS region for IoT Core: set [broker] region (or --region), or AWS_REGION / the AWS config"
        )
    return str(region)


LifecycleCallback = Callable[[Any], None]


def build_mqtt5_client(
    config: BrokerConfig,
    client_id: str,
    *,
    on_publish_received: LifecycleCallback | None = None,
    on_attempting_connect: LifecycleCallback | None = None,
    on_connection_success: LifecycleCallback | None = None,
    on_connection_failure: LifecycleCallback | None = None,
    on_disconnection: LifecycleCallback | None = None,
    on_stopped: LifecycleCallback | None = None,
) -> mqtt5.Client:
    """An unstarted awscrt MQTT5 client for `config`; shared by the subscriber and the edge simulator.

    Every variant uses a clean session, exponential backoff with FULL jitter and the configured delays, so a
    fleet of agents that lose IoT Core at once does not reconnect in lock step.
    """
    common: dict[str, Any] = {
        "client_id": client_id,
        # Clean session: after every reconnect the broker has no subscriptions, and the connection-success
        # callback subscribes again. A persistent session would replay stale QoS1 traffic the twin does not
        # want (it only cares for the newest pose) and IoT Core expires it after an hour anyway.
        "session_behavior": mqtt5.ClientSessionBehaviorType.CLEAN,
        "retry_jitter_mode": mqtt5.ExponentialBackoffJitterMode.FULL,
        "min_reconnect_delay_ms": config.min_reconnect_delay_ms,
        "max_reconnect_delay_ms": config.max_reconnect_delay_ms,
        "keep_alive_interval_sec": config.keep_alive_s,
        "on_publish_received": on_publish_received,
        "on_lifecycle_attempting_connect": on_attempting_connect,
        "on_lifecycle_connection_success": on_connection_success,
        "on_lifecycle_connection_failure": on_connection_failure,
        "on_lifecycle_disconnection": on_disconnection,
        "on_lifecycle_stopped": on_stopped,
    }

    if config.kind == "iot":
        region = _region(config)
        endpoint = resolve_iot_endpoint(config)
        # SigV4 over WebSocket. The builder's handshake transform signs every connection attempt with fresh
        # credentials from the default chain (instance role via IMDS on EC2), so both rotated role
        # credentials and IoT Core's hard 24 h WebSocket lifetime are handled the same way: IoT Core closes
        # the socket, the client reports a disconnect, auto-reconnects with a newly signed handshake, and the
        # connection-success callback re-subscribes. Nothing here needs a timer for the 24 h cut.
        return mqtt5_client_builder.websockets_with_default_aws_signing(
            region=region,
            credentials_provider=auth.AwsCredentialsProvider.new_default_chain(),
            endpoint=endpoint,
            **common,
        )

    if config.kind == "mqtts":
        # The SDK's plain-TLS builder; a private CA replaces the system trust store when given. Extended
        # validation is IoT-specific (8 filters per SUBSCRIBE, 100 publishes/s throttle), so it is off here.
        return mqtt5_client_builder.new_default_builder(
            endpoint=config.host,
            port=config.port,
            ca_filepath=config.ca_file or None,
            enable_metrics_collection=False,
            extended_validation_and_flow_control_options=(mqtt5.ExtendedValidationAndFlowControlOptions.NONE),
            **common,
        )

    # Plain TCP: every SDK builder installs TLS, so build the options directly (aws-facts.md section 3).
    options = mqtt5.ClientOptions(
        host_name=config.host,
        port=config.port,
        tls_ctx=None,
        connect_options=mqtt5.ConnectPacket(client_id=client_id, keep_alive_interval_sec=config.keep_alive_s),
        session_behavior=common["session_behavior"],
        retry_jitter_mode=common["retry_jitter_mode"],
        min_reconnect_delay_ms=config.min_reconnect_delay_ms,
        max_reconnect_delay_ms=config.max_reconnect_delay_ms,
        socket_options=io.SocketOptions(),
        on_publish_callback_fn=on_publish_received,
        on_lifecycle_event_attempting_connect_fn=on_attempting_connect,
        on_lifecycle_event_connection_success_fn=on_connection_success,
        on_lifecycle_event_connection_failure_fn=on_connection_failure,
        on_lifecycle_event_disconnection_fn=on_disconnection,
        on_lifecycle_event_stopped_fn=on_stopped,
        disable_metrics=True,
    )
    return mqtt5.Client(options)


@dataclass
class SubscriberStats:
    """Counters since start(). Written only by the CRT event-loop thread; read as a snapshot copy."""

    connection_attempts: int = 0
    connection_successes: int = 0
    # Losses of an established connection; the one stop() causes is not counted.
    connection_failures: int = 0
    disconnects: int = 0
    subscribes_sent: int = 0
    subscribes_acked: int = 0
    subscribe_failures: int = 0
    messages_received: int = 0
    callback_errors: int = 0
    last_connected_monotonic: float | None = None
    last_message_monotonic: float | None = None
    last_error: str = ""
    per_filter_granted: dict[str, int] = field(default_factory=dict)


MessageHandler = Callable[[str, bytes, float], None]


class TelemetrySubscriber:
    """Subscribes `topic_filters` on every connection and hands each message to `on_message`.

    `on_message(topic, payload, received_monotonic)` runs on the CRT thread and must not block: put the
    message into a `LatestValueMailbox` and decode elsewhere. Exceptions it raises are logged and counted.
    """

    def __init__(
        self,
        config: BrokerConfig,
        topic_filters: list[str],
        on_message: MessageHandler,
        *,
        client_id: str | None = None,
    ) -> None:
        if not topic_filters:
            raise ValueError(
                "topic_filters is empty; build them with twin.transport.subscriber.topic_filters()"
            )
        self.config = config
        self.topic_filters = list(topic_filters)
        self.client_id = client_id or new_client_id(config.client_id_prefix)
        self._on_message = on_message
        self._stats = SubscriberStats()
        self._stats_lock = threading.Lock()
        self._client: mqtt5.Client | None = None
        self._connected = threading.Event()
        self._subscribed = threading.Event()
        self._stopped = threading.Event()
        self._started = False
        self._stopping = False

    # -- public API -------------------------------------------------------------------------------------

    def start(self) -> None:
        """Build the client (resolving the IoT endpoint if needed) and start connecting; returns at once."""
        if self._started:
            return
        self._client = build_mqtt5_client(
            self.config,
            self.client_id,
            on_publish_received=self._on_publish_received,
            on_attempting_connect=self._on_attempting_connect,
            on_connection_success=self._on_connection_success,
            on_connection_failure=self._on_connection_failure,
            on_disconnection=self._on_disconnection,
            on_stopped=self._on_stopped,
        )
        self._stopped.clear()
        self._stopping = False
        self._started = True
        log.info(
            "subscriber %s connecting to %s for %s",
            self.client_id,
            self._where(),
            ", ".join(self.topic_filters),
        )
        self._client.start()

    def stop(self, timeout: float = 5.0) -> bool:
        """Disconnect and wait (bounded) for the client's Stopped event. True when it stopped in time."""
        if not self._started or self._client is None:
            return True
        self._stopping = True
        self._client.stop()
        stopped = self._stopped.wait(timeout)
        if not stopped:
            log.warning("subscriber %s did not report Stopped within %.1f s", self.client_id, timeout)
        self._started = False
        self._connected.clear()
        self._subscribed.clear()
        # Drop the client so its native resources (and our bound callbacks) are released.
        self._client = None
        return stopped

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    @property
    def stats(self) -> SubscriberStats:
        with self._stats_lock:
            return dataclasses.replace(self._stats, per_filter_granted=dict(self._stats.per_filter_granted))

    def wait_subscribed(self, timeout: float) -> bool:
        """Block (not from a callback!) until the current connection's subscriptions are acknowledged."""
        return self._subscribed.wait(timeout)

    # -- CRT callbacks: count, log, hand on; never block -------------------------------------------------

    def _where(self) -> str:
        return (
            self.config.url if self.config.kind != "iot" else f"IoT Core ({self.config.region or 'default'})"
        )

    def _on_publish_received(self, data: mqtt5.PublishReceivedData) -> None:
        received = time.monotonic()
        packet = data.publish_packet
        self._stats.messages_received += 1
        self._stats.last_message_monotonic = received
        payload = packet.payload
        if not isinstance(payload, bytes):
            payload = bytes(payload or b"")
        try:
            self._on_message(packet.topic, payload, received)
        except Exception:
            self._stats.callback_errors += 1
            # Log the first few in full, then only every 1000th: a broken handler must not flood the log.
            if self._stats.callback_errors <= 3 or self._stats.callback_errors % 1000 == 0:
                log.exception(
                    "on_message failed for %s (%d so far)", packet.topic, self._stats.callback_errors
                )

    def _on_attempting_connect(self, _data: Any) -> None:
        with self._stats_lock:
            self._stats.connection_attempts += 1
        log.debug("subscriber %s attempting to connect", self.client_id)

    def _on_connection_success(self, data: mqtt5.LifecycleConnectSuccessData) -> None:
        with self._stats_lock:
            self._stats.connection_successes += 1
            self._stats.last_connected_monotonic = time.monotonic()
        self._connected.set()
        self._subscribed.clear()
        log.info(
            "subscriber %s connected to %s (connection #%d)",
            self.client_id,
            self._where(),
            self._stats.connection_successes,
        )
        client = self._client
        if client is None:
            return
        # Clean session: the broker forgot our subscriptions, so subscribe again on every connection. The
        # SUBACK arrives on this same thread later; waiting for it here would deadlock the client.
        chunks = [
            self.topic_filters[i : i + _FILTERS_PER_SUBSCRIBE]
            for i in range(0, len(self.topic_filters), _FILTERS_PER_SUBSCRIBE)
        ]
        pending = {"left": len(chunks), "ok": True}
        for chunk in chunks:
            packet = mqtt5.SubscribePacket(
                subscriptions=[mqtt5.Subscription(topic_filter=f, qos=mqtt5.QoS.AT_MOST_ONCE) for f in chunk]
            )
            try:
                future = client.subscribe(packet)
            except Exception as exc:  # e.g. client already stopping
                self._subscribe_failed(chunk, exc)
                continue
            with self._stats_lock:
                self._stats.subscribes_sent += 1
            future.add_done_callback(functools.partial(self._on_suback, chunk=chunk, pending=pending))

    def _on_suback(self, future: Future[Any], chunk: list[str], pending: dict[str, Any]) -> None:
        try:
            suback = future.result(timeout=0)  # already done: this is its done-callback
        except Exception as exc:
            self._subscribe_failed(chunk, exc)
            return
        codes = list(getattr(suback, "reason_codes", None) or [])
        ok = True
        for topic_filter, code in zip(chunk, codes, strict=False):
            if int(code) >= 0x80:
                ok = False
                self._subscribe_failed([topic_filter], RuntimeError(f"SUBACK reason {code!r}"))
            else:
                with self._stats_lock:
                    self._stats.subscribes_acked += 1
                    granted = self._stats.per_filter_granted
                    granted[topic_filter] = granted.get(topic_filter, 0) + 1
        pending["left"] -= 1
        pending["ok"] = pending["ok"] and ok
        if pending["left"] == 0 and pending["ok"]:
            log.info("subscriber %s subscribed to %s", self.client_id, ", ".join(self.topic_filters))
            self._subscribed.set()

    def _subscribe_failed(self, filters: list[str], exc: BaseException) -> None:
        with self._stats_lock:
            self._stats.subscribe_failures += 1
            self._stats.last_error = f"subscribe {filters}: {exc}"
        # Usually a disconnect raced the SUBACK (the next connection subscribes again) or the IAM policy
        # does not allow iot:Subscribe on the filter (then the fix is in the policy).
        log.warning(
            "subscriber %s: subscribe to %s failed: %s (retried on the next connection; if it persists, "
            "check that the IAM policy allows iot:Subscribe/iot:Receive for these topics)",
            self.client_id,
            ", ".join(filters),
            exc,
        )

    def _on_connection_failure(self, data: mqtt5.LifecycleConnectFailureData) -> None:
        with self._stats_lock:
            self._stats.connection_failures += 1
            self._stats.last_error = f"connect: {data.exception}"
            failures = self._stats.connection_failures
        # Backoff retries run until stop(); one line per attempt is fine at <= 4 attempts/s, and the count
        # says how long an outage has lasted.
        log.warning(
            "subscriber %s could not connect to %s (failure #%d): %s; retrying with backoff",
            self.client_id,
            self._where(),
            failures,
            data.exception,
        )

    def _on_disconnection(self, data: mqtt5.LifecycleDisconnectData) -> None:
        self._connected.clear()
        self._subscribed.clear()
        if self._stopping:
            log.info("subscriber %s disconnected (stopping)", self.client_id)
            return
        with self._stats_lock:
            self._stats.disconnects += 1
            self._stats.last_error = f"disconnect: {data.exception}"
        reason = ""
        if data.disconnect_packet is not None:
            reason = f" (server reason {data.disconnect_packet.reason_code!r})"
        log.warning(
            "subscriber %s disconnected from %s: %s%s; reconnecting",
            self.client_id,
            self._where(),
            data.exception,
            reason,
        )

    def _on_stopped(self, _data: Any) -> None:
        self._connected.clear()
        log.info("subscriber %s stopped", self.client_id)
        self._stopped.set()
