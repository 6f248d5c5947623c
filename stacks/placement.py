"""The twin host's availability zone: one that offers its instance type, chosen at synth.

Not every AZ offers G6e, and the first AZ of a region often does not: a deploy there fails late, at the
instance, with "Unsupported". So synth asks EC2 which AZs offer the instance type
(DescribeInstanceTypeOfferings, with the deployer's credentials, in the account and region the CDK CLI
deploys to) and caches the answer in cdk.context.json as CDK caches its own lookups: the next synth reads
it without calling AWS, and the choice stays put until the entry is removed (`cdk context --reset KEY`). AZ
names map to different physical zones in different accounts, so the key names the account.

- A pinned AZ (`-c availabilityZone=...`) must be one of them, or synth stops with the list.
- Without a pin the first of them (by name) is taken; none at all stops synth.
- Without an account and region (a synth with no AWS configuration, as in CI) nothing can be looked up:
  the pin is used as given, or the subnet takes the region's first AZ at deploy time.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stacks.settings import SettingsError

# (account, region, instance type) -> the names of the AZs that offer it.
OfferingsLookup = Callable[[str, str, str], list[str]]
CONTEXT_FILE = "cdk.context.json"
OFFERINGS_COMMAND = (
    "aws ec2 describe-instance-type-offerings --region {region} --location-type availability-zone "
    "--filters Name=instance-type,Values={instance_type} --query 'InstanceTypeOfferings[].Location'"
)


class OfferingsUnknownError(Exception):
    """EC2 could not be asked (no credentials, no network, access denied)."""


@dataclass(frozen=True)
class Placement:
    availability_zone: str | None
    warning: str | None = None


def context_key(account: str, region: str, instance_type: str) -> str:
    """The cdk.context.json key of one lookup, shaped like CDK's own (provider, then its parameters)."""
    return f"instance-type-offerings:account={account}:instanceType={instance_type}:region={region}"


def read_offerings(account: str, region: str, instance_type: str, ec2: Any = None) -> list[str]:
    """The AZ names of `region` that offer `instance_type`, sorted. `account` only keys the cache."""
    try:
        from botocore.exceptions import BotoCoreError, ClientError  # noqa: PLC0415

        if ec2 is None:
            import boto3  # noqa: PLC0415
            from botocore.config import Config  # noqa: PLC0415

            ec2 = boto3.client(
                "ec2",
                region_name=region,
                config=Config(connect_timeout=5, read_timeout=10, retries={"max_attempts": 2}),
            )
        zones: set[str] = set()
        paginator = ec2.get_paginator("describe_instance_type_offerings")
        for page in paginator.paginate(
            LocationType="availability-zone",
            Filters=[{"Name": "instance-type", "Values": [instance_type]}],
        ):
            zones.update(o["Location"] for o in page.get("InstanceTypeOfferings", []))
    except ClientError as exc:
        error = exc.response.get("Error", {})
        raise OfferingsUnknownError(f"{error.get('Code')}: {error.get('Message')}") from exc
    except BotoCoreError as exc:
        raise OfferingsUnknownError(str(exc)) from exc
    return sorted(zones)


def save_context_value(path: Path, key: str, value: Any) -> None:
    """Add one entry to a cdk.context.json (created if missing), replacing the file atomically."""
    data = json.loads(path.read_text()) if path.exists() else {}
    data[key] = value
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".cdk.context.", suffix=".json")
    with os.fdopen(fd, "w") as out:
        json.dump(data, out, indent=2, sort_keys=True)
        out.write("\n")
    os.replace(tmp, path)


def _cached(value: Any) -> list[str] | None:
    if value is None:
        return None
    if isinstance(value, str):  # given on the command line: -c <key>=us-east-1b,us-east-1c
        return sorted(z.strip() for z in value.split(",") if z.strip())
    if isinstance(value, list) and all(isinstance(z, str) for z in value):
        return sorted(value)
    raise SettingsError(
        f"the cached instance type offerings {value!r} are not a list of AZ names; remove the entry from "
        f"{CONTEXT_FILE} (cdk context --reset <key>) and synth again"
    )


def choose_availability_zone(
    *,
    instance_type: str,
    pinned: str | None,
    account: str | None,
    region: str | None,
    context: Callable[[str], Any],
    lookup: OfferingsLookup = read_offerings,
    save: Callable[[str, list[str]], None] | None = None,
) -> Placement:
    """The AZ for the host, from the cache in `context` or a `lookup` (then `save`d); raises SettingsError."""
    if not (account and region):
        if region and not pinned:
            return Placement(
                None,
                f"no AWS account known, so the AZs of {region} that offer {instance_type} were not looked "
                "up: the subnet takes the region's first AZ, which may not offer it. Deploy with credentials "
                "(the CDK CLI then passes the account) or pass -c availabilityZone=<an AZ that offers it>",
            )
        return Placement(pinned)
    key = context_key(account, region, instance_type)
    offered = _cached(context(key))
    if offered is None:
        try:
            offered = sorted(lookup(account, region, instance_type))
        except OfferingsUnknownError as exc:
            command = OFFERINGS_COMMAND.format(region=region, instance_type=instance_type)
            if pinned:
                return Placement(
                    pinned,
                    f"could not check that {pinned} offers {instance_type} ({exc}); `{command}` lists them",
                )
            raise SettingsError(
                f"could not read which AZs of {region} offer {instance_type} ({exc}): allow "
                f"ec2:DescribeInstanceTypeOfferings, or pick one yourself (`{command}`) and pass "
                "-c availabilityZone=<it>"
            ) from exc
        if save is not None:
            save(key, offered)
    if not offered:
        raise SettingsError(
            f"instanceType={instance_type} is offered in no availability zone of {region} "
            "(DescribeInstanceTypeOfferings): pass an instance type the region has, e.g. -c "
            "instanceType=g6e.2xlarge, or deploy to a region that offers it (G6e: us-east-1, us-east-2, "
            f"us-west-2, ...). The answer is cached in {CONTEXT_FILE} under {key}: remove it to ask again"
        )
    if pinned and pinned not in offered:
        raise SettingsError(
            f"availabilityZone={pinned} does not offer {instance_type}; the AZs of {region} that do: "
            f"{', '.join(offered)}. Pass one of them, e.g. -c availabilityZone={offered[0]}"
        )
    return Placement(pinned or offered[0])
