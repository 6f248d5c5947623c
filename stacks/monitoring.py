"""The alarm topic and what notifies it: the host's servo alarms directly, and twenty CloudWatch alarms.

One SNS topic (encrypted, TLS only; an e-mail address subscribed when the settings give one):

- **servo alarms**: the twin host's agent publishes every transition of a critical servo alarm (and of a
  warning with `alarmWarnings`) straight to the topic, batched and rate-limited
  (agents/twin/output/alerts.py), naming the arm, the servo, the value, the threshold, the state and how to
  acknowledge: within 10 s, where a CloudWatch alarm on a once-a-minute metric took minutes and named
  neither. Its role may `sns:Publish` on this topic only (`grant_host`).
- **agent silent** (CloudWatch): the instance runs (EC2 reports its CPU) but the agent sent no AgentUp
  heartbeat for 5 minutes: the agent or the host's CloudWatch agent is down, or a full disk keeps the agent
  from writing its EMF file. A stopped instance reports no
  CPU, so stopping it (by hand or on the auto-stop schedule) does not page. The template creates it with its
  actions off and the host turns them on (userdata/lib.sh, `arm_silent_alarm`) once its first boot is over
  and at every start: the first boot installs for longer than 5 minutes before the agent runs, and would
  otherwise page on every new stack.
- **arms stale** (CloudWatch): at least one arm STALE (publishing, but with gaps) for 3 minutes in a row. An
  arm that is switched off goes OFFLINE and is not paged: arms are switched off on schedules.
- **what the twin loses** (CloudWatch, six alarms), so a loss that nobody reads in the logs still reaches
  someone: messages dropped before they were decoded (a queue was full, or a dead worker took them); samples
  a sink (USD recording, history's queue, Rerun, ROS 2) could not keep up with; a worker process that died
  and was started again; history rows dropped (the writer's buffer overflowed: storage unreachable longer
  than it holds); history commits failing for 5 minutes; history's oldest unwritten row over a minute old, 2
  minutes running (storage slow or unreachable; rows are dropped once the buffer is full).
- **metrics unwritten** (CloudWatch): the agent could not write its EMF file (a disk that filled, the
  file's permissions), told in the first document written after: CloudWatch got nothing, or only part, for
  those minutes, so every other alarm was blind then. A disk that stays full writes nothing, so no
  heartbeat: agent silent pages after 5 minutes, and this one once the disk takes a write again (the count
  outlives an agent crash or restart meanwhile: the agent keeps it in a small file of its own).
- **a refused subscription** (CloudWatch): IoT Core refuses the agent a topic filter for 2 minutes.
- **the broker out of reach** (CloudWatch): a connection of the agent to IoT Core down for 3 minutes. Its
  arms then all read OFFLINE, which does not page, so nothing else would say it.
- **messages lost on the way** (CloudWatch): the arms that are not OFFLINE deliver at least 10 % less than
  their expected rate, 5 minutes running. IoT Core discards what a connection receives over its quota without
  an error, so this is how such a loss reaches a person (as a weak edge network, or armRateHz set above the
  edges' rate, does); the console's Fleet page and /healthz name the quota's case and its fix.
- **messages refused** (CloudWatch): half or more of the messages that arrive are refused (the device
  limit's refusals aside: they have their own alarm), 5 minutes running. An arm whose every message is
  refused (the edge's units or firmware changed, a calibration refused) is OFFLINE, which does not page, and
  the loss figures leave it out: without this, a fleet-wide change of what the edges send went unpaged.
- **alarm e-mails unsent** (CloudWatch): the host's publishes of servo alarm e-mails to the topic keep
  failing, 3 minutes running (its role, the topic's key). CloudWatch publishes to the topic with rights of
  its own, so this reaches the person the e-mails did not.
- **the host's own scripts** (CloudWatch, three alarms): the checks after a start failed (host-check.sh);
  the bucket does not hold the operator's agent.local.toml as it is (save-local-config.sh), or the servo
  alarm state as the agent last wrote it (save-alarm-state.sh). Each holds its state until the script's next
  run says otherwise.

The agent writes Embedded Metric Format lines (agents/twin/output/emf.py) to a file the CloudWatch agent ships
to the host's log group; CloudWatch Logs turns them into metrics in the SO101Twin namespace with the dimension
Agent = the stack name, which the alarms watch (docs/servo-health.md says what to do for each).

A CloudWatch dashboard shows the same metrics over time: arms by status, the mirrored message rate, the
estimated loss, the servo alarms present by severity, how far history lags and what the twin lost, above
the alarms.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from aws_cdk import ArnFormat, Duration, RemovalPolicy, Stack
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
# 1 while history's last commit failed (emf.HISTORY_COMMITS_FAILING): what HistoryCommitFailures pages on.
HISTORY_COMMITS_FAILING = "HistoryCommitsFailing"
# Topic filters the broker refuses the agent (agents/twin/output/emf.py, SUBSCRIPTIONS_REFUSED).
SUBSCRIPTIONS_REFUSED = "SubscriptionsRefused"
# Broker connections down now (emf.BROKER_DISCONNECTED), and what pages: any, three minutes running (the agent
# reconnects within seconds: a broker restart or a network blip passes).
BROKER_DISCONNECTED = "BrokerDisconnected"
BROKER_DISCONNECTED_MINUTES = 3
# The share of the arms' expected messages that did not arrive (emf.LOSS_PERCENT), and what pages: a tenth,
# five minutes running (an arm starting up, or a minute of a weak network, passes).
LOSS_PERCENT = "LossPercent"
LOSS_ALARM_PERCENT = 10
LOSS_ALARM_MINUTES = 5
# The arm losing most of its messages (emf.WORST_ARM_LOSS_PERCENT), and what pages: a fifth, ten minutes
# running. Higher and longer than the fleet's line: one arm's Wi-Fi is a smaller matter than the fleet's.
WORST_ARM_LOSS_PERCENT = "WorstArmLossPercent"
ARM_LOSS_ALARM_PERCENT = 20
ARM_LOSS_ALARM_MINUTES = 10
# The highest internal latency p99 of the arms (emf.INTERNAL_LATENCY_P99), and what pages: a second, five
# minutes running. The agent reads the arms' statuses where it stands in its input, so a host short of CPU
# turns no arm STALE: this is the alarm that says the twin runs behind.
INTERNAL_LATENCY_P99 = "InternalLatencyP99"
BEHIND_ALARM_MS = 1000
BEHIND_ALARM_MINUTES = 5
# Messages refused because the agent already tracks telemetry.max_devices arms (emf.DEVICE_LIMIT_REFUSALS),
# and what pages: any, five minutes running (arms that publish and are kept out; one stray id passes).
DEVICE_LIMIT_REFUSALS = "DeviceLimitRefusals"
DEVICE_LIMIT_MINUTES = 5
# The share of arriving messages the agent refused (emf Rejects against MessagesPerSecond over the minute:
# exact because the agent's [cloudwatch] interval_s must divide 60), and what pages: half, five minutes
# running (an arm deciding its units, a stray bad message, passes).
REFUSED_ALARM_PERCENT = 50
REFUSED_ALARM_MINUTES = 5
# Servo alarm e-mails the host failed to publish (emf.ALERT_PUBLISH_FAILURES; it retries every 5 s while
# any waits), and what pages: failures in each of 3 minutes (a passing SNS error clears first).
ALERT_PUBLISH_FAILURES = "AlertPublishFailures"
ALERT_FAILURES_MINUTES = 3
# The host scripts' own metrics (userdata/lib.sh, emit_host_metrics): the verdict of the checks after each
# start (host-check.sh), and whether the bucket holds the operator's agent.local.toml (save-local-config.sh)
# and the agent's servo alarm state (save-alarm-state.sh).
HOST_CHECKS_FAILED = "HostChecksFailed"
LOCAL_CONFIG_NOT_SAVED = "LocalConfigNotSaved"
ALARM_STATE_NOT_SAVED = "AlarmStateNotSaved"
# The agent's failed publishes of its EMF file (emf.EMF_WRITE_FAILURES), told in the first document written
# after them: only once the disk has room again, so it pages an outage that ended, which AgentSilent may miss
# (one under 5 minutes, or a disk filled again and again). The agent keeps the count in a file of its own
# (emf.UnsentCount), so a crash, a kill or a restart during the outage does not lose it.
EMF_WRITE_FAILURES = "EmfWriteFailures"
PERIOD = Duration.minutes(1)
# History commits every 10 s by default (docs/history.md): a minute's lag means commits are failing.
HISTORY_LAG_ALARM_S = 60
# How long the agent may be silent on a running host before it pages (it restarts itself within seconds).
SILENT_MINUTES = 5
SEVERITIES = ("critical", "warning")


def silent_alarm_name(agent_name: str) -> str:
    """AgentSilent's name. Fixed, not generated: the host's role may enable the actions of this one alarm, and
    naming it by the resource would make the role depend on the alarm, which depends on the instance, which
    waits for the role."""
    return f"{agent_name}-AgentSilent"


class TwinMonitoring(Construct):
    """Attributes: `topic` (notifications), `alarms` (name -> cw.Alarm) and `dashboard`, both made by
    `watch_host`."""

    def __init__(self, scope: Construct, id_: str, *, agent_name: str, alarm_email: str | None) -> None:
        super().__init__(scope, id_)
        stack = Stack.of(self)
        self.agent_name = agent_name
        # CloudWatch can only publish to an encrypted topic whose key lets it encrypt: the AWS-managed SNS
        # key does not, so the topic gets a key of its own (rotated yearly).
        self.key = kms.Key(
            self,
            "AlarmTopicKey",
            description="so101-twin alarm topic encryption",
            enable_key_rotation=True,
            removal_policy=RemovalPolicy.DESTROY,
        )
        self.key.add_to_resource_policy(
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
            master_key=self.key,
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
        self.alarms: dict[str, cw.Alarm] = {}

    def grant_host(self, role: iam.IRole) -> None:
        """The host's agent publishes servo alarms to this topic and nowhere else: sns:Publish on it, and the
        topic key's encrypt side (SNS encrypts each message with it on the publisher's behalf)."""
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="AlarmTopicPublish", actions=["sns:Publish"], resources=[self.topic.topic_arn]
            )
        )
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="AlarmTopicKey",
                # The two calls SNS makes with the publisher's rights for an encrypted topic; no wildcard.
                actions=["kms:Decrypt", "kms:GenerateDataKey"],
                resources=[self.key.key_arn],
            )
        )
        stack = Stack.of(self)
        role.add_to_principal_policy(
            iam.PolicyStatement(
                sid="AgentSilentArm",
                # The host turns AgentSilent's actions on once it is up (module doc), this alarm's only.
                actions=["cloudwatch:EnableAlarmActions"],
                resources=[
                    stack.format_arn(
                        service="cloudwatch",
                        resource="alarm",
                        resource_name=silent_alarm_name(self.agent_name),
                        arn_format=ArnFormat.COLON_RESOURCE_NAME,
                    )
                ],
            )
        )

    def watch_host(self, instance_id: str) -> None:
        """The CloudWatch alarms, which need the instance: its CPU metric tells a stopped host from a silent
        agent."""
        self.alarms = {
            "AgentSilent": self._agent_silent_alarm(instance_id),
            "ArmsStale": self._arms_stale_alarm(),
            "AgentBehind": self._agent_behind_alarm(),
        }
        self._alarms_for_loss()
        self._alarms_for_history()
        self.alarms["EmfWriteFailures"] = self._emf_write_failures_alarm()
        self.alarms["SubscriptionsRefused"] = self._subscriptions_refused_alarm()
        self.alarms["BrokerDisconnected"] = self._broker_disconnected_alarm()
        self.alarms["MessagesLost"] = self._messages_lost_alarm()
        self.alarms["MessagesRefused"] = self._messages_refused_alarm()
        self.alarms["AlertsUnsent"] = self._alerts_unsent_alarm()
        self.alarms["ArmLosingMessages"] = self._arm_losing_alarm()
        self.alarms["DeviceLimitReached"] = self._device_limit_alarm()
        self._alarms_for_host_scripts()
        action = cw_actions.SnsAction(self.topic)
        for alarm in self.alarms.values():
            alarm.add_alarm_action(action)
            alarm.add_ok_action(action)
        self.dashboard = _dashboard(self, self.agent_name, self._metric, list(self.alarms.values()))

    def _metric(self, name: str, statistic: str, **extra: str) -> cw.Metric:
        """One of the agent's EMF metrics, per minute, for this agent (and the `extra` dimensions)."""
        return cw.Metric(
            namespace=NAMESPACE,
            metric_name=name,
            dimensions_map={AGENT_DIMENSION: self.agent_name, **extra},
            statistic=statistic,
            period=PERIOD,
        )

    def _agent_silent_alarm(self, instance_id: str) -> cw.Alarm:
        """AgentSilent: the instance runs, but the agent sent no heartbeat for SILENT_MINUTES."""
        running = cw.Metric(
            namespace="AWS/EC2",
            metric_name="CPUUtilization",
            dimensions_map={"InstanceId": instance_id},
            statistic="SampleCount",
            period=PERIOD,
        )
        return cw.Alarm(
            self,
            "AgentSilent",
            alarm_name=silent_alarm_name(self.agent_name),
            # Off until the host is up (module doc): the host enables them.
            actions_enabled=False,
            alarm_description=(
                f"The so101-twin agent of {self.agent_name} sent no heartbeat for 5 minutes while its "
                "host runs: the agent or the host's CloudWatch agent is down, or the host's disk is full "
                "and the agent cannot write its metrics file (`df -h /var/log`; its log says 'No space "
                "left on device'), or the host's network is cut (no route out, outbound 443, DNS): the "
                "metrics travel that way too. A stopped host does not count. docs/servo-health.md"
            ),
            # 1 while the instance reports CPU (it runs) and the agent no heartbeat; a stopped instance
            # reports nothing, which FILL makes 0: not breaching.
            metric=cw.MathExpression(
                expression="IF(FILL(running, 0) > 0 AND FILL(up, 0) < 1, 1, 0)",
                using_metrics={"running": running, "up": self._metric("AgentUp", "SampleCount")},
                label="Host runs, agent silent",
                period=PERIOD,
            ),
            threshold=1,
            comparison_operator=cw.ComparisonOperator.GREATER_THAN_OR_EQUAL_TO_THRESHOLD,
            evaluation_periods=SILENT_MINUTES,
            datapoints_to_alarm=SILENT_MINUTES,
            treat_missing_data=cw.TreatMissingData.NOT_BREACHING,
        )

    def _arms_stale_alarm(self) -> cw.Alarm:
        """ArmsStale: at least one arm STALE for 3 minutes in a row."""
        # A silent agent is AgentSilent's to report; this one judges the arms it can see.
        return self._sustained_alarm(
            "ArmsStale",
            f"At least one arm of {self.agent_name} has been STALE for 3 minutes: it publishes with "
            "gaps (a weak network, an overloaded edge). Arms switched off go OFFLINE and are not "
            "paged. docs/servo-health.md",
            self._metric("DevicesStale", "Maximum"),
            threshold=1,
            minutes=3,
        )

    def _agent_behind_alarm(self) -> cw.Alarm:
        """AgentBehind: the twin a second or more behind its arms' messages for 5 minutes."""
        return self._sustained_alarm(
            "AgentBehind",
            f"The agent of {self.agent_name} is at least {BEHIND_ALARM_MS / 1000:g} s behind its arms' "
            f"messages (InternalLatencyP99), {BEHIND_ALARM_MINUTES} minutes running: its host is short of "
            "CPU, so every pose is that old (the arms' status is read where the agent stands, so the arms "
            "stale alarm stays quiet). Give the host fewer arms or more cores. docs/scaling.md",
            self._metric(INTERNAL_LATENCY_P99, "Maximum"),
            threshold=BEHIND_ALARM_MS,
            minutes=BEHIND_ALARM_MINUTES,
        )

    def _sustained_alarm(
        self, id_: str, description: str, metric: cw.IMetric, threshold: float, minutes: int
    ) -> cw.Alarm:
        """Alarm when `metric` is at or above `threshold` in each of `minutes` minutes in a row; no data (the
        agent silent, history off) is not breaching: AgentSilent says that."""
        return cw.Alarm(
            self,
            id_,
            alarm_description=description,
            metric=metric,
            threshold=threshold,
            comparison_operator=cw.ComparisonOperator.GREATER_THAN_OR_EQUAL_TO_THRESHOLD,
            evaluation_periods=minutes,
            datapoints_to_alarm=minutes,
            treat_missing_data=cw.TreatMissingData.NOT_BREACHING,
        )

    def _any_loss_alarm(
        self, id_: str, name: str, description: str, *, doc: str = 'docs/agent.md, "Bounds and restarts"'
    ) -> cw.Alarm:
        """Alarm when `name` counted anything in a minute."""
        return cw.Alarm(
            self,
            id_,
            alarm_description=f"{description} {doc}",
            metric=self._metric(name, "Sum"),
            threshold=1,
            comparison_operator=cw.ComparisonOperator.GREATER_THAN_OR_EQUAL_TO_THRESHOLD,
            evaluation_periods=1,
            # Nothing counted (or history off, or the agent silent: AgentSilent's case) is no loss.
            treat_missing_data=cw.TreatMissingData.NOT_BREACHING,
        )

    def _alarms_for_loss(self) -> None:
        """The four alarms on anything lost in a minute: messages, sink samples, workers, history rows."""
        agent_name = self.agent_name
        self.alarms["MessagesDropped"] = self._any_loss_alarm(
            "MessagesDropped",
            MESSAGES_DROPPED,
            f"The agent of {agent_name} dropped telemetry before decoding it: a queue was full (the host "
            "cannot keep up: give it fewer arms or more cores) or a worker process died with messages it "
            "had not counted (WorkerRestarts then fires too).",
        )
        self.alarms["SinkDrops"] = self._any_loss_alarm(
            "SinkDrops",
            SINK_DROPS,
            f"An output of {agent_name} (USD recording, history, Rerun or ROS 2) dropped samples it could "
            "not keep up with, or the servo alarm state file or the event journal could not be written (a "
            "full or read-only disk: df -h /var/lib); /state agent.sinks says which, with its last_error.",
        )
        self.alarms["WorkerRestarts"] = self._any_loss_alarm(
            "WorkerRestarts",
            WORKER_RESTARTS,
            f"A worker process of {agent_name}'s agent died and was started again; its log says why.",
        )
        self.alarms["HistoryRowsDropped"] = self._any_loss_alarm(
            "HistoryRowsDropped",
            HISTORY_ROWS_DROPPED,
            f"Telemetry history of {agent_name} is being lost: storage was unreachable longer than the write "
            "buffer holds (history.max_buffer_rows).",
        )

    def _emf_write_failures_alarm(self) -> cw.Alarm:
        """EmfWriteFailures: the agent's metrics file refused writes. Those minutes reached no alarm, and
        AgentSilent pages only after five silent minutes: a disk full for less, or filled again and again (a
        log that grows, rotated), lost metrics without paging anyone."""
        return self._any_loss_alarm(
            "EmfWriteFailures",
            EMF_WRITE_FAILURES,
            f"The agent of {self.agent_name} could not publish its CloudWatch metrics: CloudWatch got "
            "nothing, or only part, for those minutes, so no other alarm could fire then. Told once a "
            "document is written again, by this run of the agent or the next (the count outlives a crash: "
            "/var/log/so101-twin/.emf.log.unsent). Usually a full disk: `df -h /var/log` and what fills it. "
            "Any failed publish counts, not only a write (reading the twin's state, a value EMF cannot "
            "hold): the agent's log ('publishing CloudWatch metrics to ... failed', or at a stop 'the last "
            "CloudWatch metrics could not be written') has the traceback, /state agent.sinks 'emf' "
            "last_error the error. A disk that stays full pages as AgentSilent after 5 minutes, and as this "
            "once it has room.",
            doc="docs/servo-health.md",
        )

    def _alarms_for_history(self) -> None:
        """History's two alarms of its own: commits failing, and the oldest unwritten row waiting too long."""
        agent_name = self.agent_name
        # Not the failures' count: the writer backs off to a retry a minute or rarer (a slow failing attempt
        # plus retry_max_s), which leaves minutes with none, and five in a row never came.
        self.alarms["HistoryCommitFailures"] = self._sustained_alarm(
            "HistoryCommitFailures",
            f"History commits of {agent_name} have failed for 5 minutes: the bucket is unreachable or "
            "refuses the role (/state agent.history.last_error). docs/history.md",
            self._metric(HISTORY_COMMITS_FAILING, "Maximum"),
            threshold=1,
            minutes=5,
        )
        self.alarms["HistoryLag"] = self._sustained_alarm(
            "HistoryLag",
            f"History of {agent_name} lags: its oldest unwritten row has waited over "
            f"{HISTORY_LAG_ALARM_S} s for 2 minutes; rows are dropped once the buffer is full. "
            "docs/history.md",
            self._metric(HISTORY_LAG, "Maximum"),
            threshold=HISTORY_LAG_ALARM_S,
            minutes=2,
        )

    def _subscriptions_refused_alarm(self) -> cw.Alarm:
        """SubscriptionsRefused: IoT Core refused a topic filter for 2 minutes (the agent asks again every
        30 s, so a passing refusal clears before it pages). The agent runs and is connected, so neither
        AgentSilent nor ArmsStale would say it: the arms of that filter are simply never heard."""
        return self._sustained_alarm(
            "SubscriptionsRefused",
            f"IoT Core refuses {self.agent_name}'s agent a telemetry subscription, so the arms of that "
            "topic filter are not mirrored: its IAM role does not allow iot:Subscribe on it (the agent's "
            "[telemetry] settings and the stack's differ). The agent's log and /healthz name the filter. "
            "docs/deploy.md, Troubleshooting",
            self._metric(SUBSCRIPTIONS_REFUSED, "Maximum"),
            threshold=1,
            minutes=2,
        )

    def _broker_disconnected_alarm(self) -> cw.Alarm:
        """BrokerDisconnected: a connection to the broker down for 3 minutes. Every arm it carries then reads
        OFFLINE (not paged: arms are switched off on schedules) and the loss figures leave OFFLINE arms out,
        while the agent runs and sends its heartbeat: no other alarm would say it."""
        return self._sustained_alarm(
            "BrokerDisconnected",
            f"The agent of {self.agent_name} has had a connection to IoT Core down for "
            f"{BROKER_DISCONNECTED_MINUTES} minutes, so the arms it carries are not heard (they read "
            "OFFLINE). /healthz says 'broker connection down' and /state agent.broker.last_error, like the "
            "agent's log, names why: the endpoint, the role's iot:Connect, or IoT Core itself (a host cut "
            "off from the network pages as AgentSilent instead: its metrics cannot leave either). "
            "docs/deploy.md, Troubleshooting",
            self._metric(BROKER_DISCONNECTED, "Maximum"),
            threshold=1,
            minutes=BROKER_DISCONNECTED_MINUTES,
        )

    def _messages_lost_alarm(self) -> cw.Alarm:
        """MessagesLost: the arms deliver a tenth less than expected for 5 minutes. Nothing in the agent drops
        these (the loss alarms above say when it does): they never arrived, and IoT Core's per-connection
        quota discards without an error, so without this a fleet past its connections is mirrored at a
        fraction of its rate while every other alarm stays quiet. A minute without LossPercent (every arm
        OFFLINE, which does not page; or no arm's rate known, its worker restarting: WorkerRestarts pages on
        that) is not breaching, and breaks the run."""
        return self._sustained_alarm(
            "MessagesLost",
            f"The arms of {self.agent_name} deliver on average at least {LOSS_ALARM_PERCENT} % fewer "
            "messages than expected (LossPercent), 5 minutes running: IoT Core's per-connection quota "
            "discarding them (the console's Fleet page and /healthz then say so, naming the fix: "
            "maxConnections, or the devices listed), an edge's weak network, or armRateHz above the rate the "
            "edges publish at. docs/servo-health.md",
            self._metric(LOSS_PERCENT, "Maximum"),
            threshold=LOSS_ALARM_PERCENT,
            minutes=LOSS_ALARM_MINUTES,
        )

    def _messages_refused_alarm(self) -> cw.Alarm:
        """MessagesRefused: half the arriving messages refused for 5 minutes. Such arms are OFFLINE (their
        status is of valid messages) and out of the loss figures, and the agent runs: nothing else pages."""
        share = cw.MathExpression(
            # No message at all in a minute divides by zero, which CloudWatch leaves out: not breaching.
            # The device limit's refusals have their own alarm (DeviceLimitReached), with its own fix.
            expression="100 * (refused - kept_out) / (refused + valid * 60)",
            using_metrics={
                "refused": self._metric("Rejects", "Sum"),
                "kept_out": self._metric(DEVICE_LIMIT_REFUSALS, "Sum"),
                "valid": self._metric("MessagesPerSecond", "Average"),
            },
            period=PERIOD,
            label="messages refused (%)",
        )
        return self._sustained_alarm(
            "MessagesRefused",
            f"The agent of {self.agent_name} refuses at least {REFUSED_ALARM_PERCENT} % of the "
            f"messages that arrive (Rejects), {REFUSED_ALARM_MINUTES} minutes running: those arms read "
            "OFFLINE and their twins hold still. The console's Fleet page names the arms whose every "
            "message is refused, and its Events page (or /state health.counters.rejected) gives the "
            "reason and the fix: the edge's units or payload changed, a calibration refused. "
            "docs/telemetry.md",
            share,
            threshold=REFUSED_ALARM_PERCENT,
            minutes=REFUSED_ALARM_MINUTES,
        )

    def _alerts_unsent_alarm(self) -> cw.Alarm:
        """AlertsUnsent: the host's servo alarm e-mails fail to publish, 3 minutes running. The failures
        showed only in /state; CloudWatch's own right to publish to the topic carries this one."""
        return self._sustained_alarm(
            "AlertsUnsent",
            f"The host of {self.agent_name} cannot publish its servo alarm e-mails to this topic "
            f"({ALERT_PUBLISH_FAILURES}), {ALERT_FAILURES_MINUTES} minutes running: servo alarms reach no "
            "one by e-mail. /state agent.sinks 'alerts' last_error, like the agent's log, names SNS's "
            "refusal: the host role's sns:Publish on the topic, or the topic's KMS key. The console's "
            "Fleet and Arm pages show the alarms meanwhile. docs/servo-health.md",
            self._metric(ALERT_PUBLISH_FAILURES, "Sum"),
            threshold=1,
            minutes=ALERT_FAILURES_MINUTES,
        )

    def _arm_losing_alarm(self) -> cw.Alarm:
        """ArmLosingMessages: one arm loses a fifth of its messages for 10 minutes. MessagesLost averages
        the arms, so at 100 arms one arm losing half its messages moves it by half a per cent. A minute
        without WorstArmLossPercent (every arm OFFLINE) is not breaching."""
        return self._sustained_alarm(
            "ArmLosingMessages",
            f"An arm of {self.agent_name} loses at least {ARM_LOSS_ALARM_PERCENT} % of its messages "
            f"(WorstArmLossPercent), {ARM_LOSS_ALARM_MINUTES} minutes running. The console's Events page "
            "names it ('is losing ... of its messages'): its edge's network (Wi-Fi), or its broker "
            "connection over IoT Core's 100 publishes/s. docs/servo-health.md",
            self._metric(WORST_ARM_LOSS_PERCENT, "Maximum"),
            threshold=ARM_LOSS_ALARM_PERCENT,
            minutes=ARM_LOSS_ALARM_MINUTES,
        )

    def _device_limit_alarm(self) -> cw.Alarm:
        """DeviceLimitReached: arms publish and are kept out by telemetry.max_devices, 5 minutes running."""
        return self._sustained_alarm(
            "DeviceLimitReached",
            f"Arms of {self.agent_name} publish, but the agent already tracks telemetry.max_devices arms, so "
            f"their messages are refused ({DEVICE_LIMIT_REFUSALS}), {DEVICE_LIMIT_MINUTES} minutes running. "
            "The console's Fleet page names them: forget the OFFLINE arms retired for good (their places go "
            "to new ones), have the agent forget arms silent for long (telemetry.forget_offline_after_s, and "
            "forget_unseen_after_s for those with alarms no one saw), or raise max_devices in "
            "agent.local.toml. docs/scaling.md",
            self._metric(DEVICE_LIMIT_REFUSALS, "Sum"),
            threshold=1,
            minutes=DEVICE_LIMIT_MINUTES,
        )

    def _outcome_alarm(self, id_: str, name: str, description: str) -> cw.Alarm:
        """Alarm on the last outcome a host script wrote to `name` (1: failed, 0: fine). The scripts write
        only when they run (a start, a save), so a minute without data keeps the alarm as it is (IGNORE): a
        failure pages until a run that succeeds clears it."""
        return cw.Alarm(
            self,
            id_,
            alarm_description=description,
            metric=self._metric(name, "Maximum"),
            threshold=1,
            comparison_operator=cw.ComparisonOperator.GREATER_THAN_OR_EQUAL_TO_THRESHOLD,
            evaluation_periods=1,
            treat_missing_data=cw.TreatMissingData.IGNORE,
        )

    def _alarms_for_host_scripts(self) -> None:
        """What the host finds about itself, outside the agent: a start whose checks failed, and the
        operator's settings or the servo alarm state not kept in the bucket."""
        agent_name = self.agent_name
        self.alarms["HostChecksFailed"] = self._outcome_alarm(
            "HostChecksFailed",
            HOST_CHECKS_FAILED,
            f"The checks after the last start of {agent_name}'s host failed: the desktop a person reaches "
            "through DCV is not working (X, the DCV session, the agent, the viewer or the screen). "
            "`twin instance check` names the check; the next start that passes clears this. "
            "docs/deploy.md, Troubleshooting",
        )
        self.alarms["LocalConfigNotSaved"] = self._outcome_alarm(
            "LocalConfigNotSaved",
            LOCAL_CONFIG_NOT_SAVED,
            f"The stack's bucket does not hold {agent_name}'s /etc/so101-twin/agent.local.toml as it is: "
            "its upload failed, the file is not a config the agent can start with (not saved over the last "
            "good copy), or the host runs a placeholder because the saved copy could not be read. A host "
            "that replaces this one would start without those settings. The host's agent log names "
            "the cause; the next save that succeeds clears this. docs/deploy.md",
        )
        self.alarms["AlarmStateNotSaved"] = self._outcome_alarm(
            "AlarmStateNotSaved",
            ALARM_STATE_NOT_SAVED,
            f"The stack's bucket does not hold {agent_name}'s servo alarm state as the agent last wrote it: "
            "a host that replaces this one would start without its acknowledged and latched alarms. The "
            "host's agent log names the cause; the next save that succeeds clears this. docs/deploy.md",
        )


