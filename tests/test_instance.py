"""`twin instance` (twin.ops.instance + twin.cli.commands.instance) against moto.

AWS cannot be reached from here, so moto stands in for CloudFormation, EC2 and SSM: each test deploys a small
stack in moto whose outputs reference a moto EC2 instance and its Elastic IP the way the CDK stack does, then
drives the real CLI through `twin.cli.main`. What moto cannot do is injected at the botocore level: an
InsufficientInstanceCapacity from StartInstances, an SSM agent that has not registered, an instance stuck in
a state, and the output of the health check on the instance (moto's Run Command executes nothing), the latter
with botocore's Stubber.
"""

from __future__ import annotations

import datetime
import json
import tomllib

import boto3
import botocore.client
import pytest
from botocore.exceptions import ClientError
from botocore.stub import Stubber
from conftest import AWS_TEST_REGION
from moto import mock_aws
from twin.cli import main
from twin.cli.commands import instance as cmd
from twin.ops import instance as lib

from stacks import replacement_guard

REGION = AWS_TEST_REGION
COMMAND_ID = "5c9a1d1e-0000-4000-8000-000000000001"  # SSM command ids are UUIDs

TEMPLATE = {
    "Resources": {
        "Host": {
            "Type": "AWS::EC2::Instance",
            "Properties": {"ImageId": "ami-12c6146b", "InstanceType": "g6e.2xlarge"},
        },
        "Eip": {"Type": "AWS::EC2::EIP", "Properties": {"Domain": "vpc", "InstanceId": {"Ref": "Host"}}},
    },
    "Outputs": {
        "InstanceId": {"Value": {"Ref": "Host"}},
        # Ref of an EIP is its public address; moto lacks GetAtt PublicIp.
        "DcvUrl": {"Value": {"Fn::Join": ["", ["https://", {"Ref": "Eip"}, ":8443/#console"]]}},
        "IotEndpoint": {"Value": "abc123-ats.iot.us-east-1.amazonaws.com"},
        "DcvPasswordSecret": {"Value": "so101-twin/dcv aws secretsmanager get-secret-value ..."},
        "SsmSessionCommand": {
            "Value": {"Fn::Join": ["", ["aws ssm start-session --target ", {"Ref": "Host"}]]}
        },
        # As stacks/settings_guard.py writes it: kept settings in order, and where the given ones came from.
        "Settings": {
            "Value": json.dumps(
                {
                    "version": 1,
                    "values": {
                        "clientCidr": "203.0.113.7/32",
                        "stackName": "So101TwinStack",
                        "devices": ["arm-001", "arm-002"],
                        "alarmEmail": "",
                        "alarmWarnings": True,
                    },
                    "given": {"clientCidr": "file", "devices": "file", "alarmWarnings": "-c"},
                },
                separators=(",", ":"),
            )
        },
    },
}


@pytest.fixture
def stack(aws_env):
    """The deployed twin stack in moto: yields its outputs as a dict."""
    with mock_aws():
        cfn = boto3.client("cloudformation", region_name=REGION)
        cfn.create_stack(StackName=lib.DEFAULT_STACK_NAME, TemplateBody=json.dumps(TEMPLATE))
        outputs = cfn.describe_stacks(StackName=lib.DEFAULT_STACK_NAME)["Stacks"][0]["Outputs"]
        yield {o["OutputKey"]: o["OutputValue"] for o in outputs}


def ec2_state(instance_id: str) -> str:
    ec2 = boto3.client("ec2", region_name=REGION)
    return ec2.describe_instances(InstanceIds=[instance_id])["Reservations"][0]["Instances"][0]["State"][
        "Name"
    ]


def intercept(monkeypatch: pytest.MonkeyPatch, operation: str, handler) -> None:
    """Route one AWS operation through `handler(original, kwargs)`; the rest still reaches moto."""
    original = botocore.client.BaseClient._make_api_call

    def patched(self, operation_name, api_params):
        if operation_name == operation:
            return handler(lambda: original(self, operation_name, api_params), api_params)
        return original(self, operation_name, api_params)

    monkeypatch.setattr(botocore.client.BaseClient, "_make_api_call", patched)


