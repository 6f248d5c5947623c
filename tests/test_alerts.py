"""Servo alarm e-mails: the publisher's batching, rate limit and retries (a list stands in for SNS), and the
agent publishing an alarm transition to the alarm topic, naming arm and servo. AWS cannot be reached from
here: moto stands in for SNS (and for an SQS queue subscribed to the topic, which reads the messages back)."""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from typing import Any

import boto3
import pytest
from conftest import AWS_TEST_REGION, NO_BROKER, wait_for
from moto import mock_aws
from twin.core.alarms import (
    SERVO_ERROR_BIT_ADVICE,
    WHAT_TO_DO,
    AlarmKind,
    AlarmState,
    AlarmView,
    Severity,
)
from twin.output.alerts import BODY_MAX, MAX_FLUSH_S, SUBJECT_MAX, Alert, AlertPublisher
from twin.robot import so101, sts3215
from twin.service.agent import AgentService, fleet_totals
from twin.service.config import ConfigError, load_config
from twin.service.shards import UNMIRRORED, alarm_info

ACK = "Open the console and press Acknowledge."


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def alert(action: str = "raised", *, device: str = "arm-003", joint: str = "elbow_flex", **kw: Any) -> Alert:
    fields: dict[str, Any] = {
        "alarm_id": f"{device}/{joint}/over_temperature_critical",
        "device": device,
        "joint": joint,
        "kind": "over_temperature_critical",
        "severity": "critical",
        "action": action,
        "state": {"raised": "ACTIVE", "cleared": "LATCHED", "acknowledged": "ACKNOWLEDGED"}.get(
            action, "NORMAL"
        ),
        "value": 67.0,
        "threshold": 65.0,
        "unit": "C",
        "message": f"{joint} servo at 67 C, near the 70 C cut-out (critical at 65 C)",
        "at": 1_795_000_000.0,
    }
    fields.update(kw)
    return Alert(**fields)


def publisher(sent: list[tuple[str, str]], clock: Clock, **kw: Any) -> AlertPublisher:
    return AlertPublisher(
        lambda subject, body: sent.append((subject, body)),
        agent_name="LabTwin",
        how_to_acknowledge=ACK,
        clock=clock,
        **kw,
    )


def unless_failing(sent: list[tuple[str, str]], failing: list[bool]) -> Callable[[str, str], None]:
    """A publish into `sent` that fails as SNS out of reach does while `failing[0]`."""

    def publish(subject: str, body: str) -> None:
        if failing[0]:
            raise ConnectionError("no route to SNS")
        sent.append((subject, body))

    return publish


def test_one_transition_is_one_message_that_says_what() -> None:
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock())
    assert p.flush() is False and sent == []  # nothing pending, nothing sent
    p.offer(alert())
    assert p.flush() is True
    ((subject, body),) = sent
    assert subject == "[LabTwin] CRITICAL arm-003 elbow_flex over_temperature_critical raised"
    assert "arm arm-003, elbow_flex servo (motor id 3)" in body
    assert "now ACTIVE; value 67 C, threshold 65 C" in body
    assert "near the 70 C cut-out" in body
    assert body.rstrip().endswith(f"How to acknowledge:\n{ACK}")
    assert p.counters().pending == 0 and p.flush() is False


def test_a_servo_error_says_its_bits_and_no_threshold() -> None:
    """A walk: the e-mail said "value 32 status, threshold 1 status" (and "threshold 0" when acknowledged)."""
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock())
    for action, threshold in (("raised", 1.0), ("acknowledged", 0.0)):
        p.offer(alert(action, kind="servo_error", value=33.0, threshold=threshold, unit="status"))
        assert p.flush() is True
        assert "; value status bits 33 (voltage, overload)\n" in sent[-1][1], sent[-1][1]
        assert "threshold" not in sent[-1][1]


