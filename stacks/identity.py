"""The host's IAM role: exactly what the agent, DCV and SSM need, in this account and region only."""

from __future__ import annotations

from aws_cdk import Acknowledgment, RemovalPolicy, Stack, Validations
from aws_cdk import aws_iam as iam
from aws_cdk import aws_logs as logs
from constructs import Construct
from twin.core.topics import TELEMETRY_SUFFIX
from twin.transport.plan import (
    DEFAULT_MAX_CONNECTIONS,
    IOT_PUBLISHES_PER_CONNECTION,
    listed_connections,
    pool_client_ids,
    shared_group,
)

from stacks.skips import LOG_GROUP_KMS, nag_arn, skip_checkov

# The edge's default publish rate (telemetry contract); the agent plans its listed connections with it.
EDGE_RATE_HZ = 10.0


class TwinIdentity(Construct):
    """Instance role plus the agent's log group.

    Attributes: `role`, `agent_log_group`. Grants for things created elsewhere (the DCV password
    secret, the S3 assets) are made by the stack where the two meet.
    """

    def __init__(
        self,
        scope: Construct,
        id_: str,
        *,
        topic_prefix: str,
        devices: tuple[str, ...],
        client_id_prefix: str,
        stack_name: str,
    ) -> None:
        super().__init__(scope, id_)
        stack = Stack.of(self)
        self.role = iam.Role(
            self,
            "HostRole",
            assumed_by=iam.ServicePrincipal("ec2.amazonaws.com"),
            description="so101-twin host: IoT telemetry subscribe, DCV licence, SSM, agent logs",
            managed_policies=[iam.ManagedPolicy.from_aws_managed_policy_name("AmazonSSMManagedInstanceCore")],
        )
        Validations.of(self.role).acknowledge(
            Acknowledgment(
                # Managed policy ARNs keep the partition as a token even in a concrete environment.
                id="AwsSolutions-IAM4[Policy::arn:<AWS::Partition>:iam::aws:policy/AmazonSSMManagedInstanceCore]",
                reason="SSM Session Manager is the way onto the host instead of SSH; AWS maintains this "
                "policy as the minimum for the SSM agent, and a hand-copied inline version would drift "
                "from it.",
            )
        )

        def iot_arn(resource: str) -> str:
            return stack.format_arn(service="iot", resource=resource)

        fleet = devices == ("*",)
        # IoT Core delivers at most 100 publishes/s per connection, so the agent receives over a pool of
        # connections (twin.transport.pool) with client ids `<prefix><random>-<index>`: the policy allows
        # exactly those indexes. Listed devices are subscribed one filter each; the whole fleet through the
        # shared subscription `$share/<group>/<prefix>/+/telemetry` (MQTT '+' is literal in a policy
        # resource, so the filter is granted exactly; Receive matches the shared topic form per device).
        if fleet:
            connections = DEFAULT_MAX_CONNECTIONS
            group = shared_group(client_id_prefix)
            filters = [f"$share/{group}/{topic_prefix}/+/{TELEMETRY_SUFFIX}"]
            topics = [f"$share/{group}/{topic_prefix}/*/{TELEMETRY_SUFFIX}"]
        else:
            connections = listed_connections(
                devices, rate_hz=EDGE_RATE_HZ, limit=IOT_PUBLISHES_PER_CONNECTION, iot=True
            )
            filters = [f"{topic_prefix}/{d}/{TELEMETRY_SUFFIX}" for d in devices]
            topics = filters
        client_ids = pool_client_ids(client_id_prefix, connections)
        self.role.add_to_policy(
            iam.PolicyStatement(
                sid="IotConnectAsAgent",
                actions=["iot:Connect"],
                resources=[iot_arn(f"client/{c}") for c in client_ids],
            )
        )
        self.role.add_to_policy(
            iam.PolicyStatement(
                sid="IotSubscribeTelemetry",
                actions=["iot:Subscribe"],
                resources=[iot_arn(f"topicfilter/{f}") for f in filters],
            )
        )
        self.role.add_to_policy(
            iam.PolicyStatement(
                sid="IotReceiveTelemetry",
                actions=["iot:Receive"],
                resources=[iot_arn(f"topic/{t}") for t in topics],
            )
        )
        self.role.add_to_policy(
            iam.PolicyStatement(sid="IotFindEndpoint", actions=["iot:DescribeEndpoint"], resources=["*"])
        )
        dcv_license = f"arn:{stack.partition}:s3:::dcv-license.{stack.region}/*"
        self.role.add_to_policy(
            iam.PolicyStatement(sid="DcvLicense", actions=["s3:GetObject"], resources=[dcv_license])
        )

        self.agent_log_group = logs.LogGroup(
            self,
            "AgentLogGroup",
            log_group_name=f"/so101-twin/{stack_name}/host",
            retention=logs.RetentionDays.ONE_YEAR,
            removal_policy=RemovalPolicy.DESTROY,
        )
        skip_checkov(self.agent_log_group, {"CKV_AWS_158": LOG_GROUP_KMS})
        self.role.add_to_policy(
            iam.PolicyStatement(
                sid="HostLogs",
                actions=["logs:CreateLogStream", "logs:PutLogEvents", "logs:DescribeLogStreams"],
                resources=[self.agent_log_group.log_group_arn],
            )
        )

        # One acknowledgement per wildcard, each saying why it cannot be narrower.
        client_reason = (
            "Each agent process connects with unique client ids (fixed prefix, a random part so two agents "
            "never kick each other off, then the connection's index in its pool); the wildcard covers the "
            "random part only, one resource per pool connection, in this account and region."
        )
        reasons = {
            **{
                nag_arn(stack, "arn:{partition}:iot:{region}:{account}:client/") + c: client_reason
                for c in client_ids
            },
            "*": (
                "iot:DescribeEndpoint has no resource type (IoT action-resources table), so it cannot be "
                "scoped; it only returns the account's data endpoint address."
            ),
            nag_arn(stack, "arn:{partition}:s3:::dcv-license.{region}/*"): (
                "DCV on EC2 licenses itself by reading objects from this AWS-owned regional bucket; the "
                "object keys are not documented, so the grant is read-only on that bucket's objects (DCV "
                "admin guide, setting-up-license)."
            ),
        }
        if fleet:
            receive = nag_arn(stack, "arn:{partition}:iot:{region}:{account}:topic/") + topics[0]
            reasons[receive] = (
                "devices='*' mirrors the whole fleet through the agent's shared subscription: it "
                "receives every device's telemetry topic under the prefix; the wildcard stands for the "
                "device-id topic level only."
            )
        for resource, reason in reasons.items():
            Validations.of(self.role).acknowledge(
                Acknowledgment(id=f"AwsSolutions-IAM5[Resource::{resource}]", reason=reason)
            )
