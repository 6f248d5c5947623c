"""The agent's state file (twin.service.persist): the alarms a restart must not forget, written atomically,
read back on another process's clock, and a broken file set aside instead of stopping the agent."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from twin.core.alarms import AlarmKind, AlarmRecord, AlarmState
from twin.service.persist import StateFile, parse, write_atomically


def _record(state: AlarmState, joint: str = "elbow_flex", since: float = 100.0) -> AlarmRecord:
    return AlarmRecord(
        device="arm-001",
        joint=joint,
        kind=AlarmKind.OVER_TEMPERATURE,
        state=state,
        since=since,
        present=state is not AlarmState.LATCHED,
        raised=2,
        value=63.0,
        message="elbow_flex servo at 63 C",
    )


def test_kept_alarms_are_written_and_read_back_on_a_new_clock(tmp_path: Path) -> None:
    path = tmp_path / "state" / "state.json"
    store = StateFile(path)
    records = [
        _record(AlarmState.ACKNOWLEDGED),
        _record(AlarmState.LATCHED, joint="wrist_flex", since=90.0),
        _record(AlarmState.NORMAL, joint="gripper"),  # never kept
    ]
    # Written at monotonic 110 s = wall 1,000,010 s: the elbow changed 10 s before, the wrist 20 s.
    assert store.save(records, now_mono=110.0, now_wall=1_000_010.0)
    assert not store.save(records, now_mono=111.0, now_wall=1_000_011.0)  # unchanged: not written again
    document = json.loads(path.read_text())
    assert document["version"] == 1 and [a["state"] for a in document["alarms"]] == [
        "ACKNOWLEDGED",
        "LATCHED",
    ]
    assert not list(path.parent.glob(".state.json.*"))  # no temporary file left behind

    # A reboot later: a new monotonic clock (5 s since boot), wall time 1,000,060.
    back = StateFile(path).load(now_mono=5.0, now_wall=1_000_060.0)
    by_joint = {r.joint: r for r in back}
    assert by_joint["elbow_flex"].state is AlarmState.ACKNOWLEDGED and by_joint["elbow_flex"].present
    assert by_joint["elbow_flex"].since == pytest.approx(5.0 - 60.0)
    assert by_joint["wrist_flex"].state is AlarmState.LATCHED and not by_joint["wrist_flex"].present
    assert by_joint["wrist_flex"].raised == 2 and by_joint["wrist_flex"].message.startswith("elbow_flex")


def test_no_file_is_no_alarms_and_a_broken_one_is_set_aside(tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    assert StateFile(path).load(0.0, 0.0) == []
    path.write_text('{"version": 1, "alarms": [{"device": "arm-001"}]}')
    assert StateFile(path).load(0.0, 0.0) == []
    assert not path.exists() and (tmp_path / "state.json.bad").exists()
    with pytest.raises(ValueError, match="never keeps"):
        parse(
            json.dumps(
                {
                    "version": 1,
                    "alarms": [
                        {
                            "device": "a",
                            "joint": "gripper",
                            "kind": "overload",
                            "state": "NORMAL",
                            "changed_at": 0,
                        }
                    ],
                }
            ),
            0.0,
            0.0,
        )


def test_a_failed_write_leaves_the_previous_file_whole(tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    write_atomically(path, "old\n")
    with pytest.raises(TypeError):
        write_atomically(path, None)  # type: ignore[arg-type]  # fails mid-write
    assert path.read_text() == "old\n" and [p.name for p in tmp_path.iterdir()] == ["state.json"]