def test_a_servo_error_that_cleared_before_its_message_is_advised_on_the_bits_that_raised_it() -> None:
    """A walk: an overload error raised and cleared within one flush was sent with the advice for every
    bit (check the supply, calibrate again, power-cycle), since its value had gone back to no bits."""
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock())
    error = {"kind": "servo_error", "joint": "wrist_flex", "threshold": 1.0, "unit": "status"}
    p.offer(alert("raised", value=32.0, **error))
    p.offer(alert("cleared", value=0.0, **error))
    assert p.flush() is True
    body = sent[-1][1]
    assert "What to do: the arm may not hold its pose" in body, body
    assert "Overload: reduce the payload" in body, body
    assert "Voltage" not in body, body
    # A review: of two raises in one message only the last was advised on; and an acknowledged error whose
    # condition lasts was advised on its raise's bits, not those it holds now.
    p.offer(alert("raised", value=32.0, **error))
    p.offer(alert("cleared", value=0.0, **error))
    p.offer(alert("raised", value=1.0, **error))
    p.offer(alert("cleared", value=0.0, **error))
    assert p.flush() is True
    body = sent[-1][1]
    assert "Overload: reduce the payload" in body and "Voltage: check the supply" in body, body
    p.offer(alert("raised", value=32.0, **error))
    p.offer(alert("acknowledged", value=33.0, **error, state="ACKNOWLEDGED"))
    assert p.flush() is True
    body = sent[-1][1]
    assert "Overload: reduce the payload" in body and "Voltage: check the supply" in body, body


def test_a_raised_alarm_says_what_to_do_at_the_arm_and_a_cleared_one_does_not() -> None:
    """A walk: the e-mail named the arm and the servo, and how to acknowledge, but not what to do about an
    over-current at 3 a.m.; that was only in docs/servo-health.md."""
    assert set(WHAT_TO_DO) == set(AlarmKind)
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock())
    p.offer(alert(kind="over_current", joint="gripper", value=2.9, threshold=1.3, unit="A"))
    assert p.flush() is True
    body = sent[-1][1]
    assert "arm arm-003, gripper servo (motor id 6), over_current" in body
    assert "\n  What to do: stop the motion; check for a collision or a trapped cable." in body, body
    for action in ("cleared", "acknowledged"):
        p.offer(alert(action, kind="over_current", joint="gripper", value=1.0, threshold=1.06, unit="A"))
        assert p.flush() is True
        assert "What to do" not in sent[-1][1], sent[-1][1]
    # The advice is the servo's: an elbow's overload is not the gripper's jaw, nor the other way round.
    p.offer(alert(kind="overload", joint="elbow_flex", value=96.0, threshold=90.0, unit="%"))
    assert p.flush() is True
    assert "What to do: reduce the payload" in sent[-1][1] and "jaw" not in sent[-1][1], sent[-1][1]
    p.offer(alert(kind="overload", joint="gripper", value=30.0, threshold=25.0, unit="%"))
    assert p.flush() is True
    assert "What to do: the jaw is squeezing" in sent[-1][1] and "payload" not in sent[-1][1], sent[-1][1]
    # Raised and cleared between two messages: LATCHED, but the servo went through it.
    p.offer(alert("raised"))
    p.offer(alert("cleared"))
    assert p.flush() is True
    assert "now LATCHED" in sent[-1][1] and "What to do: stop the task now" in sent[-1][1], sent[-1][1]


def test_a_flapping_servo_makes_one_message_per_flush_not_one_per_change() -> None:
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock())
    for action in ("raised", "cleared", "raised", "cleared", "raised"):
        p.offer(alert(action))
    p.offer(alert(joint="wrist_roll", severity="warning", kind="over_temperature"))
    assert p.flush()
    ((subject, body),) = sent
    assert subject.endswith("(+1 more)")
    assert "(5 changes since the last message: raised, cleared, raised, cleared, raised)" in body
    # The critical one first.
    assert body.index("elbow_flex servo (motor id 3)") < body.index("wrist_roll servo (motor id 5)")


def test_a_servo_flapping_through_an_outage_is_counted_and_its_last_changes_named() -> None:
    sent: list[tuple[str, str]] = []
    failing = [True]
    p = AlertPublisher(
        unless_failing(sent, failing), agent_name="LabTwin", how_to_acknowledge=ACK, clock=Clock()
    )
    for _ in range(1000):
        p.offer(alert("raised"))
        assert p.flush() is False
        p.offer(alert("cleared"))
    failing[0] = False
    assert p.flush()
    (line,) = [line for line in sent[0][1].splitlines() if "changes since" in line]
    assert line.endswith(
        "(2000 changes since the last message, the last 10: " + "raised, cleared, " * 4 + "raised, cleared)"
    ), line
    assert "\n  What to do: stop the task now" in sent[0][1]


