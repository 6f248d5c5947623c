"""Settings validation: every refusal names the key and what to pass (no synth needed, so these are fast)."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest

from stacks.settings import (
    DEFAULT_AMI_SSM_PARAMETER,
    MAX_LISTED_DEVICES,
    SETTING_FIELDS,
    SettingsError,
    TwinSettings,
)

from .synth import cdk_json_context


def settings(**overrides: Any) -> TwinSettings:
    context = cdk_json_context()
    context.update({"clientCidr": "203.0.113.7/32", **overrides})
    return TwinSettings.from_context(context.get)


def refused(**overrides: Any) -> str:
    with pytest.raises(SettingsError) as info:
        settings(**overrides)
    return str(info.value)


def test_defaults_live_in_the_settings_class() -> None:
    s = settings()
    assert s.client_cidr == "203.0.113.7/32"
    assert s.instance_type == "g6e.2xlarge"
    assert s.volume_gb == 100
    assert s.devices == ("arm-001",)
    assert s.topic_prefix == "dt/lerobot"
    assert s.units == "auto"
    assert s.ros2 is False
    assert s.record_sessions is False
    assert s.replace_instance is False
    assert s.ami_ssm_parameter == DEFAULT_AMI_SSM_PARAMETER
    assert s.ami_id is None
    assert s.termination_protection is False
    assert s.auto_stop_cron is None
    assert s.availability_zone is None
    assert s.stack_name == "So101TwinStack"
    assert s.alarm_email is None
    assert s.alarm_warnings is False


def test_cdk_json_holds_no_setting_so_context_is_only_what_the_deployer_passed() -> None:
    assert set(cdk_json_context()) & set(SETTING_FIELDS) == set()


def test_every_field_has_a_key() -> None:
    assert set(SETTING_FIELDS.values()) == {f.name for f in dataclasses.fields(TwinSettings)}


def test_client_cidr_missing_blocks_the_deploy_but_not_the_synth() -> None:
    s = settings(clientCidr="")
    assert s.client_cidr is None
    (message,) = s.deploy_blockers()
    assert "clientCidr is required" in message
    assert "-c clientCidr=203.0.113.7/32" in message
    assert 'clientCidr = "203.0.113.7/32"' in message and "twin.settings.toml" in message
    assert settings().deploy_blockers() == []


def test_open_cidr_is_refused_without_allow_any_client() -> None:
    message = refused(clientCidr="0.0.0.0/0")
    assert "whole internet" in message
    assert "allowAnyClient=true" in message


@pytest.mark.parametrize("cidr", ["0.0.0.0/0"])
@pytest.mark.parametrize("flag", [True, "true"])
def test_open_cidr_is_accepted_with_allow_any_client(cidr: str, flag: object) -> None:
    s = settings(clientCidr=cidr, allowAnyClient=flag)
    assert s.client_cidr == cidr
    assert s.allow_any_client is True


@pytest.mark.parametrize(
    ("cidr", "hint"),
    [
        ("203.0.113.7", "203.0.113.7/32"),
        ("203.0.113.7/24", "203.0.113.0/24"),
        ("not-an-ip/32", "203.0.113.7/32"),
        ("203.0.113.300/32", "203.0.113.7/32"),
    ],
)
def test_bad_cidrs_are_refused_with_a_fix(cidr: str, hint: str) -> None:
    assert hint in refused(clientCidr=cidr)


@pytest.mark.parametrize("cidr", ["2001:db8::1/128", "2001:db8::/64", "::/0"])
def test_ipv6_client_is_refused_because_nothing_has_an_ipv6_address(cidr: str) -> None:
    message = refused(clientCidr=cidr, allowAnyClient="true")
    assert f"clientCidr={cidr} is IPv6" in message
    assert "-c clientCidr=203.0.113.7/32" in message


@pytest.mark.parametrize("value", [True, "true", "1"])
def test_ssh_access_was_removed_and_says_what_to_use(value: object) -> None:
    message = refused(sshAccess=value)
    assert "sshAccess was removed" in message
    assert "SsmSessionCommand" in message


@pytest.mark.parametrize("value", [False, "false", ""])
def test_ssh_access_false_is_harmless(value: object) -> None:
    assert settings(sshAccess=value).client_cidr == "203.0.113.7/32"


def test_record_sessions_and_replace_instance_flags() -> None:
    assert settings(recordSessions="true").record_sessions is True
    assert settings(replaceInstance=True).replace_instance is True


def test_dcv_idle_timeout_never_disconnects_by_default_and_takes_minutes() -> None:
    """DCV's own default (60 minutes) would disconnect a viewer watched, untouched, for more than an hour."""
    assert settings().dcv_idle_timeout_minutes == 0
    assert settings(dcvIdleTimeoutMinutes="90").dcv_idle_timeout_minutes == 90
    assert settings(dcvIdleTimeoutMinutes=120).dcv_idle_timeout_minutes == 120
    assert "dcvIdleTimeoutMinutes=-1 is outside 0..10080" in refused(dcvIdleTimeoutMinutes="-1")
    assert "is not a whole number" in refused(dcvIdleTimeoutMinutes="1h")


