"""The replacement guard: a change of availabilityZone, volumeGb or the image stops the deploy unless
-c replaceInstance=true confirms it. The deployed stack is read with DescribeStacks; AWS cannot be reached
from here, so moto stands in for CloudFormation (a stack whose outputs are what the twin stack publishes).
"""

from __future__ import annotations

import json
from pathlib import Path

import boto3
import pytest
from moto import mock_aws

from stacks.deployed import DeployedUnknownError, read_deployed_outputs
from stacks.replacement_guard import deployed_fingerprint, replacement_refusal, replacing_changes

from .synth import CLIENT_CIDR, annotations, app_stack

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


def outputs(cfn) -> dict[str, str]:
    found = read_deployed_outputs("So101TwinStack", REGION, cloudformation=cfn)
    assert found is not None
    return found


def test_reads_the_fingerprint_output_with_describe_stacks(cfn) -> None:
    assert deployed_fingerprint(outputs(cfn)) == DEPLOYED


def test_a_stack_not_yet_deployed_has_no_outputs(cfn) -> None:
    assert read_deployed_outputs("OtherStack", REGION, cloudformation=cfn) is None


def test_a_stack_without_the_output_has_no_fingerprint() -> None:
    assert deployed_fingerprint({"DcvUrl": "https://x"}) is None


def test_a_broken_fingerprint_is_reported_not_guessed() -> None:
    with pytest.raises(DeployedUnknownError, match="not JSON"):
        deployed_fingerprint({"InstanceFingerprint": "{broken"})


def test_unreadable_stack_is_reported_not_guessed(cfn, monkeypatch: pytest.MonkeyPatch) -> None:
    from botocore.exceptions import ClientError

    def denied(**_kwargs):
        raise ClientError({"Error": {"Code": "AccessDenied", "Message": "no"}}, "DescribeStacks")

    monkeypatch.setattr(cfn, "describe_stacks", denied)
    with pytest.raises(DeployedUnknownError, match="AccessDenied"):
        read_deployed_outputs("So101TwinStack", REGION, cloudformation=cfn)


def test_changes_are_named_with_both_values() -> None:
    wanted = {**DEPLOYED, "volumeGb": "200", "availabilityZone": ""}
    assert replacing_changes(DEPLOYED, wanted) == [
        "availabilityZone: us-east-1b -> (not set)",
        "volumeGb: 100 -> 200",
    ]
    assert replacing_changes(DEPLOYED, dict(DEPLOYED)) == []


def test_a_host_generation_left_out_is_the_first_host() -> None:
    """Fingerprints leave hostGeneration out at 1, the value of stacks deployed before the setting."""
    assert replacing_changes(DEPLOYED, {**DEPLOYED, "hostGeneration": "2"}) == ["hostGeneration: 1 -> 2"]
    assert replacing_changes({**DEPLOYED, "hostGeneration": "3"}, DEPLOYED) == ["hostGeneration: 3 -> 1"]
    assert replacing_changes({**DEPLOYED, "hostGeneration": "2"}, {**DEPLOYED, "hostGeneration": "2"}) == []


def refusal(cfn, wanted: dict[str, str], *, confirmed: bool = False) -> str | None:
    return replacement_refusal(
        stack_name="So101TwinStack", deployed_outputs=outputs(cfn), wanted=wanted, confirmed=confirmed
    )


def test_a_replacing_change_is_refused_with_the_fix(cfn) -> None:
    message = refusal(cfn, {**DEPLOYED, "volumeGb": "200"})
    assert message is not None
    assert "volumeGb: 100 -> 200" in message
    assert "-c replaceInstance=true" in message
    assert "first boot" in message
    # What is lost, and what stays: the operator's own settings file and the servo alarm state are kept in
    # S3 by the host.
    assert "is lost: the USD recordings, and servo alarm changes made on the old host" in message
    assert "your /etc/so101-twin/agent.local.toml and the servo alarms as the new host boots" in message


def test_confirmed_or_unchanged_passes(cfn) -> None:
    assert refusal(cfn, {**DEPLOYED, "volumeGb": "200"}, confirmed=True) is None
    assert refusal(cfn, dict(DEPLOYED)) is None


def test_the_app_stops_the_deploy_with_an_error_annotation(tmp_path: Path) -> None:
    """Through the real app wiring: build_app reads the deployed outputs once and turns the refusal into an
    error annotation (the CDK CLI refuses to deploy it; `cdk destroy` ignores it)."""
    deployed = {"availabilityZone": "us-east-1b", "volumeGb": "100", "image": "ami-0123456789abcdef0"}
    stack = app_stack(
        tmp_path,
        reader=lambda _n, _r: {"InstanceFingerprint": json.dumps(deployed)},
        clientCidr=CLIENT_CIDR,
        availabilityZone="us-east-1c",
        amiId="ami-0123456789abcdef0",
    )
    (error,) = annotations(stack, "error")
    assert "availabilityZone: us-east-1b -> us-east-1c" in error


def test_a_new_host_generation_asks_for_the_confirmation_once(tmp_path: Path) -> None:
    """The way back from a terminated host: a stack deployed before hostGeneration existed (its fingerprint
    has no such key) and hostGeneration = 2 in the settings file is refused until -c replaceInstance=true."""
    deployed = {"InstanceFingerprint": json.dumps({**DEPLOYED, "image": "ami-0123456789abcdef0"})}
    settings = tmp_path / "twin.settings.toml"
    settings.write_text(
        f'clientCidr = "{CLIENT_CIDR}"\navailabilityZone = "us-east-1b"\namiId = "ami-0123456789abcdef0"\n'
        "hostGeneration = 2\n"
    )
    refused = app_stack(tmp_path / "refused", reader=lambda _n, _r: deployed, settings_file=settings)
    (error,) = annotations(refused, "error")
    assert "hostGeneration: 1 -> 2" in error and "-c replaceInstance=true" in error
    confirmed = app_stack(
        tmp_path / "confirmed", reader=lambda _n, _r: deployed, settings_file=settings, replaceInstance="true"
    )
    assert annotations(confirmed, "error") == []


def test_without_credentials_nothing_is_compared(tmp_path: Path) -> None:
    # No account from the CDK CLI (a synth without credentials): no AWS call, no refusal, no warning.
    def never(_name: str, _region: str):
        raise AssertionError("must not call AWS")

    stack = app_stack(tmp_path, reader=never, account=None, clientCidr=CLIENT_CIDR)
    assert annotations(stack, "error") == []


def test_a_failed_lookup_warns_instead_of_refusing(tmp_path: Path) -> None:
    def broken(_name: str, _region: str):
        raise DeployedUnknownError("ExpiredToken: refresh")

    stack = app_stack(tmp_path, reader=broken, clientCidr=CLIENT_CIDR)
    assert annotations(stack, "error") == []
    warnings = " ".join(annotations(stack, "warning"))
    assert "ExpiredToken" in warnings and "replaces the instance" in warnings
    assert "amiSsmParameter or hostGeneration replaces" in warnings
