"""How messages cross the pipe from the agent to one of its worker processes (`twin run --workers N`).

The agent (service.shards, a sender thread per worker) and `twin bench worker` write batches with
`send_batch` and end with `send_end`; the worker's PipeInbox (service.mirror) reads them with `read_batch`.
One pipe message is a pickled list of (mailbox key, (topic, payload, receive monotonic, receive wall)): the
key is the device, or transport.mailbox.UNTRACKED_KEY for a topic that names none. An empty message is the
end marker.

Light on purpose: the agent imports it, and must not load MuJoCo.
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from multiprocessing.connection import Connection

Message = tuple[str, tuple[str, bytes, float, float]]

_END = b""


def send_batch(conn: Connection, messages: Sequence[Message]) -> None:
    """Write one batch (one pipe message); raises OSError or ValueError when the pipe is closed or broken."""
    conn.send_bytes(pickle.dumps(messages, protocol=pickle.HIGHEST_PROTOCOL))


def send_end(conn: Connection) -> None:
    """Tell the worker nothing follows: it handles what it has read, then stops."""
    conn.send_bytes(_END)


def read_batch(raw: bytes) -> list[Message] | None:
    """The messages of one pipe message (as `Connection.recv_bytes` returned it); None for the end marker."""
    if raw == _END:
        return None
    # Only this agent's own receiving process writes to the pipe (it is inherited, never listened on).
    messages: list[Message] = pickle.loads(raw)
    return messages
