"""The topic and device-id rules (twin.core.topics) and everyone who applies them: the agent config, the
decoder, the subscriber's filters, the edge simulator, the CDK stack's settings and the calibration stores
agree on one table."""

from __future__ import annotations

import random
from collections.abc import Iterable
from pathlib import Path

import pytest
from twin.core.telemetry import RejectReason, TelemetryDecoder, TelemetryRejected
from twin.core.topics import (
    TopicError,
    case_twin,
    check_deployed_devices,
    check_devices,
    device_from_topic,
    device_id_problem,
    listed_device_notes,
    policy_device_id_problem,
    telemetry_topic,
    topic_filters,
    topic_prefix_problem,
)
from twin.edge.payload import encode, make_payload
from twin.service.calibrations import DirectoryStore
from twin.service.config import ConfigError, config_notes, load_config

from stacks.settings import SettingsError, TwinSettings

# (device id, the agent mirrors it from an edge, a person may list it). Hand-written from the rules: a topic
# level of 1..128 printable characters without '/', '+', '#' or surrounding spaces, not '.' or '..'; a listed
# id (telemetry.devices, the stack's devices, a calibration store's file name) is also 1..64 of letters,
# digits, '-', '_', '.', not '.' first nor '.json' last.
DEVICE_IDS = [
    ("arm-001", True, True),
    ("ARM_7", True, True),
    ("a", True, True),
    ("x" * 64, True, True),
    ("x" * 65, True, False),
    ("x" * 128, True, False),
    ("x" * 129, False, False),
    ("arm.001", True, True),
    ("so101.lab.7", True, True),
    ("arm-001.", True, True),
    (".arm", True, False),  # a hidden file in a directory store
    ("arm.json", True, False),  # a calibration file's name, typed for the arm's
    ("ARM.JSON", True, False),
    ("arm.jsonl", True, True),
    ("arm:001", True, False),  # a valid Greengrass thing name, but not in the stack's IAM-safe set
    ("arm 001", True, False),
    ("bras-été", True, False),
    ("arm/001", False, False),
    ("arm+", False, False),
    ("#", False, False),
    ("", False, False),
    (" arm-001", False, False),
    ("arm-001 ", False, False),
    ("arm\x00", False, False),
    ("arm\n1", False, False),
    # A path step to a browser: the arm's console page (/arm/..) could never be opened.
    (".", False, False),
    ("..", False, False),
    ("...", True, False),
    ("-", True, True),
]

# (prefix, usable): plain levels of letters, digits, '.', '_', '-' joined by '/'.
PREFIXES = [
    ("dt/lerobot", True),
    ("fleet", True),
    ("a/b/c.d_e-f", True),
    ("dt/lerobot/", False),
    ("/dt/lerobot", False),
    ("dt//lerobot", False),
    ("dt/+", False),
    ("dt/#", False),
    ("$aws/things", False),
    ("dt/le robot", False),
    ("", False),
]


def _stack_accepts(**context: object) -> bool:
    values = {"clientCidr": "203.0.113.7/32", **context}
    try:
        TwinSettings.from_context(values.get)
    except SettingsError:
        return False
    return True


def _config_accepts(**overrides: object) -> bool:
    try:
        load_config(None, overrides)
    except ConfigError:
        return False
    return True


def _store_accepts(tmp_path: Path, device_id: str) -> bool:
    """A directory store takes the id's calibration and its listing names the arm by it (the S3 store checks
    the same rule: tests/test_calibrations.py)."""
    store = DirectoryStore(tmp_path / "cal")
    try:
        store.write(device_id, b"{}")
    except ValueError:
        return False
    return store.listing() == {device_id: store.listing()[device_id]}


def _decoder_accepts(device_id: str) -> bool:
    payload = make_payload("placeholder", 0.0, "ticks", random.Random(0))
    payload["device_id"] = device_id
    try:
        TelemetryDecoder().decode(encode(payload))
    except TelemetryRejected as exc:
        return exc.reason != RejectReason.BAD_DEVICE_ID
    return True


@pytest.mark.parametrize(("device_id", "agent", "deployable"), DEVICE_IDS)
def test_every_part_applies_the_same_device_id_rule(
    tmp_path: Path, device_id: str, agent: bool, deployable: bool
) -> None:
    assert (device_id_problem(device_id) is None) is agent
    assert (policy_device_id_problem(device_id) is None) is deployable
    # The agent's list takes every id it can mirror (a list that ran before an update must start after it);
    # one no store can keep a calibration for is a note of the config's, with the fix. The stack refuses it.
    assert _config_accepts(**{"telemetry.devices": [device_id]}) is agent
    if agent:
        notes = listed_device_notes([device_id])
        assert (notes == []) is deployable, notes
        assert all("cannot have a calibration of its own" in note for note in notes), notes
    assert _store_accepts(tmp_path, device_id) is deployable
    assert _decoder_accepts(device_id) is agent
    if device_id == device_id.strip():  # the stack trims the items of `-c devices=a, b` before the rule
        assert _stack_accepts(devices=[device_id]) is deployable
    if agent:
        assert topic_filters("dt/lerobot", [device_id]) == [f"dt/lerobot/{device_id}/telemetry"]
        assert device_from_topic(telemetry_topic("dt/lerobot", device_id), "dt/lerobot") == device_id
    else:
        with pytest.raises(TopicError, match="not usable"):
            telemetry_topic("dt/lerobot", device_id)


