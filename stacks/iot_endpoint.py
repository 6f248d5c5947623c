"""The account's IoT Core data endpoint, resolved at deploy time so it can be a stack output."""

from __future__ import annotations

from aws_cdk import Acknowledgment, Stack, Validations
from aws_cdk import aws_iam as iam
from aws_cdk import custom_resources as cr
from constructs import Construct

from stacks.skips import LAMBDA_DEPLOY_TIME_ONLY, LOG_GROUP_KMS, skip_checkov

_PROVIDER_ID = "AWS679f53fac002430cb0da5b7982bd2287"


class IotDataEndpoint(Construct):
    """AwsCustomResource calling iot:DescribeEndpoint (iot:Data-ATS). Attribute: `address`."""

    def __init__(self, scope: Construct, id_: str) -> None:
        super().__init__(scope, id_)
        call = cr.AwsSdkCall(
            service="Iot",
            action="describeEndpoint",
            parameters={"endpointType": "iot:Data-ATS"},
            physical_resource_id=cr.PhysicalResourceId.from_response("endpointAddress"),
        )
        self.resource = cr.AwsCustomResource(
            self,
            "DescribeEndpoint",
            on_create=call,
            on_update=call,
            policy=cr.AwsCustomResourcePolicy.from_statements(
                [iam.PolicyStatement(actions=["iot:DescribeEndpoint"], resources=["*"])]
            ),
            # The SDK bundled with the Lambda runtime has DescribeEndpoint; no download at deploy time.
            install_latest_aws_sdk=False,
        )
        Validations.of(self.resource).acknowledge(
            Acknowledgment(
                id="AwsSolutions-IAM5[Resource::*]",
                reason="iot:DescribeEndpoint has no resource type, so it cannot be scoped; it is the "
                "only action the deploy-time lookup may call.",
            )
        )
        # The lookup's Lambda is a singleton CDK places at stack level (AwsCustomResource's fixed id).
        provider = Stack.of(self).node.try_find_child(_PROVIDER_ID)
        if provider is not None:
            skip_checkov(provider, LAMBDA_DEPLOY_TIME_ONLY)
            log_group = provider.node.try_find_child("LogGroup")
            if log_group is not None:
                skip_checkov(log_group, {"CKV_AWS_158": LOG_GROUP_KMS})
            Validations.of(provider).acknowledge(
                Acknowledgment(
                    id="AwsSolutions-IAM4[Policy::arn:<AWS::Partition>:iam::aws:policy/service-role/"
                    "AWSLambdaBasicExecutionRole]",
                    reason="The deploy-time lookup Lambda only needs to write its own logs; this AWS "
                    "policy grants exactly CreateLogGroup/CreateLogStream/PutLogEvents.",
                )
            )
        self.address: str = self.resource.get_response_field("endpointAddress")
