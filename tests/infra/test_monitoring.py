"""CloudWatch alarms and their SNS topic in the synthesized template (cdk-nag runs on every synth).

The alarms watch the metrics the agent writes as EMF (agents/twin/output/emf.py): the names, namespace and
dimensions are checked against the agent's own constants, so the two cannot drift apart.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
from typing import Any

import pytest
from twin.output import emf
from twin.output.history import HistorySettings

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


def alarms_described(synth: Synth) -> list[str]:
    return [a["Properties"]["AlarmDescription"] for a in synth.resources("AWS::CloudWatch::Alarm").values()]


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
    assert monitoring.SUBSCRIPTIONS_REFUSED == emf.SUBSCRIPTIONS_REFUSED
    assert monitoring.HISTORY_COMMITS_FAILING == emf.HISTORY_COMMITS_FAILING
    assert monitoring.BROKER_DISCONNECTED == emf.BROKER_DISCONNECTED
    assert monitoring.LOSS_PERCENT == emf.LOSS_PERCENT
    assert monitoring.WORST_ARM_LOSS_PERCENT == emf.WORST_ARM_LOSS_PERCENT
    assert monitoring.INTERNAL_LATENCY_P99 == emf.INTERNAL_LATENCY_P99
    assert monitoring.DEVICE_LIMIT_REFUSALS == emf.DEVICE_LIMIT_REFUSALS
    assert monitoring.EMF_WRITE_FAILURES == emf.EMF_WRITE_FAILURES


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
    # Servo alarms reach the topic from the host directly (test_host_publishes_servo_alarms_to_the_topic_
    # only), not through a CloudWatch alarm on a once-a-minute metric: agent silent, arms stale, the six
    # loss alarms, a refused subscription, the broker out of reach, the device limit, the fleet's and one
    # arm's messages lost, most messages refused, alarm e-mails unsent, metrics unwritten, the host scripts'
    # three.
    synth_default.template.resource_count_is("AWS::CloudWatch::Alarm", 20)
    ref = topic_ref(synth_default)
    for props in synth_default.resources("AWS::CloudWatch::Alarm").values():
        assert props["Properties"]["AlarmActions"] == [ref]
        assert props["Properties"]["OKActions"] == [ref]


def queries(props: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {q["Id"]: q for q in props["Metrics"]}


def test_agent_silent_pages_only_while_the_host_runs(synth_default: Synth) -> None:
    """A stopped instance reports no CPU: the expression is 0 then, so a stop (by hand or by schedule) does
    not page; a running host whose agent sends no heartbeat for 5 minutes does."""
    props = alarm(synth_default, "The so101-twin agent")
    q = queries(props)
    expression = next(v for v in q.values() if "Expression" in v)
    assert expression["Expression"] == "IF(FILL(running, 0) > 0 AND FILL(up, 0) < 1, 1, 0)"
    up = q["up"]["MetricStat"]
    assert up["Metric"]["MetricName"] == "AgentUp" and up["Metric"]["Namespace"] == emf.NAMESPACE
    assert up["Metric"]["Dimensions"] == [{"Name": "Agent", "Value": "So101TwinStack"}]
    assert (up["Stat"], up["Period"]) == ("SampleCount", 60)
    running = q["running"]["MetricStat"]
    assert (running["Metric"]["Namespace"], running["Metric"]["MetricName"]) == ("AWS/EC2", "CPUUtilization")
    (instance,) = synth_default.resources("AWS::EC2::Instance")
    assert running["Metric"]["Dimensions"] == [{"Name": "InstanceId", "Value": {"Ref": instance}}]
    assert (props["ComparisonOperator"], props["Threshold"]) == ("GreaterThanOrEqualToThreshold", 1)
    assert (props["EvaluationPeriods"], props["DatapointsToAlarm"]) == (5, 5)
    assert props["TreatMissingData"] == "notBreaching"


def test_agent_silent_names_a_full_disk(synth_default: Synth) -> None:
    """A full disk keeps the agent from writing its EMF file while it runs on, so the heartbeat stops with
    the agent and the CloudWatch agent both up: a walk's person would look for a dead process."""
    description = alarm(synth_default, "The so101-twin agent")["AlarmDescription"]
    assert "disk is full" in description and "df -h /var/log" in description
    # A review: a host cut off from the network sends no metric at all, so this alarm, not the broker's
    # (whose description named the network), is the one that pages for it.
    assert "the host's network is cut" in description, description
    broker = next(a for a in alarms_described(synth_default) if "IoT Core down" in a)
    assert "pages as AgentSilent instead" in broker and "network or DNS" not in broker, broker