def _dashboard(
    scope: Construct, agent_name: str, metric: Callable[..., cw.Metric], alarms: list[cw.Alarm]
) -> cw.Dashboard:
    """The fleet at a glance, one graph per question an operator asks, each from the agent's EMF metrics."""

    def labelled(name: str, statistic: str, label: str, **extra: str) -> cw.Metric:
        return metric(name, statistic, **extra).with_(label=label)

    dashboard = cw.Dashboard(
        scope,
        "Dashboard",
        dashboard_name=f"{agent_name}-fleet",
        default_interval=Duration.hours(3),
    )
    dashboard.add_widgets(
        *_fleet_graphs(labelled),
        cw.AlarmStatusWidget(title="Alarms", alarms=alarms, width=24, height=6),
    )
    return dashboard


def _graph(
    title: str, left: list[cw.IMetric], right: list[cw.IMetric] | None = None, **options: Any
) -> cw.GraphWidget:
    """A half-width graph of the dashboard."""
    return cw.GraphWidget(title=title, left=left, right=right or [], width=12, height=6, **options)


def _fleet_graphs(labelled: Callable[..., cw.Metric]) -> list[cw.GraphWidget]:
    """The dashboard's graphs, in order: arms, messages, loss, servo alarms, history, what was lost, whether
    history's commits fail."""
    return [
        _graph(
            "Arms by status",
            [
                labelled("DevicesOnline", "Maximum", "online"),
                labelled("DevicesStale", "Maximum", "stale"),
                labelled("DevicesOffline", "Maximum", "offline"),
            ],
            stacked=True,
        ),
        _graph(
            "Mirrored messages per second (all arms) and rejected messages",
            [labelled("MessagesPerSecond", "Average", "mirrored msg/s")],
            [labelled("Rejects", "Sum", "rejected per minute")],
        ),
        _graph(
            # The agent sends no loss it did not measure (agent.fleet_totals): 0 % read as an all-clear.
            "Loss: share of expected messages that never arrived (%; no line while nothing is measured)",
            [
                labelled(LOSS_PERCENT, "Maximum", "loss % (fleet)"),
                labelled(WORST_ARM_LOSS_PERCENT, "Maximum", "loss % (the arm losing most)"),
            ],
            left_y_axis=cw.YAxisProps(min=0),
        ),
        _graph(
            "Servo alarms present, by severity",
            [
                labelled("ActiveAlarms", "Maximum", severity, **{SEVERITY_DIMENSION: severity})
                for severity in SEVERITIES
            ],
            left_y_axis=cw.YAxisProps(min=0),
        ),
        _graph(
            "History: lag of the oldest unwritten row (s) and rows dropped",
            [labelled(HISTORY_LAG, "Maximum", "lag s")],
            [labelled(HISTORY_ROWS_DROPPED, "Sum", "rows dropped per minute")],
        ),
        _graph(
            "Lost: messages dropped, sink drops, worker restarts, history commit failures, "
            "metrics file writes failed (per minute)",
            [
                labelled(MESSAGES_DROPPED, "Sum", "messages dropped"),
                labelled(SINK_DROPS, "Sum", "sink drops"),
                labelled(WORKER_RESTARTS, "Sum", "worker restarts"),
                labelled(HISTORY_COMMIT_FAILURES, "Sum", "history commit failures"),
                labelled(EMF_WRITE_FAILURES, "Sum", "metrics file writes failed"),
            ],
            left_y_axis=cw.YAxisProps(min=0),
        ),
        # Under the history graph, after the one counting commit failures: in an outage the writer backs off
        # to a commit a minute or rarer, so those counts leave minutes at 0; this is what the alarm reads.
        _graph(
            "History: commits failing (1 while the last commit failed)",
            [labelled(HISTORY_COMMITS_FAILING, "Maximum", "commits failing")],
            left_y_axis=cw.YAxisProps(min=0, max=1),
        ),
    ]
