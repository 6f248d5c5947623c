"""The synthesized template, point by point against issues 4 and 9, plus a normalised snapshot.

Each synth runs cdk-nag (AwsSolutions) and CDK's CloudFormation validation through the real
app wiring, so merely getting a template here proves zero unacknowledged findings.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Any

import pytest
from aws_cdk.assertions import Match
from syrupy.extensions.json import JSONSnapshotExtension

from stacks.settings import DEFAULT_AMI_SSM_PARAMETER, MAX_LISTED_DEVICES
from stacks.twin_host import BOOT_TIMEOUT_MINUTES
from stacks.twin_stack import OUTPUT_KEYS as STACK_OUTPUT_KEYS

from .iam_limits import RoleSize, role_size
from .synth import CLIENT_CIDR, Synth, normalise

OUTPUT_KEYS = set(STACK_OUTPUT_KEYS)


def flatten(value: Any) -> str:
    """A template fragment as text, for 'this ARN pattern appears somewhere in here' checks."""
    return json.dumps(value, sort_keys=True)


def policy_statements(synth: Synth, role_logical_prefix: str) -> list[dict[str, Any]]:
    statements = []
    for policy in synth.resources("AWS::IAM::Policy").values():
        roles = flatten(policy["Properties"].get("Roles", []))
        if role_logical_prefix in roles:
            statements += policy["Properties"]["PolicyDocument"]["Statement"]
    assert statements, f"no policy attached to a role like {role_logical_prefix}"
    return statements


def statement(statements: list[dict[str, Any]], sid: str) -> dict[str, Any]:
    found = [s for s in statements if s.get("Sid") == sid]
    assert len(found) == 1, f"statement {sid}: {found}"
    return found[0]


# --- snapshot -------------------------------------------------------------------------------------


def test_template_snapshot(synth_default: Synth, snapshot) -> None:
    assert normalise(synth_default.json) == snapshot.use_extension(JSONSnapshotExtension)


def test_snapshot_normalisation_removes_every_asset_hash(synth_default: Synth) -> None:
    text = json.dumps(normalise(synth_default.json))
    assert "<asset-hash>" in text
    assert not re.search(r"[0-9a-f]{64}", text)
    version = synth_default.json["Outputs"]["DeploymentVersion"]["Value"]
    assert version not in text
    assert text.count("<deployment-version>") == 3  # the output, the parameter, the association


# --- network --------------------------------------------------------------------------------------


def test_vpc_is_one_public_subnet_without_nat(synth_default: Synth) -> None:
    t = synth_default.template
    t.has_resource_properties("AWS::EC2::VPC", {"CidrBlock": "10.0.0.0/16"})
    t.resource_count_is("AWS::EC2::Subnet", 1)
    t.resource_count_is("AWS::EC2::NatGateway", 0)
    t.resource_count_is("AWS::EC2::InternetGateway", 1)
    # The EIP is the host's only public address.
    t.has_resource_properties("AWS::EC2::Subnet", {"MapPublicIpOnLaunch": False})


def test_vpc_flow_logs_go_to_a_log_group_with_retention(synth_default: Synth) -> None:
    t = synth_default.template
    t.has_resource_properties(
        "AWS::EC2::FlowLog",
        {"ResourceType": "VPC", "TrafficType": "ALL", "LogDestinationType": "cloud-watch-logs"},
    )
    flow_log = synth_default.one("AWS::EC2::FlowLog")
    group_id = flow_log["Properties"]["LogGroupName"]["Ref"]
    group = synth_default.json["Resources"][group_id]
    assert group["Properties"]["RetentionInDays"] == 365
    assert group["DeletionPolicy"] == "Delete"


def test_pinned_availability_zone_is_used_by_the_subnet(
    synth_default: Synth, synth_all_options: Synth
) -> None:
    synth_all_options.template.has_resource_properties("AWS::EC2::Subnet", {"AvailabilityZone": "us-east-1b"})
    # Unpinned and environment-agnostic: the region's first AZ, chosen at deploy time.
    synth_default.template.has_resource_properties(
        "AWS::EC2::Subnet", {"AvailabilityZone": {"Fn::Select": [0, {"Fn::GetAZs": ""}]}}
    )


def ingress_rules(synth: Synth) -> list[dict[str, Any]]:
    group = next(
        g
        for g in synth.resources("AWS::EC2::SecurityGroup").values()
        if "DCV" in g["Properties"]["GroupDescription"]
    )
    return group["Properties"]["SecurityGroupIngress"]


def test_security_group_opens_dcv_to_the_client_only(synth_default: Synth) -> None:
    rules = ingress_rules(synth_default)
    ports = sorted((r["IpProtocol"], r["FromPort"], r["ToPort"]) for r in rules)
    assert ports == [("tcp", 8443, 8443), ("udp", 8443, 8443)]
    assert {r["CidrIp"] for r in rules} == {CLIENT_CIDR}
    assert all(r.get("Description") for r in rules)


def test_no_ssh_port_in_any_variant(synth_all_options: Synth, synth_default: Synth) -> None:
    for synth in (synth_default, synth_all_options):
        rules = ingress_rules(synth)
        assert sorted((r["IpProtocol"], r["FromPort"]) for r in rules) == [("tcp", 8443), ("udp", 8443)]
        assert all("CidrIpv6" not in r for r in rules)
    assert {r["CidrIp"] for r in ingress_rules(synth_all_options)} == {"198.51.100.0/24"}
    assert "KeyName" not in synth_default.one("AWS::EC2::Instance")["Properties"]


def test_egress_is_only_http_and_https(synth_default: Synth) -> None:
    group = next(
        g
        for g in synth_default.resources("AWS::EC2::SecurityGroup").values()
        if "DCV" in g["Properties"]["GroupDescription"]
    )
    egress = sorted((r["IpProtocol"], r["FromPort"]) for r in group["Properties"]["SecurityGroupEgress"])
    assert egress == [("tcp", 80), ("tcp", 443)]


def test_open_cidr_synthesizes_only_with_allow_any_client(synth_factory) -> None:
    synth = synth_factory(clientCidr="0.0.0.0/0", allowAnyClient="true")
    assert {r["CidrIp"] for r in ingress_rules(synth)} == {"0.0.0.0/0"}


def test_concrete_region_synth_is_nag_clean_and_checks_the_zone(synth_factory) -> None:
    """`cdk synth` with a configured region resolves ARNs to literals; acknowledgements must still match."""
    from stacks.settings import SettingsError

    from .synth import ALL_OPTIONS

    synth = synth_factory(region="us-east-1", **ALL_OPTIONS)
    statements = policy_statements(synth, "IdentityHostRole")
    assert ":iot:us-east-1:" in flatten(statement(statements, "IotReceiveTelemetry"))
    with pytest.raises(SettingsError, match="not in the stack's region us-west-2"):
        synth_factory(region="us-west-2", availabilityZone="us-east-1b")


# --- identity -------------------------------------------------------------------------------------


def test_host_role_is_for_ec2_without_any_managed_policy(synth_default: Synth) -> None:
    roles = [
        r["Properties"]
        for r in synth_default.resources("AWS::IAM::Role").values()
        if "ec2.amazonaws.com" in flatten(r["Properties"]["AssumeRolePolicyDocument"])
    ]
    assert len(roles) == 1
    assert "ManagedPolicyArns" not in roles[0]
    assert "AmazonSSMManagedInstanceCore" not in json.dumps(synth_default.json)
    synth_default.template.has_resource_properties(
        "AWS::IAM::InstanceProfile", {"Roles": [{"Ref": Match.string_like_regexp("^IdentityHostRole")}]}
    )


def test_ssm_is_granted_only_what_the_agent_calls(synth_default: Synth) -> None:
    """Session Manager, Run Command and the State Manager association; no inventory, patching, Distributor,
    and no parameter reads but the stack's own."""
    statements = policy_statements(synth_default, "IdentityHostRole")
    core = statement(statements, "SsmAgentCore")
    assert sorted(core["Action"]) == [
        "ssm:DescribeAssociation",
        "ssm:ListInstanceAssociations",
        "ssm:UpdateInstanceAssociationStatus",
        "ssm:UpdateInstanceInformation",
    ]
    document = statement(statements, "SsmAssociationDocument")
    assert sorted(document["Action"]) == ["ssm:DescribeDocument", "ssm:GetDocument"]
    assert document["Resource"] == {
        "Fn::Join": [
            "",
            [
                "arn:",
                {"Ref": "AWS::Partition"},
                ":ssm:",
                {"Ref": "AWS::Region"},
                "::document/AWS-RunShellScript",
            ],
        ]
    }
    assert all(a.startswith("ec2messages:") for a in statement(statements, "RunCommandMessages")["Action"])
    assert all(
        a.startswith("ssmmessages:") for a in statement(statements, "SessionManagerChannels")["Action"]
    )
    ssm_actions = {
        action
        for s in statements
        for action in ([s["Action"]] if isinstance(s["Action"], str) else s["Action"])
        if action.startswith("ssm:")
    }
    assert not ssm_actions & {
        "ssm:PutInventory",
        "ssm:PutComplianceItems",
        "ssm:GetManifest",
        "ssm:ListAssociations",
    }
    assert not [a for a in ssm_actions | {flatten(s["Action"]) for s in statements} if a.endswith("*")]