def test_changes_during_a_publish_are_named_in_the_next_message() -> None:
    sent: list[tuple[str, str]] = []
    p: AlertPublisher

    def publish(subject: str, body: str) -> None:
        if not sent:
            for action in ("cleared", "acknowledged", "reset"):
                p.offer(alert(action))
        sent.append((subject, body))

    p = AlertPublisher(publish, agent_name="LabTwin", how_to_acknowledge=ACK, clock=Clock())
    for action in ("raised", "cleared") * 5 + ("raised",):
        p.offer(alert(action))
    assert p.flush() and p.flush()
    assert "(11 changes since the last message, the last 10: cleared, raised, " in sent[0][1]
    assert "(3 changes since the last message: cleared, acknowledged, reset)" in sent[1][1], sent[1][1]


def test_the_rate_limit_holds_transitions_back_and_sends_them_together_later() -> None:
    sent: list[tuple[str, str]] = []
    clock = Clock()
    p = publisher(sent, clock, burst=2, max_per_hour=60)  # two at once, then one a minute
    for i in range(2):
        p.offer(alert(device=f"arm-00{i}"))
        assert p.flush()
        clock.now += 5
    for i in range(3):
        p.offer(alert(device=f"arm-01{i}"))
        assert p.flush() is False  # held back, not dropped
        clock.now += 5
    assert p.counters().delayed == 3 and p.counters().pending == 3
    clock.now += 60
    assert p.flush()
    assert len(sent) == 3 and all(f"arm arm-01{i}" in sent[-1][1] for i in range(3))


def test_the_stop_sends_what_the_rate_limit_held_back() -> None:
    """A restart never sends this run's transitions again, so the stop's flush may not leave them held."""
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock(), burst=1, max_per_hour=1)
    p.offer(alert("raised"))
    assert p.flush()
    p.offer(alert("cleared"))
    assert p.flush() is False  # the limit is used up
    p.stop()
    assert len(sent) == 2 and "CRITICAL cleared: arm arm-003" in sent[1][1], sent
    assert p.counters().pending == 0


def test_what_the_stop_could_not_send_is_logged(caplog: pytest.LogCaptureFixture) -> None:
    def publish(subject: str, body: str) -> None:
        raise ConnectionError("no route to SNS")

    p = AlertPublisher(publish, agent_name="LabTwin", how_to_acknowledge=ACK, clock=Clock())
    p.offer(alert("raised"))
    p.offer(alert("raised", device="arm-004"))
    with caplog.at_level(logging.WARNING, logger="twin.output.alerts"):
        p.stop()
    said = [r.getMessage() for r in caplog.records if getattr(r, "event", "") == "alerts_unsent"]
    assert said == [
        "2 alarm(s) changed but were not notified (ConnectionError: no route to SNS): the console's Events "
        "page lists them"
    ], said


def test_a_burst_of_warnings_past_max_pending_never_pushes_a_critical_alarm_out() -> None:
    """Beyond `max_pending` alarms one is only counted: it was the oldest, so a critical alarm that came
    first became a bare count under a burst of model-mismatch warnings, and the subject a warning's."""
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock(), max_pending=3)
    p.offer(alert(device="arm-001"))
    for arm in (2, 3, 4):
        p.offer(alert(device=f"arm-00{arm}", severity="warning", kind="model_mismatch", alarm_id=f"w{arm}"))
    assert p.flush()
    subject, body = sent[0]
    assert subject == "[LabTwin] CRITICAL arm-001 elbow_flex over_temperature_critical raised (+3 more)"
    assert "arm arm-001" in body and "arm arm-002" not in body and "arm arm-004" in body, body
    assert "... and 1 more alarm(s) changed" in body
    # Every waiting alarm critical: a warning is the one counted, a critical one pushes the oldest out.
    sent.clear()
    p = publisher(sent, Clock(), max_pending=2)
    for arm in (1, 2):
        p.offer(alert(device=f"arm-00{arm}"))
    p.offer(alert(device="arm-003", severity="warning", kind="model_mismatch", alarm_id="w3"))
    p.offer(alert(device="arm-004"))
    assert p.flush()
    body = sent[0][1]
    assert "arm arm-002" in body and "arm arm-004" in body and "arm arm-003" not in body, body
    assert "... and 2 more alarm(s) changed" in body


