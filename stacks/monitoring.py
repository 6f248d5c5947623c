"""CloudWatch alarms on the agent's EMF metrics, notifying one SNS topic (and an e-mail address, if given).

The agent writes Embedded Metric Format lines (agents/twin/output/emf.py) to a file the CloudWatch agent
ships to the host's log group; CloudWatch Logs turns them into metrics in the SO101Twin namespace with the
dimension Agent = the stack name. Three alarms watch them (docs/servo-health.md says what to do for each):

- agent silent: no AgentUp heartbeat for 3 minutes (the agent, the host or its CloudWatch agent is down; a
  host stopped on purpose, by the auto-stop schedule say, reads the same: nobody is watching the arms);
- arms stale: at least one arm STALE or OFFLINE for 3 minutes in a row;
- critical servo alarm: a critical servo alarm (over-temperature near the cut-out, over-current) present.

A CloudWatch dashboard shows the same metrics over time: arms by status, the mirrored message rate, the
estimated loss, the servo alarms present by severity and how far history lags, next to the three alarms.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from aws_cdk import Duration, RemovalPolicy, Stack
from aws_cdk import aws_cloudwatch as cw
from aws_cdk import aws_cloudwatch_actions as cw_actions
from aws_cdk import aws_iam as iam
from aws_cdk import aws_kms as kms
from aws_cdk import aws_sns as sns
from aws_cdk import aws_sns_subscriptions as subs
from constructs import Construct

# The agent's EMF names (agents/twin/output/emf.py); tests/infra check both sides agree.
NAMESPACE = "SO101Twin"
AGENT_DIMENSION = "Agent"
SEVERITY_DIMENSION = "Severity"
PERIOD = Duration.minutes(1)
SEVERITIES = ("critical", "warning")
# History's figures (emf.HISTORY_LAG, emf.HISTORY_ROWS_DROPPED where the agent defines them).
HISTORY_LAG = "HistoryLagSeconds"
HISTORY_ROWS_DROPPED = "HistoryRowsDropped"


class TwinMonitoring(Construct):
    """Attributes: `topic` (alarm notifications), `alarms` (name -> cw.Alarm)."""

    def __init__(self, scope: Construct, id_: str, *, agent_name: str, alarm_email: str | None) -> None:
        super().__init__(scope, id_)
        stack = Stack.of(self)
        # CloudWatch can only publish to an encrypted topic whose key lets it encrypt: the AWS-managed SNS
        # key does not, so the topic gets a key of its own (rotated yearly).
        key = kms.Key(
            self,
            "AlarmTopicKey",
            description="so101-twin alarm topic encryption",
            enable_key_rotation=True,
            removal_policy=RemovalPolicy.DESTROY,
        )
        key.add_to_resource_policy(
            iam.PolicyStatement(
                sid="CloudWatchAlarmsPublish",
                principals=[iam.ServicePrincipal("cloudwatch.amazonaws.com")],
                actions=["kms:Decrypt", "kms:GenerateDataKey*"],
                resources=["*"],  # in a key policy, "*" means this key
                conditions={"StringEquals": {"aws:SourceAccount": stack.account}},
            )
        )
        self.topic = sns.Topic(
            self,
            "AlarmTopic",
            display_name="so101-twin alarms",
            master_key=key,
            enforce_ssl=True,
        )
        self.topic.add_to_resource_policy(
            iam.PolicyStatement(
                sid="CloudWatchAlarmsPublish",
                principals=[iam.ServicePrincipal("cloudwatch.amazonaws.com")],
                actions=["sns:Publish"],
                resources=[self.topic.topic_arn],
                conditions={"StringEquals": {"aws:SourceAccount": stack.account}},
            )
        )
        if alarm_email:
            self.topic.add_subscription(subs.EmailSubscription(alarm_email))

        def metric(name: str, statistic: str, **extra: str) -> cw.Metric:
            return cw.Metric(
                namespace=NAMESPACE,
                metric_name=name,
                dimensions_map={AGENT_DIMENSION: agent_name, **extra},
                statistic=statistic,
                period=PERIOD,
            )

        self.alarms: dict[str, cw.Alarm] = {
            "AgentSilent": cw.Alarm(
                self,
                "AgentSilent",
                alarm_description=(
                    f"The so101-twin agent of {agent_name} sent no heartbeat for 3 minutes: the agent, the "
                    "host or its CloudWatch agent is down (or the host was stopped). docs/servo-health.md"
                ),
                metric=metric("AgentUp", "SampleCount"),
                threshold=1,
                comparison_operator=cw.ComparisonOperator.LESS_THAN_THRESHOLD,
                evaluation_periods=3,
                datapoints_to_alarm=3,
                # Silence is the signal: no data at all must alarm.
                treat_missing_data=cw.TreatMissingData.BREACHING,
            ),
            "ArmsStale": cw.Alarm(
                self,
                "ArmsStale",
                alarm_description=(
                    f"At least one arm of {agent_name} has been STALE or OFFLINE for 3 minutes: its edge "
                    "stopped publishing or the network drops its telemetry. docs/servo-health.md"
                ),
                metric=cw.MathExpression(
                    expression="stale + offline",
                    using_metrics={
                        "stale": metric("DevicesStale", "Maximum"),
                        "offline": metric("DevicesOffline", "Maximum"),
                    },
                    label="Arms not online",
                    period=PERIOD,
                ),
                threshold=1,
                comparison_operator=cw.ComparisonOperator.GREATER_THAN_OR_EQUAL_TO_THRESHOLD,
                evaluation_periods=3,
                datapoints_to_alarm=3,
                # A silent agent is AgentSilent's to report; this one judges the arms it can see.
                treat_missing_data=cw.TreatMissingData.NOT_BREACHING,
            ),
            "CriticalServoAlarm": cw.Alarm(
                self,
                "CriticalServoAlarm",
                alarm_description=(
                    f"A servo of {agent_name} has a critical alarm (near the 70 C cut-out, or over-current): "
                    "see GET /alarms on the host and docs/servo-health.md"
                ),
                metric=metric("ActiveAlarms", "Maximum", **{SEVERITY_DIMENSION: "critical"}),
                threshold=1,
                comparison_operator=cw.ComparisonOperator.GREATER_THAN_OR_EQUAL_TO_THRESHOLD,
                evaluation_periods=1,
                treat_missing_data=cw.TreatMissingData.NOT_BREACHING,
            ),
        }
        action = cw_actions.SnsAction(self.topic)
        for alarm in self.alarms.values():
            alarm.add_alarm_action(action)
            alarm.add_ok_action(action)
        self.dashboard = _dashboard(self, agent_name, metric, list(self.alarms.values()))


def _dashboard(
    scope: Construct, agent_name: str, metric: Callable[..., cw.Metric], alarms: list[cw.Alarm]
) -> cw.Dashboard:
    """The fleet at a glance, one graph per question an operator asks, each from the agent's EMF metrics."""

    def graph(
        title: str, left: list[cw.IMetric], right: list[cw.IMetric] | None = None, **options: Any
    ) -> cw.GraphWidget:
        return cw.GraphWidget(title=title, left=left, right=right or [], width=12, height=6, **options)

    def labelled(name: str, statistic: str, label: str, **extra: str) -> cw.Metric:
        return metric(name, statistic, **extra).with_(label=label)

    dashboard = cw.Dashboard(
        scope,
        "Dashboard",
        dashboard_name=f"{agent_name}-fleet",
        default_interval=Duration.hours(3),
    )
    dashboard.add_widgets(
        graph(
            "Arms by status",
            [
                labelled("DevicesOnline", "Maximum", "online"),
                labelled("DevicesStale", "Maximum", "stale"),
                labelled("DevicesOffline", "Maximum", "offline"),
            ],
            stacked=True,
        ),
        graph(
            "Mirrored messages per second (all arms) and rejected messages",
            [labelled("MessagesPerSecond", "Average", "mirrored msg/s")],
            [labelled("Rejects", "Sum", "rejected per minute")],
        ),
        graph(
            "Loss: share of expected messages that never arrived (%)",
            [labelled("LossPercent", "Maximum", "loss %")],
            left_y_axis=cw.YAxisProps(min=0),
        ),
        graph(
            "Servo alarms present, by severity",
            [
                labelled("ActiveAlarms", "Maximum", severity, **{SEVERITY_DIMENSION: severity})
                for severity in SEVERITIES
            ],
            left_y_axis=cw.YAxisProps(min=0),
        ),
        graph(
            "History: lag of the oldest unwritten row (s) and rows dropped",
            [labelled(HISTORY_LAG, "Maximum", "lag s")],
            [labelled(HISTORY_ROWS_DROPPED, "Sum", "rows dropped per minute")],
        ),
        cw.AlarmStatusWidget(title="Alarms", alarms=alarms, width=12, height=6),
    )
    return dashboard
