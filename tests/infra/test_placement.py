"""The host's availability zone comes from the instance type's offerings, cached like CDK's own lookups.

A synth never asks AWS here: the offerings are given as context (the cdk.context.json entry the first real
synth writes), or a lookup is passed in. The lookup itself (DescribeInstanceTypeOfferings) is tested with
moto, which cannot be AWS: its offerings table is its own, so only the call and its shape are checked.
"""

from __future__ import annotations

import json
from pathlib import Path

import boto3
import pytest
from moto import mock_aws

from stacks.placement import (
    OfferingsUnknownError,
    choose_availability_zone,
    context_key,
    read_offerings,
    save_context_value,
)
from stacks.settings import SettingsError

from .synth import Synth

ACCOUNT = "123456789012"
REGION = "us-east-1"
OFFERED = ["us-east-1b", "us-east-1c", "us-east-1d"]
KEY = context_key(ACCOUNT, REGION, "g6e.2xlarge")


def subnet_zone(synth: Synth) -> object:
    return synth.one("AWS::EC2::Subnet")["Properties"]["AvailabilityZone"]


def fingerprint(synth: Synth) -> dict[str, str]:
    return json.loads(synth.json["Outputs"]["InstanceFingerprint"]["Value"])


# --- synth --------------------------------------------------------------------------------------------------


def test_without_a_pin_the_first_az_that_offers_the_type_is_taken(synth_factory) -> None:
    synth = synth_factory(region=REGION, account=ACCOUNT, **{KEY: OFFERED})
    assert subnet_zone(synth) == "us-east-1b"
    # The replacement guard sees the AZ actually used, so the next synth compares like with like.
    assert fingerprint(synth)["availabilityZone"] == "us-east-1b"


def test_an_instance_type_no_az_offers_fails_at_synth(synth_factory) -> None:
    with pytest.raises(SettingsError) as info:
        synth_factory(
            region=REGION,
            account=ACCOUNT,
            instanceType="g6e.48xlarge",
            **{context_key(ACCOUNT, REGION, "g6e.48xlarge"): []},
        )
    message = str(info.value)
    assert message.startswith("instanceType=g6e.48xlarge is offered in no availability zone of us-east-1")
    assert "-c instanceType=g6e.2xlarge" in message


def test_a_pinned_az_that_does_not_offer_the_type_fails_with_the_ones_that_do(synth_factory) -> None:
    with pytest.raises(SettingsError) as info:
        synth_factory(region=REGION, account=ACCOUNT, availabilityZone="us-east-1a", **{KEY: OFFERED})
    assert str(info.value) == (
        "availabilityZone=us-east-1a does not offer g6e.2xlarge; the AZs of us-east-1 that do: us-east-1b, "
        "us-east-1c, us-east-1d. Pass one of them, e.g. -c availabilityZone=us-east-1b"
    )
    pinned = synth_factory(region=REGION, account=ACCOUNT, availabilityZone="us-east-1c", **{KEY: OFFERED})
    assert subnet_zone(pinned) == "us-east-1c"


def test_a_synth_with_credentials_looks_up_once_and_caches_in_cdk_context(
    synth_factory, tmp_path: Path
) -> None:
    asked = []

    def lookup(account: str, region: str, instance_type: str) -> list[str]:
        asked.append((account, region, instance_type))
        return ["us-east-1d", "us-east-1c"]

    context_file = tmp_path / "cdk.context.json"
    context_file.write_text(json.dumps({"vpc-provider:x": {"kept": True}}))
    synth = synth_factory(region=REGION, account=ACCOUNT, offerings_lookup=lookup, context_file=context_file)
    assert asked == [(ACCOUNT, REGION, "g6e.2xlarge")]
    assert subnet_zone(synth) == "us-east-1c"
    cached = json.loads(context_file.read_text())
    assert cached == {"vpc-provider:x": {"kept": True}, KEY: ["us-east-1c", "us-east-1d"]}
    # The next synth reads the cache (as the CDK CLI hands cdk.context.json to the app) and asks nothing.
    again = synth_factory(region=REGION, account=ACCOUNT, offerings_lookup=lookup, **{KEY: cached[KEY]})
    assert len(asked) == 1 and subnet_zone(again) == "us-east-1c"


