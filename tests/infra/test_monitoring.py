"""CloudWatch alarms and their SNS topic in the synthesized template (cdk-nag runs on every synth).

The alarms watch the metrics the agent writes as EMF (agents/twin/output/emf.py): the names, namespace and
dimensions are checked against the agent's own constants, so the two cannot drift apart.
"""

from __future__ import annotations

from typing import Any

import pytest
from aws_cdk.assertions import Match
from twin.output import emf

from stacks import monitoring

from .synth import Synth


def alarm(synth: Synth, description_start: str) -> dict[str, Any]:
    found = [
        a["Properties"]
        for a in synth.resources("AWS::CloudWatch::Alarm").values()
        if a["Properties"]["AlarmDescription"].startswith(description_start)
    ]
    assert len(found) == 1, found
    return found[0]


def topic_ref(synth: Synth) -> dict[str, str]:
    (logical_id,) = synth.resources("AWS::SNS::Topic")
    return {"Ref": logical_id}


def test_names_agree_with_the_agents_emf() -> None:
    assert monitoring.NAMESPACE == emf.NAMESPACE
    assert monitoring.AGENT_DIMENSION == emf.AGENT_DIMENSION
    assert monitoring.SEVERITY_DIMENSION == emf.SEVERITY_DIMENSION
    stack_side = (
        monitoring.MESSAGES_DROPPED,
        monitoring.SINK_DROPS,
        monitoring.WORKER_RESTARTS,
        monitoring.HISTORY_ROWS_DROPPED,
        monitoring.HISTORY_COMMIT_FAILURES,
        monitoring.HISTORY_LAG,
    )
    assert stack_side == emf.LOSS_METRICS


def test_topic_is_encrypted_tls_only_and_cloudwatch_may_publish(synth_default: Synth) -> None:
    t = synth_default.template
    t.resource_count_is("AWS::SNS::Topic", 1)
    t.resource_count_is("AWS::SNS::Subscription", 0)  # no alarmEmail by default
    topic = synth_default.one("AWS::SNS::Topic")["Properties"]
    key_id = topic["KmsMasterKeyId"]["Fn::GetAtt"][0]
    key = synth_default.json["Resources"][key_id]["Properties"]
    assert key["EnableKeyRotation"] is True
    key_statements = key["KeyPolicy"]["Statement"]
    assert any(
        s.get("Principal") == {"Service": "cloudwatch.amazonaws.com"}
        and set(s["Action"]) == {"kms:Decrypt", "kms:GenerateDataKey*"}
        for s in key_statements
    )
    policy = synth_default.one("AWS::SNS::TopicPolicy")["Properties"]["PolicyDocument"]["Statement"]
    assert any(
        s["Effect"] == "Deny" and s["Condition"] == {"Bool": {"aws:SecureTransport": "false"}} for s in policy
    )
    assert any(
        s["Effect"] == "Allow" and s["Principal"] == {"Service": "cloudwatch.amazonaws.com"} for s in policy
    )
    outputs = synth_default.json["Outputs"]
    assert outputs["AlarmTopic"]["Value"] == topic_ref(synth_default)


def test_alarm_email_subscribes_to_the_topic(synth_factory: Any) -> None:
    synth = synth_factory(alarmEmail="ops@example.com")
    synth.template.has_resource_properties(
        "AWS::SNS::Subscription",
        {"Protocol": "email", "Endpoint": "ops@example.com", "TopicArn": topic_ref(synth)},
    )


def test_every_alarm_notifies_the_topic_on_alarm_and_ok(synth_default: Synth) -> None:
    synth_default.template.resource_count_is("AWS::CloudWatch::Alarm", 9)
    ref = topic_ref(synth_default)
    for props in synth_default.resources("AWS::CloudWatch::Alarm").values():
        assert props["Properties"]["AlarmActions"] == [ref]
        assert props["Properties"]["OKActions"] == [ref]


def test_agent_silent_alarms_on_a_missing_heartbeat(synth_default: Synth) -> None:
    props = alarm(synth_default, "The so101-twin agent")
    assert props["MetricName"] == "AgentUp"
    assert props["Namespace"] == emf.NAMESPACE
    assert props["Dimensions"] == [{"Name": "Agent", "Value": "So101TwinStack"}]
    assert (props["Statistic"], props["Period"]) == ("SampleCount", 60)
    assert (props["ComparisonOperator"], props["Threshold"]) == ("LessThanThreshold", 1)
    assert (props["EvaluationPeriods"], props["DatapointsToAlarm"]) == (3, 3)
    assert props["TreatMissingData"] == "breaching"


