"""Topic and device-id rules of the telemetry contract: the one home for what a device id and a topic may be.

The edge publishes each arm on `{prefix}/{device_id}/telemetry` (docs/telemetry.md), so a device id is one
MQTT topic level and the prefix is one or more. Every part of the project that accepts, builds or parses
these uses this module: the agent config, the subscriber's filters, the decoder's `device_id` check, the edge
simulator and the CDK stack's settings (`stacks/settings.py`), so a value one of them accepts is never refused
by another. Pure standard library: the stack imports it without MuJoCo or awscrt.

Two device-id rules, one narrower than the other:
- `device_id_problem`: what the agent mirrors from an edge (a usable topic level, 1..128 printable characters
  without `/`, `+`, `#` or surrounding spaces). An edge's id is not ours to choose, so with `devices = ["*"]`
  the agent mirrors any such id.
- `policy_device_id_problem`: an id that has a calibration of its own or a place in the host's IAM policy:
  the calibration stores (`twin calibration push`) and the stack's `-c devices=...`. It is a file name and
  an S3 key (`<store>/<device>.json`) and part of an IAM resource ARN, so it is letters, digits, `-`, `_` and
  `.` (not first: a hidden file; not ending in `.json`: a file's name typed as an arm's), at most 64.
  Every id this rule accepts is also accepted by the first (tests/test_topics.py checks both on one table).

The agent's own `telemetry.devices` takes any id of the first rule (`check_devices`): a list that ran before
must start after an update, whatever ids it names. One outside the second rule is mirrored without a
calibration of its own, and `listed_device_notes` says so, with the fix, where `twin run` and `twin config
check` show a config's notes. The stack's list takes the second rule only (`check_deployed_devices`).

Device ids are case-sensitive, as MQTT topics, S3 keys and IAM ARNs are: `ARM-001` and `arm-001` are two
arms. The stack refuses a list naming two ids that differ only in case (`case_twin`), the agent's notes name
them, and a push or a restore is refused for an id whose store already holds such a twin: a directory store
on a case-insensitive file system (macOS's and Windows's by default) would keep the two arms' calibrations
in one file.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable, Sequence

DEFAULT_TOPIC_PREFIX = "dt/lerobot"
TELEMETRY_SUFFIX = "telemetry"
# `devices = ["*"]`: the whole fleet under the prefix, subscribed with a single-level '+' wildcard.
ALL_DEVICES = "*"
DEVICE_ID_MAX_CHARS = 128
POLICY_DEVICE_ID_MAX_CHARS = 64
# MQTT's level separator and its two wildcards: a device id that held one would change what a topic means.
_TOPIC_SPECIAL = ("/", "+", "#")
# No '.' first: `.arm.json` is a hidden file (and write_atomically's temporary files start with '.').
_POLICY_DEVICE_ID_RE = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]*$")
# The calibration file's own suffix (twin.service.calibrations.SUFFIX): an id ending in it is a file's name.
_FILE_SUFFIX = ".json"
# Plain levels only: no wildcards, no '$' (broker-reserved topics such as $aws/ and $share/), nothing that
# needs quoting in an IAM ARN or a shell.
_PREFIX_LEVEL_RE = re.compile(r"^[A-Za-z0-9_.-]+$")

DEVICE_ID_RULE = (
    f"1..{DEVICE_ID_MAX_CHARS} printable characters without '/', '+', '#' (MQTT topic separators and "
    "wildcards) or surrounding spaces, and not '.' or '..', e.g. 'arm-001'"
)
POLICY_DEVICE_ID_RULE = (
    f"1..{POLICY_DEVICE_ID_MAX_CHARS} letters, digits, '-', '_' or '.', not starting with '.' nor ending in "
    "'.json' (it names the arm's calibration file and is part of an IAM resource ARN), e.g. 'arm-001' or "
    "'so101.lab.7'"
)
# What to do about an id that cannot have a calibration of its own.
_RENAME = (
    "Give the arm's edge an id that follows this rule (its deviceId) and list that, or mirror it through "
    'devices = ["*"], where it cannot have a calibration of its own either'
)
TOPIC_PREFIX_RULE = (
    "plain topic levels (letters, digits, '.', '_', '-') joined by '/', without wildcards or a leading or "
    f"trailing '/', e.g. '{DEFAULT_TOPIC_PREFIX}'"
)


class TopicError(ValueError):
    """A device id, topic prefix or device list breaks the topic rules; the message says which and why."""


def device_id_problem(device_id: object) -> str | None:
    """None when `device_id` may be a device id the agent mirrors, else what is wrong with it.

    Called once per message by the decoder: the common case (a short, clean id) costs a few comparisons.
    """
    if type(device_id) is not str or not device_id:
        return "a device id must be a non-empty string"
    if len(device_id) > DEVICE_ID_MAX_CHARS:
        return f"it is longer than {DEVICE_ID_MAX_CHARS} characters"
    if "/" in device_id or "+" in device_id or "#" in device_id:
        return "it holds an MQTT topic character ('/', '+' or '#')"
    if not device_id.isprintable():
        return "it holds unprintable characters"
    if device_id[0].isspace() or device_id[-1].isspace():
        return "it starts or ends with a space"
    if device_id in {".", ".."}:
        # A browser reads it as a path step: the arm's console page, /arm/.., would be the Fleet page.
        return "'.' and '..' are path steps to a browser (its console page could not be opened)"
    return None


def policy_device_id_problem(device_id: object) -> str | None:
    """None when a deployment may list `device_id` (stricter than `device_id_problem`), else the problem."""
    problem = device_id_problem(device_id)
    if problem is not None:
        return problem
    text = str(device_id)  # device_id_problem accepted it, so it is a string
    if (
        len(text) > POLICY_DEVICE_ID_MAX_CHARS
        or not _POLICY_DEVICE_ID_RE.match(text)
        or text.lower().endswith(_FILE_SUFFIX)
    ):
        return f"a listed device id must be {POLICY_DEVICE_ID_RULE}"
    return None


def case_twin(device_id: str, others: Iterable[str]) -> str | None:
    """The first of `others` that differs from `device_id` in case alone (`ARM-001` for `arm-001`), else None.

    Two such ids are two arms to MQTT and S3, but one file to a case-insensitive file system, and one arm
    to the person who typed them."""
    folded = device_id.casefold()
    return next((o for o in others if o != device_id and o.casefold() == folded), None)


def check_device_id(device_id: object) -> str:
    """`device_id` unchanged, or TopicError naming the value, the rule and an example."""
    problem = device_id_problem(device_id)
    if problem is not None:
        raise TopicError(f"device id {device_id!r} is not usable: {problem}; a device id is {DEVICE_ID_RULE}")
    return str(device_id)


def topic_prefix_problem(prefix: object) -> str | None:
    """None when `prefix` is a usable topic prefix, else what is wrong with it."""
    if type(prefix) is not str or not prefix:
        return "the topic prefix is empty"
    if not all(_PREFIX_LEVEL_RE.match(level) for level in prefix.split("/")):
        return f"a topic prefix must be {TOPIC_PREFIX_RULE}"
    return None


def check_topic_prefix(prefix: object) -> str:
    """`prefix` unchanged, or TopicError naming the value and the rule."""
    problem = topic_prefix_problem(prefix)
    if problem is not None:
        raise TopicError(f"topic prefix {prefix!r} is not usable: {problem}")
    return str(prefix)


def check_devices(devices: Sequence[str]) -> tuple[str, ...]:
    """A device list as the agent takes it: ids it can mirror (`device_id_problem`), each once, or ["*"]
    alone for the whole fleet. Ids no store can keep a calibration for are `listed_device_notes`'."""
    devices = tuple(devices)
    if not devices:
        raise TopicError(
            'the device list is empty: list device ids (e.g. ["arm-001"]) or ["*"] for the fleet'
        )
    if ALL_DEVICES in devices:
        if len(devices) > 1:
            raise TopicError(
                f'the device list {list(devices)} mixes "*" with ids; "*" alone already covers the fleet'
            )
        return devices
    for device in devices:
        check_device_id(device)
    if len(set(devices)) != len(devices):
        # Named: a walk's list of 40 ids said only that one of them was there twice.
        twice = sorted(d for d, n in Counter(devices).items() if n > 1)
        raise TopicError(
            f"the device list names {', '.join(map(repr, twice))} more than once ({len(devices)} ids); "
            "list each once"
        )
    return devices