def test_parameter_reads_name_this_stacks_parameter_only(synth_default: Synth) -> None:
    statements = policy_statements(synth_default, "IdentityHostRole")
    reads = [s for s in statements if "ssm:GetParameter" in flatten(s["Action"])]
    assert len(reads) == 1
    parameter_id = next(iter(synth_default.resources("AWS::SSM::Parameter")))
    resource = flatten(reads[0]["Resource"])
    assert f'"Ref": "{parameter_id}"' in resource and ":parameter" in resource
    assert "*" not in resource


def test_iot_permissions_are_scoped_to_the_agent_and_the_devices(synth_default: Synth) -> None:
    statements = policy_statements(synth_default, "IdentityHostRole")
    connect = statement(statements, "IotConnectAsAgent")
    assert connect["Action"] == "iot:Connect"
    # One listed device: the pool has one connection, and only its client id is allowed.
    resource = connect["Resource"][0] if isinstance(connect["Resource"], list) else connect["Resource"]
    # The host agent's own prefix, named for the stack: never an agent's on a laptop beside it.
    assert ":client/so101-twin-So101TwinStack-*-0" in flatten(connect["Resource"])
    assert ":client/so101-twin-So101TwinStack-*-1" not in flatten(connect["Resource"])
    assert {"Ref": "AWS::Region"} in resource["Fn::Join"][1]
    assert {"Ref": "AWS::AccountId"} in resource["Fn::Join"][1]
    subscribe = statement(statements, "IotSubscribeTelemetry")
    assert subscribe["Action"] == "iot:Subscribe"
    assert ":topicfilter/dt/lerobot/arm-001/telemetry" in flatten(subscribe["Resource"])
    receive = statement(statements, "IotReceiveTelemetry")
    assert receive["Action"] == "iot:Receive"
    assert ":topic/dt/lerobot/arm-001/telemetry" in flatten(receive["Resource"])
    assert "*" not in flatten(subscribe) + flatten(receive)
    endpoint = statement(statements, "IotFindEndpoint")
    assert (endpoint["Action"], endpoint["Resource"]) == ("iot:DescribeEndpoint", "*")
    # Nothing may publish: the host only mirrors.
    assert "iot:Publish" not in flatten(statements)


