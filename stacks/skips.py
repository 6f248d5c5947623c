"""Justified exceptions for the template scanners (Checkov, cfn-lint), written into resource Metadata.

Keeping them in the template, next to the resource, means every scanner run sees the same
exceptions with their reasons, and a reviewer reads them where the resource is defined.
"""

from __future__ import annotations

from aws_cdk import CfnResource, Stack, Token
from constructs import IConstruct

LOG_GROUP_KMS = (
    "CloudWatch Logs already encrypts at rest with an AWS-owned key; these logs hold no secrets and a "
    "customer key would add cost and a key policy for no gain in a single-user dev stack."
)
LAMBDA_DEPLOY_TIME_ONLY = {
    "CKV_AWS_115": "Runs only during CloudFormation deploys, one invocation at a time: a concurrency "
    "reservation would only take capacity from the account.",
    "CKV_AWS_116": "Invoked synchronously by CloudFormation, which reports failures itself; an async DLQ "
    "would never receive anything.",
    "CKV_AWS_117": "Calls AWS APIs only and the VPC has no NAT or endpoints by design; in the VPC it "
    "could not reach them.",
}


def _cfn(construct: IConstruct) -> CfnResource:
    child = construct.node.default_child if not isinstance(construct, CfnResource) else construct
    if not isinstance(child, CfnResource):
        raise TypeError(f"{construct.node.path} has no CloudFormation resource to annotate")
    return child


def skip_checkov(construct: IConstruct, reasons: dict[str, str]) -> None:
    """Record Checkov skips (id -> justification) on the construct's CloudFormation resource."""
    resource = _cfn(construct)
    existing = resource.get_metadata("checkov") or {"skip": []}
    existing["skip"].extend({"id": check, "comment": reason} for check, reason in sorted(reasons.items()))
    resource.add_metadata("checkov", existing)


def ignore_cfn_lint(construct: IConstruct, checks: list[str]) -> None:
    """Ignore cfn-lint rules on one resource (the reason sits in the caller's comment and acknowledgement)."""
    _cfn(construct).add_metadata("cfn-lint", {"config": {"ignore_checks": checks}})


def nag_arn(stack: Stack, template: str) -> str:
    """An ARN as cdk-nag prints it in finding ids: pseudo parameters shown as <AWS::Region> while they are
    unresolved tokens (environment-agnostic synth), as their values once the environment is concrete
    (`cdk synth` with a default region). Template fields: {partition}, {region}, {account}."""

    def shown(value: str, name: str) -> str:
        return f"<AWS::{name}>" if Token.is_unresolved(value) else value

    return template.format(
        partition=shown(stack.partition, "Partition"),
        region=shown(stack.region, "Region"),
        account=shown(stack.account, "AccountId"),
    )