def test_agent_silent_is_armed_by_the_host_once_it_is_up(synth_default: Synth) -> None:
    """A first boot installs for longer than 5 minutes before the agent runs: the alarm is created with its
    actions off, under a fixed name, and the host's role may turn on this alarm's actions and no other's
    (the boot does it after verifying, every start again: tests/infra/test_bootstrap.py). Every other alarm
    pages from the start."""
    from .test_stack import policy_statements, statement

    props = alarm(synth_default, "The so101-twin agent")
    assert props["ActionsEnabled"] is False
    assert props["AlarmName"] == "So101TwinStack-AgentSilent"
    others = [
        p["Properties"]
        for p in synth_default.resources("AWS::CloudWatch::Alarm").values()
        if p["Properties"].get("AlarmName") != "So101TwinStack-AgentSilent"
    ]
    assert len(others) == 19 and all(p.get("ActionsEnabled", True) for p in others)
    arm = statement(policy_statements(synth_default, "IdentityHostRole"), "AgentSilentArm")
    assert arm["Action"] == "cloudwatch:EnableAlarmActions"
    resource = json.dumps(arm["Resource"])
    assert ":cloudwatch:" in resource and ":alarm:So101TwinStack-AgentSilent" in resource
    assert "*" not in resource
    parameter = json.dumps(synth_default.one("AWS::SSM::Parameter")["Properties"]["Value"])
    assert "SILENT_ALARM=So101TwinStack-AgentSilent" in parameter


def test_arms_stale_counts_stale_arms_not_the_ones_switched_off(synth_default: Synth) -> None:
    props = alarm(synth_default, "At least one arm")
    assert (props["MetricName"], props["Statistic"], props["Period"]) == ("DevicesStale", "Maximum", 60)
    assert props["Dimensions"] == [{"Name": "Agent", "Value": "So101TwinStack"}]
    assert props["ComparisonOperator"] == "GreaterThanOrEqualToThreshold"
    assert (props["Threshold"], props["EvaluationPeriods"]) == (1, 3)
    assert props["TreatMissingData"] == "notBreaching"
    assert "DevicesOffline" not in str(props)


def test_a_host_behind_its_messages_pages_with_its_own_alarm(synth_default: Synth) -> None:
    # The arms' statuses are read where the agent stands in its input: the arms stale alarm no longer fires
    # for a host short of CPU, so this one must.
    props = alarm(synth_default, "The agent of So101TwinStack is at least 1 s behind")
    assert (props["MetricName"], props["Statistic"], props["Period"]) == ("InternalLatencyP99", "Maximum", 60)
    assert props["Dimensions"] == [{"Name": "Agent", "Value": "So101TwinStack"}]
    assert props["ComparisonOperator"] == "GreaterThanOrEqualToThreshold"
    assert (props["Threshold"], props["EvaluationPeriods"], props["DatapointsToAlarm"]) == (1000, 5, 5)
    assert props["TreatMissingData"] == "notBreaching"
    assert "docs/scaling.md" in props["AlarmDescription"]


def test_arms_kept_out_by_the_device_limit_page(synth_default: Synth) -> None:
    props = alarm(synth_default, "Arms of So101TwinStack publish, but the agent already tracks")
    assert (props["MetricName"], props["Statistic"], props["Period"]) == ("DeviceLimitRefusals", "Sum", 60)
    assert props["ComparisonOperator"] == "GreaterThanOrEqualToThreshold"
    assert (props["Threshold"], props["EvaluationPeriods"], props["DatapointsToAlarm"]) == (1, 5, 5)
    assert props["TreatMissingData"] == "notBreaching"
    assert "max_devices" in props["AlarmDescription"] and "Fleet page" in props["AlarmDescription"]
    # A fleet whose ids come and go fills its places with silent arms: the settings that let them go.
    assert "forget_offline_after_s" in props["AlarmDescription"]
    assert "forget_unseen_after_s" in props["AlarmDescription"]