def test_fleet_subscribes_exactly_the_shared_filter_from_the_pool_client_ids(
    synth_all_options: Synth,
) -> None:
    # The whole fleet comes through the agent's shared subscription over at most 8 pool connections
    # (IoT Core's 100 publishes/s per connection): exactly that filter and those client ids are allowed.
    statements = policy_statements(synth_all_options, "IdentityHostRole")
    subscribe = statement(statements, "IotSubscribeTelemetry")
    receive = statement(statements, "IotReceiveTelemetry")
    connect = statement(statements, "IotConnectAsAgent")
    subscribe_arns = (
        subscribe["Resource"] if isinstance(subscribe["Resource"], list) else [subscribe["Resource"]]
    )
    assert len(subscribe_arns) == 1
    # The group is the host agent's own (its client id prefix), so a laptop's agent has a group of its own.
    group = "so101-twin-So101TwinStack"
    assert f":topicfilter/$share/{group}/fleet/so101/+/telemetry" in flatten(subscribe_arns[0])
    assert f":topic/$share/{group}/fleet/so101/*/telemetry" in flatten(receive)
    assert ":topicfilter/fleet/so101/+/telemetry" not in flatten(subscribe)  # no plain, unshared filter
    ids = [flatten(r).rsplit(":client/", 1)[1].split('"', 1)[0] for r in connect["Resource"]]
    assert ids == [f"so101-twin-So101TwinStack-*-{i}" for i in range(8)]
    # Partition-aware: every IoT ARN is built from the stack's partition, never a literal "aws".
    for arn in (*connect["Resource"], *subscribe_arns, receive["Resource"]):
        assert "AWS::Partition" in flatten(arn)


def role_statements(synth: Synth, role_logical_prefix: str) -> list[dict[str, Any]]:
    """The role's statements in its inline policy and in the managed ones CDK moves the overflow into."""
    statements = []
    for kind in ("AWS::IAM::Policy", "AWS::IAM::ManagedPolicy"):
        for policy in synth.resources(kind).values():
            if role_logical_prefix in flatten(policy["Properties"].get("Roles", [])):
                statements += policy["Properties"]["PolicyDocument"]["Statement"]
    return statements


def host_role_size(synth: Synth) -> RoleSize:
    (role,) = [k for k in synth.resources("AWS::IAM::Role") if k.startswith("IdentityHostRole")]
    return role_size(synth.json, role)


def granted(statements: list[dict[str, Any]], action: str, kind: str) -> list[str]:
    """The `kind` resources (client, topicfilter, topic) granted for `action`, after the ARN's kind."""
    found = []
    for s in statements:
        if s["Action"] == action:
            resources = s["Resource"] if isinstance(s["Resource"], list) else [s["Resource"]]
            found += [flatten(r).rsplit(f":{kind}/", 1)[1].split('"', 1)[0] for r in resources]
    return found


