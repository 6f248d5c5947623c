"""AWS_REGION is the region a command uses when none is given, as with the AWS CLI (twin.core.aws).

boto3 itself reads only AWS_DEFAULT_REGION and the profile's config, and the docs tell people to set
AWS_REGION. moto stands in for AWS: in-process for IoT Core's DescribeEndpoint, and its server on loopback
for the commands run as a user runs them (AWS_ENDPOINT_URL points boto3 at it).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
from conftest import run_twin
from moto import mock_aws
from moto_s3 import MotoS3
from twin.cli.commands.run import overrides_from_args
from twin.cli.main import build_parser
from twin.core.aws import region_or_env
from twin.transport import client
from twin.transport.broker import BrokerConfig

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "robots" / "so101" / "calibration" / "so101_follower_example.json"


@pytest.fixture
def aws_region_only(aws_env: None, monkeypatch: pytest.MonkeyPatch) -> None:
    """moto's fake credentials, empty AWS config files, and the region in AWS_REGION alone."""
    monkeypatch.delenv("AWS_DEFAULT_REGION")
    monkeypatch.setenv("AWS_REGION", "eu-west-1")


def test_a_given_region_then_aws_region_then_boto3s_own_chain(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AWS_REGION", "eu-west-1")
    assert region_or_env("us-east-2") == "us-east-2"
    assert region_or_env("") == region_or_env(None) == "eu-west-1"
    monkeypatch.setenv("AWS_REGION", " ")
    assert region_or_env() is None  # boto3 then reads AWS_DEFAULT_REGION and the profile's config
    monkeypatch.delenv("AWS_REGION")
    assert region_or_env() is None


def test_iot_core_is_found_in_the_region_aws_region_names(aws_region_only: None) -> None:
    config = BrokerConfig(url="iot")
    assert client._region(config) == "eu-west-1"
    with mock_aws():
        assert ".iot.eu-west-1.amazonaws.com" in client.resolve_iot_endpoint(config)
    # A region in the agent's config (or --region) still comes first.
    assert client._region(BrokerConfig(url="iot", region="us-east-2")) == "us-east-2"


@pytest.mark.slow
def test_the_aws_commands_work_with_aws_region_alone(tmp_path: Path) -> None:
    server = MotoS3(bucket="so101-calibration")
    try:
        empty = tmp_path / "empty"
        empty.write_text("")
        env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
        env.update(
            AWS_REGION="us-east-1",
            AWS_ENDPOINT_URL=server.endpoint,
            AWS_ACCESS_KEY_ID="testing",
            AWS_SECRET_ACCESS_KEY="testing",
            AWS_CONFIG_FILE=str(empty),
            AWS_SHARED_CREDENTIALS_FILE=str(empty),
            AWS_EC2_METADATA_DISABLED="true",
        )
        env.pop("SO101_TWIN_STACK", None)

        def twin(*args: str) -> subprocess.CompletedProcess[str]:
            return run_twin(args, env, cwd=tmp_path, timeout=120)

        store = "s3://so101-calibration/calibration"
        pushed = twin("calibration", "push", "arm-001", str(EXAMPLE), "--store", store)
        assert pushed.returncode == 0, pushed.stderr
        listed = twin("calibration", "ls", "--store", store)
        assert listed.returncode == 0 and "arm-001" in listed.stdout, listed.stderr
        # No stack in this (moto) account: "stack not found" (4), not "no AWS region" (3).
        status = twin("instance", "status")
        assert status.returncode == 4, status.stderr
        assert "no AWS region" not in status.stderr and "us-east-1" in status.stderr, status.stderr
    finally:
        server.close()


def test_twin_run_takes_the_region_its_error_names() -> None:
    args = build_parser().parse_args(["run", "--broker", "iot", "--region", "eu-north-1"])
    assert overrides_from_args(args)["broker.region"] == "eu-north-1"
    assert overrides_from_args(build_parser().parse_args(["run"]))["broker.region"] is None


def test_an_aws_profile_that_does_not_exist_is_named_with_its_fix(
    aws_env: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`AWS_PROFILE=my-profile`, as the docs write it, with no such profile: botocore raises ProfileNotFound
    wherever a session is made, which `twin instance`, `twin calibration`, `twin edge-sim --broker iot`,
    `twin replay --broker iot` and `twin run --broker iot` let out as a traceback. Each says it, with the
    fix."""
    from twin.ops.instance import AwsSetupError, TwinInstance
    from twin.transport.broker import BrokerConfigError

    monkeypatch.setenv("AWS_PROFILE", "no-such-profile")
    monkeypatch.delenv("AWS_DEFAULT_REGION")
    said = r"\(no-such-profile\).*AWS_PROFILE.*aws configure list-profiles"
    with pytest.raises(BrokerConfigError, match=said):
        client._region(BrokerConfig(url="iot"))
    with pytest.raises(BrokerConfigError, match="could not look up the IoT Core endpoint: .*" + said):
        client.resolve_iot_endpoint(BrokerConfig(url="iot", region="eu-west-1"))
    with pytest.raises(AwsSetupError, match=said):
        TwinInstance(stack_name="So101TwinStack").stack_description()
