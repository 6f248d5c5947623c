"""The telemetry subscriber: subscribes the topic filters on every connection and hands each message on.

awscrt calls every callback here on its event-loop thread: they only count, log and hand data on, and never
wait for anything (a blocking callback deadlocks the client). Broker settings live in
`twin.transport.broker`, client construction in `twin.transport.client`, topic rules in `twin.core.topics`.
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, TypedDict

from awscrt import mqtt5

from twin.core.throttle import Throttle
from twin.transport.broker import (
    CONNACK_REFUSALS,
    BrokerConfig,
    connack_code,
    crt_error_text,
    failure_hint,
    new_client_id,
)
from twin.transport.client import build_mqtt5_client

if TYPE_CHECKING:
    from concurrent.futures import Future

log = logging.getLogger(__name__)

# IoT Core takes at most 8 topic filters per SUBSCRIBE packet (docs/aws-facts.md, "IoT Core quotas").
_FILTERS_PER_SUBSCRIBE = 8
# A filter the broker refused (a SUBACK failure code: on IoT Core, a policy without iot:Subscribe on it) is
# asked for again this often while the connection lasts, so a corrected policy takes effect without a restart.
RESUBSCRIBE_S = 30.0
# A broker out of reach: each of the first this many failed connects is logged, then one line a minute.
FAILURES_TOLD_EACH = 3
FAILURE_LOG_INTERVAL_S = 60.0
Clock = Callable[[], float]


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
    # Wall time of that connection: the agent's event of it carries it, not the later moment it read it.
    last_connected_at: float | None = None
    last_message_monotonic: float | None = None
    # The latest error, kept after the connection recovered (the "connection lost" event reads it after a
    # quick reconnect), and its wall time: an error older than the latest connect is past, not current.
    last_error: str = ""
    last_error_at: float | None = None
    per_filter_granted: dict[str, int] = field(default_factory=dict)


MessageHandler = Callable[[str, bytes, float], None]

# awscrt calls into Python from its own event-loop threads, which CPython did not start. A thread without a
# Python thread state of its own gets a new one for every call (PyGILState_Ensure) and loses it at the end
# (PyGILState_Release), and in CPython 3.11 a new thread state maps its frame stack afresh: an mmap, page
# faults and a munmap for every message, two thirds of the receiving process's CPU at 10,000 messages a
# second (docs/performance.md, "Cost per message"). Taking the thread state once more on each such thread,
# and never giving that back, keeps it for the thread's life; PyGILState_Ensure on a thread that already
# holds the GIL only counts, so it is safe inside the callback. The event-loop threads live as long as the
# process (awscrt's default event loop group), so this is one thread state per core, kept.
_KEPT_THREAD_STATES: set[int] = set()


def keep_thread_state() -> None:
    """On a thread CPython did not start, keep its Python thread state from one callback to the next (above).
    Call it with the GIL held, from the callback; cheap after the first call on a thread."""
    ident = threading.get_ident()
    if ident not in _KEPT_THREAD_STATES:
        _KEPT_THREAD_STATES.add(ident)
        ctypes.pythonapi.PyGILState_Ensure()


class _PendingSubacks(TypedDict):
    """One connection's SUBSCRIBEs: how many await a SUBACK, and whether all so far granted every filter."""

    left: int
    ok: bool