@pytest.mark.parametrize("id_chars", [1, 64], ids=["shortest-ids", "longest-ids"])
def test_a_listed_fleet_at_its_bound_fits_iams_quotas_naming_each_device(
    synth_factory, id_chars: int
) -> None:
    """IAM refuses a role's policies over its size quotas only at deploy time; the settings bound the list
    so that it never happens, with ids of any allowed length (the shortest pack into the most statements,
    the longest make the longest ARNs)."""
    # "0".."149" (one to three characters), or 64 characters each.
    devices = [str(i).ljust(id_chars, "x") for i in range(MAX_LISTED_DEVICES)]
    synth = synth_factory(devices=",".join(devices))
    assert host_role_size(synth).problems() == []
    statements = role_statements(synth, "IdentityHostRole")
    topics = [f"dt/lerobot/{d}/telemetry" for d in devices]
    # CDK packs whole statements into the policies in its own order.
    assert sorted(granted(statements, "iot:Subscribe", "topicfilter")) == sorted(topics)
    assert sorted(granted(statements, "iot:Receive", "topic")) == sorted(topics)
    # 150 arms at 10 Hz, 8 on a connection: 19 connections, and exactly their client ids.
    patterns = granted(statements, "iot:Connect", "client")
    assert matched_indexes(patterns, "so101-twin-So101TwinStack-*-") == [str(i) for i in range(19)]


def matched_indexes(patterns: list[str], prefix: str) -> list[str]:
    """The indexes 0..9999 (and any with a leading zero) that IAM's '?' in the patterns would let connect."""
    assert all(p.startswith(prefix) for p in patterns), patterns
    rules = [re.compile(re.escape(p[len(prefix) :]).replace(r"\?", "[0-9]") + "$") for p in patterns]
    candidates = [str(i) for i in range(10_000)] + [f"0{i}" for i in range(1_000)]
    return [c for c in candidates if any(r.match(c) for r in rules)]


def test_the_fleets_client_ids_follow_max_connections(synth_factory) -> None:
    synth = synth_factory(devices="*", maxConnections="64", armRateHz="20")
    statements = role_statements(synth, "IdentityHostRole")
    patterns = granted(statements, "iot:Connect", "client")
    # Exactly the pool's 64 indexes, in a few patterns rather than one ARN each.
    assert matched_indexes(patterns, "so101-twin-So101TwinStack-*-") == [str(i) for i in range(64)]
    assert len(patterns) < 20
    assert host_role_size(synth).problems() == []
    parameter = flatten(synth.resources("AWS::SSM::Parameter"))
    assert "MAX_CONNECTIONS=64" in parameter and "ARM_RATE_HZ=20.0" in parameter


def test_dcv_license_logs_assets_and_secret_are_granted_narrowly(synth_default: Synth) -> None:
    statements = policy_statements(synth_default, "IdentityHostRole")
    license_ = statement(statements, "DcvLicense")
    assert license_["Action"] == "s3:GetObject"
    assert license_["Resource"] == {
        "Fn::Join": [
            "",
            ["arn:", {"Ref": "AWS::Partition"}, ":s3:::dcv-license.", {"Ref": "AWS::Region"}, "/*"],
        ]
    }
    logs = statement(statements, "HostLogs")
    assert logs["Resource"]["Fn::GetAtt"][0].startswith("IdentityAgentLogGroup")
    assets = statement(statements, "ReadBootstrapAssets")
    assert assets["Action"] == "s3:GetObject"
    assert len(assets["Resource"]) == 2
    assert all(".zip" in flatten(r) for r in assets["Resource"])
    secret_reads = [s for s in statements if "secretsmanager:GetSecretValue" in flatten(s.get("Action"))]
    assert len(secret_reads) == 1
    assert secret_reads[0]["Resource"]["Ref"].startswith("HostDcvPassword")
    # A bare "*" resource only where the action has no resource type: DescribeEndpoint and the SSM Agent's
    # own calls for the instance it runs on.
    bare = sorted(s.get("Sid") for s in statements if s["Resource"] == "*")
    assert bare == ["IotFindEndpoint", "RunCommandMessages", "SessionManagerChannels", "SsmAgentCore"]


def test_agent_log_group_is_named_retained_a_year_and_removed_on_destroy(synth_default: Synth) -> None:
    synth_default.template.has_resource(
        "AWS::Logs::LogGroup",
        {
            "Properties": {"LogGroupName": "/so101-twin/So101TwinStack/host", "RetentionInDays": 365},
            "DeletionPolicy": "Delete",
        },
    )


# --- host -----------------------------------------------------------------------------------------


