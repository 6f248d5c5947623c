"""CloudWatch alarms on the agent's EMF metrics, notifying one SNS topic (and an e-mail address, if given).

The agent writes Embedded Metric Format lines (agents/twin/output/emf.py) to a file the CloudWatch agent
ships to the host's log group; CloudWatch Logs turns them into metrics in the SO101Twin namespace with the
dimension Agent = the stack name. Three alarms watch the fleet (docs/servo-health.md says what to do for
each):

- agent silent: no AgentUp heartbeat for 3 minutes (the agent, the host or its CloudWatch agent is down; a
  host stopped on purpose, by the auto-stop schedule say, reads the same: nobody is watching the arms);
- arms stale: at least one arm STALE or OFFLINE for 3 minutes in a row;
- critical servo alarm: a critical servo alarm (over-temperature near the cut-out, over-current) present.

And six on what the twin loses, so a loss that nobody reads in the logs still reaches someone:

- messages dropped: telemetry dropped before it was decoded (a queue was full, or a dead worker took it);
- sink drops: samples a sink (USD recording, history's queue, Rerun, ROS 2) could not keep up with;
- worker restarts: a worker process died and was started again;
- history rows dropped: the history writer's buffer overflowed (storage unreachable longer than it holds);
- history commit failures: history commits kept failing for 5 minutes;
- history lag: the oldest unwritten history row is over a minute old, 2 minutes running (storage is slow
  or unreachable; rows are dropped once the buffer is full).
"""

from __future__ import annotations

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
# The loss metrics (agents/twin/output/emf.py, LOSS_METRICS).
MESSAGES_DROPPED = "MessagesDropped"
SINK_DROPS = "SinkDrops"
WORKER_RESTARTS = "WorkerRestarts"
HISTORY_ROWS_DROPPED = "HistoryRowsDropped"
HISTORY_COMMIT_FAILURES = "HistoryCommitFailures"
HISTORY_LAG = "HistoryLagSeconds"
PERIOD = Duration.minutes(1)
# History commits every 10 s by default (docs/history.md): a minute's lag means commits are failing.
HISTORY_LAG_ALARM_S = 60


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

        def any_loss(id_: str, name: str, description: str) -> cw.Alarm:
            """Alarm when `name` counted anything in a minute."""
            return cw.Alarm(
                self,
                id_,
                alarm_description=f'{description} docs/agent.md, "Bounds and restarts"',
                metric=metric(name, "Sum"),
                threshold=1,
                comparison_operator=cw.ComparisonOperator.GREATER_THAN_OR_EQUAL_TO_THRESHOLD,
                evaluation_periods=1,
                # Nothing counted (or history off, or the agent silent: AgentSilent's case) is no loss.
                treat_missing_data=cw.TreatMissingData.NOT_BREACHING,
            )

        self.alarms["MessagesDropped"] = any_loss(
            "MessagesDropped",
            MESSAGES_DROPPED,
            f"The agent of {agent_name} dropped telemetry before decoding it: a queue was full (the host "
            "cannot keep up) or a worker process died with messages it had not counted.",
        )
        self.alarms["SinkDrops"] = any_loss(
            "SinkDrops",
            SINK_DROPS,
            f"An output of {agent_name} (USD recording, history, Rerun or ROS 2) dropped samples it could "
            "not keep up with; /state agent.sinks says which.",
        )
        self.alarms["WorkerRestarts"] = any_loss(
            "WorkerRestarts",
            WORKER_RESTARTS,
            f"A worker process of {agent_name}'s agent died and was started again; its log says why.",
        )
        self.alarms["HistoryRowsDropped"] = any_loss(
            "HistoryRowsDropped",
            HISTORY_ROWS_DROPPED,
            f"Telemetry history of {agent_name} is being lost: storage was unreachable longer than the write "
            "buffer holds (history.max_buffer_rows).",
        )
        self.alarms["HistoryCommitFailures"] = cw.Alarm(
            self,
            "HistoryCommitFailures",
            alarm_description=(
                f"History commits of {agent_name} have failed for 5 minutes: the bucket is unreachable or "
                "refuses the role (/state agent.history.last_error). docs/history.md"
            ),
            metric=metric(HISTORY_COMMIT_FAILURES, "Sum"),
            threshold=1,
            comparison_operator=cw.ComparisonOperator.GREATER_THAN_OR_EQUAL_TO_THRESHOLD,
            evaluation_periods=5,
            datapoints_to_alarm=5,
            treat_missing_data=cw.TreatMissingData.NOT_BREACHING,
        )
        self.alarms["HistoryLag"] = cw.Alarm(
            self,
            "HistoryLag",
            alarm_description=(
                f"History of {agent_name} lags: its oldest unwritten row has waited over "
                f"{HISTORY_LAG_ALARM_S} s for 2 minutes; rows are dropped once the buffer is full. "
                "docs/history.md"
            ),
            metric=metric(HISTORY_LAG, "Maximum"),
            threshold=HISTORY_LAG_ALARM_S,
            comparison_operator=cw.ComparisonOperator.GREATER_THAN_OR_EQUAL_TO_THRESHOLD,
            evaluation_periods=2,
            datapoints_to_alarm=2,
            treat_missing_data=cw.TreatMissingData.NOT_BREACHING,
        )
        action = cw_actions.SnsAction(self.topic)
        for alarm in self.alarms.values():
            alarm.add_alarm_action(action)
            alarm.add_ok_action(action)