def test_a_failed_publish_keeps_the_batch_for_the_next_flush() -> None:
    sent: list[tuple[str, str]] = []
    failing = [True]
    p = AlertPublisher(
        unless_failing(sent, failing), agent_name="LabTwin", how_to_acknowledge=ACK, clock=Clock()
    )
    p.offer(alert())
    assert p.flush() is False
    assert p.counters().failures == 1 and "no route to SNS" in p.counters().last_error
    failing[0] = False
    assert p.flush() and len(sent) == 1


def test_transitions_during_a_publish_go_in_the_next_message() -> None:
    sent: list[tuple[str, str]] = []
    p: AlertPublisher

    def publish(subject: str, body: str) -> None:
        if not sent:
            p.offer(alert("cleared"))  # arrives while the first message is on its way
        sent.append((subject, body))

    p = AlertPublisher(publish, agent_name="LabTwin", how_to_acknowledge=ACK, clock=Clock())
    p.offer(alert("raised"))
    assert p.flush() and p.flush()
    assert "raised: arm arm-003" in sent[0][1] and "cleared: arm arm-003" in sent[1][1]
    assert p.counters().pending == 0


def test_subjects_keep_to_snss_rules() -> None:
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock())
    p.offer(alert(device="a" * 120 + "é"))
    p.flush()
    subject = sent[0][0]
    assert len(subject) <= SUBJECT_MAX and subject.isascii() and "\n" not in subject


def test_a_long_device_id_is_shortened_so_the_subject_still_names_the_servo() -> None:
    """A walk: a valid 64-character device id (and a 24-character one with a second alarm) cut the subject
    at 100 characters before the servo ("... aaaa elbow_...") or the count of other alarms."""
    for device, more in (("lab2-" + "x" * 51 + "-left-07", 0), ("so101-follower-lab2-left", 1)):
        sent: list[tuple[str, str]] = []
        p = publisher(sent, Clock())
        p.offer(alert(device=device))
        if more:
            p.offer(alert(device=device, joint="gripper"))
        p.flush()
        subject = sent[0][0]
        assert len(subject) <= SUBJECT_MAX, subject
        tail = " elbow_flex over_temperature_critical raised" + (" (+1 more)" if more else "")
        assert subject.endswith(tail), subject
        assert subject.startswith("[LabTwin] CRITICAL " + device[:5]), subject
        assert "-left" in subject, subject  # the id's end, where a fleet's ids differ


def test_a_transition_goes_out_on_the_next_flush_which_comes_within_10_s() -> None:
    """The 10 s is a design property: the agent collects events every 0.5 s and the publisher flushes every
    flush_s, which may not exceed 9.5 s; the config refuses more."""
    assert MAX_FLUSH_S <= 9.5
    with pytest.raises(ValueError, match="within 10 s"):
        AlertPublisher(lambda _s, _b: None, agent_name="x", how_to_acknowledge="", flush_s=10.0)
    with pytest.raises(ConfigError, match=r"alerts.flush_s = 10 must be in \(0, 9.5\]"):
        load_config(None, {"alerts.flush_s": 10.0})
    with pytest.raises(ConfigError, match="not an SNS topic ARN"):
        load_config(None, {"alerts.topic_arn": "alarms"})


# --- the agent, with moto standing in for SNS --------------------------------------------------------------


@pytest.fixture
def topic(aws_env: None) -> Any:
    """A moto SNS topic with an SQS queue subscribed to it, from which the test reads what was published."""
    with mock_aws():
        sns = boto3.client("sns", region_name=AWS_TEST_REGION)
        sqs = boto3.client("sqs", region_name=AWS_TEST_REGION)
        arn = sns.create_topic(Name="so101-twin-alarms")["TopicArn"]
        queue = sqs.create_queue(QueueName="inbox")["QueueUrl"]
        queue_arn = sqs.get_queue_attributes(QueueUrl=queue, AttributeNames=["QueueArn"])["Attributes"][
            "QueueArn"
        ]
        sns.subscribe(TopicArn=arn, Protocol="sqs", Endpoint=queue_arn)

        def received() -> list[dict[str, Any]]:
            messages = sqs.receive_message(QueueUrl=queue, MaxNumberOfMessages=10).get("Messages", [])
            for m in messages:
                sqs.delete_message(QueueUrl=queue, ReceiptHandle=m["ReceiptHandle"])
            return [json.loads(m["Body"]) for m in messages]

        yield arn, received