def test_arms_stale_counts_stale_and_offline_arms(synth_default: Synth) -> None:
    props = alarm(synth_default, "At least one arm")
    queries = {q["Id"]: q for q in props["Metrics"]}
    expression = next(q for q in props["Metrics"] if "Expression" in q)
    assert expression["Expression"] == "stale + offline" and expression["ReturnData"] is True
    for query_id, name in (("stale", "DevicesStale"), ("offline", "DevicesOffline")):
        stat = queries[query_id]["MetricStat"]
        assert stat["Metric"]["MetricName"] == name
        assert stat["Metric"]["Dimensions"] == [{"Name": "Agent", "Value": "So101TwinStack"}]
        assert (stat["Stat"], stat["Period"]) == ("Maximum", 60)
    assert props["ComparisonOperator"] == "GreaterThanOrEqualToThreshold"
    assert (props["Threshold"], props["EvaluationPeriods"]) == (1, 3)
    assert props["TreatMissingData"] == "notBreaching"


def test_critical_servo_alarm_watches_critical_active_alarms(synth_default: Synth) -> None:
    synth_default.template.has_resource_properties(
        "AWS::CloudWatch::Alarm",
        {
            "MetricName": "ActiveAlarms",
            "Namespace": "SO101Twin",
            "Dimensions": Match.array_equals(
                [{"Name": "Agent", "Value": "So101TwinStack"}, {"Name": "Severity", "Value": "critical"}]
            ),
            "Statistic": "Maximum",
            "Threshold": 1,
            "ComparisonOperator": "GreaterThanOrEqualToThreshold",
            "TreatMissingData": "notBreaching",
        },
    )


def test_the_agent_name_follows_the_stack_name(synth_factory: Any) -> None:
    synth = synth_factory(stackName="LabTwin")
    props = alarm(synth, "The so101-twin agent")
    assert props["Dimensions"] == [{"Name": "Agent", "Value": "LabTwin"}]


def _alarm_on(synth: Synth, metric_name: str) -> dict[str, Any]:
    found = [
        a["Properties"]
        for a in synth.resources("AWS::CloudWatch::Alarm").values()
        if a["Properties"].get("MetricName") == metric_name
    ]
    assert len(found) == 1, found
    return found[0]


@pytest.mark.parametrize(
    "name",
    [emf.MESSAGES_DROPPED, emf.SINK_DROPS, emf.WORKER_RESTARTS, emf.HISTORY_ROWS_DROPPED],
)
def test_any_loss_in_a_minute_alarms(synth_default: Synth, name: str) -> None:
    props = _alarm_on(synth_default, name)
    assert props["Namespace"] == emf.NAMESPACE
    assert props["Dimensions"] == [{"Name": "Agent", "Value": "So101TwinStack"}]
    assert (props["Statistic"], props["Period"]) == ("Sum", 60)
    assert (props["ComparisonOperator"], props["Threshold"]) == ("GreaterThanOrEqualToThreshold", 1)
    assert props["EvaluationPeriods"] == 1 and props["TreatMissingData"] == "notBreaching"


def test_history_commit_failures_alarm_after_five_minutes_of_them(synth_default: Synth) -> None:
    props = _alarm_on(synth_default, emf.HISTORY_COMMIT_FAILURES)
    assert (props["Statistic"], props["Threshold"]) == ("Sum", 1)
    assert (props["EvaluationPeriods"], props["DatapointsToAlarm"]) == (5, 5)


def test_history_lag_alarms_over_a_minute_for_two(synth_default: Synth) -> None:
    props = _alarm_on(synth_default, emf.HISTORY_LAG)
    assert (props["Statistic"], props["Period"]) == ("Maximum", 60)
    assert (props["ComparisonOperator"], props["Threshold"]) == ("GreaterThanOrEqualToThreshold", 60)
    assert (props["EvaluationPeriods"], props["DatapointsToAlarm"]) == (2, 2)
    assert props["TreatMissingData"] == "notBreaching"