def test_instance_fingerprint_names_what_replaces_the_instance() -> None:
    assert settings().instance_fingerprint == {
        "availabilityZone": "",
        "volumeGb": "100",
        "image": f"resolve:ssm:{DEFAULT_AMI_SSM_PARAMETER}",
    }
    pinned = settings(availabilityZone="us-east-1b", volumeGb="200", amiId="ami-0123456789abcdef0")
    assert pinned.instance_fingerprint == {
        "availabilityZone": "us-east-1b",
        "volumeGb": "200",
        "image": "ami-0123456789abcdef0",
    }


def test_host_generation_is_in_the_fingerprint_once_raised() -> None:
    """The first host's fingerprint is the one stacks deployed before the setting publish (no key), so an
    upgrade of so101-twin compares equal; a raised generation is a replacing change."""
    assert settings().host_generation == 1
    assert "hostGeneration" not in settings(hostGeneration="1").instance_fingerprint
    # -c gives a string, the settings file a TOML integer.
    assert settings(hostGeneration="2").instance_fingerprint["hostGeneration"] == "2"
    assert settings(hostGeneration=3).instance_fingerprint["hostGeneration"] == "3"


@pytest.mark.parametrize("value", ["0", "-1", "10000", "two", "1.5"])
def test_bad_host_generation_is_refused(value: str) -> None:
    message = refused(hostGeneration=value)
    assert message.startswith("hostGeneration=") and value in message and "-c hostGeneration=2" in message


@pytest.mark.parametrize("zone", ["us-east-1b", "eu-central-1a", "us-west-2-lax-1a", "us-gov-west-1a"])
def test_availability_zone_names_are_accepted(zone: str) -> None:
    assert settings(availabilityZone=zone).availability_zone == zone


def test_availability_zone_id_is_refused_with_the_name_hint() -> None:
    assert "zone ID" in refused(availabilityZone="use1-az4")


@pytest.mark.parametrize("zone", ["us-east-1", "useast1b", "US-EAST-1B", "us-east-1bx"])
def test_bad_availability_zone_is_refused(zone: str) -> None:
    message = refused(availabilityZone=zone)
    assert "availabilityZone" in message
    assert "describe-instance-type-offerings" in message


def test_availability_zone_must_be_in_the_stack_region() -> None:
    s = settings(availabilityZone="us-west-2a")
    s.check_region("us-west-2")
    s.check_region(None)
    with pytest.raises(SettingsError, match="not in the stack's region us-east-1"):
        s.check_region("us-east-1")


@pytest.mark.parametrize("value", ["g6e", "g6e-2xlarge", "G6E.2XLARGE", "g6e.2xhuge", ""])
def test_bad_instance_type_is_refused(value: str) -> None:
    if value == "":
        assert settings(instanceType=value).instance_type == "g6e.2xlarge"
        return
    assert "-c instanceType=g6e.2xlarge" in refused(instanceType=value)


@pytest.mark.parametrize("value", ["g6e.xlarge", "g6e.4xlarge", "g5.xlarge", "g4dn.xlarge", "p5.48xlarge"])
def test_instance_types_are_accepted(value: str) -> None:
    assert settings(instanceType=value).instance_type == value


@pytest.mark.parametrize("value", ["m5.large", "t3.large", "g4ad.xlarge", "g5g.xlarge", "c7i.2xlarge"])
def test_an_instance_type_without_an_nvidia_gpu_is_refused_at_synth(value: str) -> None:
    """A deploy walk synthesised m5.large cleanly; its first boot would fail at the GPU check, ten minutes in.
    AMD (g4ad) and Arm (g5g) GPU types are no better: the image is the x86_64 NVIDIA one."""
    message = refused(instanceType=value)
    assert f"instanceType={value} has no NVIDIA GPU" in message and "-c instanceType=g6e.2xlarge" in message


@pytest.mark.parametrize("value", ["10", "16385", "big", "1.5"])
def test_bad_volume_is_refused(value: str) -> None:
    assert "-c volumeGb=100" in refused(volumeGb=value)


def test_arm_rate_and_max_connections_default_and_parse() -> None:
    assert (settings().arm_rate_hz, settings().max_connections) == (10.0, 8)
    # A settings file's TOML numbers or -c strings.
    assert settings(armRateHz=2.5).arm_rate_hz == 2.5
    # TOML's 32 and 32.0, and -c's "32", are one whole number; 32.5 is none.
    assert {settings(maxConnections=v).max_connections for v in (32, 32.0, "32")} == {32}
    assert "maxConnections=32.5 is not a whole number" in refused(maxConnections=32.5)


