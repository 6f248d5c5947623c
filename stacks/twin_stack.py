"""The single so101-twin stack: network + identity + twin host (+ auto-stop), and the outputs users need."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from aws_cdk import CfnOutput, Stack
from constructs import Construct

from stacks.auto_stop import AutoStop
from stacks.history_bucket import HistoryBucket
from stacks.identity import TwinIdentity
from stacks.iot_endpoint import IotDataEndpoint
from stacks.monitoring import TwinMonitoring, silent_alarm_name
from stacks.network import DCV_PORT, TwinNetwork
from stacks.settings import TwinSettings
from stacks.twin_host import DESKTOP_USER, REPO_ROOT, TwinHost

# `twin instance` reads these keys; renaming one breaks it.
OUTPUT_KEYS = (
    "DcvUrl",
    "InstanceId",
    "IotEndpoint",
    "DcvPasswordSecret",
    "SsmSessionCommand",
    "DeploymentVersion",
    "InstanceFingerprint",
    "UpdateAssociationId",
    "HostLogGroup",
    "Settings",
    "CalibrationUri",
)


class TwinStack(Stack):
    """Everything for one cloud twin: `cdk deploy` builds it, `cdk destroy` removes all of it."""

    def __init__(
        self,
        scope: Construct,
        id_: str,
        *,
        settings: TwinSettings,
        settings_output: str,
        agent_source: Path | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(scope, id_, **kwargs)
        self.settings = settings

        self.network = TwinNetwork(
            self,
            "Network",
            client_cidr=settings.client_cidr,
            allow_any_client=settings.allow_any_client,
            availability_zone=settings.availability_zone,
        )
        self.identity = TwinIdentity(
            self,
            "Identity",
            topic_prefix=settings.topic_prefix,
            devices=settings.devices,
            client_id_prefix=settings.client_id_prefix,
            stack_name=settings.stack_name,
            arm_rate_hz=settings.arm_rate_hz,
            max_connections=settings.max_connections,
        )
        self.history = HistoryBucket(
            self,
            "History",
            infrequent_access_after_days=settings.history_ia_after_days,
            retain=settings.retain_history,
        )
        self.history.grant_agent(self.identity.role)
        self.monitoring = TwinMonitoring(
            self, "Monitoring", agent_name=settings.stack_name, alarm_email=settings.alarm_email
        )
        self.monitoring.grant_host(self.identity.role)
        self.host = self._host(settings, agent_source)
        self.monitoring.watch_host(self.host.instance.instance_id)
        self.iot_endpoint = IotDataEndpoint(self, "IotEndpointLookup")
        self.auto_stop = self._auto_stop(settings)

        self._access_outputs()
        self._alarm_and_data_outputs(settings)
        self._operation_outputs(settings, settings_output)

    def _host(self, settings: TwinSettings, agent_source: Path | None) -> TwinHost:
        """The twin host, on the network with the identity's role, and the settings its agent runs with."""
        return TwinHost(
            self,
            "Host",
            vpc=self.network.vpc,
            security_group=self.network.security_group,
            role=self.identity.role,
            instance_type=settings.instance_type,
            volume_gb=settings.volume_gb,
            ami_ssm_parameter=settings.ami_ssm_parameter,
            ami_id=settings.ami_id,
            termination_protection=settings.termination_protection,
            host_generation=settings.host_generation,
            agent_settings={
                "TOPIC_PREFIX": settings.topic_prefix,
                "DEVICES": ",".join(settings.devices),
                # The agent plans its connections with these, and the role allows exactly that many.
                "ARM_RATE_HZ": str(settings.arm_rate_hz),
                "MAX_CONNECTIONS": str(settings.max_connections),
                "UNITS": settings.units,
                "ROS2": "true" if settings.ros2 else "false",
                "CLIENT_ID_PREFIX": settings.client_id_prefix,
                "DESKTOP_USER": DESKTOP_USER,
                "LOG_GROUP": self.identity.agent_log_group.log_group_name,
                # The CloudWatch metrics' Agent dimension, which the monitoring alarms below watch.
                "AGENT_NAME": settings.stack_name,
                "HISTORY_URI": self.history.uri,
                "CALIBRATIONS_URI": self.history.calibration_uri,
                # The copy of the operator's agent.local.toml: a host that replaces this one starts with it.
                "HOST_STATE_URI": self.history.host_state_uri,
                # The host's agent publishes servo alarm transitions here (critical ones; warnings too
                # with alarmWarnings).
                "ALERT_TOPIC_ARN": self.monitoring.topic.topic_arn,
                "ALERT_WARNINGS": "true" if settings.alarm_warnings else "false",
                # The host turns this alarm's actions on once it is up (stacks/monitoring.py).
                "SILENT_ALARM": silent_alarm_name(settings.stack_name),
                "RECORD_SESSIONS": "true" if settings.record_sessions else "false",
                # DCV's idle-timeout in dcv.conf (bootstrap.sh, step dcv).
                "DCV_IDLE_TIMEOUT": str(settings.dcv_idle_timeout_minutes),
            },
            agent_source=agent_source or REPO_ROOT,
        )

    def _auto_stop(self, settings: TwinSettings) -> AutoStop | None:
        """The host's stop schedule, when the settings give one."""
        return (
            AutoStop(
                self,
                "AutoStop",
                instance_id=self.host.instance.instance_id,
                cron=settings.auto_stop_cron,
                timezone=settings.auto_stop_timezone,
            )
            if settings.auto_stop_cron
            else None
        )

    def _access_outputs(self) -> None:
        """Outputs for reaching the host: the DCV URL and password, the instance, the IoT endpoint."""
        secret_arn = self.host.password_secret.secret_arn
        CfnOutput(
            self,
            "DcvUrl",
            value=f"https://{self.host.eip.attr_public_ip}:{DCV_PORT}/#console",
            # `twin instance password` first: it names what is wrong (no credentials, a secret gone) where
            # the raw secret ARN leaves a user to find the AWS CLI call themselves.
            description=f"Open in a browser; log in as '{DESKTOP_USER}' with the password "
            "`twin instance password` prints (with the AWS CLI: the command in DcvPasswordCommand); "
            "the certificate is self-signed: accept the warning.",
        )
        CfnOutput(self, "InstanceId", value=self.host.instance.instance_id, description="The twin host")
        CfnOutput(
            self,
            "IotEndpoint",
            value=self.iot_endpoint.address,
            description="IoT Core data endpoint (iot:Data-ATS) the agent subscribes to",
        )
        CfnOutput(
            self,
            "DcvPasswordSecret",
            value=secret_arn,
            description="Secret holding the DCV password; read it with `twin instance password` "
            "(with the AWS CLI: the command in DcvPasswordCommand)",
        )
        CfnOutput(
            self,
            "DcvPasswordCommand",
            value=f"aws secretsmanager get-secret-value --region {self.region} --secret-id {secret_arn} "
            "--query SecretString --output text",
            description="Prints the DCV password",
        )

    def _alarm_and_data_outputs(self, settings: TwinSettings) -> None:
        """Outputs for the alarms (topic, dashboard) and the data the stack keeps (history, calibrations)."""
        CfnOutput(
            self,
            "AlarmTopic",
            value=self.monitoring.topic.topic_arn,
            description="SNS topic of the alarms: the host's servo alarms and the CloudWatch alarms "
            "(subscribe more endpoints to it)",
        )
        CfnOutput(
            self,
            "Dashboard",
            value=f"https://console.aws.amazon.com/cloudwatch/home?region={self.region}#dashboards/dashboard/"
            f"{self.monitoring.dashboard.dashboard_name}",
            description="CloudWatch dashboard of the fleet: arms, rates, loss, alarms, history lag",
        )
        CfnOutput(
            self,
            "HistoryUri",
            value=self.history.uri,
            description="Telemetry history (Delta Lake); read it with `twin history ls --history <this>`. "
            + (
                "Kept on cdk destroy: delete it with aws s3 rb s3://<bucket> --force (docs/history.md)"
                if settings.retain_history
                else "Deleted with the stack (retainHistory=false)"
            ),
        )
        CfnOutput(
            self,
            "CalibrationUri",
            value=self.history.calibration_uri,
            description="Where each arm's LeRobot calibration is kept (<device>.json); `twin calibration "
            "push ARM FILE` uploads one and the agent picks it up within calibration_poll_s",
        )

    def _operation_outputs(self, settings: TwinSettings, settings_output: str) -> None:
        """Outputs for operating the host: what it runs with which settings, its update, logs and shell."""
        CfnOutput(
            self,
            "DeploymentVersion",
            value=self.host.deployment_version,
            description="Version of agent code + settings for the host; `twin instance status` shows its own",
        )
        CfnOutput(
            self,
            "InstanceFingerprint",
            value=json.dumps(settings.instance_fingerprint, sort_keys=True),
            description="Settings whose change replaces the instance; synth compares them (replaceInstance)",
        )
        CfnOutput(
            self,
            "UpdateAssociationId",
            value=self.host.update_association.attr_association_id,
            description="State Manager association that updates the host in place after a deploy",
        )
        CfnOutput(
            self,
            "HostLogGroup",
            value=self.identity.agent_log_group.log_group_name,
            description=(
                "Host log group: streams <instance-id>/bootstrap, /agent, /dcv, /emf, /start, /host-emf"
            ),
        )
        CfnOutput(
            self,
            "Settings",
            value=settings_output,
            description="The settings this stack was deployed with (JSON); `twin instance settings` prints "
            "them as twin.settings.toml, and the next synth refuses to reset one it is not given",
        )
        CfnOutput(
            self,
            "SsmSessionCommand",
            value=f"aws ssm start-session --region {self.region} --target {self.host.instance.instance_id}",
            description="A shell on the host without SSH (needs the Session Manager plugin)",
        )