def test_instance_metadata_is_imdsv2_with_a_hop_limit_of_one(synth_default: Synth) -> None:
    """Set explicitly: no container or forwarded packet on the host reaches the role's credentials."""
    template = synth_default.one("AWS::EC2::LaunchTemplate")
    assert template["Properties"]["LaunchTemplateData"]["MetadataOptions"] == {
        "HttpEndpoint": "enabled",
        "HttpPutResponseHopLimit": 1,
        "HttpTokens": "required",
        "InstanceMetadataTags": "disabled",
    }
    template_id = next(iter(synth_default.resources("AWS::EC2::LaunchTemplate")))
    assert synth_default.one("AWS::EC2::Instance")["Properties"]["LaunchTemplate"] == {
        "LaunchTemplateId": {"Ref": template_id},
        "Version": {"Fn::GetAtt": [template_id, "LatestVersionNumber"]},
    }


def test_instance_monitoring_volume_and_stable_ami(synth_default: Synth) -> None:
    t = synth_default.template
    t.has_resource_properties(
        "AWS::EC2::Instance",
        {
            "InstanceType": "g6e.2xlarge",
            "Monitoring": True,
            "EbsOptimized": True,
            "DisableApiTermination": False,
            "ImageId": f"resolve:ssm:{DEFAULT_AMI_SSM_PARAMETER}",
            "BlockDeviceMappings": [
                {
                    "DeviceName": "/dev/sda1",
                    "Ebs": {
                        "VolumeSize": 100,
                        "VolumeType": "gp3",
                        "Encrypted": True,
                        "DeleteOnTermination": True,
                    },
                }
            ],
        },
    )
    # No CFN parameter for the AMI: a deploy-time SSM lookup would replace the instance on a new AMI release.
    assert not any("Ssm" in name for name in synth_default.json.get("Parameters", {}))


def test_ami_id_variant_and_termination_protection(synth_all_options: Synth) -> None:
    synth_all_options.template.has_resource_properties(
        "AWS::EC2::Instance",
        {
            "ImageId": "ami-0123456789abcdef0",
            "InstanceType": "g6e.4xlarge",
            "DisableApiTermination": True,
            "BlockDeviceMappings": [Match.object_like({"Ebs": Match.object_like({"VolumeSize": 200})})],
        },
    )


def test_elastic_ip_is_associated_with_the_instance(synth_default: Synth) -> None:
    t = synth_default.template
    t.resource_count_is("AWS::EC2::EIP", 1)
    t.has_resource_properties("AWS::EC2::EIP", {"Domain": "vpc"})
    t.has_resource_properties(
        "AWS::EC2::EIPAssociation",
        {
            "AllocationId": {"Fn::GetAtt": [Match.string_like_regexp("Eip"), "AllocationId"]},
            "InstanceId": {"Ref": Match.string_like_regexp("HostInstance")},
        },
    )


def test_dcv_password_is_generated_and_destroyed_with_the_stack(synth_default: Synth) -> None:
    synth_default.template.has_resource(
        "AWS::SecretsManager::Secret",
        {
            "Properties": Match.object_like(
                {
                    "GenerateSecretString": Match.object_like(
                        {"ExcludePunctuation": True, "PasswordLength": 24}
                    )
                }
            ),
            "DeletionPolicy": "Delete",
        },
    )


def user_data_text(synth: Synth) -> str:
    """The UserData as the instance will see it, with CFN tokens shown as ${...}."""
    data = synth.one("AWS::EC2::Instance")["Properties"]["UserData"]["Fn::Base64"]
    if isinstance(data, str):
        return data
    parts = data["Fn::Join"][1]
    return "".join(p if isinstance(p, str) else "${" + flatten(p) + "}" for p in parts)


def test_user_data_is_small_names_no_secret_and_no_changing_value(synth_default: Synth) -> None:
    text = user_data_text(synth_default)
    assert len(text.encode()) < 16 * 1024
    assert text.startswith("#!/bin/bash\n")
    assert "@@" not in text
    # Only what never changes for the stack: no asset URL, no setting, no secret.
    assert not re.search(r"[0-9a-f]{64}", text), "an asset hash in the UserData"
    assert "cdk-hnb659fds-assets" not in text, "an asset location in the UserData"
    assert "TOPIC_PREFIX" not in text and "DEVICES=" not in text
    assert "GetSecretValue" not in text and "SecretString" not in text and "DcvPassword" not in text
    assert "SO101_TWIN_PARAMETER='/so101-twin/So101TwinStack/deployment'" in text
    assert "SO101_TWIN_STACK='So101TwinStack'" in text
    logical_id = next(iter(synth_default.resources("AWS::EC2::Instance")))
    assert f"SO101_TWIN_RESOURCE='{logical_id}'" in text
    assert "bootstrap.sh" in text