def refuse_state(monkeypatch: pytest.MonkeyPatch, operation: str, instance_id: str) -> None:
    """EC2's IncorrectInstanceState for `operation` (StartInstances, StopInstances), which moto never
    answers: injected."""
    done = {"StartInstances": "started", "StopInstances": "stopped"}[operation]

    def refuse(original, params):
        raise client_error(
            "IncorrectInstanceState",
            f"The instance '{instance_id}' is not in a state from which it can be {done}.",
            operation,
        )

    intercept(monkeypatch, operation, refuse)


def client_error(code: str, message: str, operation: str) -> ClientError:
    return ClientError({"Error": {"Code": code, "Message": message}}, operation)


# --- happy paths -------------------------------------------------------------------------------------------


def test_url_prints_only_the_dcv_url(stack, capsys):
    assert main(["instance", "url"]) == 0
    out = capsys.readouterr().out
    assert out == stack["DcvUrl"] + "\n"
    assert out.startswith("https://") and out.endswith(":8443/#console\n")


def test_settings_print_the_deployed_stack_as_a_settings_file(stack, capsys):
    assert main(["instance", "settings"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("# The settings of stack So101TwinStack in us-east-1, as deployed")
    body = [
        line for line in out.splitlines() if not line.startswith("# The") and not line.startswith("# Save")
    ]
    assert body == [
        'clientCidr = "203.0.113.7/32"',
        '# stackName = "So101TwinStack"  # default',
        'devices = ["arm-001", "arm-002"]',
        '# alarmEmail = ""  # default',
        "alarmWarnings = true  # given with -c: keep it here, or the next deploy resets it",
    ]
    assert tomllib.loads(out) == {
        "clientCidr": "203.0.113.7/32",
        "devices": ["arm-001", "arm-002"],
        "alarmWarnings": True,
    }


def test_settings_of_an_older_stack_say_to_deploy_once(aws_env, capsys):
    template = {"Resources": TEMPLATE["Resources"], "Outputs": dict(TEMPLATE["Outputs"])}
    del template["Outputs"]["Settings"]
    with mock_aws():
        boto3.client("cloudformation", region_name=REGION).create_stack(
            StackName="OldTwin", TemplateBody=json.dumps(template)
        )
        assert main(["instance", "settings", "--stack", "OldTwin"]) == cmd.EXIT_NO_OUTPUTS
    err = capsys.readouterr().err
    assert "has no Settings output" in err and "cdk deploy" in err


def test_stop_then_start_changes_the_ec2_state(stack, capsys):
    instance_id = stack["InstanceId"]
    assert ec2_state(instance_id) == "running"

    assert main(["instance", "stop", "--timeout", "30"]) == 0
    assert ec2_state(instance_id) == "stopped"
    assert f"instance {instance_id}: stopped" in capsys.readouterr().out

    # moto's Run Command runs nothing, so no verdict of the host's start checks ever comes: the state is
    # running, and `start` says it got no verdict within its time (tests/test_instance_check.py has both).
    assert main(["instance", "start", "--timeout", "2"]) == cmd.EXIT_WAIT
    assert ec2_state(instance_id) == "running"
    out = capsys.readouterr().out
    assert f"instance {instance_id}: running" in out
    assert f"DCV URL: {stack['DcvUrl']}" in out
    assert "start checks: no verdict: none within 2 s (the start checks have not finished yet)" in out
    commands = boto3.client("ssm", region_name=REGION).list_commands(InstanceId=instance_id)["Commands"]
    assert commands[-1]["DocumentName"] == "AWS-RunShellScript"
    assert commands[-1]["Parameters"]["commands"] == lib.START_VERDICT_COMMANDS


def test_start_of_a_running_host_says_so_and_waits_for_nothing(stack, capsys, monkeypatch):
    """Right after `cdk deploy` the host runs and its start checks have never run (the first boot verifies
    itself): waiting for their verdict would take the whole --timeout and end in "no verdict"."""
    instance_id = stack["InstanceId"]
    sent: list[str] = []
    intercept(monkeypatch, "SendCommand", lambda original, params: sent.append("x") or original())

    assert main(["instance", "start", "--timeout", "5"]) == 0
    out = capsys.readouterr().out
    assert f"instance {instance_id}: already running" in out
    assert "`twin instance check`" in out
    assert f"DCV URL: {stack['DcvUrl']}" in out
    assert "waiting" not in out
    assert sent == []
    assert ec2_state(instance_id) == "running"


def test_stop_of_a_host_still_starting_says_what_to_wait_for(stack, capsys, monkeypatch):
    """EC2 refuses StopInstances while the instance is pending (moto does not, so the refusal is injected)."""
    instance_id = stack["InstanceId"]

    refuse_state(monkeypatch, "StopInstances", instance_id)
    assert main(["instance", "stop", "--timeout", "5"]) == cmd.EXIT_AWS
    err = capsys.readouterr().err
    # The state in parentheses is EC2's at the time (pending on AWS; moto's instance runs).
    assert f"instance {instance_id} cannot be stopped now (" in err
    assert "wait until it is running (`twin instance status`), then stop it again" in err


def test_start_of_a_host_still_stopping_says_what_to_wait_for(stack, capsys, monkeypatch):
    """EC2 refuses StartInstances while the instance is stopping (moto does not: the refusal is injected)."""
    instance_id = stack["InstanceId"]
    assert main(["instance", "stop", "--no-wait"]) == 0

    refuse_state(monkeypatch, "StartInstances", instance_id)
    capsys.readouterr()
    assert main(["instance", "start", "--timeout", "5"]) == cmd.EXIT_AWS
    err = capsys.readouterr().err
    assert f"instance {instance_id} cannot be started now (" in err
    assert "wait until it is stopped (`twin instance status`), then start it again" in err


def test_a_terminated_host_is_not_waited_for(stack, capsys, monkeypatch):
    """A host terminated outside the stack: "wait until it is stopped" would never come true."""
    instance_id = stack["InstanceId"]
    boto3.client("ec2", region_name=REGION).terminate_instances(InstanceIds=[instance_id])

    refuse_state(monkeypatch, "StartInstances", instance_id)
    assert main(["instance", "start", "--timeout", "5"]) == cmd.EXIT_AWS
    err = capsys.readouterr().err
    assert f"instance {instance_id} cannot be started: it is terminated, and EC2 never starts" in err, err
    # The stack's first host (its Settings output has no hostGeneration): the exact line and command.
    assert "write hostGeneration = 2 into twin.settings.toml" in err, err
    assert "and run `cdk deploy -c replaceInstance=true`" in err, err
    # What comes back and what does not.
    assert "It keeps the DCV address and password" in err, err
    assert "the history, the calibrations, the servo alarms and your agent.local.toml" in err, err
    assert "USD recordings, the console's Events list) is gone" in err, err
    assert "wait until" not in err, err


def test_the_status_of_a_terminated_host_gives_the_way_to_a_new_one(stack, capsys, monkeypatch):
    """It said "terminated" and "agent health unknown", and nothing of what to do."""
    instance_id = stack["InstanceId"]
    boto3.client("ec2", region_name=REGION).terminate_instances(InstanceIds=[instance_id])
    assert main(["instance", "status"]) == 0
    out = capsys.readouterr().out
    assert f"instance {instance_id}: terminated" in out, out
    assert "Build a new host in its place: write hostGeneration = 2 into twin.settings.toml" in out, out


def deployed_with(settings: dict | None, stack_name: str) -> str:
    """A twin stack in moto whose Settings output holds `settings` as the given values (None: a stack older
    than the output, without it); its instance id."""
    template = json.loads(json.dumps(TEMPLATE))
    if settings is None:
        del template["Outputs"]["Settings"]
    else:
        document = {"version": 1, "values": settings, "given": {key: "file" for key in settings}}
        template["Outputs"]["Settings"]["Value"] = json.dumps(document)
    cfn = boto3.client("cloudformation", region_name=REGION)
    cfn.create_stack(StackName=stack_name, TemplateBody=json.dumps(template))
    outputs = cfn.describe_stacks(StackName=stack_name)["Stacks"][0]["Outputs"]
    return next(o["OutputValue"] for o in outputs if o["OutputKey"] == "InstanceId")


def terminated_refusal(monkeypatch: pytest.MonkeyPatch, capsys, settings: dict | None, action: str) -> str:
    """What `twin instance <action>` (start, stop) prints for a terminated host of a stack deployed with
    `settings`."""
    operation, done = {"start": ("StartInstances", "started"), "stop": ("StopInstances", "stopped")}[action]
    with mock_aws():
        instance_id = deployed_with(settings, "LaterTwin")
        boto3.client("ec2", region_name=REGION).terminate_instances(InstanceIds=[instance_id])
        refuse_state(monkeypatch, operation, instance_id)
        capsys.readouterr()
        assert main(["instance", action, "--stack", "LaterTwin", "--timeout", "5"]) == cmd.EXIT_AWS
    err = capsys.readouterr().err
    assert f"instance {instance_id} cannot be {done}: it is terminated" in err, err
    return err


def test_a_terminated_later_host_is_told_the_next_generation(aws_env, capsys, monkeypatch):
    deployed = {"clientCidr": "203.0.113.7/32", "hostGeneration": 3}
    err = terminated_refusal(monkeypatch, capsys, deployed, "stop")
    assert "write hostGeneration = 4 into twin.settings.toml" in err, err


def test_a_terminated_host_of_an_older_stack_is_told_to_raise_the_generation(aws_env, capsys, monkeypatch):
    err = terminated_refusal(monkeypatch, capsys, None, "start")
    assert "raise hostGeneration by one in twin.settings.toml (write hostGeneration = 2 if" in err, err
    assert "instance settings" not in err, err  # it fails alike on a stack without that output
    assert "`cdk deploy -c replaceInstance=true`" in err, err


@pytest.mark.parametrize("command", [["start", "--timeout", "5"], ["stop", "--timeout", "5"], ["status"]])
def test_a_host_ec2_has_forgotten_gets_the_same_way_back(stack, capsys, monkeypatch, command):
    """EC2 lists a terminated instance for about an hour; an account's cleanup is noticed later, when every
    call about the instance answers InvalidInstanceID.NotFound (which moto never does for a known id)."""
    instance_id = stack["InstanceId"]
    original = botocore.client.BaseClient._make_api_call

    def forgotten(self, operation_name, api_params):
        if operation_name in ("DescribeInstances", "StartInstances", "StopInstances"):
            message = f"The instance ID '{instance_id}' does not exist"
            raise client_error("InvalidInstanceID.NotFound", message, operation_name)
        return original(self, operation_name, api_params)

    monkeypatch.setattr(botocore.client.BaseClient, "_make_api_call", forgotten)
    assert main(["instance", *command]) == cmd.EXIT_AWS
    err = capsys.readouterr().err
    assert f"instance {instance_id} of stack So101TwinStack no longer exists: it was terminated" in err, err
    assert "write hostGeneration = 2 into twin.settings.toml" in err, err
    assert "InvalidInstanceID" not in err, err


def test_no_wait_returns_the_transitional_state(stack, capsys):
    assert main(["instance", "stop", "--no-wait"]) == 0
    out = capsys.readouterr().out
    assert f"instance {stack['InstanceId']}: stopping" in out
    assert "not waiting" in out


def test_status_shows_state_type_url_and_health(stack, capsys):
    assert main(["instance", "status"]) == 0
    out = capsys.readouterr().out
    assert f"instance {stack['InstanceId']}: running (g6e.2xlarge in {REGION}a)" in out
    assert f"DCV URL: {stack['DcvUrl']}" in out
    assert "agent health" in out

    assert main(["instance", "stop"]) == 0
    capsys.readouterr()
    assert main(["instance", "status"]) == 0
    out = capsys.readouterr().out
    assert ": stopped (g6e.2xlarge" in out
    assert "agent health unknown: the instance is stopped" in out


def test_status_when_ssm_agent_not_registered(stack, capsys, monkeypatch):
    def unregistered(_call, params):
        raise client_error(
            "InvalidInstanceId", f"Instances [[{params['InstanceIds'][0]}]] not valid", "SendCommand"
        )

    intercept(monkeypatch, "SendCommand", unregistered)
    assert main(["instance", "status"]) == 0
    assert "agent health unknown: the SSM agent has not registered yet" in capsys.readouterr().out


def test_stack_name_from_flag_and_environment(stack, capsys, monkeypatch):
    assert main(["instance", "url", "--stack", lib.DEFAULT_STACK_NAME, "--region", REGION]) == 0
    assert capsys.readouterr().out == stack["DcvUrl"] + "\n"
    monkeypatch.setenv(lib.STACK_ENV_VAR, "OtherTwin")
    assert main(["instance", "url"]) == cmd.EXIT_NO_STACK
    assert "stack OtherTwin not found" in capsys.readouterr().err


# --- errors users can fix ----------------------------------------------------------------------------------


def test_missing_stack_is_a_clear_message(aws_env, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with mock_aws():
        assert main(["instance", "start", "--stack", "GoneTwin"]) == cmd.EXIT_NO_STACK
        captured = capsys.readouterr()
        assert captured.err.strip() == (
            "twin instance start: stack GoneTwin not found in us-east-1: deploy it with "
            "`cdk deploy` (docs/deploy.md) or pass --stack, or --region if it was deployed to another region"
        )
        assert "Traceback" not in captured.err and captured.out == ""
        # The default name, with no settings file here or above: said, since the deployed stack may be named
        # in a settings file this command did not see (run from another directory).
        assert main(["instance", "start"]) == cmd.EXIT_NO_STACK
        assert captured.err.strip() != (err := capsys.readouterr().err.strip())
        assert err == (
            "twin instance start: stack So101TwinStack not found in us-east-1 (the default name: no "
            f"twin.settings.toml in {tmp_path.resolve()} or above it; run from the checkout you deployed "
            "from): deploy it with `cdk deploy` (docs/deploy.md) or pass --stack, or --region if it was "
            "deployed to another region"
        )


def test_a_stack_looked_for_in_another_region_points_at_region(stack, capsys):
    """The stack is there, in another region (AWS_REGION, the profile's, or --region): a person told only to
    deploy it would build a second twin host."""
    assert main(["instance", "status", "--region", "eu-west-1"]) == cmd.EXIT_NO_STACK
    err = capsys.readouterr().err
    assert "stack So101TwinStack not found in eu-west-1" in err
    assert "or --region if it was deployed to another region" in err


def test_the_stack_name_comes_from_the_settings_file_where_there_is_one(aws_env, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert lib.default_stack_name() == "So101TwinStack"
    (tmp_path / "twin.settings.toml").write_text('clientCidr = "203.0.113.7/32"\nstackName = "FiveArms"\n')
    assert lib.default_stack_name() == "FiveArms"
    monkeypatch.setenv(lib.STACK_ENV_VAR, "Other")
    assert lib.default_stack_name() == "Other"
    monkeypatch.delenv(lib.STACK_ENV_VAR)
    # From a folder of the checkout (docs/), the checkout's file: the stack `cdk deploy` made there.
    (tmp_path / "cdk.json").write_text("{}")
    (tmp_path / "docs").mkdir()
    monkeypatch.chdir(tmp_path / "docs")
    assert lib.default_stack_name() == "FiveArms"
    # Not past the checkout's root: a file above it belongs to no deployment of this checkout.
    (tmp_path / "docs" / "cdk.json").write_text("{}")
    assert lib.default_stack_name() == "So101TwinStack"
    monkeypatch.chdir(tmp_path)
    (tmp_path / "twin.settings.toml").write_text("not toml [")
    assert lib.default_stack_name() == "So101TwinStack"  # `cdk deploy` says what is wrong with the file


def test_missing_outputs_names_them(aws_env, capsys):
    template = {
        "Resources": TEMPLATE["Resources"],
        "Outputs": {"InstanceId": TEMPLATE["Outputs"]["InstanceId"]},
    }
    with mock_aws():
        boto3.client("cloudformation", region_name=REGION).create_stack(
            StackName="HalfTwin", TemplateBody=json.dumps(template)
        )
        assert main(["instance", "status", "--stack", "HalfTwin"]) == cmd.EXIT_NO_OUTPUTS
    err = capsys.readouterr().err
    assert "stack HalfTwin in us-east-1" in err and "has no output DcvUrl" in err
    assert "cdk deploy" in err


def test_missing_credentials_says_how_to_configure(aws_env, capsys, monkeypatch):
    monkeypatch.delenv("AWS_ACCESS_KEY_ID")
    monkeypatch.delenv("AWS_SECRET_ACCESS_KEY")
    assert main(["instance", "url"]) == cmd.EXIT_SETUP
    err = capsys.readouterr().err
    assert "no AWS credentials found" in err and "aws configure" in err
    assert "Traceback" not in err


def test_missing_region_says_how_to_configure(aws_env, capsys, monkeypatch):
    monkeypatch.delenv("AWS_DEFAULT_REGION")
    assert main(["instance", "status"]) == cmd.EXIT_SETUP
    err = capsys.readouterr().err
    assert "no AWS region configured" in err and "--region" in err


def test_rejected_credentials_are_a_setup_error(stack, capsys, monkeypatch):
    def expired(_call, _params):
        raise client_error(
            "ExpiredToken", "The security token included in the request is expired", "DescribeStacks"
        )

    intercept(monkeypatch, "DescribeStacks", expired)
    assert main(["instance", "url"]) == cmd.EXIT_SETUP
    assert "AWS rejected the credentials (ExpiredToken" in capsys.readouterr().err


def test_insufficient_capacity_explains_the_way_out(stack, capsys, monkeypatch):
    assert main(["instance", "stop"]) == 0
    capsys.readouterr()

    def no_capacity(_call, _params):
        raise client_error(
            "InsufficientInstanceCapacity",
            "We currently do not have sufficient g6e.2xlarge capacity in the Availability Zone you requested",
            "StartInstances",
        )

    intercept(monkeypatch, "StartInstances", no_capacity)
    assert main(["instance", "start"]) == cmd.EXIT_CAPACITY
    captured = capsys.readouterr()
    err = captured.err
    assert "no g6e.2xlarge capacity in us-east-1a" in err
    assert "that Availability Zone's g6e.2xlarge capacity is exhausted" in err
    # A bare -c availabilityZone= is refused at synth (it replaces the host) and undone by the next deploy
    # without it: the way out named is the one the replacement guard lets through.
    assert "-c availabilityZone=" not in err
    assert 'write availabilityZone = "<zone>" into twin.settings.toml' in err
    assert f"cdk deploy -c {replacement_guard.CONFIRM_FLAG}=true" in err
    assert (
        "aws ec2 describe-instance-type-offerings --location-type availability-zone "
        "--filters Name=instance-type,Values=g6e.2xlarge --region us-east-1" in err
    )
    assert "Traceback" not in err and captured.out == ""
    assert ec2_state(stack["InstanceId"]) == "stopped"


def test_wait_is_bounded_by_timeout(stack, capsys, monkeypatch):
    assert main(["instance", "stop"]) == 0
    capsys.readouterr()

    def stuck_pending(call, _params):
        response = call()
        for reservation in response["Reservations"]:
            for inst in reservation["Instances"]:
                inst["State"] = {"Code": 0, "Name": "pending"}
        return response

    intercept(monkeypatch, "DescribeInstances", stuck_pending)
    assert main(["instance", "start", "--timeout", "1"]) == cmd.EXIT_WAIT
    err = capsys.readouterr().err
    assert f"instance {stack['InstanceId']} was not running after 1 s (now pending)" in err
    assert "--timeout" in err


def test_help_documents_exit_codes(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["instance", "start", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for text in (
        "--stack",
        "--region",
        "--no-wait",
        "--timeout",
        "exit codes",
        "4 stack not found",
        "6 InsufficientInstanceCapacity",
        "SO101_TWIN_STACK",
    ):
        assert text in out


# --- agent health through SSM ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("stdout", "state", "status", "reason_part"),
    [
        ('{"status": "ok", "devices": {"arm-001": {"status": "ok"}}}200', lib.HEALTHY, 200, "arm-001=ok"),
        (
            '{"devices": {"arm-001": "stale", "arm-002": "ok"}}503',
            lib.UNHEALTHY,
            503,
            "arm-001=stale, arm-002=ok",
        ),
        (
            '{"devices": [{"device_id": "arm-7", "state": "offline"}]}\n503\n',
            lib.UNHEALTHY,
            503,
            "arm-7=offline",
        ),
        ("000", lib.UNHEALTHY, 0, f"nothing answers on {lib.HEALTH_URL}"),
        ("not json at all500", lib.UNHEALTHY, 500, "HTTP 500"),
        ("", lib.UNKNOWN, None, "printed no HTTP status"),
        ("curl: command not found", lib.UNKNOWN, None, "printed no HTTP status"),
    ],
)
def test_parse_health_output(stdout, state, status, reason_part):
    health = lib.parse_health_output(stdout)
    assert health.state == state
    assert health.http_status == status
    assert reason_part in health.reason
    assert health.healthy is (state == lib.HEALTHY)


def _stubbed_twin(stack) -> tuple[lib.TwinInstance, Stubber]:
    ssm = boto3.client("ssm", region_name=REGION)
    twin = lib.TwinInstance(ssm=ssm, health_poll_interval_s=0.0)
    return twin, Stubber(ssm)


def _invocation(status: str, stdout: str = "") -> dict:
    return {"CommandId": COMMAND_ID, "InstanceId": "i-x", "Status": status, "StandardOutputContent": stdout}


def test_health_polls_until_the_command_finishes(stack):
    twin, stubber = _stubbed_twin(stack)
    instance_id = stack["InstanceId"]
    sent = {
        "InstanceIds": [instance_id],
        "DocumentName": "AWS-RunShellScript",
        "Comment": "twin instance: agent /healthz",
        "Parameters": {"commands": lib.STATUS_COMMANDS},
        "TimeoutSeconds": 30,
    }
    stubber.add_response("send_command", {"Command": {"CommandId": COMMAND_ID}}, sent)
    stubber.add_client_error("get_command_invocation", "InvocationDoesNotExist")
    stubber.add_response("get_command_invocation", _invocation("InProgress"))
    body = json.dumps({"status": "ok", "devices": {"arm-001": {"status": "ok"}}})
    stubber.add_response("get_command_invocation", _invocation("Success", "version=abc123\n" + body + "200"))
    with stubber:
        health = twin.health(timeout_s=10)
    stubber.assert_no_pending_responses()
    assert health.healthy
    assert health.body == json.loads(body)
    assert health.describe() == "agent healthy: arm-001=ok"
    assert health.host_version == "abc123"


def test_health_reads_output_of_a_failed_curl(stack):
    twin, stubber = _stubbed_twin(stack)
    stubber.add_response("send_command", {"Command": {"CommandId": COMMAND_ID}})
    stubber.add_response("get_command_invocation", _invocation("Failed", "000"))
    with stubber:
        health = twin.health(timeout_s=10)
    assert health.state == lib.UNHEALTHY and health.http_status == 0


def test_health_wait_is_bounded(stack):
    twin, stubber = _stubbed_twin(stack)
    stubber.add_response("send_command", {"Command": {"CommandId": COMMAND_ID}})
    stubber.add_response("get_command_invocation", _invocation("InProgress"))
    with stubber:
        started = datetime.datetime.now()
        health = twin.health(timeout_s=0.0)
    assert (datetime.datetime.now() - started).total_seconds() < 5
    assert health.state == lib.UNKNOWN
    assert "did not finish within 0 s" in health.reason


@pytest.mark.parametrize(
    ("code", "expected"),
    [
        ("InvalidInstanceId", "agent health unknown: the SSM agent has not registered yet"),
        ("AccessDeniedException", "agent health unknown: SSM could not run the check (AccessDeniedException"),
    ],
)
def test_health_unknown_when_ssm_cannot_ask(stack, code, expected):
    twin, stubber = _stubbed_twin(stack)
    stubber.add_client_error("send_command", code, "refused")
    with stubber:
        health = twin.health(timeout_s=10)
    assert health.state == lib.UNKNOWN
    assert health.describe().startswith(expected)


def test_clients_are_built_lazily(aws_env):
    twin = lib.TwinInstance("AnyStack", region="eu-west-1")
    assert twin._clients == {"cloudformation": None, "ec2": None, "ssm": None}
    assert twin.region == "eu-west-1"
    assert lib.default_stack_name() == "So101TwinStack"