def test_host_publishes_servo_alarms_to_the_topic_only(synth_default: Synth) -> None:
    from .test_stack import policy_statements, statement

    statements = policy_statements(synth_default, "IdentityHostRole")
    publish = statement(statements, "AlarmTopicPublish")
    assert (publish["Action"], publish["Resource"]) == ("sns:Publish", topic_ref(synth_default))
    key = statement(statements, "AlarmTopicKey")
    (key_id,) = synth_default.resources("AWS::KMS::Key")
    assert sorted(key["Action"]) == ["kms:Decrypt", "kms:GenerateDataKey"]
    assert key["Resource"] == {"Fn::GetAtt": [key_id, "Arn"]}
    # The host's config names the topic and whether warnings go too.
    parameter = json.dumps(synth_default.one("AWS::SSM::Parameter")["Properties"]["Value"])
    assert "ALERT_TOPIC_ARN=" in parameter and "ALERT_WARNINGS=false" in parameter


def test_warnings_are_a_setting(synth_factory: Any) -> None:
    synth = synth_factory(alarmWarnings="true")
    parameter = json.dumps(synth.one("AWS::SSM::Parameter")["Properties"]["Value"])
    assert "ALERT_WARNINGS=true" in parameter


def test_the_agent_name_follows_the_stack_name(synth_factory: Any) -> None:
    synth = synth_factory(stackName="LabTwin")
    props = alarm(synth, "The so101-twin agent")
    assert queries(props)["up"]["MetricStat"]["Metric"]["Dimensions"] == [
        {"Name": "Agent", "Value": "LabTwin"}
    ]
    assert props["AlarmName"] == "LabTwin-AgentSilent"


# --- the dashboard ---------------------------------------------------------------------------------------


def dashboard_body(synth: Synth) -> dict[str, Any]:
    """The dashboard's JSON, its CloudFormation tokens (region, alarm ARNs) written as "<token>"."""
    body = synth.one("AWS::CloudWatch::Dashboard")["Properties"]["DashboardBody"]

    def text(value: Any) -> str:
        if isinstance(value, str):
            return value
        if isinstance(value, dict) and "Fn::Join" in value:
            separator, parts = value["Fn::Join"]
            return separator.join(text(part) for part in parts)
        return "<token>"

    return json.loads(text(body))


def emitted_metrics() -> set[tuple[str, frozenset[tuple[str, str]]]]:
    """Every (metric, dimensions) the agent writes, from its own EMF documents with every figure set."""
    fields = {f.name for f in dataclasses.fields(emf.FleetMetrics)}
    values: dict[str, Any] = {
        "messages_per_s": 10.0,
        "rejects": 1,
        "loss_percent": 1.0,
        "devices_online": 2,
        "devices_stale": 1,
        "devices_offline": 1,
        "internal_latency_p99_ms": 3.0,
        "active_alarms": {"critical": 1, "warning": 2},
    }
    # History's figures are written only while history is on: set here, so the document has them.
    values.update({"history_lag_s": 1.5, "history_rows_dropped": 0, "history_commit_failures": 0})
    assert set(values) <= fields
    out = set()
    for doc in emf.fleet_documents(emf.FleetMetrics(**values), "So101TwinStack", 0):
        (directive,) = doc["_aws"]["CloudWatchMetrics"]
        (dimension_names,) = directive["Dimensions"]
        dims = frozenset((name, doc[name]) for name in dimension_names)
        out |= {(m["Name"], dims) for m in directive["Metrics"]}
    return out


def dashboard_metrics(body: dict[str, Any]) -> list[tuple[str, str, frozenset[tuple[str, str]]]]:
    """(widget title, metric, dimensions) of every metric a graph draws."""
    out = []
    for widget in body["widgets"]:
        props = widget["properties"]
        for row in props.get("metrics", []):
            names = [v for v in row if isinstance(v, str)]
            namespace, metric, *pairs = names
            assert namespace == emf.NAMESPACE, row
            dims = frozenset(zip(pairs[::2], pairs[1::2], strict=True))
            out.append((props["title"], metric, dims))
    return out