def test_deployment_parameter_carries_assets_settings_and_version(synth_default: Synth) -> None:
    parameter = synth_default.one("AWS::SSM::Parameter")["Properties"]
    assert parameter["Name"] == "/so101-twin/So101TwinStack/deployment"
    value = flatten(parameter["Value"])
    for key in (
        "DEPLOYMENT_VERSION=",
        "AGENT_URL=",
        "SCRIPTS_URL=",
        "DCV_SECRET_ARN=",
        "s3://cdk-",
        "TOPIC_PREFIX=dt/lerobot",
        "DEVICES=arm-001",
        "UNITS=auto",
        "RECORD_SESSIONS=false",
        "ROS2=false",
        # DCV never disconnects an untouched viewer unless dcvIdleTimeoutMinutes says so.
        "DCV_IDLE_TIMEOUT=0",
        "HISTORY_URI=s3://",
        "CLIENT_ID_PREFIX=so101-twin-So101TwinStack-",
        "LOG_GROUP=",
        "URL_SUFFIX=",
    ):
        assert key in value, key
    statements = policy_statements(synth_default, "IdentityHostRole")
    reads = [s for s in statements if "ssm:GetParameter" in flatten(s.get("Action"))]
    assert len(reads) == 1
    resource = flatten(reads[0]["Resource"])
    assert ":parameter" in resource and '"Ref": "HostDeployment' in resource


def test_dcv_idle_timeout_setting_reaches_the_host(synth_all_options: Synth) -> None:
    value = flatten(synth_all_options.one("AWS::SSM::Parameter")["Properties"]["Value"])
    assert "DCV_IDLE_TIMEOUT=90" in value


def test_ros2_setting_reaches_the_host_and_opens_no_port(synth_all_options: Synth) -> None:
    # The installer turns ROS2=true into the ros2 extra and [ros2] enabled (tests/infra/test_userdata.py).
    value = flatten(synth_all_options.one("AWS::SSM::Parameter")["Properties"]["Value"])
    assert "ROS2=true" in value
    # DDS has no authentication, so the stack opens nothing for it (docs/ros2.md says how to reach RViz):
    # with ros2 on, the only ingress rule is still DCV's.
    assert {r["FromPort"] for r in ingress_rules(synth_all_options)} == {8443}


# --- first boot proves itself --------------------------------------------------------------------------


def test_instance_has_a_creation_policy_sized_to_the_boot(synth_default: Synth) -> None:
    instance = synth_default.one("AWS::EC2::Instance")
    assert instance["CreationPolicy"] == {
        "ResourceSignal": {"Count": 1, "Timeout": f"PT{BOOT_TIMEOUT_MINUTES}M"}
    }
    # The boot needs its settings and its permissions before the instance starts.
    depends = instance["DependsOn"]
    assert any(d.startswith("HostDeployment") for d in depends)
    assert any(d.startswith("IdentityHostRoleDefaultPolicy") for d in depends)


def test_wait_condition_carries_the_failure_reason(synth_default: Synth) -> None:
    wait = synth_default.one("AWS::CloudFormation::WaitCondition")["Properties"]
    handle_id = wait["Handle"]["Ref"]
    assert synth_default.json["Resources"][handle_id]["Type"] == "AWS::CloudFormation::WaitConditionHandle"
    assert wait["Count"] == 1
    assert int(wait["Timeout"]) >= BOOT_TIMEOUT_MINUTES * 60
    assert {"Ref": handle_id} in synth_default.one("AWS::EC2::Instance")["Properties"]["UserData"][
        "Fn::Base64"
    ]["Fn::Join"][1]


def test_signal_permission_is_scoped_to_this_stack(synth_default: Synth) -> None:
    statements = policy_statements(synth_default, "IdentityHostRole")
    signal = statement(statements, "SignalFirstBoot")
    assert signal["Action"] == "cloudformation:SignalResource"
    # The stack's own ARN (with its unique id), no wildcard.
    assert signal["Resource"] == {"Ref": "AWS::StackId"}
    assert not [s for s in statements if "cloudformation:" in flatten(s["Action"]) and s is not signal]


def test_first_boot_gets_a_public_address_before_the_elastic_ip(synth_default: Synth) -> None:
    interfaces = synth_default.one("AWS::EC2::Instance")["Properties"]["NetworkInterfaces"]
    assert interfaces[0]["AssociatePublicIpAddress"] is True


# --- updates in place ----------------------------------------------------------------------------------


