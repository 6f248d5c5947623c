"""The history bucket: encrypted, private, TLS only, cheaper storage after N days, retained by default, and
the host role limited to its `history/` prefix (docs/history.md)."""

from __future__ import annotations

from typing import Any

import pytest
from aws_cdk.assertions import Match

from stacks.settings import SettingsError, TwinSettings

from .synth import CLIENT_CIDR, Synth
from .test_stack import flatten, policy_statements, statement, user_data_text


def bucket(synth: Synth) -> dict[str, Any]:
    return synth.one("AWS::S3::Bucket")


def bucket_id(synth: Synth) -> str:
    return next(iter(synth.resources("AWS::S3::Bucket")))


def test_bucket_is_encrypted_private_and_retained(synth_default: Synth) -> None:
    resource = bucket(synth_default)
    props = resource["Properties"]
    assert props["BucketEncryption"]["ServerSideEncryptionConfiguration"] == [
        {"ServerSideEncryptionByDefault": {"SSEAlgorithm": "AES256"}}
    ]
    assert props["PublicAccessBlockConfiguration"] == {
        "BlockPublicAcls": True,
        "BlockPublicPolicy": True,
        "IgnorePublicAcls": True,
        "RestrictPublicBuckets": True,
    }
    assert resource["DeletionPolicy"] == "Retain" and resource["UpdateReplacePolicy"] == "Retain"


def test_bucket_refuses_requests_without_tls(synth_default: Synth) -> None:
    synth_default.template.has_resource_properties(
        "AWS::S3::BucketPolicy",
        {
            "PolicyDocument": {
                "Statement": Match.array_with(
                    [
                        Match.object_like(
                            {
                                "Effect": "Deny",
                                "Action": "s3:*",
                                "Condition": {"Bool": {"aws:SecureTransport": "false"}},
                            }
                        )
                    ]
                )
            }
        },
    )


def test_history_moves_to_infrequent_access_after_the_set_days(synth_default: Synth, synth_factory) -> None:
    rules = {r["Id"]: r for r in bucket(synth_default)["Properties"]["LifecycleConfiguration"]["Rules"]}
    ia = rules["HistoryToInfrequentAccess"]
    assert ia["Prefix"] == "history/"
    assert ia["Transitions"] == [{"StorageClass": "STANDARD_IA", "TransitionInDays": 30}]
    assert ia["ObjectSizeGreaterThan"] == "131072"  # small Delta log files would cost more in IA
    assert rules["ExpireMaintenanceLeases"]["ExpirationInDays"] == 2
    later = synth_factory(historyIaAfterDays="90")
    rules = {r["Id"]: r for r in bucket(later)["Properties"]["LifecycleConfiguration"]["Rules"]}
    assert rules["HistoryToInfrequentAccess"]["Transitions"][0]["TransitionInDays"] == 90


def test_retain_history_false_deletes_the_bucket_with_the_stack(synth_factory) -> None:
    synth = synth_factory(retainHistory="false")
    resource = bucket(synth)
    assert resource["DeletionPolicy"] == "Delete"
    # Emptied first by CDK's auto-delete custom resource, or CloudFormation could not delete it.
    assert synth.resources("Custom::S3AutoDeleteObjects")


def test_host_role_gets_exactly_the_history_prefix(synth_default: Synth) -> None:
    statements = policy_statements(synth_default, "IdentityHostRole")
    objects = statement(statements, "HistoryObjects")
    assert sorted(objects["Action"]) == ["s3:DeleteObject", "s3:GetObject", "s3:PutObject"]
    joined = objects["Resource"]["Fn::Join"][1]
    assert joined[0]["Fn::GetAtt"][0].startswith("HistoryBucket") and joined[1] == "/history/*"
    listing = statement(statements, "HistoryList")
    assert listing["Action"] == "s3:ListBucket"
    assert listing["Resource"]["Fn::GetAtt"][0].startswith("HistoryBucket")
    assert listing["Condition"] == {"StringLike": {"s3:prefix": ["history/*", "history"]}}
    # The calibration prefix: read and list only (people push with their own credentials).
    calibration = statement(statements, "CalibrationRead")
    assert calibration["Action"] == "s3:GetObject"
    assert calibration["Resource"]["Fn::Join"][1][1] == "/calibration/*"
    calibration_list = statement(statements, "CalibrationList")
    assert calibration_list["Condition"] == {"StringLike": {"s3:prefix": ["calibration/*", "calibration"]}}
    # The host's copy of the operator's agent.local.toml: that one object, and a listing of its key only
    # (userdata/install-agent.sh tells a missing copy from one it may not read by the listing).
    local_config = statement(statements, "HostLocalConfig")
    assert sorted(local_config["Action"]) == ["s3:GetObject", "s3:PutObject"]
    assert local_config["Resource"]["Fn::Join"][1][1] == "/host/agent.local.toml"
    local_list = statement(statements, "HostLocalConfigList")
    assert local_list["Action"] == "s3:ListBucket"
    assert local_list["Condition"] == {"StringEquals": {"s3:prefix": ["host/agent.local.toml"]}}
    # The hosts' copies of the servo alarm state: read and write one per host id, no delete; a listing of
    # that prefix only (a new host picks the copy written last: userdata/install-agent.sh).
    alarm_state = statement(statements, "HostAlarmState")
    assert sorted(alarm_state["Action"]) == ["s3:GetObject", "s3:PutObject"]
    assert alarm_state["Resource"]["Fn::Join"][1][1] == "/host/alarm-state/*"
    alarm_list = statement(statements, "HostAlarmStateList")
    assert alarm_list["Action"] == "s3:ListBucket"
    assert alarm_list["Condition"] == {"StringEquals": {"s3:prefix": ["host/alarm-state/"]}}
    # No other statement reaches the bucket.
    others = [s.get("Sid") for s in statements if "HistoryBucket" in flatten(s["Resource"])]
    assert sorted(others) == [
        "CalibrationList",
        "CalibrationRead",
        "HistoryList",
        "HistoryObjects",
        "HostAlarmState",
        "HostAlarmStateList",
        "HostLocalConfig",
        "HostLocalConfigList",
    ]


def test_host_agent_writes_history_to_the_bucket(synth_default: Synth) -> None:
    # Through the deployment parameter, as every setting the host reads; the UserData stays the same.
    value = synth_default.one("AWS::SSM::Parameter")["Properties"]["Value"]["Fn::Join"][1]
    refs = [i for i, part in enumerate(value) if part == {"Ref": bucket_id(synth_default)}]
    uris = {value[i - 1].rsplit("\n", 1)[1] + "<bucket>" + value[i + 1].split("\n", 1)[0] for i in refs}
    assert uris == {
        "HISTORY_URI=s3://<bucket>/history",
        "CALIBRATIONS_URI=s3://<bucket>/calibration",
        "HOST_STATE_URI=s3://<bucket>/host",
    }
    assert "HISTORY_URI" not in user_data_text(synth_default)
    output = synth_default.json["Outputs"]["HistoryUri"]
    assert "aws s3 rb" in output["Description"]


def test_history_days_setting_is_validated() -> None:
    def get(values: dict[str, Any]):
        return {"clientCidr": CLIENT_CIDR, **values}.get

    assert TwinSettings.from_context(get({})).history_ia_after_days == 30
    assert TwinSettings.from_context(get({"retainHistory": "false"})).retain_history is False
    with pytest.raises(SettingsError, match=r"historyIaAfterDays=7 is outside 30\.\.3650"):
        TwinSettings.from_context(get({"historyIaAfterDays": "7"}))