def test_the_dashboard_draws_only_metrics_the_agent_emits(synth_default: Synth) -> None:
    synth_default.template.resource_count_is("AWS::CloudWatch::Dashboard", 1)
    props = synth_default.one("AWS::CloudWatch::Dashboard")["Properties"]
    assert props["DashboardName"] == "So101TwinStack-fleet"
    drawn = dashboard_metrics(dashboard_body(synth_default))
    emitted = emitted_metrics()
    missing = {(m, d) for _, m, d in drawn if (m, d) not in emitted}
    assert not missing, f"the dashboard draws metrics the agent never writes: {missing}"
    agent = frozenset({("Agent", "So101TwinStack")})
    by_metric = {(m, d) for _, m, d in drawn}
    # What an operator asks of the fleet: arms online, the mirrored rate, loss, alarms by severity, history.
    assert {("DevicesOnline", agent), ("DevicesStale", agent), ("DevicesOffline", agent)} <= by_metric
    assert ("MessagesPerSecond", agent) in by_metric and ("LossPercent", agent) in by_metric
    for severity in ("critical", "warning"):
        assert ("ActiveAlarms", agent | {("Severity", severity)}) in by_metric
    assert {(monitoring.HISTORY_LAG, agent), (monitoring.HISTORY_ROWS_DROPPED, agent)} <= by_metric
    # What the HistoryCommitFailures alarm reads: the failure counts leave minutes of an outage at 0.
    assert (monitoring.HISTORY_COMMITS_FAILING, agent) in by_metric
    assert monitoring.HISTORY_LAG == emf.HISTORY_LAG
    assert monitoring.HISTORY_ROWS_DROPPED == emf.HISTORY_ROWS_DROPPED
    # ... and what the twin lost, each figure a loss alarm watches.
    losses = {emf.MESSAGES_DROPPED, emf.SINK_DROPS, emf.WORKER_RESTARTS, emf.HISTORY_COMMIT_FAILURES}
    # The metrics file's failed writes too: its alarm fires for a minute, the graph keeps them in sight.
    losses.add(emf.EMF_WRITE_FAILURES)
    assert {(name, agent) for name in losses} <= by_metric


def test_the_dashboard_shows_every_alarm_and_is_an_output(synth_default: Synth) -> None:
    body = dashboard_body(synth_default)
    status = [w for w in body["widgets"] if w["type"] == "alarm"]
    alarms = synth_default.resources("AWS::CloudWatch::Alarm")
    assert len(status) == 1 and len(status[0]["properties"]["alarms"]) == len(alarms) == 20
    # One point a minute, the agent's EMF interval, each with the statistic its figure needs.
    for widget in body["widgets"]:
        for row in widget["properties"].get("metrics", []):
            options = row[-1]
            # CloudWatch draws the average unless told otherwise (the rendered body then names no stat).
            assert options["period"] == 60 and options.get("stat", "Average") in (
                "Average",
                "Maximum",
                "Sum",
            ), row
    output = synth_default.json["Outputs"]["Dashboard"]["Value"]
    parts = output["Fn::Join"][1]
    assert parts[0].startswith("https://console.aws.amazon.com/cloudwatch/home?region=")
    assert {"Ref": next(iter(synth_default.resources("AWS::CloudWatch::Dashboard")))} in parts


def test_the_dashboard_follows_the_stack_name(synth_factory: Any) -> None:
    synth = synth_factory(stackName="LabTwin")
    assert synth.one("AWS::CloudWatch::Dashboard")["Properties"]["DashboardName"] == "LabTwin-fleet"
    drawn = dashboard_metrics(dashboard_body(synth))
    assert drawn and all(("Agent", "LabTwin") in dims for _, _, dims in drawn)


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
    [
        emf.MESSAGES_DROPPED,
        emf.SINK_DROPS,
        emf.WORKER_RESTARTS,
        emf.HISTORY_ROWS_DROPPED,
        emf.EMF_WRITE_FAILURES,
    ],
)
def test_any_loss_in_a_minute_alarms(synth_default: Synth, name: str) -> None:
    props = _alarm_on(synth_default, name)
    assert props["Namespace"] == emf.NAMESPACE
    assert props["Dimensions"] == [{"Name": "Agent", "Value": "So101TwinStack"}]
    assert (props["Statistic"], props["Period"]) == ("Sum", 60)
    assert (props["ComparisonOperator"], props["Threshold"]) == ("GreaterThanOrEqualToThreshold", 1)
    assert props["EvaluationPeriods"] == 1 and props["TreatMissingData"] == "notBreaching"