def test_update_association_reruns_the_installer_with_the_version(synth_default: Synth) -> None:
    association = synth_default.one("AWS::SSM::Association")["Properties"]
    assert association["Name"] == "AWS-RunShellScript"
    assert association["Targets"] == [
        {"Key": "InstanceIds", "Values": [{"Ref": next(iter(synth_default.resources("AWS::EC2::Instance")))}]}
    ]
    commands = association["Parameters"]["commands"]
    version = synth_default.json["Outputs"]["DeploymentVersion"]["Value"]
    assert f"export SO101_TWIN_EXPECTED_VERSION='{version}'" in commands
    assert any("latest/user-data" in line for line in commands)
    assert "ApplyOnlyAtCronInterval" not in association and "ScheduleExpression" not in association
    # No WaitForSuccessTimeoutSeconds: a stopped host would fail the deploy and its rollback (docs/deploy.md).
    assert "WaitForSuccessTimeoutSeconds" not in association


def agent_copy(tmp_path: Path) -> Path:
    """The agent distribution with one line of code changed."""
    from .synth import REPO_ROOT

    copy = tmp_path / "agent-src"
    copy.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO_ROOT / name, copy / name)
    for name in ("agents", "robots"):
        shutil.copytree(REPO_ROOT / name, copy / name, ignore=shutil.ignore_patterns("__pycache__"))
    init = copy / "agents" / "twin" / "__init__.py"
    init.write_text(init.read_text() + "\n# a code change\n")
    return copy


@pytest.mark.slow
def test_settings_and_code_changes_leave_the_instance_untouched(
    synth_default: Synth, synth_factory, tmp_path: Path
) -> None:
    changed = synth_factory(
        agent_source=agent_copy(tmp_path),
        devices="arm-002,arm-003",
        units="degrees",
        topicPrefix="fleet/so101",
        recordSessions="true",
        ros2="true",
    )

    def instance(synth: Synth) -> dict[str, Any]:
        return next(iter(synth.resources("AWS::EC2::Instance").values()))

    # Same UserData, same everything: CloudFormation neither stops nor replaces the instance.
    assert instance(changed)["Properties"]["UserData"] == instance(synth_default)["Properties"]["UserData"]
    assert instance(changed) == instance(synth_default)
    assert list(changed.resources("AWS::EC2::Instance")) == list(
        synth_default.resources("AWS::EC2::Instance")
    )
    # ... while what the host should run did change, and with it the association's parameters.
    old_v = synth_default.json["Outputs"]["DeploymentVersion"]["Value"]
    new_v = changed.json["Outputs"]["DeploymentVersion"]["Value"]
    assert old_v != new_v
    assert (
        changed.one("AWS::SSM::Parameter")["Properties"]["Value"]
        != synth_default.one("AWS::SSM::Parameter")["Properties"]["Value"]
    )
    commands = changed.one("AWS::SSM::Association")["Properties"]["Parameters"]["commands"]
    assert f"export SO101_TWIN_EXPECTED_VERSION='{new_v}'" in commands


@pytest.mark.slow
def test_code_change_alone_changes_the_version(synth_default: Synth, synth_factory, tmp_path: Path) -> None:
    changed = synth_factory(agent_source=agent_copy(tmp_path))
    assert (
        changed.json["Outputs"]["DeploymentVersion"]["Value"]
        != synth_default.json["Outputs"]["DeploymentVersion"]["Value"]
    )
    assert user_data_text(changed) == user_data_text(synth_default)


def test_same_input_same_version(synth_default: Synth, synth_factory) -> None:
    again = synth_factory()
    assert again.json["Outputs"]["DeploymentVersion"] == synth_default.json["Outputs"]["DeploymentVersion"]


# --- partitions ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("variant", ["synth_default", "synth_all_options"])
def test_no_arn_hard_codes_the_aws_partition(variant: str, request: pytest.FixtureRequest) -> None:
    text = json.dumps(request.getfixturevalue(variant).json)
    assert "arn:aws:" not in text
    assert "arn:aws-" not in text


def test_agent_asset_holds_only_the_distribution(synth_default: Synth) -> None:
    outdir = synth_default.stack.node.root.outdir
    asset_dirs = [p for p in Path(outdir).glob("asset.*") if (p / "pyproject.toml").exists()]
    assert len(asset_dirs) == 1
    top = sorted(p.name for p in asset_dirs[0].iterdir())
    assert top == sorted(
        n for n in ["README.md", "agents", "pyproject.toml", "requirements", "robots"] if n in top
    )
    assert {"agents", "pyproject.toml", "robots"} <= set(top)
    # Of the dependency locks, the host's only (when the lock exists; the installer refuses to run without).
    if "requirements" in top:
        assert [p.name for p in (asset_dirs[0] / "requirements").iterdir()] == ["host.txt"]
    names = {p.name for p in asset_dirs[0].rglob("*")}
    assert not names & {"__pycache__", ".venv", "node_modules", "cdk.out", "tests"}
    assert (asset_dirs[0] / "agents" / "twin" / "cli" / "main.py").exists()
    # What the instance runs, not the development tooling (the layers rig and bench).
    package = asset_dirs[0] / "agents" / "twin"
    assert (package / "edge" / "simulator.py").exists() and (package / "ops" / "instance.py").exists()
    assert not [name for name in ("rig", "bench") if (package / name).exists()]
    meshes = asset_dirs[0] / "robots" / "so101" / "meshes"
    assert len(list((meshes / "visual").glob("*.stl"))) == 13
    assert {"LICENSE", "NOTICE", "provenance.json"} <= {p.name for p in meshes.iterdir()}
    assert not (meshes / "source").exists()  # originals stay in the repository, not in every deploy
    scripts = [p for p in Path(outdir).glob("asset.*") if (p / "bootstrap.sh").exists()]
    assert len(scripts) == 1
    # The templates are rendered into the UserData and the association; the host gets the rest.
    assert {p.name for p in scripts[0].iterdir()} == {
        "bootstrap.sh",
        "install-agent.sh",
        "lib.sh",
        "host-check.sh",
        "view-supervisor.sh",
        "save-local-config.sh",
        "save-alarm-state.sh",
        "releases.env",
    }