@pytest.mark.parametrize("value", ["0", "-1", "81", "nan", "inf", "fast"])
def test_a_bad_arm_rate_is_refused(value: str) -> None:
    message = refused(armRateHz=value)
    assert f"armRateHz={value}" in message or f"armRateHz='{value}'" in message
    assert "-c armRateHz=10" in message


@pytest.mark.parametrize(
    ("value", "said"),
    [
        ("0", "maxConnections=0 is below 1"),
        ("-3", "maxConnections=-3 is below 1"),
        ("65", "maxConnections=65 is above 64, the agent's bound for the whole fleet (about 512 arms"),
        ("8.5", "is not a whole number"),
        ("many", "is not a whole number"),
    ],
)
def test_a_bad_max_connections_is_refused(value: str, said: str) -> None:
    message = refused(maxConnections=value)
    assert said in message and "-c maxConnections=8" in message
    # Kinesis is the way past the bound, not an answer to a count below one.
    assert ("Kinesis" in message) == (value == "65")


def test_a_listed_fleet_longer_than_the_role_can_name_is_refused_with_the_fleet_as_the_fix() -> None:
    assert len(settings(devices=",".join(f"arm-{i}" for i in range(MAX_LISTED_DEVICES))).devices) == 150
    message = refused(devices=",".join(f"arm-{i}" for i in range(MAX_LISTED_DEVICES + 1)))
    assert "devices lists 151 arms; the host's IAM role can name at most 150" in message
    # The fix worked out for the arms given: 151 at 8 a connection.
    assert 'devices = ["*"] and maxConnections = 19 in the settings file' in message
    assert "-c devices='*'" in message
    # Past one host's connections, several stacks.
    message = refused(devices=",".join(f"arm-{i}" for i in range(600)))
    assert "600 arms at 10 Hz need 75 connections, more than one host's 64" in message
    assert "several stacks" in message and "docs/scale-out.md" in message


def test_devices_parse_lists_and_fleet() -> None:
    assert settings(devices="arm-001, arm-002").devices == ("arm-001", "arm-002")
    assert settings(devices=["arm-003"]).devices == ("arm-003",)
    assert settings(devices="*").whole_fleet


@pytest.mark.parametrize("value", ["arm/1", "arm+", "*,arm-001", "arm-001,arm-001", " , "])
def test_bad_devices_are_refused(value: str) -> None:
    assert "devices" in refused(devices=value) or "device id" in refused(devices=value)


@pytest.mark.parametrize("value", ["dt/+/x", "dt/#", "/dt", "dt/", "$aws/things", "dt lerobot"])
def test_bad_topic_prefix_is_refused(value: str) -> None:
    assert "-c topicPrefix=dt/lerobot" in refused(topicPrefix=value)


def test_units_must_be_known() -> None:
    assert settings(units="degrees").units == "degrees"
    assert "ticks, degrees, range100, auto" in refused(units="radians")


@pytest.mark.parametrize("value", ["maybe", "2"])
def test_bad_booleans_are_refused(value: str) -> None:
    assert "-c recordSessions=true or -c recordSessions=false" in refused(recordSessions=value)
    assert "-c ros2=true or -c ros2=false" in refused(ros2=value)


def test_ros2_is_a_boolean_off_by_default() -> None:
    assert settings(ros2="true").ros2 is True
    assert settings(ros2=True).ros2 is True
    assert settings(ros2="false").ros2 is False


def test_ami_id_and_parameter_are_checked() -> None:
    assert settings(amiId="ami-0123456789abcdef0").ami_id == "ami-0123456789abcdef0"
    assert "-c amiId=ami-0123456789abcdef0" in refused(amiId="ami-xyz")
    assert "not an SSM parameter path" in refused(amiSsmParameter="aws/service/x")


@pytest.mark.parametrize(
    ("value", "expected"),
    [("0 20 * * ? *", "cron(0 20 * * ? *)"), ("cron(30 19 ? * MON-FRI *)", "cron(30 19 ? * MON-FRI *)")],
)
def test_auto_stop_cron_is_normalised(value: str, expected: str) -> None:
    assert settings(autoStopCron=value).auto_stop_cron == expected


@pytest.mark.parametrize(
    "value", ["0 20 * * *", "0 20 * * 1 *", "0 20 ? * ? *", "rate(1 day)", "0 20 * * ? * ;"]
)
def test_bad_auto_stop_cron_is_refused(value: str) -> None:
    assert "autoStopCron" in refused(autoStopCron=value)


def test_bad_timezone_and_stack_name_are_refused() -> None:
    assert "-c autoStopTimezone=UTC" in refused(autoStopTimezone="Berlin time")
    assert "-c stackName=" in refused(stackName="1-bad_name")


def test_alarm_email_is_optional_and_checked() -> None:
    assert settings(alarmEmail="ops@example.com").alarm_email == "ops@example.com"
    assert "-c alarmEmail=ops@example.com" in refused(alarmEmail="ops at example")