@pytest.mark.parametrize(
    ("name", "needles"),
    [
        (emf.MESSAGES_DROPPED, ("fewer arms or more cores",)),
        # The state file and the event journal report their failed writes as sink drops (docs/agent.md):
        # a walk filled the disk and the e-mail's cause was a sink that could not keep up.
        (emf.SINK_DROPS, ("state file", "event journal", "full or read-only disk", "last_error")),
        # A walk: only AgentSilent paged on a full disk, and only one that stayed full for 5 minutes.
        (
            emf.EMF_WRITE_FAILURES,
            # Its log line: any failed publish, at a stop too, not only a write.
            (
                "df -h /var/log",
                "agent.sinks 'emf'",
                "AgentSilent",
                "docs/servo-health.md",
                "'publishing CloudWatch metrics to ... failed'",
                "'the last CloudWatch metrics could not be written'",
                # The count is no longer lost with a crashed agent: the description says where it is kept.
                "outlives a crash",
                ".emf.log.unsent",
            ),
        ),
    ],
)
def test_a_loss_alarm_names_each_cause_and_its_fix(synth_default: Synth, name: str, needles: tuple) -> None:
    description = _alarm_on(synth_default, name)["AlarmDescription"]
    assert all(n in description for n in needles), description


def _outage_documents(outage_s: float, attempt_s: float, minutes: int) -> list[dict[str, Any]]:
    """The agent's EMF documents, as its publisher schedules them, through a storage outage of `outage_s`
    from 0: each commit attempt fails after `attempt_s` (a connect timeout) and the writer waits its backoff
    (the defaults, doubling from retry_min_s to retry_max_s) before the next; the first attempt after the
    outage works."""
    settings = HistorySettings(uri="s3://b/t")
    failures: list[float] = []
    backoff, at = settings.retry_min_s, 0.0
    while at < outage_s:
        failures.append(at + attempt_s)
        at += attempt_s + backoff
        backoff = min(backoff * 2.0, settings.retry_max_s)
    works_at = at + 1.0
    now = [-0.5]  # the publisher's slots then fall near the end of each minute

    def totals() -> emf.FleetTotals:
        failed = sum(t <= now[0] for t in failures)
        failing = int(bool(failed) and now[0] < works_at)
        now[0] += 10.0  # asking the workers for their state can take up to ASK_TIMEOUT_S
        return emf.FleetTotals(
            0,
            0,
            1,
            0,
            0,
            0.0,
            None,
            {},
            history_rows_dropped=0,
            history_commit_failures=failed,
            history_lag_s=0.0,
            history_commits_failing=failing,
        )

    written: list[dict[str, Any]] = []
    writer = types.SimpleNamespace(write=written.extend, path="memory")

    def wait(seconds: float) -> bool:
        now[0] += seconds
        return publisher.published >= minutes

    # The publisher's own loop, not documents written at chosen times: its schedule is what the alarm sees.
    publisher = emf.EmfPublisher(
        writer, "So101TwinStack", totals, clock=lambda: now[0], wall=lambda: now[0], wait=wait
    )
    publisher.run()
    return [d for d in written if "AgentUp" in d]