def check_deployed_devices(devices: Sequence[str]) -> tuple[str, ...]:
    """A device list a deployment may name (the stack's): `check_devices`, each id also one a store and an
    IAM policy can take, and no two differing only in case; TopicError naming the first that is not."""
    devices = check_devices(devices)
    if devices == (ALL_DEVICES,):
        return devices
    for device in devices:
        problem = policy_device_id_problem(device)
        if problem is not None:
            raise TopicError(f"device id {device!r} cannot be listed: {problem}. {_RENAME}")
    twins = case_twins(devices)
    if twins:
        first, second = twins[0]
        raise TopicError(
            f"the device list names {first!r} and {second!r}, which differ only in case: device ids are "
            "case-sensitive, so they would be two arms, whose calibrations a case-insensitive file "
            "system keeps in one file; list the id each edge publishes as, once"
        )
    return devices


def case_twins(devices: Sequence[str]) -> list[tuple[str, str]]:
    """Each listed id that differs from an earlier one in case alone, with that one (earlier first)."""
    # Each id is compared with the listed ids it folds to only: against every earlier one, 10,000 ids
    # (telemetry.max_devices) took seconds at each check (the config's, then each pool plan's).
    folded: dict[str, str] = {}
    found = []
    for device in devices:
        twin = case_twin(device, (folded.setdefault(device.casefold(), device),))
        if twin is not None:
            found.append((twin, device))
    return found


