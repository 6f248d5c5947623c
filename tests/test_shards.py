"""The replies a worker's mirror sends back to the agent are checked before they are used."""

from __future__ import annotations

import pytest
from twin.service.shards import WorkerError, statuses_of


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
