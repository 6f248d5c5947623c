"""The replacement guard: a change of availabilityZone, volumeGb or the image is refused at synth unless
-c replaceInstance=true confirms it. The deployed stack is read with DescribeStacks; AWS cannot be reached
from here, so moto stands in for CloudFormation (a stack whose outputs are what the twin stack publishes).
"""

from __future__ import annotations

import json

import boto3
import pytest
from moto import mock_aws

from stacks.replacement_guard import (
    DeployedUnknownError,
    check_replacement,
    read_deployed_fingerprint,
    replacing_changes,
)
from stacks.settings import SettingsError

DEPLOYED = {"availabilityZone": "us-east-1b", "volumeGb": "100", "image": "resolve:ssm:/aws/x"}
REGION = "us-east-1"


@pytest.fixture
def cfn(monkeypatch: pytest.MonkeyPatch):
    for name in ("AWS_PROFILE", "AWS_SESSION_TOKEN"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    with mock_aws():
        client = boto3.client("cloudformation", region_name=REGION)
        template = {
            "Resources": {"Topic": {"Type": "AWS::SNS::Topic"}},
            "Outputs": {"InstanceFingerprint": {"Value": json.dumps(DEPLOYED, sort_keys=True)}},
        }
        client.create_stack(StackName="So101TwinStack", TemplateBody=json.dumps(template))
        yield client


def test_reads_the_fingerprint_output_with_describe_stacks(cfn) -> None:
    assert read_deployed_fingerprint("So101TwinStack", REGION, cloudformation=cfn) == DEPLOYED


def test_a_stack_not_yet_deployed_has_no_fingerprint(cfn) -> None:
    assert read_deployed_fingerprint("OtherStack", REGION, cloudformation=cfn) is None


def test_unreadable_stack_is_reported_not_guessed(cfn, monkeypatch: pytest.MonkeyPatch) -> None:
    from botocore.exceptions import ClientError

    def denied(**_kwargs):
        raise ClientError({"Error": {"Code": "AccessDenied", "Message": "no"}}, "DescribeStacks")

    monkeypatch.setattr(cfn, "describe_stacks", denied)
    with pytest.raises(DeployedUnknownError, match="AccessDenied"):
        read_deployed_fingerprint("So101TwinStack", REGION, cloudformation=cfn)


def test_changes_are_named_with_both_values() -> None:
    wanted = {**DEPLOYED, "volumeGb": "200", "availabilityZone": ""}
    assert replacing_changes(DEPLOYED, wanted) == [
        "availabilityZone: us-east-1b -> (not set)",
        "volumeGb: 100 -> 200",
    ]
    assert replacing_changes(DEPLOYED, dict(DEPLOYED)) == []


def guard(wanted: dict[str, str], *, confirmed: bool = False, cfn=None, account: str | None = "111111111111"):
    return check_replacement(
        stack_name="So101TwinStack",
        wanted=wanted,
        confirmed=confirmed,
        region=REGION,
        account=account,
        reader=lambda name, region: read_deployed_fingerprint(name, region, cloudformation=cfn),
    )


def test_a_replacing_change_is_refused_with_the_fix(cfn) -> None:
    with pytest.raises(SettingsError) as info:
        guard({**DEPLOYED, "volumeGb": "200"}, cfn=cfn)
    message = str(info.value)
    assert "volumeGb: 100 -> 200" in message
    assert "-c replaceInstance=true" in message
    assert "first boot" in message


def test_confirmed_or_unchanged_passes(cfn) -> None:
    assert guard({**DEPLOYED, "volumeGb": "200"}, confirmed=True, cfn=cfn) is None
    assert guard(dict(DEPLOYED), cfn=cfn) is None


def test_without_credentials_nothing_is_compared() -> None:
    # No account from the CDK CLI (a synth without credentials): no AWS call, no refusal, no warning.
    def never(_name: str, _region: str):
        raise AssertionError("must not call AWS")

    result = check_replacement(
        stack_name="So101TwinStack",
        wanted={**DEPLOYED, "volumeGb": "200"},
        confirmed=False,
        region=None,
        account=None,
        reader=never,
    )
    assert result is None


def test_a_failed_lookup_warns_instead_of_refusing() -> None:
    def broken(_name: str, _region: str):
        raise DeployedUnknownError("ExpiredToken: refresh")

    warning = check_replacement(
        stack_name="So101TwinStack",
        wanted=DEPLOYED,
        confirmed=False,
        region=REGION,
        account="111111111111",
        reader=broken,
    )
    assert warning is not None and "ExpiredToken" in warning and "replaces the instance" in warning


def test_the_app_refuses_at_synth(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Through the real app wiring: build_app consults the reader with the settings' fingerprint."""
    import aws_cdk as cdk

    from app import build_app

    from .synth import CLIENT_CIDR, cdk_json_context

    monkeypatch.setenv("CDK_DEFAULT_ACCOUNT", "111111111111")
    monkeypatch.setenv("CDK_DEFAULT_REGION", REGION)
    deployed = {"availabilityZone": "us-east-1b", "volumeGb": "100", "image": "ami-0123456789abcdef0"}
    context = {**cdk_json_context(), "clientCidr": CLIENT_CIDR, "availabilityZone": "us-east-1c"}
    context["amiId"] = "ami-0123456789abcdef0"
    app = cdk.App(context=context, outdir=str(tmp_path))
    with pytest.raises(SettingsError, match=r"availabilityZone: us-east-1b -> us-east-1c"):
        build_app(app, deployed_reader=lambda _n, _r: deployed)