@pytest.mark.parametrize(("prefix", "usable"), PREFIXES)
def test_every_part_applies_the_same_topic_prefix_rule(prefix: str, usable: bool) -> None:
    assert (topic_prefix_problem(prefix) is None) is usable
    assert _config_accepts(**{"telemetry.topic_prefix": prefix}) is usable
    if prefix:  # an empty context value means "the default" to the stack
        assert _stack_accepts(topicPrefix=prefix) is usable
    if usable:
        assert topic_filters(prefix, ["*"]) == [f"{prefix}/+/telemetry"]
    else:
        with pytest.raises(TopicError):
            topic_filters(prefix, ["*"])


def test_deployable_ids_are_a_subset_of_what_the_agent_accepts() -> None:
    for device_id, _, _ in DEVICE_IDS:
        if policy_device_id_problem(device_id) is None:
            assert device_id_problem(device_id) is None, device_id


@pytest.mark.parametrize(
    ("devices", "problem"),
    [
        ([], "empty"),
        (["*", "arm-001"], "mixes"),
        (["arm-001", "arm-001"], "names 'arm-001' more than once"),
        (["arm-001", "arm-002", "arm-003", "arm-002"], "names 'arm-002' more than once"),
        (["arm/1"], "not usable"),
    ],
)
def test_device_lists(devices: list[str], problem: str) -> None:
    with pytest.raises(TopicError, match=problem):
        check_devices(devices)
    assert not _config_accepts(**{"telemetry.devices": devices})
    if devices:  # an empty context value means "the default" to the stack
        assert not _stack_accepts(devices=devices)


@pytest.mark.parametrize(
    ("devices", "problem", "note"),
    [
        (["arm 1"], "cannot be listed", "cannot have a calibration of its own"),
        (["ARM-001", "arm-001"], "differ only in case", "'ARM-001' and 'arm-001', which differ only in case"),
        (["arm-001", "arm-002", "Arm-002"], "differ only in case", "'arm-002' and 'Arm-002'"),
    ],
)
def test_device_lists_a_deployment_refuses_and_the_agent_notes(
    tmp_path: Path, devices: list[str], problem: str, note: str
) -> None:
    """Ids the agent took before they were refused here: an upgraded host whose local config names them must
    start (a refusal exits 2, which systemd does not restart), so the agent says what it means instead."""
    with pytest.raises(TopicError, match=problem):
        check_deployed_devices(devices)
    assert not _stack_accepts(devices=devices)
    assert check_devices(devices) == tuple(devices)
    config_file = tmp_path / "agent.toml"
    config_file.write_text(f"[telemetry]\ndevices = {devices!r}\n".replace("'", '"'))
    notes = config_notes(config_file, load_config(config_file))
    assert any(note in n for n in notes), notes


def test_a_listed_id_the_stores_cannot_keep_says_why_and_what_to_do() -> None:
    with pytest.raises(TopicError) as raised:
        check_deployed_devices(["arm 9"])
    message = str(raised.value)
    assert "cannot be listed" in message and "letters, digits, '-', '_' or '.'" in message, message
    assert "deviceId" in message and 'devices = ["*"]' in message, message
    # A new user reads what to do, not "an id that is (its deviceId)".
    assert "Give the arm's edge an id that follows this rule (its deviceId) and list that" in message, message


def test_a_long_list_compares_each_id_with_its_case_folded_kin_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """check_devices compared each id with every id before it: 10,000 listed ids (telemetry.max_devices'
    bound) were 50 million comparisons, seconds of a start at each check. Counted here, not timed."""
    from twin.core import topics

    compared = 0

    def counting(device_id: str, others: Iterable[str]) -> str | None:
        nonlocal compared
        others = list(others)
        compared += len(others)
        assert compared <= 10_001, f"{compared} comparisons for 10,001 ids or fewer by {device_id}"
        return case_twin(device_id, others)

    monkeypatch.setattr(topics, "case_twin", counting)
    devices = [f"arm-{i:05d}" for i in range(10_000)]
    assert topics.check_deployed_devices(devices) == tuple(devices)
    compared = 0
    with pytest.raises(TopicError, match="'ARM-00007' and 'arm-00007', which differ only in case"):
        topics.check_deployed_devices(["ARM-00007", *devices])


def test_case_twins() -> None:
    assert case_twin("arm-001", ["ARM-001", "arm-002"]) == "ARM-001"
    assert case_twin("arm-001", ["arm-001", "arm-002"]) is None
    assert case_twin("so101.lab.7", []) is None


@pytest.mark.parametrize(
    ("topic", "device"),
    [
        ("dt/lerobot/arm-001/telemetry", "arm-001"),
        ("dt/lerobot/arm-001/status", None),
        ("dt/lerobot/a/b/telemetry", None),
        ("dt/lerobot//telemetry", None),
        ("other/arm-001/telemetry", None),
        ("dt/lerobotX/arm-001/telemetry", None),
        ("dt/lerobot", None),
    ],
)
def test_device_from_topic(topic: str, device: str | None) -> None:
    assert device_from_topic(topic, "dt/lerobot") == device
