"""A loopback MQTT proxy that enforces a per-connection publish budget the way AWS IoT Core does.

IoT Core accepts at most 100 PUBLISH requests per second on one connection, inbound plus outbound, and
discards the excess without telling anyone (docs/aws-facts.md, "IoT Core quotas"). That binds a
subscriber too: one connection subscribed to a fleet receives at most 100 messages a second. mosquitto has
no such limit, so tests and `twin bench quota` put this proxy between the clients and mosquitto: each client
connection gets its own upstream connection, every MQTT packet is forwarded whole, and a PUBLISH that finds
its connection's budget spent is dropped and counted for that connection and direction.

The budget is a token bucket per connection: `budget` tokens a second, holding at most `budget * burst_s`
(IoT Core does not document its algorithm; a one-second bucket is the simplest reading of "per second"). Both
directions draw from the same bucket, as IoT Core counts inbound plus outbound. Only PUBLISH packets are
metered; CONNECT, SUBSCRIBE, PINGREQ and the acknowledgements always pass. The project publishes telemetry at
QoS 0; a dropped QoS 1 PUBLISH would be redelivered by its sender, which this proxy does not model.

It also stands in for an IoT policy that does not allow `iot:Subscribe` on some topic filters
(`denied_filters`, matched as written, which is how IoT Core matches a `topicfilter/` resource). IoT Core
answers such a subscription with a SUBACK whose reason code for that filter is 0x87, Not authorized (0x80,
Failure, under MQTT 3.1.1), and grants the others of the same SUBSCRIBE. The proxy does the same: it forwards
the SUBSCRIBE without the denied filters (or not at all when every one is denied) and puts their failure
codes back into the SUBACK in the client's order. `allow` lifts a denial, as a corrected policy would.

Packets are framed by the MQTT fixed header (packet type, then the remaining length as a variable-byte
integer), which MQTT 3.1.1 and 5 share; the CONNECT packet is read far enough to label a connection with its
client id and protocol level. For tests and benchmarks only: it listens on loopback, forwards to loopback, and
runs its own asyncio loop in a background thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import socket
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)

PUBLISH = 3
CONNECT = 1
SUBSCRIBE = 8
SUBACK = 9
# A denied filter's SUBACK reason code: MQTT 5's Not authorized, MQTT 3.1.1's only failure code.
NOT_AUTHORIZED = 0x87
FAILURE_V311 = 0x80
# The variable-byte remaining length has at most four bytes (MQTT 3.1.1 2.2.3, MQTT 5 1.5.5).
_MAX_LENGTH_BYTES = 4
_READ_CHUNK = 1 << 16


class ProxyError(ValueError):
    """A proxy setting is not usable; the message says which and what to use instead."""


@dataclass
class ConnectionStats:
    """Counts for one client connection; `to_broker` is the client's direction, `to_client` the broker's."""

    number: int
    client_id: str = ""
    # The CONNECT's protocol level: 4 is MQTT 3.1.1, 5 is MQTT 5.
    level: int = 4
    open: bool = True
    forwarded_to_broker: int = 0
    forwarded_to_client: int = 0
    dropped_to_broker: int = 0
    dropped_to_client: int = 0
    # Topic filters refused as an IoT policy without iot:Subscribe on them would (`denied_filters`).
    subscriptions_denied: int = 0

    @property
    def dropped(self) -> int:
        return self.dropped_to_broker + self.dropped_to_client

    @property
    def forwarded(self) -> int:
        return self.forwarded_to_broker + self.forwarded_to_client

    def as_dict(self) -> dict[str, Any]:
        return {
            "number": self.number,
            "client_id": self.client_id,
            "open": self.open,
            "forwarded_to_broker": self.forwarded_to_broker,
            "forwarded_to_client": self.forwarded_to_client,
            "dropped_to_broker": self.dropped_to_broker,
            "dropped_to_client": self.dropped_to_client,
        }


class TokenBucket:
    """`rate` tokens a second, at most `capacity` held; starts full. `clock` is injectable for tests."""

    def __init__(self, rate: float, capacity: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.rate = rate
        self.capacity = capacity
        self._clock = clock
        self._tokens = capacity
        self._stamp = clock()

    def take(self) -> bool:
        now = self._clock()
        self._tokens = min(self.capacity, self._tokens + (now - self._stamp) * self.rate)
        self._stamp = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False


def split_packets(buffer: bytearray) -> tuple[list[tuple[int, bytes]], int]:
    """Complete MQTT packets at the start of `buffer`: ([(packet type, packet bytes)], bytes consumed).

    Raises ValueError on a remaining length longer than four bytes (not MQTT)."""
    packets: list[tuple[int, bytes]] = []
    pos = 0
    end = len(buffer)
    while pos + 2 <= end:
        length = 0
        shift = 0
        i = pos + 1
        while True:
            if i >= end:
                return packets, pos  # the length itself is not complete yet
            byte = buffer[i]
            length |= (byte & 0x7F) << shift
            i += 1
            if not byte & 0x80:
                break
            shift += 7
            if i - pos - 1 >= _MAX_LENGTH_BYTES:
                raise ValueError("MQTT remaining length longer than four bytes: not an MQTT stream")
        if i + length > end:
            return packets, pos
        packets.append((buffer[pos] >> 4, bytes(buffer[pos : i + length])))
        pos = i + length
    return packets, pos


def _level_at(packet: bytes) -> int:
    """Where a CONNECT packet's protocol level is: after the fixed header and the protocol name."""
    _, i = _read_varint(packet, 1)
    return i + 2 + int.from_bytes(packet[i : i + 2], "big")