class TelemetrySubscriber:
    """Subscribes `topic_filters` on every connection and hands each message to `on_message`.

    `on_message(topic, payload, received)` runs on the CRT thread, `received` being `clock()` at arrival. It
    must not block: put the message into the `InboundQueue` (transport.mailbox) and decode elsewhere.
    Exceptions it raises are logged and counted.
    """

    def __init__(
        self,
        config: BrokerConfig,
        topic_filters: list[str],
        on_message: MessageHandler,
        *,
        client_id: str | None = None,
        clock: Clock = time.monotonic,
    ) -> None:
        if not topic_filters:
            raise ValueError("topic_filters is empty; build them with twin.core.topics.topic_filters()")
        self.config = config
        self.topic_filters = list(topic_filters)
        self.client_id = client_id or new_client_id(config.client_id_prefix)
        self._on_message = on_message
        # The receive stamp every message carries; the agent injects its own clock so its latencies and
        # health ages are measured on one timeline.
        self._clock = clock
        self._stats = SubscriberStats()
        self._stats_lock = threading.Lock()
        # Connection failures since the last success, and which of them are logged (_on_connection_failure).
        self._failure_lines = Throttle(FAILURE_LOG_INTERVAL_S, first=FAILURES_TOLD_EACH, clock=clock)
        self._client: mqtt5.Client | None = None
        self._connected = threading.Event()
        self._subscribed = threading.Event()
        self._stopped = threading.Event()
        self._started = False
        self._stopping = False
        # The filters the broker refused in its last answer to each, with the SUBACK's reason, and when they
        # were last asked for (the clock's time); guarded by _stats_lock.
        self._refused: dict[str, str] = {}
        self._refused_at = 0.0

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

    @property
    def refused(self) -> dict[str, str]:
        """The topic filters the broker refused in its last answer to each, with the SUBACK's reason."""
        with self._stats_lock:
            return dict(self._refused)

    def retry_refused(self) -> bool:
        """Ask again for the filters the broker refused, once RESUBSCRIBE_S has passed since they were last
        asked for; True if it asked. Called from the pool's thread, not from a callback."""
        client = self._client
        with self._stats_lock:
            filters = list(self._refused)
            if not filters or client is None or not self.connected:
                return False
            now = self._clock()
            if now - self._refused_at < RESUBSCRIBE_S:
                return False
            self._refused_at = now
        log.info("subscriber %s: asking again for %s, refused before", self.client_id, ", ".join(filters))
        self._subscribe(client, filters)
        return True

    # -- CRT callbacks: count, log, hand on; never block -------------------------------------------------

    def _where(self) -> str:
        return self.config.where()

    def _on_publish_received(self, data: mqtt5.PublishReceivedData) -> None:
        received = self._clock()
        if threading.get_ident() not in _KEPT_THREAD_STATES:
            keep_thread_state()
        packet = data.publish_packet
        self._stats.messages_received += 1
        self._stats.last_message_monotonic = received
        if packet is None or packet.topic is None:  # never: awscrt hands on a PUBLISH, which has a topic
            return
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

    def _error(self, text: str) -> None:
        """Under the stats lock: the latest error, and when it happened."""
        self._stats.last_error = text
        self._stats.last_error_at = time.time()

    def _on_attempting_connect(self, _data: mqtt5.LifecycleAttemptingConnectData) -> None:
        with self._stats_lock:
            self._stats.connection_attempts += 1
        log.debug("subscriber %s attempting to connect", self.client_id)

    def _on_connection_success(self, data: mqtt5.LifecycleConnectSuccessData) -> None:
        with self._stats_lock:
            self._stats.connection_successes += 1
            self._stats.last_connected_monotonic = self._clock()
            self._stats.last_connected_at = time.time()
            self._failure_lines.clear()
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
        # Clean session: the broker forgot our subscriptions, so subscribe again on every connection. A filter
        # refused before stays refused until a SUBACK grants it (no "granted" between two refusals).
        self._subscribe(client, self.topic_filters)

    def _subscribe(self, client: mqtt5.Client, filters: list[str]) -> None:
        """SUBSCRIBE to `filters`, at most _FILTERS_PER_SUBSCRIBE in a packet. The SUBACK arrives on the
        client's thread later; waiting for it here would deadlock the client."""
        chunks = [
            filters[i : i + _FILTERS_PER_SUBSCRIBE] for i in range(0, len(filters), _FILTERS_PER_SUBSCRIBE)
        ]
        pending: _PendingSubacks = {"left": len(chunks), "ok": True}
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

    def _on_suback(
        self, future: Future[mqtt5.SubackPacket], chunk: list[str], pending: _PendingSubacks
    ) -> None:
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
                self._refuse(topic_filter, code)
            else:
                with self._stats_lock:
                    self._stats.subscribes_acked += 1
                    granted = self._stats.per_filter_granted
                    granted[topic_filter] = granted.get(topic_filter, 0) + 1
                    was_refused = self._refused.pop(topic_filter, None) is not None
                if was_refused:
                    log.info("subscriber %s: %s granted now, refused before", self.client_id, topic_filter)
        pending["left"] -= 1
        pending["ok"] = pending["ok"] and ok
        if pending["left"] == 0 and pending["ok"] and not self.refused:
            log.info("subscriber %s subscribed to %s", self.client_id, ", ".join(self.topic_filters))
            self._subscribed.set()

    def _refuse(self, topic_filter: str, code: object) -> None:
        """The broker refused `topic_filter` (a SUBACK failure code): count it, say what to fix, and ask
        again every RESUBSCRIBE_S (retry_refused)."""
        reason = getattr(code, "name", None) or str(code)
        with self._stats_lock:
            self._stats.subscribe_failures += 1
            self._error(f"subscribe {topic_filter}: refused by the broker ({reason})")
            first = topic_filter not in self._refused
            self._refused[topic_filter] = reason
            self._refused_at = self._clock()
        # Once until the filter is granted: the retries' refusals are counted, not logged again.
        if first:
            log.error(
                "subscriber %s: the broker refused the subscription to %s (%s), so no telemetry of it "
                "arrives. On AWS IoT Core the agent's IAM role must allow iot:Subscribe on topicfilter/%s "
                "and iot:Receive on its topics; the stack's role allows those of the topic prefix and "
                "devices it was deployed with. Asked for again every %.0f s.",
                self.client_id,
                topic_filter,
                reason,
                topic_filter,
                RESUBSCRIBE_S,
            )

    def _subscribe_failed(self, filters: list[str], exc: BaseException) -> None:
        with self._stats_lock:
            self._stats.subscribe_failures += 1
            self._error(f"subscribe {filters}: {exc}")
        # No SUBACK (a refusal has one: _refuse): usually a disconnect raced it, and the next connection
        # subscribes again.
        log.warning(
            "subscriber %s: subscribe to %s failed: %s (retried on the next connection)",
            self.client_id,
            ", ".join(filters),
            exc,
        )

    def _on_connection_failure(self, data: mqtt5.LifecycleConnectFailureData) -> None:
        code = connack_code(data)
        refused = CONNACK_REFUSALS.get(code, "") if code is not None else ""
        with self._stats_lock:
            self._stats.connection_failures += 1
            said = f" (CONNACK reason {code}: {refused})" if refused else ""
            self._error(f"connect: {crt_error_text(data.exception)}{said}")
            failures = self._stats.connection_failures
            # Backoff retries run until stop(), every few seconds: an outage of a day would be tens of
            # thousands of lines. The first few are each told, then one a minute, with the count.
            if self._failure_lines.due() is None:
                return
            streak = self._failure_lines.streak
        # The hint rides on each line: the first may have scrolled away.
        hint = failure_hint(self.config, data)
        log.warning(
            "subscriber %s could not connect to %s (failure #%d%s): %s; retrying with backoff%s",
            self.client_id,
            self._where(),
            failures,
            "; told once a minute from now on" if streak == FAILURES_TOLD_EACH else "",
            crt_error_text(data.exception),
            f". {hint}" if hint else "",
        )

    def _on_disconnection(self, data: mqtt5.LifecycleDisconnectData) -> None:
        self._connected.clear()
        self._subscribed.clear()
        if self._stopping:
            log.info("subscriber %s disconnected (stopping)", self.client_id)
            return
        with self._stats_lock:
            self._stats.disconnects += 1
            self._error(f"disconnect: {crt_error_text(data.exception)}")
        reason = ""
        if data.disconnect_packet is not None:
            reason = f" (server reason {data.disconnect_packet.reason_code!r})"
        log.warning(
            "subscriber %s disconnected from %s: %s%s; reconnecting",
            self.client_id,
            self._where(),
            crt_error_text(data.exception),
            reason,
        )

    def _on_stopped(self, _data: mqtt5.LifecycleStoppedData) -> None:
        self._connected.clear()
        log.info("subscriber %s stopped", self.client_id)
        self._stopped.set()