def _alarm_states(props: dict[str, Any], documents: list[dict[str, Any]]) -> list[bool]:
    """Whether the alarm `props` is in ALARM at the end of each minute, as CloudWatch evaluates it: the
    statistic of each minute's values, the last EvaluationPeriods minutes all at or over the threshold (a
    minute without the metric is missing, not breaching)."""
    assert props["ComparisonOperator"] == "GreaterThanOrEqualToThreshold"
    assert props["Period"] == 60 and props["TreatMissingData"] == "notBreaching"
    assert props["EvaluationPeriods"] == props["DatapointsToAlarm"]
    reduce = {"Sum": sum, "Maximum": max}[props["Statistic"]]
    by_minute: dict[int, list[float]] = {}
    for doc in documents:
        if props["MetricName"] in doc:
            by_minute.setdefault(int(doc["_aws"]["Timestamp"] // 60_000), []).append(doc[props["MetricName"]])
    last = max(by_minute)
    breaching = [
        bool(by_minute.get(m)) and reduce(by_minute[m]) >= props["Threshold"] for m in range(last + 1)
    ]
    n = props["EvaluationPeriods"]
    return [m + 1 >= n and all(breaching[m + 1 - n : m + 1]) for m in range(last + 1)]


@pytest.mark.parametrize("attempt_s", [0.5, 30.0, 90.0])
def test_history_commit_failures_pages_a_sustained_outage_in_its_five_minutes_and_clears(
    synth_default: Synth, attempt_s: float
) -> None:
    """The writer backs off to a retry every retry_max_s (60 s) after a failing attempt (a connect timeout
    takes 30 s or more): the failures' count left minutes at 0, so five failing minutes in a row never came
    and an S3 outage paged no one. The alarm reads "commits failing" now, present in every document."""
    props = alarm(synth_default, "History commits of So101TwinStack have failed for 5 minutes")
    # Twenty minutes of outage, then storage back; thirty minutes of documents.
    states = _alarm_states(props, _outage_documents(1200.0, attempt_s, 30))
    # The first failure is told in the first minute (at attempt_s), and pages five minutes of them later,
    # plus the minute a slow attempt takes to fail.
    first_page = states.index(True)
    assert first_page <= 4 + math.ceil(attempt_s / 60.0), states
    assert all(states[first_page:20]), states
    # Once a commit works, the next minute clears it.
    assert not any(states[22:]), states


def test_history_lag_alarms_over_a_minute_for_two(synth_default: Synth) -> None:
    props = _alarm_on(synth_default, emf.HISTORY_LAG)
    assert (props["Statistic"], props["Period"]) == ("Maximum", 60)
    assert (props["ComparisonOperator"], props["Threshold"]) == ("GreaterThanOrEqualToThreshold", 60)
    assert (props["EvaluationPeriods"], props["DatapointsToAlarm"]) == (2, 2)
    assert props["TreatMissingData"] == "notBreaching"


def assert_sustained_maximum(props: dict[str, Any], *, threshold: float, minutes: int) -> None:
    """An alarm on the agent's metric's per-minute maximum at or over `threshold` in each of `minutes`
    minutes, missing data not breaching."""
    assert props["Namespace"] == emf.NAMESPACE
    assert props["Dimensions"] == [{"Name": "Agent", "Value": "So101TwinStack"}]
    assert (props["Statistic"], props["Period"]) == ("Maximum", 60)
    assert (props["ComparisonOperator"], props["Threshold"]) == ("GreaterThanOrEqualToThreshold", threshold)
    assert (props["EvaluationPeriods"], props["DatapointsToAlarm"]) == (minutes, minutes)
    assert props["TreatMissingData"] == "notBreaching"


def test_a_refused_subscription_alarms_after_two_minutes_of_it(synth_default: Synth) -> None:
    """The agent runs and stays connected while IoT Core refuses it a filter, so AgentSilent and ArmsStale
    stay quiet: this alarm is what pages."""
    props = _alarm_on(synth_default, emf.SUBSCRIPTIONS_REFUSED)
    assert_sustained_maximum(props, threshold=1, minutes=2)
    assert "iot:Subscribe" in props["AlarmDescription"]


def test_a_broker_connection_down_alarms_after_three_minutes_of_it(synth_default: Synth) -> None:
    """Cut off from IoT Core, the agent runs and sends its heartbeat while every arm reads OFFLINE, which
    is not paged and which the loss alarms leave out: this alarm is what pages, naming where to look."""
    props = _alarm_on(synth_default, emf.BROKER_DISCONNECTED)
    assert_sustained_maximum(props, threshold=1, minutes=3)
    assert "iot:Connect" in props["AlarmDescription"] and "Troubleshooting" in props["AlarmDescription"]


def test_half_the_messages_refused_pages_after_five_minutes_of_it(synth_default: Synth) -> None:
    """A walk: arms whose every message is refused (the edges' units changed, a calibration refused) read
    OFFLINE, which does not page, and the loss figures leave them out: nothing paged. The share of arriving
    messages refused does, from the agent's Rejects and MessagesPerSecond of each minute."""
    (props,) = [
        a["Properties"]
        for a in synth_default.resources("AWS::CloudWatch::Alarm").values()
        if "refuses at least" in a["Properties"]["AlarmDescription"]
    ]
    (expression,) = [m["Expression"] for m in props["Metrics"] if "Expression" in m]
    # The device limit's refusals are DeviceLimitReached's (a review: it fired with advice on units).
    assert expression == "100 * (refused - kept_out) / (refused + valid * 60)"
    used = {m["Id"]: m["MetricStat"] for m in props["Metrics"] if "MetricStat" in m}
    assert {k: (v["Metric"]["MetricName"], v["Stat"]) for k, v in used.items()} == {
        "refused": ("Rejects", "Sum"),
        "kept_out": ("DeviceLimitRefusals", "Sum"),
        "valid": ("MessagesPerSecond", "Average"),
    }
    assert props["Threshold"] == 50 and props["EvaluationPeriods"] == props["DatapointsToAlarm"] == 5
    assert props["TreatMissingData"] == "notBreaching"
    assert "Events page" in props["AlarmDescription"] and "OFFLINE" in props["AlarmDescription"]


def test_alarm_e_mails_the_host_cannot_publish_page_after_three_minutes(synth_default: Synth) -> None:
    """A walk: SNS refusing the host's publishes (the role, the topic's key) held every servo alarm e-mail
    back, shown only in /state. The agent counts the failures, and this alarm, which CloudWatch publishes
    with rights of its own, says so."""
    props = _alarm_on(synth_default, emf.ALERT_PUBLISH_FAILURES)
    assert props["Statistic"] == "Sum" and props["Threshold"] == 1
    assert props["EvaluationPeriods"] == props["DatapointsToAlarm"] == 3
    assert props["TreatMissingData"] == "notBreaching"
    assert "sns:Publish" in props["AlarmDescription"] and "KMS key" in props["AlarmDescription"]


def test_messages_that_never_arrive_page_after_five_minutes_of_a_tenth_lost(synth_default: Synth) -> None:
    """IoT Core discards what a connection receives over its quota without an error, and nothing in the
    agent drops those messages, so none of the loss alarms above would say it: the arms' loss does."""
    props = _alarm_on(synth_default, emf.LOSS_PERCENT)
    # No data (no agent, or no arm that is not OFFLINE: the agent then writes 0) is no loss.
    assert_sustained_maximum(props, threshold=10, minutes=5)
    description = props["AlarmDescription"]
    assert "per-connection quota" in description and "maxConnections" in description


def test_one_arm_losing_a_fifth_of_its_messages_pages_after_ten_minutes(synth_default: Synth) -> None:
    """LossPercent averages the arms: at 100 arms, one losing half its messages moves it by half a per
    cent, so MessagesLost never pages for it. The arm losing most does, and the Events page names it."""
    props = _alarm_on(synth_default, emf.WORST_ARM_LOSS_PERCENT)
    assert_sustained_maximum(props, threshold=20, minutes=10)
    assert "Events page names" in props["AlarmDescription"]


@pytest.mark.parametrize(
    "name",
    [monitoring.HOST_CHECKS_FAILED, monitoring.LOCAL_CONFIG_NOT_SAVED, monitoring.ALARM_STATE_NOT_SAVED],
)
def test_a_host_scripts_failure_pages_until_a_later_run_succeeds(synth_default: Synth, name: str) -> None:
    """The host's scripts write their outcome (1 failed, 0 fine) only when they run, a start or a save, often
    days apart: a minute without data must keep the alarm as it is, not clear it (notBreaching would)."""
    props = _alarm_on(synth_default, name)
    assert props["Namespace"] == emf.NAMESPACE
    assert props["Dimensions"] == [{"Name": "Agent", "Value": "So101TwinStack"}]
    assert (props["Statistic"], props["Period"]) == ("Maximum", 60)
    assert (props["ComparisonOperator"], props["Threshold"]) == ("GreaterThanOrEqualToThreshold", 1)
    assert props["EvaluationPeriods"] == 1 and props["TreatMissingData"] == "ignore"


def test_every_alarm_description_fits_cloudwatch(synth_default: Synth) -> None:
    # PutMetricAlarm refuses an AlarmDescription over 1,024 characters, so a long fix text would only
    # fail at deploy time; the longest grows each time an alarm learns a new cause.
    longest = max(alarms_described(synth_default), key=len)
    assert len(longest) <= 1024, f"{len(longest)} characters: {longest[:80]}..."