# --- auto-stop and the endpoint -------------------------------------------------------------------


def test_auto_stop_is_off_by_default(synth_default: Synth) -> None:
    synth_default.template.resource_count_is("AWS::Scheduler::Schedule", 0)


def test_auto_stop_schedule_can_only_stop_this_instance(synth_all_options: Synth) -> None:
    t = synth_all_options.template
    t.has_resource_properties(
        "AWS::Scheduler::Schedule",
        {
            "ScheduleExpression": "cron(0 20 * * ? *)",
            "ScheduleExpressionTimezone": "Europe/Berlin",
            "Target": Match.object_like(
                {
                    "Arn": {
                        "Fn::Join": [
                            "",
                            ["arn:", {"Ref": "AWS::Partition"}, ":scheduler:::aws-sdk:ec2:stopInstances"],
                        ]
                    }
                }
            ),
        },
    )
    statements = policy_statements(synth_all_options, "AutoStopSchedulerRole")
    assert len(statements) == 1
    stop = statements[0]
    assert stop["Action"] == "ec2:StopInstances"
    assert ":instance/" in flatten(stop["Resource"])
    assert "HostInstance" in flatten(stop["Resource"])


def test_iot_endpoint_is_looked_up_for_data_ats(synth_default: Synth) -> None:
    resource = synth_default.one("Custom::AWS")
    assert "iot:Data-ATS" in flatten(resource["Properties"]["Create"])
    assert "describeEndpoint" in flatten(resource["Properties"]["Create"])


# --- outputs --------------------------------------------------------------------------------------


def test_outputs_have_the_keys_twin_instance_reads(synth_default: Synth) -> None:
    outputs = synth_default.json["Outputs"]
    assert set(outputs) >= OUTPUT_KEYS


def test_dcv_url_is_built_from_the_elastic_ip(synth_default: Synth) -> None:
    url = synth_default.json["Outputs"]["DcvUrl"]["Value"]
    join = url["Fn::Join"][1]
    assert join[0] == "https://"
    assert join[1]["Fn::GetAtt"][1] == "PublicIp"
    assert join[1]["Fn::GetAtt"][0].startswith("HostEip")
    assert join[2] == ":8443/#console"


def test_dcv_url_says_to_read_the_password_with_twin_instance_password(synth_default: Synth) -> None:
    # A walk: the description sent users to the DcvPasswordSecret ARN, not to the command that reads it.
    description = synth_default.json["Outputs"]["DcvUrl"]["Description"]
    assert "`twin instance password`" in description and "DcvPasswordCommand" in description, description
    assert "DcvPasswordSecret" not in description, description


def test_the_password_secret_output_names_twin_instance_password_too(synth_default: Synth) -> None:
    # A review: the secret's own output sent users only to the AWS CLI command, not to the project's own.
    description = synth_default.json["Outputs"]["DcvPasswordSecret"]["Description"]
    assert "`twin instance password`" in description and "DcvPasswordCommand" in description, description


def test_other_outputs(synth_default: Synth) -> None:
    outputs = synth_default.json["Outputs"]
    assert outputs["InstanceId"]["Value"]["Ref"].startswith("HostInstance")
    assert outputs["IotEndpoint"]["Value"]["Fn::GetAtt"][1] == "endpointAddress"
    assert "Ref" in outputs["DcvPasswordSecret"]["Value"]
    command = flatten(outputs["DcvPasswordCommand"]["Value"])
    assert "aws secretsmanager get-secret-value" in command and "--query SecretString" in command
    assert "aws ssm start-session" in flatten(outputs["SsmSessionCommand"]["Value"])


@pytest.mark.parametrize("key", sorted(OUTPUT_KEYS))
def test_output_has_a_description(synth_default: Synth, key: str) -> None:
    assert synth_default.json["Outputs"][key]["Description"]
