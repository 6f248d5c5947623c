"""How messages cross the pipe from the agent to one of its worker processes (`twin run --workers N`).

The agent (service.shards, a sender thread per worker) and `twin bench worker` write batches with
`send_batch` and end with `send_end`; the worker's PipeInbox (service.mirror) reads them with `read_batch`.
A shard encodes a batch once (`encode_batch`), sends those bytes (`send_encoded`) and keeps them until the
worker's checkpoint counts them; after a restart `messages_of` gives them back to be sent again.

One pipe message is one batch as columns, in arrival order: the devices the topics name (the mailbox key,
transport.mailbox.UNTRACKED_KEY for a topic that names none), the topics, the payloads (raw bytes), and the
receive times on the agent's monotonic and wall clocks, pickled as five sequences at once. The receiving
process hands over every message the fleet sends, so its cost per message is what counts: pickling the
columns of 1,000 messages and reading them back took 0.35-0.4 us a message here, against 0.5 us for a list
of per-message tuples and 0.6 us for a hand-made frame of lengths and offsets (slicing and decoding each
topic and payload out of one bytes object costs more than pickle's C loop). An empty pipe message is the
end marker.

Light on purpose: the agent imports it, and must not load MuJoCo.
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import NamedTuple

# One message as a shard's queue holds it: (mailbox key, (topic, payload, receive monotonic, receive wall)).
Message = tuple[str, tuple[str, bytes, float, float]]

_END = b""


class Batch(NamedTuple):
    """Messages in arrival order, as columns: what a mirror takes from its inbox."""

    keys: Sequence[str]  # the device each topic names, or transport.mailbox.UNTRACKED_KEY
    topics: Sequence[str]
    payloads: Sequence[bytes]
    recv_mono: Sequence[float]
    recv_wall: Sequence[float]


EMPTY = Batch((), (), (), (), ())


def batch_of(messages: Sequence[Message]) -> Batch:
    """`messages` (a shard queue's items) as columns."""
    if not messages:
        return EMPTY
    keys, fields = zip(*messages, strict=True)
    topics, payloads, monos, walls = zip(*fields, strict=True)
    return Batch(keys, topics, payloads, monos, walls)


def encode_batch(messages: Sequence[Message]) -> bytes:
    """`messages` as one pipe message (not empty: an empty pipe message is the end marker)."""
    return pickle.dumps(tuple(batch_of(messages)), protocol=pickle.HIGHEST_PROTOCOL)


def messages_of(raw: bytes) -> list[Message]:
    """The messages `encode_batch` encoded into `raw`, as a shard's queue held them."""
    batch = read_batch(raw)
    if batch is None:
        return []
    return list(
        zip(
            batch.keys,
            zip(batch.topics, batch.payloads, batch.recv_mono, batch.recv_wall, strict=True),
            strict=True,
        )
    )


def send_batch(conn: Connection, messages: Sequence[Message]) -> None:
    """Write one batch (one pipe message); raises OSError or ValueError when the pipe is closed or broken."""
    conn.send_bytes(encode_batch(messages))


def send_encoded(conn: Connection, raw: bytes) -> None:
    """Write one batch `encode_batch` encoded; raises OSError or ValueError as `send_batch` does."""
    conn.send_bytes(raw)


def send_end(conn: Connection) -> None:
    """Tell the worker nothing follows: it handles what it has read, then stops."""
    conn.send_bytes(_END)


def read_batch(raw: bytes) -> Batch | None:
    """The messages of one pipe message (as `Connection.recv_bytes` returned it); None for the end marker."""
    if raw == _END:
        return None
    # Only this agent's own receiving process writes to the pipe (it is inherited, never listened on).
    return Batch(*pickle.loads(raw))
