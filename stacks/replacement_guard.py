"""Refuse, at synth, a settings change that would replace the twin host, unless the deployer confirms it.

CloudFormation replaces an instance whose availability zone, root volume size or image changes: a new root
disk, the first boot again (about 15 minutes), everything kept on the old disk gone. A template cannot see
the values it was deployed with, so the stack publishes them as the output `InstanceFingerprint` and synth
compares: the CDK CLI hands the app the account and region it deploys to (CDK_DEFAULT_ACCOUNT/REGION), and
one DescribeStacks call with the deployer's own credentials reads the output. Without credentials (a synth
in CI) or when the call fails there is nothing to compare, and synth warns instead of refusing.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Mapping
from typing import Any

from stacks.settings import SettingsError

log = logging.getLogger(__name__)

FINGERPRINT_OUTPUT = "InstanceFingerprint"
CONFIRM_FLAG = "replaceInstance"
_SHOWN = {"availabilityZone": "availabilityZone", "volumeGb": "volumeGb", "image": "amiId/amiSsmParameter"}

# (stack name, region) -> the deployed fingerprint, None when the stack does not exist.
DeployedReader = Callable[[str, str], Mapping[str, str] | None]


class DeployedUnknownError(Exception):
    """The deployed stack could not be read (no credentials, no network, access denied)."""


def read_deployed_fingerprint(
    stack_name: str, region: str, cloudformation: Any = None
) -> dict[str, str] | None:
    """The `InstanceFingerprint` output of the deployed stack; None if the stack or the output is absent."""
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
    outputs = {o["OutputKey"]: o.get("OutputValue", "") for o in stacks[0].get("Outputs", [])}
    if FINGERPRINT_OUTPUT not in outputs:
        return None
    try:
        value = json.loads(outputs[FINGERPRINT_OUTPUT])
    except ValueError as exc:
        raise DeployedUnknownError(
            f"output {FINGERPRINT_OUTPUT} is not JSON: {outputs[FINGERPRINT_OUTPUT]!r}"
        ) from exc
    return {str(k): str(v) for k, v in value.items()}


def replacing_changes(deployed: Mapping[str, str], wanted: Mapping[str, str]) -> list[str]:
    """Human-readable `key: deployed -> wanted` for every fingerprint entry that differs."""
    changes = []
    for key in sorted(set(deployed) | set(wanted)):
        before, after = deployed.get(key, ""), wanted.get(key, "")
        if before != after:
            changes.append(f"{_SHOWN.get(key, key)}: {before or '(not set)'} -> {after or '(not set)'}")
    return changes


def check_replacement(
    *,
    stack_name: str,
    wanted: Mapping[str, str],
    confirmed: bool,
    region: str | None = None,
    account: str | None = None,
    reader: DeployedReader | None = None,
) -> str | None:
    """Raise SettingsError for an unconfirmed replacing change; return a warning when it cannot compare.

    `region`/`account` default to the CDK CLI's CDK_DEFAULT_REGION/CDK_DEFAULT_ACCOUNT; without them (a
    synth without credentials) nothing is compared.
    """
    if confirmed:
        return None
    region = region or os.environ.get("CDK_DEFAULT_REGION")
    account = account or os.environ.get("CDK_DEFAULT_ACCOUNT")
    if not (region and account):
        return None
    reader = reader or read_deployed_fingerprint
    try:
        deployed = reader(stack_name, region)
    except DeployedUnknownError as exc:
        return (
            f"could not read the deployed {stack_name} in {region} ({exc}); a change of availabilityZone, "
            "volumeGb, amiId or amiSsmParameter replaces the instance and its disk"
        )
    if deployed is None:
        return None
    changes = replacing_changes(deployed, wanted)
    if changes:
        raise SettingsError(
            f"this deploy would replace the twin host of {stack_name} ({'; '.join(changes)}): a new root "
            "disk and a new first boot (~15 min), and anything kept on the old disk is lost. Pass the "
            f"deployed values again to keep the host, or confirm with -c {CONFIRM_FLAG}=true"
        )
    return None
