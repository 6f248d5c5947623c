"""The host's IAM role: exactly what the agent, DCV and SSM need, in this account and region only.

SSM: instead of the managed AmazonSSMManagedInstanceCore (which also reads every SSM parameter of the account
and region, and serves patching, inventory and Distributor), the calls the SSM Agent makes for what this
host uses: registration and heartbeat, Run Command (`twin instance status|check|start`), Session Manager
(the shell) and the State Manager association that updates it in place (AWS-RunShellScript). Parameter
reads are granted where the parameter is made (stacks/twin_host.py), on the stack's own parameter only.
"""

from __future__ import annotations

from aws_cdk import Acknowledgment, RemovalPolicy, Stack, Validations
from aws_cdk import aws_iam as iam
from aws_cdk import aws_logs as logs
from constructs import Construct
from twin.core.topics import TELEMETRY_SUFFIX
from twin.transport.plan import (
    IOT_PUBLISHES_PER_CONNECTION,
    PoolSettings,
    pool_client_ids,
    shared_group,
)

from stacks.skips import LOG_GROUP_KMS, nag_arn, skip_checkov

# Listed devices per IoT statement: IAM keeps a statement whole, and CDK moves whole statements into the
# role's overflow policies (each at most 6,144 characters), so a long list is granted in short statements.
DEVICES_PER_STATEMENT = 16


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
        arm_rate_hz: float,
        max_connections: int,
    ) -> None:
        super().__init__(scope, id_)
        stack = Stack.of(self)
        self.role = iam.Role(
            self,
            "HostRole",
            assumed_by=iam.ServicePrincipal("ec2.amazonaws.com"),
            description="so101-twin host: IoT telemetry subscribe, DCV licence, SSM, agent logs",
        )
        self._grant_ssm_agent(stack)

        # The agent's own plan on IoT Core (twin.transport.plan), so the role allows exactly its client ids.
        plan = PoolSettings(
            topic_prefix,
            devices,
            rate_hz=arm_rate_hz,
            limit=IOT_PUBLISHES_PER_CONNECTION,
            max_connections=max_connections,
        )
        client_ids = pool_client_ids(client_id_prefix, plan.most_connections(iot=True))
        filters, topics = _telemetry_topics(plan.fleet, topic_prefix, devices, client_id_prefix)
        self._grant_iot_telemetry(stack, client_ids, filters, topics)
        dcv_license = f"arn:{stack.partition}:s3:::dcv-license.{stack.region}/*"
        self.role.add_to_policy(
            iam.PolicyStatement(sid="DcvLicense", actions=["s3:GetObject"], resources=[dcv_license])
        )

        self.agent_log_group = self._agent_log_group(stack_name)
        self._acknowledge_wildcards(stack, client_ids, topics, plan.fleet)

    def _grant_iot_telemetry(
        self, stack: Stack, client_ids: list[str], filters: list[str], topics: list[str]
    ) -> None:
        """IoT Core: connect as the pool's client ids, subscribe and receive telemetry, find the endpoint."""

        def iot_arn(resource: str) -> str:
            return stack.format_arn(service="iot", resource=resource)

        self.role.add_to_policy(
            iam.PolicyStatement(
                sid="IotConnectAsAgent",
                actions=["iot:Connect"],
                resources=[iot_arn(f"client/{c}") for c in client_ids],
            )
        )
        for n in range(0, len(filters), DEVICES_PER_STATEMENT):
            part = "" if n == 0 else str(n // DEVICES_PER_STATEMENT + 1)
            self.role.add_to_policy(
                iam.PolicyStatement(
                    sid=f"IotSubscribeTelemetry{part}",
                    actions=["iot:Subscribe"],
                    resources=[iot_arn(f"topicfilter/{f}") for f in filters[n : n + DEVICES_PER_STATEMENT]],
                )
            )
            self.role.add_to_policy(
                iam.PolicyStatement(
                    sid=f"IotReceiveTelemetry{part}",
                    actions=["iot:Receive"],
                    resources=[iot_arn(f"topic/{t}") for t in topics[n : n + DEVICES_PER_STATEMENT]],
                )
            )
        self.role.add_to_policy(
            iam.PolicyStatement(sid="IotFindEndpoint", actions=["iot:DescribeEndpoint"], resources=["*"])
        )

    def _agent_log_group(self, stack_name: str) -> logs.LogGroup:
        """The host's log group, which the role may write streams to."""
        agent_log_group = logs.LogGroup(
            self,
            "AgentLogGroup",
            log_group_name=f"/so101-twin/{stack_name}/host",
            retention=logs.RetentionDays.ONE_YEAR,
            removal_policy=RemovalPolicy.DESTROY,
        )
        skip_checkov(agent_log_group, {"CKV_AWS_158": LOG_GROUP_KMS})
        self.role.add_to_policy(
            iam.PolicyStatement(
                sid="HostLogs",
                actions=["logs:CreateLogStream", "logs:PutLogEvents", "logs:DescribeLogStreams"],
                resources=[agent_log_group.log_group_arn],
            )
        )
        return agent_log_group

    def _acknowledge_wildcards(
        self, stack: Stack, client_ids: list[str], topics: list[str], fleet: bool
    ) -> None:
        """The role's cdk-nag acknowledgements (AwsSolutions-IAM5)."""
        # One acknowledgement per wildcard, each saying why it cannot be narrower.
        client_reason = (
            "Each agent process connects with unique client ids (fixed prefix, a random part so two agents "
            "never kick each other off, then the connection's index in its pool); the wildcard covers the "
            "random part only; the index patterns ('?' one character, where the pool writes a digit) "
            "match exactly the pool's connection indexes, in this account and region."
        )
        reasons = {
            **{
                nag_arn(stack, "arn:{partition}:iot:{region}:{account}:client/") + c: client_reason
                for c in client_ids
            },
            "*": (
                "iot:DescribeEndpoint has no resource type (IoT action-resources table), so it cannot be "
                "scoped; it only returns the account's data endpoint address. The SSM Agent's own calls "
                "(SsmAgentCore, RunCommandMessages, SessionManagerChannels) act on the calling instance "
                "itself, which the service identifies from the instance role's credentials; AWS grants "
                "them on '*' in its own policy, and no resource ARN narrows them."
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

    def _grant_ssm_agent(self, stack: Stack) -> None:
        """The SSM Agent's calls for registration, Run Command, Session Manager and the association."""
        self.role.add_to_policy(
            iam.PolicyStatement(
                sid="SsmAgentCore",
                actions=[
                    # Registration and heartbeat (every SSM feature needs the instance to be managed).
                    "ssm:UpdateInstanceInformation",
                    # State Manager: the agent lists its associations, reads each one's document and
                    # reports the outcome (amazon-ssm-agent, agent/association/service).
                    "ssm:ListInstanceAssociations",
                    "ssm:DescribeAssociation",
                    "ssm:UpdateInstanceAssociationStatus",
                ],
                resources=["*"],
            )
        )
        self.role.add_to_policy(
            iam.PolicyStatement(
                sid="SsmAssociationDocument",
                actions=["ssm:GetDocument", "ssm:DescribeDocument"],
                # The one document the association and `twin instance` run: AWS-owned, so no account.
                resources=[f"arn:{stack.partition}:ssm:{stack.region}::document/AWS-RunShellScript"],
            )
        )
        self.role.add_to_policy(
            iam.PolicyStatement(
                sid="RunCommandMessages",
                actions=[
                    "ec2messages:AcknowledgeMessage",
                    "ec2messages:DeleteMessage",
                    "ec2messages:FailMessage",
                    "ec2messages:GetEndpoint",
                    "ec2messages:GetMessages",
                    "ec2messages:SendReply",
                ],
                resources=["*"],
            )
        )
        self.role.add_to_policy(
            iam.PolicyStatement(
                sid="SessionManagerChannels",
                actions=[
                    "ssmmessages:CreateControlChannel",
                    "ssmmessages:CreateDataChannel",
                    "ssmmessages:OpenControlChannel",
                    "ssmmessages:OpenDataChannel",
                ],
                resources=["*"],
            )
        )
        skip_checkov(
            self.role.node.find_child("DefaultPolicy"),
            {
                "CKV_AWS_111": "The writes without a resource constraint are the SSM Agent's reports about "
                "the instance it runs on (instance information, association status, Run Command replies, "
                "Session Manager channels): the service ties each to the calling instance's role, and these "
                "actions take no resource ARN that could narrow them."
            },
        )


def _telemetry_topics(
    fleet: bool, topic_prefix: str, devices: tuple[str, ...], client_id_prefix: str
) -> tuple[list[str], list[str]]:
    """The topic filters the agent subscribes and the topics it receives."""
    # IoT Core delivers at most 100 publishes/s per connection, so the agent receives over a pool of
    # connections (twin.transport.pool) with client ids `<prefix><random>-<index>`: the policy allows
    # exactly those indexes (as many as the listed devices need, or maxConnections for the fleet). Listed
    # devices are subscribed one filter each; the whole fleet through the shared subscription
    # `$share/<group>/<prefix>/+/telemetry` (MQTT '+' is literal in a policy resource, so the filter is
    # granted exactly; Receive matches the shared topic form per device).
    if fleet:
        group = shared_group(client_id_prefix)
        return (
            [f"$share/{group}/{topic_prefix}/+/{TELEMETRY_SUFFIX}"],
            [f"$share/{group}/{topic_prefix}/*/{TELEMETRY_SUFFIX}"],
        )
    filters = [f"{topic_prefix}/{d}/{TELEMETRY_SUFFIX}" for d in devices]
    return filters, filters
