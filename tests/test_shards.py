"""The replies a worker's mirror sends back to the agent are checked before they are used, and its refusals
read as the agent's errors."""

from __future__ import annotations

import pytest
from twin.service.shards import (
    AskTimedOutError,
    Refusal,
    Refused,
    WorkerError,
    _raise_refusal,
    statuses_of,
)


def test_statuses_of_takes_device_status_pairs() -> None:
    assert statuses_of((("arm-001", "ONLINE"), ("arm-002", "STALE"))) == (
        ("arm-001", "ONLINE"),
        ("arm-002", "STALE"),
    )
    assert statuses_of(()) == ()


@pytest.mark.parametrize(
    ("reply", "named"),
    [
        (None, "NoneType"),
        ([("arm-001", "ONLINE")], "list"),
        ((("arm-001", "ONLINE"), ["arm-002", "STALE"]), "['arm-002', 'STALE']"),
        ((("arm-001", "ONLINE", "extra"),), "('arm-001', 'ONLINE', 'extra')"),
        ((("arm-001", 3),), "('arm-001', 3)"),
    ],
)
def test_statuses_of_names_a_reply_that_is_not_statuses(reply: object, named: str) -> None:
    with pytest.raises(WorkerError, match="statuses were asked for") as raised:
        statuses_of(reply)  # type: ignore[arg-type]
    assert named in str(raised.value)


def test_a_worker_refusing_as_busy_is_a_timed_out_ask() -> None:
    """The worker's own "did not get to it, busy" is a timed-out ask, as its "stuck" and the agent's own wait
    are (WorkerShard._answer): a forget refused so is answered 504 forget_timed_out, not 503, since the
    request still waits in the worker's mirror and may yet be made."""
    busy = "the mirror's worker did not get to the request within 10 s; it handled 3 batches meanwhile"
    with pytest.raises(AskTimedOutError, match=r"^worker 1: the mirror's worker did not get to the request"):
        _raise_refusal(Refused(7, Refusal.BUSY, busy), 1)
    # Any other refusal of the worker's is not.
    with pytest.raises(WorkerError) as other:
        _raise_refusal(Refused(8, Refusal.ERROR, "ValueError: no"), 1)
    assert not isinstance(other.value, AskTimedOutError)