def test_a_failed_lookup_without_a_pin_stops_synth_with_the_way_out(synth_factory) -> None:
    def denied(account: str, region: str, instance_type: str) -> list[str]:
        raise OfferingsUnknownError("UnauthorizedOperation: not allowed")

    with pytest.raises(SettingsError, match="allow ec2:DescribeInstanceTypeOfferings, or pick one yourself"):
        synth_factory(region=REGION, account=ACCOUNT, offerings_lookup=denied)
    # With a pin it goes ahead and warns.
    synth = synth_factory(
        region=REGION, account=ACCOUNT, offerings_lookup=denied, availabilityZone="us-east-1b"
    )
    assert subnet_zone(synth) == "us-east-1b"


def test_without_aws_configuration_nothing_is_looked_up(synth_default: Synth) -> None:
    """CI: no account, no region. The synth's default lookup would raise if it were called."""
    assert subnet_zone(synth_default) == {"Fn::Select": [0, {"Fn::GetAZs": ""}]}


# --- the pieces ---------------------------------------------------------------------------------------------


def test_choice_rules() -> None:
    def never(*_args: str) -> list[str]:
        raise AssertionError("no lookup expected")

    given = {KEY: ["us-east-1c", "us-east-1b"]}.get
    choose = dict(instance_type="g6e.2xlarge", account=ACCOUNT, region=REGION, lookup=never)
    assert choose_availability_zone(pinned=None, context=given, **choose).availability_zone == "us-east-1b"
    # A cache given on the command line (-c KEY=a,b) is a comma list.
    from_cli = {KEY: "us-east-1d, us-east-1c"}.get
    assert choose_availability_zone(pinned=None, context=from_cli, **choose).availability_zone == "us-east-1c"
    with pytest.raises(SettingsError, match="not a list of AZ names"):
        choose_availability_zone(pinned=None, context={KEY: {"a": 1}}.get, **choose)
    # Region without an account: nothing to key the cache by; the pin as given, else a warning.
    none = {}.get
    unpinned = choose_availability_zone(
        instance_type="g6e.2xlarge", pinned=None, account=None, region=REGION, context=none, lookup=never
    )
    assert unpinned.availability_zone is None and "may not offer it" in (unpinned.warning or "")
    pinned = choose_availability_zone(
        instance_type="g6e.2xlarge",
        pinned="us-east-1b",
        account=None,
        region=REGION,
        context=none,
        lookup=never,
    )
    assert (pinned.availability_zone, pinned.warning) == ("us-east-1b", None)


def test_save_context_value_keeps_the_other_entries(tmp_path: Path) -> None:
    path = tmp_path / "cdk.context.json"
    save_context_value(path, "b", [1])
    save_context_value(path, "a", "x")
    assert json.loads(path.read_text()) == {"a": "x", "b": [1]}
    assert path.read_text().endswith("\n")


def test_read_offerings_asks_describe_instance_type_offerings_by_az(aws_env) -> None:
    """moto stands in for EC2 (its offerings table is its own, not AWS's): the call and its shape."""
    with mock_aws():
        ec2 = boto3.client("ec2", region_name=REGION)
        expected = sorted(
            {
                o["Location"]
                for o in ec2.describe_instance_type_offerings(
                    LocationType="availability-zone",
                    Filters=[{"Name": "instance-type", "Values": ["t3.micro"]}],
                )["InstanceTypeOfferings"]
            }
        )
        assert expected and all(z.startswith(REGION) for z in expected)
        assert read_offerings(ACCOUNT, REGION, "t3.micro", ec2=ec2) == expected
        assert read_offerings(ACCOUNT, REGION, "nonexistent.type", ec2=ec2) == []


def test_read_offerings_reports_an_unusable_answer(aws_env, monkeypatch: pytest.MonkeyPatch) -> None:
    from botocore.exceptions import ClientError

    with mock_aws():
        ec2 = boto3.client("ec2", region_name=REGION)

        def denied(*_args, **_kwargs):
            raise ClientError({"Error": {"Code": "UnauthorizedOperation", "Message": "no"}}, "Describe")

        monkeypatch.setattr(ec2, "get_paginator", denied)
        with pytest.raises(OfferingsUnknownError, match="UnauthorizedOperation: no"):
            read_offerings(ACCOUNT, REGION, "g6e.2xlarge", ec2=ec2)
