"""`twin instance password`: the DCV password from the secret the stack's DcvPasswordSecret output names.

AWS cannot be reached from here, so moto stands in for CloudFormation and Secrets Manager: each test makes
the secret in moto, deploys a small stack whose DcvPasswordSecret output holds its ARN the way the CDK stack
does, and drives the real CLI through `twin.cli.main`. moto lets every caller read every secret, so a caller
AWS would refuse is injected at the botocore level.
"""

from __future__ import annotations

import json

import boto3
import pytest
from conftest import AWS_TEST_REGION
from moto import mock_aws
from test_instance import TEMPLATE, client_error, intercept
from twin.cli import main
from twin.cli.commands import instance as cmd
from twin.ops import instance as lib

FIRST = "Xq7pL2mN9vR4tY8wK3zB6cD1"
ROTATED = "Hf5jS0gA2eU7iO9pW4rT1yQ3"


def deploy(stack_name: str, outputs: dict) -> None:
    """The twin stack in moto, with these outputs besides InstanceId and DcvUrl."""
    template = {
        "Resources": TEMPLATE["Resources"],
        "Outputs": {key: TEMPLATE["Outputs"][key] for key in ("InstanceId", "DcvUrl")} | outputs,
    }
    boto3.client("cloudformation", region_name=AWS_TEST_REGION).create_stack(
        StackName=stack_name, TemplateBody=json.dumps(template)
    )


@pytest.fixture
def secret_arn(aws_env, tmp_path, monkeypatch):
    """A stack named FiveArms whose secret went through a second version: the current one is ROTATED."""
    monkeypatch.chdir(tmp_path)
    with mock_aws():
        secrets = boto3.client("secretsmanager", region_name=AWS_TEST_REGION)
        arn = secrets.create_secret(Name="DcvPassword-abc", SecretString=FIRST)["ARN"]
        secrets.put_secret_value(SecretId=arn, SecretString=ROTATED)
        deploy("FiveArms", {"DcvPasswordSecret": {"Value": arn}})
        yield arn


def test_prints_the_current_password_of_the_stack_the_settings_file_names(secret_arn, tmp_path, capsys):
    (tmp_path / "twin.settings.toml").write_text('clientCidr = "203.0.113.7/32"\nstackName = "FiveArms"\n')
    assert main(["instance", "password"]) == cmd.EXIT_OK
    assert capsys.readouterr().out == ROTATED + "\n"


def test_the_stack_comes_from_the_flag_and_the_environment(secret_arn, capsys, monkeypatch):
    assert main(["instance", "password", "--stack", "FiveArms"]) == cmd.EXIT_OK
    assert capsys.readouterr().out == ROTATED + "\n"
    monkeypatch.setenv(lib.STACK_ENV_VAR, "FiveArms")
    assert main(["instance", "password"]) == cmd.EXIT_OK
    assert capsys.readouterr().out == ROTATED + "\n"


def test_no_stack_says_which_and_how_to_name_it(secret_arn, capsys):
    assert main(["instance", "password"]) == cmd.EXIT_NO_STACK
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("twin instance password: stack So101TwinStack not found in us-east-1")
    assert "pass --stack" in captured.err


def test_a_stack_without_the_output_names_it(aws_env, capsys):
    with mock_aws():
        deploy("OldTwin", {})
        assert main(["instance", "password", "--stack", "OldTwin"]) == cmd.EXIT_NO_OUTPUTS
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "stack OldTwin in us-east-1 has no output DcvPasswordSecret" in captured.err
    assert "cdk deploy" in captured.err


def test_access_denied_names_the_secret_the_permission_and_aws_reason(secret_arn, capsys, monkeypatch):
    # An explicit deny (SCP, boundary, resource policy) or a KMS refusal differ only in AWS's message.
    reason = (
        "User: arn:aws:iam::123456789012:user/viewer is not authorized to perform: "
        "secretsmanager:GetSecretValue with an explicit deny in a service control policy"
    )

    def refuse(_call, _params):
        raise client_error("AccessDeniedException", reason, "GetSecretValue")

    intercept(monkeypatch, "GetSecretValue", refuse)
    assert main(["instance", "password", "--stack", "FiveArms"]) == cmd.EXIT_AWS
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.strip() == (
        f"twin instance password: not allowed to read the DCV password secret {secret_arn} "
        f"(AccessDeniedException: {reason}): use credentials allowed secretsmanager:GetSecretValue on "
        f"{secret_arn}"
    )


def test_a_secret_deleted_outside_the_stack_says_how_to_get_one_back(secret_arn, capsys):
    boto3.client("secretsmanager", region_name=AWS_TEST_REGION).delete_secret(
        SecretId=secret_arn, ForceDeleteWithoutRecovery=True
    )
    assert main(["instance", "password", "--stack", "FiveArms"]) == cmd.EXIT_AWS
    err = capsys.readouterr().err
    assert f"the DCV password secret {secret_arn} no longer exists (ResourceNotFoundException" in err
    assert "`cdk deploy` does not recreate it; `cdk destroy` then `cdk deploy`" in err


def test_a_secret_scheduled_for_deletion_says_how_to_restore_it(secret_arn, capsys):
    boto3.client("secretsmanager", region_name=AWS_TEST_REGION).delete_secret(SecretId=secret_arn)
    assert main(["instance", "password", "--stack", "FiveArms"]) == cmd.EXIT_AWS
    err = capsys.readouterr().err
    assert f"secret {secret_arn} is scheduled for deletion (InvalidRequestException" in err
    assert f"`aws secretsmanager restore-secret --secret-id {secret_arn}`" in err


def test_a_binary_secret_says_so_without_a_traceback(aws_env, capsys):
    with mock_aws():
        secrets = boto3.client("secretsmanager", region_name=AWS_TEST_REGION)
        arn = secrets.create_secret(Name="DcvPassword-bin", SecretBinary=b"\x00\x01")["ARN"]
        deploy("FiveArms", {"DcvPasswordSecret": {"Value": arn}})
        assert main(["instance", "password", "--stack", "FiveArms"]) == cmd.EXIT_AWS
    captured = capsys.readouterr()
    assert captured.out == "" and "Traceback" not in captured.err
    assert f"the DCV password secret {arn} holds binary data" in captured.err
    assert "put-secret-value" in captured.err


def test_no_credentials_says_how_to_configure(secret_arn, capsys, monkeypatch):
    monkeypatch.delenv("AWS_ACCESS_KEY_ID")
    monkeypatch.delenv("AWS_SECRET_ACCESS_KEY")
    assert main(["instance", "password", "--stack", "FiveArms"]) == cmd.EXIT_SETUP
    captured = capsys.readouterr()
    assert captured.out == "" and "Traceback" not in captured.err
    assert "no AWS credentials found" in captured.err and "aws configure" in captured.err
