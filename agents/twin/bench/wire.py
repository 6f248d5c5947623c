"""A load generator's MQTT publisher: QoS 0 PUBLISH packets written straight to a plain-TCP broker.

The benchmarks share two cores between the load, the broker and the agent under test. Through a full client
(awscrt, as the first benchmarks used) a publisher spends about 25 us of Python per message: half a core for
a 2,000-arm fleet, which the agent then does not get. An MQTT 3.1.1 QoS 0 PUBLISH is a fixed byte layout
(OASIS MQTT 3.1.1, section 3.3), so this writes the packets of one time slot with one `sendall`, for about a
microsecond each. It is a load generator only: no TLS, no QoS 1, no reconnect; the agent under test always
uses its real client.
"""

from __future__ import annotations

import socket
import struct
from urllib.parse import urlsplit

# MQTT 3.1.1 control packet types (first byte, flags 0 for these).
_CONNECT = 0x10
_CONNACK = 0x20
_PUBLISH_QOS0 = 0x30
_DISCONNECT = b"\xe0\x00"
_PROTOCOL = b"\x00\x04MQTT\x04"  # protocol name and level 4 (3.1.1)
_CLEAN_SESSION = 0x02


class WireError(ConnectionError):
    """The broker refused the connection or the socket failed."""


def remaining_length(n: int) -> bytes:
    """The variable-length "remaining length" of an MQTT fixed header (7 bits a byte, low first)."""
    if not 0 <= n <= 268_435_455:
        raise ValueError(f"an MQTT packet cannot hold {n} bytes")
    out = bytearray()
    while True:
        byte, n = n % 128, n // 128
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _string(text: bytes) -> bytes:
    return struct.pack("!H", len(text)) + text


def topic_field(topic: str) -> bytes:
    """A topic as a PUBLISH carries it (length-prefixed UTF-8): encode once, publish many times."""
    return _string(topic.encode())


def publish_packet(topic: bytes, payload: bytes) -> bytes:
    """A QoS 0 PUBLISH of `payload` on a `topic_field`."""
    return bytes((_PUBLISH_QOS0,)) + remaining_length(len(topic) + len(payload)) + topic + payload


class WirePublisher:
    """One MQTT connection that only publishes QoS 0 (module doc)."""

    def __init__(self, url: str, client_id: str, *, timeout_s: float = 10.0) -> None:
        parts = urlsplit(url)
        if parts.scheme != "mqtt" or not parts.hostname:
            raise WireError(f"{url!r}: the load generator publishes over plain mqtt://host:port only")
        self._address = (parts.hostname, parts.port or 1883)
        self._client_id = client_id.encode()
        self._timeout_s = timeout_s
        self._sock: socket.socket | None = None

    def connect(self) -> None:
        sock = socket.create_connection(self._address, timeout=self._timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        # Keep-alive 0: no PINGREQ is needed for a run of a few minutes (MQTT 3.1.1, section 3.1.2.10).
        body = _PROTOCOL + bytes((_CLEAN_SESSION,)) + struct.pack("!H", 0) + _string(self._client_id)
        sock.sendall(bytes((_CONNECT,)) + remaining_length(len(body)) + body)
        ack = b""
        while len(ack) < 4:
            chunk = sock.recv(4 - len(ack))
            if not chunk:
                sock.close()
                raise WireError(f"{self._address}: the broker closed the connection before CONNACK")
            ack += chunk
        if ack[0] != _CONNACK or ack[3] != 0:
            sock.close()
            raise WireError(f"{self._address}: CONNECT refused (CONNACK {ack.hex()})")
        sock.settimeout(None)
        self._sock = sock

    def send(self, packets: list[bytes]) -> None:
        """Write the packets (or the pieces of packets) in one go (blocks while the broker's socket buffer is
        full)."""
        if self._sock is None:
            raise WireError("not connected")
        try:
            self._sock.sendall(b"".join(packets))
        except OSError as exc:
            raise WireError(f"{self._address}: {exc}") from exc

    def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is None:
            return
        try:
            sock.sendall(_DISCONNECT)
            sock.shutdown(socket.SHUT_WR)
            # Wait for the broker to close its side: everything written before DISCONNECT has been read.
            sock.settimeout(self._timeout_s)
            while sock.recv(4096):
                pass
        except OSError:
            pass
        finally:
            sock.close()