def mismatches(p: AlertPublisher, arms: int) -> None:
    """Every still servo of `arms` arms mismatching at once (another edge publishing under their ids)."""
    text = (
        "wrist_flex servo (motor id 4) load differs from the model's holding load (8.6 %) by 81.4 points "
        "while still (alarm at 15): contact, a payload or a failing servo"
    )
    for arm in range(arms):
        for joint in so101.JOINT_NAMES[:5]:
            p.offer(
                alert(
                    device=f"arm-{arm:03d}",
                    joint=joint,
                    alarm_id=f"arm-{arm:03d}/{joint}/model_mismatch",
                    kind="model_mismatch",
                    severity="warning",
                    unit="% points",
                    message=text,
                )
            )
    p.offer(alert(device="arm-099", at=1_795_000_100.0))  # the critical one comes last


def test_a_fleets_burst_goes_out_in_messages_sns_accepts_and_names_every_alarm(topic: Any) -> None:
    """SNS refuses a message over 256 KiB (moto as well): 500 alarms in one were refused at every flush, so
    nothing was sent again. Those that do not fit wait for the next message, the critical one first."""
    arn, received = topic
    sns = boto3.client("sns", region_name=AWS_TEST_REGION)
    p = AlertPublisher(
        lambda subject, body: sns.publish(TopicArn=arn, Subject=subject, Message=body),
        agent_name="LabTwin",
        how_to_acknowledge=ACK,
        clock=Clock(),
    )
    mismatches(p, 99)  # 496 alarms: under max_pending (500), so every one is named
    assert p.flush() and p.flush()
    assert p.counters().failures == 0 and p.counters().pending == 0, p.counters()
    bodies = [m["Message"] for m in received() + received()]
    assert len(bodies) == 2 and bodies[0].startswith("CRITICAL raised: arm arm-099"), bodies[0][:80]
    assert "more alarm(s) changed: too many for one message, they follow in the next." in bodies[0]
    named = [line for body in bodies for line in body.splitlines() if line.startswith("  alarm id ")]
    assert len(named) == len(set(named)) == 496


def test_the_stop_sends_a_burst_too_big_for_one_message_in_several() -> None:
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock())
    mismatches(p, 99)
    p.stop()
    assert len(sent) == 2 and p.counters().pending == 0, (len(sent), p.counters())


def test_the_stop_begins_no_publish_past_its_timeout() -> None:
    """A review: the stop's sends after the thread's join had no deadline, so a slow SNS (each publish
    taking seconds through boto's retries) held the agent's stop past its 60 s budget and systemd's 90 s.
    Here each publish takes 6 s of the injected clock: a 10 s stop begins two, and says what is left."""
    sent: list[tuple[str, str]] = []
    clock = Clock()

    def slow(subject: str, body: str) -> None:
        clock.now += 6.0
        sent.append((subject, body))

    p = AlertPublisher(slow, agent_name="LabTwin", how_to_acknowledge=ACK, clock=clock, burst=1)
    for arm in range(400):  # about 800 kB of alarms: four messages at least
        p.offer(alert(device=f"arm-{arm:03d}", message="over its line " * 140))
    p.stop(timeout=10.0)
    assert len(sent) == 2 and p.counters().pending > 0, (len(sent), p.counters())


def test_an_alarm_with_a_message_beyond_reason_still_fits_an_sns_message() -> None:
    """A review: the first alarm always goes into a message, so one whose text alone passed SNS's 256 KiB
    was refused at every flush and no alarm e-mail went out again."""
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock())
    p.offer(alert(message="x" * 300_000))
    assert p.flush() is True
    ((_, body),) = sent
    assert len(body.encode()) < BODY_MAX and "x" * 2000 + " ..." in body, len(body)


def hot(device: str, ts: int, temp: float) -> bytes:
    joints = {name: {"position": 2048, "temp": 35} for name in so101.JOINT_NAMES}
    joints["elbow_flex"]["temp"] = temp
    return json.dumps({"device_id": device, "timestamp": ts, "joints": joints}).encode()


