"""What the deployed stack publishes, read at synth: its CloudFormation outputs.

A template cannot see the values it was deployed with, so the stack publishes what later synths compare
with as outputs (`InstanceFingerprint` for the replacement guard, `Settings` for the settings guard). The
CDK CLI hands the app the account and region it deploys to (CDK_DEFAULT_ACCOUNT/REGION), and one
DescribeStacks call with the deployer's own credentials reads the outputs. Without credentials (a synth in
CI) or when the call fails there is nothing to compare, and the guards warn instead of refusing.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

# (stack name, region) -> the deployed stack's outputs by key, None when the stack does not exist.
DeployedReader = Callable[[str, str], Mapping[str, str] | None]


class DeployedUnknownError(Exception):
    """The deployed stack could not be read (no credentials, no network, access denied)."""


def read_deployed_outputs(stack_name: str, region: str, cloudformation: Any = None) -> dict[str, str] | None:
    """The deployed stack's outputs; None if the stack does not exist."""
    try:
        from botocore.exceptions import BotoCoreError, ClientError  # noqa: PLC0415

        if cloudformation is None:
            import boto3  # noqa: PLC0415
            from botocore.config import Config  # noqa: PLC0415

            cloudformation = boto3.client(
                "cloudformation",
                region_name=region,
                config=Config(connect_timeout=5, read_timeout=10, retries={"max_attempts": 2}),
            )
        try:
            stacks = cloudformation.describe_stacks(StackName=stack_name)["Stacks"]
        except ClientError as exc:
            error = exc.response.get("Error", {})
            if error.get("Code") == "ValidationError" and "does not exist" in error.get("Message", ""):
                return None
            raise DeployedUnknownError(f"{error.get('Code')}: {error.get('Message')}") from exc
    except BotoCoreError as exc:
        raise DeployedUnknownError(str(exc)) from exc
    return {o["OutputKey"]: o.get("OutputValue", "") for o in stacks[0].get("Outputs", [])}