def connect_client_id(packet: bytes) -> str:
    """The client id of an MQTT 3.1.1 or 5 CONNECT packet, or "" if it cannot be read."""
    try:
        i = _level_at(packet)
        level = packet[i]
        i += 1 + 1 + 2  # level, flags, keep alive
        if level == 5:
            props, i = _read_varint(packet, i)
            i += props
        id_len = int.from_bytes(packet[i : i + 2], "big")
        return packet[i + 2 : i + 2 + id_len].decode("utf-8", "replace")
    except (IndexError, ValueError):
        return ""


def connect_level(packet: bytes) -> int:
    """The protocol level of an MQTT CONNECT packet (4: 3.1.1, 5: MQTT 5), or 4 if it cannot be read."""
    try:
        return packet[_level_at(packet)]
    except IndexError:
        return 4


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _read_varint(packet: bytes, i: int) -> tuple[int, int]:
    """A variable-byte integer at `i`: (value, index after it)."""
    value, shift = 0, 0
    while True:
        byte = packet[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, i


@dataclass(frozen=True)
class _Subscribe:
    """A SUBSCRIBE taken apart: its packet id, what precedes the filters (packet id and, in MQTT 5, the
    properties), and each filter with its entry's bytes (length, name, options)."""

    packet_id: int
    head: bytes
    entries: tuple[tuple[str, bytes], ...]


def parse_subscribe(packet: bytes, level: int) -> _Subscribe:
    """A SUBSCRIBE packet of protocol `level` taken apart (ValueError if it is not one)."""
    try:
        _, i = _read_varint(packet, 1)
        start = i
        packet_id = int.from_bytes(packet[i : i + 2], "big")
        i += 2
        if level == 5:
            props, i = _read_varint(packet, i)
            i += props
        head = packet[start:i]
        entries = []
        while i < len(packet):
            length = int.from_bytes(packet[i : i + 2], "big")
            end = i + 2 + length + 1  # the filter and its options byte
            if end > len(packet):
                raise ValueError("a SUBSCRIBE's topic filter runs past its end")
            entries.append((packet[i + 2 : i + 2 + length].decode("utf-8"), packet[i:end]))
            i = end
    except (IndexError, UnicodeDecodeError) as exc:
        raise ValueError(f"not a SUBSCRIBE packet: {exc}") from exc
    return _Subscribe(packet_id, head, tuple(entries))


def _packet_of(first_byte: int, body: bytes) -> bytes:
    return bytes([first_byte]) + _varint(len(body)) + body


def suback_with(packet: bytes, level: int, denied: dict[int, int]) -> bytes:
    """The SUBACK `packet` with failure codes put back at the client's positions: `denied` maps a position
    in the client's SUBSCRIBE to its code; the broker's codes fill the other positions in order."""
    _, i = _read_varint(packet, 1)
    head_end = i + 2
    if level == 5:
        props, head_end = _read_varint(packet, head_end)
        head_end += props
    granted = iter(packet[head_end:])
    total = len(packet) - head_end + len(denied)
    codes = bytes(denied[k] if k in denied else next(granted) for k in range(total))
    return _packet_of(packet[0], packet[i:head_end] + codes)


def _require_loopback(what: str, host: str) -> None:
    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = host == "localhost"
    if not loopback:
        raise ProxyError(
            f"{what} {host!r} is not a loopback address; the quota proxy is for local tests: use 127.0.0.1"
        )


class QuotaProxy:
    """Forwards MQTT from 127.0.0.1:`port` to `upstream_host:upstream_port`, dropping PUBLISH packets over
    `budget` per second per connection (None: no limit, a plain proxy). `start()` returns once listening."""

    def __init__(
        self,
        upstream_host: str,
        upstream_port: int,
        *,
        budget: float | None = 100.0,
        burst_s: float = 1.0,
        listen_host: str = "127.0.0.1",
        listen_port: int = 0,
        clock: Callable[[], float] = time.monotonic,
        denied_filters: Iterable[str] = (),
    ) -> None:
        _require_loopback("upstream host", upstream_host)
        _require_loopback("listen host", listen_host)
        if budget is not None and not budget > 0:
            raise ProxyError(f"budget {budget!r} must be a positive number of publishes per second (or None)")
        if not burst_s > 0:
            raise ProxyError(f"burst_s {burst_s!r} must be positive")
        self.upstream = (upstream_host, upstream_port)
        self.budget = budget
        self.burst_s = burst_s
        self._listen = (listen_host, listen_port)
        self._clock = clock
        self._denied = frozenset(denied_filters)
        self._connections: list[ConnectionStats] = []
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: asyncio.AbstractServer | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._shutdown: asyncio.Event | None = None
        self._error: BaseException | None = None
        self.port = 0

    # -- lifecycle ------------------------------------------------------------------------------------------

    def start(self, timeout: float = 10.0) -> QuotaProxy:
        if self._thread is not None:
            return self
        self._thread = threading.Thread(target=self._run, name="quota-proxy", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            raise RuntimeError(f"the quota proxy did not start listening within {timeout} s")
        if self._error is not None:
            raise RuntimeError(f"the quota proxy could not start: {self._error}") from self._error
        log.info(
            "quota proxy 127.0.0.1:%d -> %s:%d, %s publishes/s per connection",
            self.port,
            *self.upstream,
            "unlimited" if self.budget is None else f"{self.budget:g}",
        )
        return self

    def stop(self, timeout: float = 5.0) -> None:
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return
        shutdown = self._shutdown
        if shutdown is not None:
            with contextlib.suppress(RuntimeError):  # the loop already ended
                loop.call_soon_threadsafe(shutdown.set)
        thread.join(timeout)
        self._thread = None

    def allow(self, topic_filter: str) -> None:
        """Stop denying `topic_filter` (a corrected policy): the next SUBSCRIBE to it is forwarded."""
        self._denied = self._denied - {topic_filter}

    def __enter__(self) -> QuotaProxy:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    # -- figures --------------------------------------------------------------------------------------------

    def connections(self) -> list[ConnectionStats]:
        """A copy of every connection's counts so far, in the order they connected (closed ones included)."""
        with self._lock:
            return [ConnectionStats(**vars(c)) for c in self._connections]

    def totals(self) -> dict[str, Any]:
        conns = self.connections()
        return {
            "budget_per_connection": self.budget,
            "connections": len(conns),
            "forwarded": sum(c.forwarded for c in conns),
            "dropped": sum(c.dropped for c in conns),
            "dropped_to_client": sum(c.dropped_to_client for c in conns),
            "dropped_to_broker": sum(c.dropped_to_broker for c in conns),
            "per_connection": [c.as_dict() for c in conns],
        }

    # -- the loop thread ------------------------------------------------------------------------------------

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # reported to start(), or logged if it happens later
            self._error = exc
            self._ready.set()
            log.exception("quota proxy stopped on an error")

    async def _main(self) -> None:
        shutdown = self._shutdown = asyncio.Event()
        self._loop = asyncio.get_running_loop()
        tasks: set[asyncio.Task[None]] = set()

        async def on_client(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            task = asyncio.current_task()
            if task is not None:
                tasks.add(task)
            try:
                await self._serve(reader, writer)
            finally:
                if task is not None:
                    tasks.discard(task)

        server = await asyncio.start_server(on_client, *self._listen)
        self.port = server.sockets[0].getsockname()[1]
        self._ready.set()
        async with server:
            await shutdown.wait()
            server.close()
            for task in list(tasks):
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _serve(self, client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter) -> None:
        with self._lock:
            stats = ConnectionStats(number=len(self._connections) + 1)
            self._connections.append(stats)
        _nodelay(client_writer)
        try:
            broker_reader, broker_writer = await asyncio.open_connection(*self.upstream)
        except OSError as exc:
            log.warning("quota proxy: cannot reach the broker at %s:%d: %s", *self.upstream, exc)
            stats.open = False
            client_writer.close()
            return
        _nodelay(broker_writer)
        bucket = None
        if self.budget is not None:
            bucket = TokenBucket(self.budget, self.budget * self.burst_s, self._clock)
        link = _Link(client_writer, stats, bucket)
        upstream = asyncio.create_task(self._pump(client_reader, broker_writer, link, to_broker=True))
        downstream = asyncio.create_task(self._pump(broker_reader, client_writer, link, to_broker=False))
        try:
            # Either side hanging up ends the connection, as a broker closing its socket would.
            await asyncio.wait({upstream, downstream}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (upstream, downstream):
                task.cancel()
            await asyncio.gather(upstream, downstream, return_exceptions=True)
            for writer in (client_writer, broker_writer):
                writer.close()
                with contextlib.suppress(Exception):
                    await writer.wait_closed()
            stats.open = False

    async def _pump(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, link: _Link, *, to_broker: bool
    ) -> None:
        buffer = bytearray()
        while True:
            chunk = await reader.read(_READ_CHUNK)
            if not chunk:
                return
            buffer += chunk
            try:
                packets, used = split_packets(buffer)
            except ValueError as exc:
                log.warning("quota proxy: connection %d: %s; closing it", link.stats.number, exc)
                return
            del buffer[:used]
            out = [p for kind, packet in packets if (p := self._forward(kind, packet, link, to_broker))]
            if out:
                writer.write(b"".join(out))
                await writer.drain()

    def _forward(self, kind: int, packet: bytes, link: _Link, to_broker: bool) -> bytes | None:
        """What goes on of one packet (None: nothing): counted, metered, policed."""
        stats = link.stats
        if kind == CONNECT and to_broker and not stats.client_id:
            stats.client_id = connect_client_id(packet)
            stats.level = connect_level(packet)
        if kind == PUBLISH:
            if link.bucket is not None and not link.bucket.take():
                if to_broker:
                    stats.dropped_to_broker += 1
                else:
                    stats.dropped_to_client += 1
                return None
            if to_broker:
                stats.forwarded_to_broker += 1
            else:
                stats.forwarded_to_client += 1
        elif kind == SUBSCRIBE and to_broker and self._denied:
            return self._police(packet, link)
        elif kind == SUBACK and not to_broker and link.denials:
            return _suback_for(packet, link)
        return packet

    def _police(self, packet: bytes, link: _Link) -> bytes | None:
        """A SUBSCRIBE as the policy lets it through: without its denied filters (their codes kept for the
        SUBACK), or None when every filter is denied and the client has been answered here."""
        stats = link.stats
        try:
            subscribe = parse_subscribe(packet, stats.level)
        except ValueError as exc:
            log.warning("quota proxy: connection %d: %s; forwarded as it is", stats.number, exc)
            return packet
        code = NOT_AUTHORIZED if stats.level == 5 else FAILURE_V311
        denied = {k: code for k, (name, _) in enumerate(subscribe.entries) if name in self._denied}
        if not denied:
            return packet
        stats.subscriptions_denied += len(denied)
        if len(denied) == len(subscribe.entries):
            head = subscribe.head[:2] + (b"\x00" if stats.level == 5 else b"")
            link.client.write(_packet_of(SUBACK << 4, head + bytes(denied.values())))
            return None
        link.denials[subscribe.packet_id] = denied
        kept = b"".join(entry for k, (_, entry) in enumerate(subscribe.entries) if k not in denied)
        return _packet_of(packet[0], subscribe.head + kept)


@dataclass
class _Link:
    """One client connection as both of its pumps share it: the client's writer (a SUBSCRIBE the policy
    refuses whole is answered on it), its counts and budget, and the failure codes a SUBACK on its way back
    must carry, by packet id."""

    client: asyncio.StreamWriter
    stats: ConnectionStats
    bucket: TokenBucket | None
    denials: dict[int, dict[int, int]] = field(default_factory=dict)


def _suback_for(packet: bytes, link: _Link) -> bytes:
    try:
        _, i = _read_varint(packet, 1)
        packet_id = int.from_bytes(packet[i : i + 2], "big")
    except IndexError:
        return packet
    denied = link.denials.pop(packet_id, None)
    return packet if denied is None else suback_with(packet, link.stats.level, denied)


def _nodelay(writer: asyncio.StreamWriter) -> None:
    # Small telemetry packets must not wait for Nagle's algorithm (the private broker sets it too).
    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