def hot_arm_settings(**overrides: Any) -> dict[str, Any]:
    """An agent of arm-003 alone, fed through feed() (no broker answers), whose heat alarms raise at once."""
    return {
        "broker.url": NO_BROKER,
        "http.listen": "127.0.0.1:0",
        "telemetry.devices": ["arm-003"],
        "telemetry.units": "ticks",
        "alarms.temperature_raise_after_s": 0.0,
        **overrides,
    }


def agent_with_topic(arn: str, workers: int = 1, **overrides: Any) -> AgentService:
    settings = hot_arm_settings(
        **{
            "alerts.topic_arn": arn,
            "alerts.region": AWS_TEST_REGION,
            "alerts.flush_s": 1.0,
            "cloudwatch.agent_name": "LabTwin",
            **overrides,
        }
    )
    return AgentService(load_config(None, settings), workers=workers)


def test_an_alarm_transition_reaches_sns_as_one_message_naming_arm_and_servo(topic: Any) -> None:
    """Done when: an alarm transition produces one SNS-bound message naming the arm and the servo, published
    on the flush after it (moto stands in for SNS). 68 C raises the warning (60 C) and the critical alarm
    (65 C) together; warnings are off by default, so only the critical one is in it."""
    arn, received = topic
    agent = agent_with_topic(arn)
    agent.start()
    try:
        agent.feed("dt/lerobot/arm-003/telemetry", hot("arm-003", int(time.time() * 1000), 68))
        messages = wait_for(received, 60, "the alarm at the topic's queue", interval=0.2)
        assert len(messages) == 1
        (notification,) = messages
        assert (
            notification["Subject"]
            == "[LabTwin] CRITICAL arm-003 elbow_flex over_temperature_critical raised"
        )
        body = notification["Message"]
        assert "arm arm-003, elbow_flex servo (motor id 3)" in body
        assert "now ACTIVE; value 68 C, threshold 65 C" in body
        assert "How to acknowledge:" in body and "/alarms/<alarm id>/ack" in body
        # Read away from the host: the console through the port forward, first.
        assert "run `twin instance console` on your machine" in body, body
        assert "over_temperature raised" not in body  # the warning: not sent unless asked for
        # Acknowledging is a transition too; it goes out on the next flush.
        agent.acknowledge_alarm("arm-003/elbow_flex/over_temperature_critical")
        (ack,) = wait_for(received, 60, "the acknowledgement at the queue", interval=0.2)
        assert ack["Subject"].endswith("elbow_flex over_temperature_critical acknowledged")
        assert "now ACKNOWLEDGED" in ack["Message"]
    finally:
        agent.stop()
    assert received() == []


def test_warnings_go_too_when_asked(topic: Any) -> None:
    arn, received = topic
    agent = agent_with_topic(arn, **{"alerts.warnings": True})
    agent.start()
    try:
        agent.feed("dt/lerobot/arm-003/telemetry", hot("arm-003", int(time.time() * 1000), 68))
        (notification,) = wait_for(received, 60, "the alarms at the queue", interval=0.2)
    finally:
        agent.stop()
    assert notification["Subject"].endswith("(+1 more)")
    said = notification["Message"]
    assert "WARNING raised: arm arm-003, elbow_flex servo (motor id 3), over_temperature" in said