def listed_device_notes(devices: Sequence[str]) -> list[str]:
    """What a valid agent device list holds that a person likely did not mean, one sentence each with the
    fix: ids no calibration store can keep a file for (mirrored uncalibrated), and ids differing only in
    case. Not refused: a list that ran before an update must still start after it."""
    if tuple(devices) == (ALL_DEVICES,):
        return []
    notes = [
        f"[telemetry] devices lists {device!r}, which cannot have a calibration of its own ({problem}), "
        f"so its twin is mirrored uncalibrated. {_RENAME}"
        for device in devices
        if (problem := policy_device_id_problem(device)) is not None
    ]
    notes += [
        f"[telemetry] devices lists {first!r} and {second!r}, which differ only in case: two arms to the "
        "agent (device ids are case-sensitive), but one calibration file in a directory store on a "
        "case-insensitive file system (macOS's, Windows's); if they are one arm, list the id its edge "
        "publishes as, once"
        for first, second in case_twins(devices)
    ]
    return notes


def telemetry_topic(prefix: str, device_id: str) -> str:
    """`{prefix}/{device_id}/telemetry`, the topic the edge publishes one arm on."""
    return f"{check_topic_prefix(prefix)}/{check_device_id(device_id)}/{TELEMETRY_SUFFIX}"


def topic_filters(prefix: str, devices: Sequence[str]) -> list[str]:
    """MQTT topic filters for `devices` under `prefix` (["*"] = every device, through a '+' wildcard)."""
    check_topic_prefix(prefix)
    devices = check_devices(devices)
    if devices == (ALL_DEVICES,):
        return [f"{prefix}/+/{TELEMETRY_SUFFIX}"]
    return [f"{prefix}/{device}/{TELEMETRY_SUFFIX}" for device in devices]


def device_from_topic(topic: str, prefix: str) -> str | None:
    """The device level of `{prefix}/{device}/telemetry`, or None for any other topic.

    Runs on the MQTT client's thread for every message, so it only slices; the decoder applies the device-id
    rule to the message's own `device_id` and checks that the two agree.
    """
    head_len = len(prefix) + 1
    if not topic.startswith(prefix) or topic[len(prefix) : head_len] != "/":
        return None
    if not topic.endswith("/" + TELEMETRY_SUFFIX):
        return None
    device = topic[head_len : -len(TELEMETRY_SUFFIX) - 1]
    if not device or "/" in device:
        return None
    return device