def test_a_publish_that_keeps_failing_shows_in_the_agents_sinks(topic: Any) -> None:
    """SNS refusing every publish (here a topic that is not there; on the host the role or the topic's key)
    held every servo alarm e-mail back with only a log line to say so: /state shows it as an output."""
    arn, _received = topic
    agent = agent_with_topic(arn + "-deleted")
    agent.start()
    try:
        agent.feed("dt/lerobot/arm-003/telemetry", hot("arm-003", int(time.time() * 1000), 68))

        def failing() -> Any:
            found = [s for s in agent.state().agent.sinks if s.name == "alerts"]
            return found[0] if found and found[0].errors >= 2 else None

        alerts = wait_for(failing, 60, "two failed publishes in agent.sinks", interval=0.2)
        # ... and in the CloudWatch totals, whose AlertPublishFailures pages (AlertsUnsent).
        totals = fleet_totals(agent.state(), 10.0)
    finally:
        agent.stop()
    assert alerts.pending >= 1 and alerts.delivered == 0 and alerts.dropped == 0
    assert "NotFound" in alerts.last_error, alerts
    assert totals.alert_publish_failures >= alerts.errors >= 2, totals


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_a_start_that_fails_after_a_message_arrived_sends_its_alert_or_counts_it(
    topic: Any, workers: int, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The subscription runs while the mirrors start, so a message can be queued when a later step of the
    start fails. In process, the mirror handles its queue as it stops: the alarm it raises goes to SNS
    although the publisher never started. A worker process is never handed its queue: the message is
    counted in the stop's line, not dropped unsaid."""
    arn, received = topic
    agent = agent_with_topic(arn, workers)

    def queue_one_then_fail(self: AgentService) -> None:
        self.feed("dt/lerobot/arm-003/telemetry", hot("arm-003", int(time.time() * 1000), 68))
        raise OSError("the state file's disk went away")

    monkeypatch.setattr(AgentService, "_restore_state_file", queue_one_then_fail)
    failing = pytest.raises(OSError, match="went away")
    with caplog.at_level(logging.INFO, logger="twin.service.agent"), failing:
        agent.start()
    agent.stop()  # nothing left to do: the failed start stopped what it launched
    unmirrored = sum(r.unwritten.get(UNMIRRORED, 0) for r in agent.stop_reports.values() if r is not None)
    stopped = [r.getMessage() for r in caplog.records if r.getMessage().startswith("agent stopped")]
    if workers == 1:
        (notification,) = wait_for(received, 60, "the alarm at the topic's queue", interval=0.2)
        assert notification["Subject"].endswith("arm-003 elbow_flex over_temperature_critical raised")
        assert unmirrored == 0 and stopped == ["agent stopped"], stopped
    else:
        assert unmirrored == 1 and received() == []
        assert stopped == [f"agent stopped; not everything was written: 1 {UNMIRRORED}"], stopped


def test_a_servo_errors_advice_is_for_the_bits_its_servo_set() -> None:
    """A read-through: every servo error's e-mail listed the advice for all six bits, so a voltage error
    also told the person at the arm to calibrate again."""
    sent: list[tuple[str, str]] = []
    p = publisher(sent, Clock())
    p.offer(alert(kind="servo_error", value=1.0, threshold=1.0, unit="status"))  # voltage
    assert p.flush() is True
    advice = sent[-1][1].split("What to do: ", 1)[1].split("\n", 1)[0]
    assert advice.startswith("the arm may not hold its pose: stop the motion and support it."), advice
    assert "Voltage: check the supply" in advice and "calibrate" not in advice, advice
    p.offer(alert(kind="servo_error", joint="wrist_flex", value=17.0, threshold=1.0, unit="status"))
    assert p.flush() is True
    advice = sent[-1][1].split("What to do: ", 1)[1].split("\n", 1)[0]
    assert "Voltage:" in advice and "Angle: " in advice and "Overload" not in advice, advice
    # The gripper's overload bit is its jaw, as its overload alarm's advice says.
    p.offer(alert(kind="servo_error", joint="gripper", value=32.0, threshold=1.0, unit="status"))
    assert p.flush() is True
    advice = sent[-1][1].split("What to do: ", 1)[1].split("\n", 1)[0]
    assert "Overload: the jaw is squeezing" in advice and "payload" not in advice, advice
    # Every bit has its own advice.
    assert set(SERVO_ERROR_BIT_ADVICE) == set(sts3215.STATUS_BITS)
    # The console's Arm page and GET /alarms say the same while the bits are set; with none set (the
    # condition gone, the alarm waiting to clear or latched) it is for the bits its raise message names, and
    # covers every bit only if it names none.
    view = AlarmView(
        alarm_id="arm-003/elbow_flex/servo_error",
        device="arm-003",
        joint="elbow_flex",
        kind=AlarmKind.SERVO_ERROR,
        severity=Severity.CRITICAL,
        state=AlarmState.ACTIVE,
        value=32.0,  # the overload bit
        threshold=1.0,
        unit="status",
        since=0.0,
        raised=1,
        message="elbow_flex servo reports an error of its own: overload",
    )
    advice = alarm_info(view, 0.0, 0.0).advice
    assert "Overload: reduce the payload" in advice and "Voltage" not in advice, advice
    assert alarm_info(dataclasses.replace(view, value=0.0), 0.0, 0.0).advice == WHAT_TO_DO["servo_error"]
