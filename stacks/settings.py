"""Deployment settings: read once from CDK context (defaults in cdk.json), validated in one place.

Every refusal says what to pass instead, because the person reading it is at a terminal running
`cdk deploy` and wants the fix, not a stack trace.
"""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Callable
from dataclasses import dataclass

from twin.core.topics import ALL_DEVICES, policy_device_id_problem, topic_prefix_problem

# The agent's own rules (pure modules, no MuJoCo or awscrt), so the stack accepts exactly what the agent it
# deploys accepts: device ids and the topic prefix (twin.core.topics), units, and the client id prefix the
# IAM policy scopes iot:Connect to.
from twin.core.units import UNITS_CHOICES
from twin.transport.broker import DEFAULT_CLIENT_ID_PREFIX

CLIENT_ID_PREFIX = DEFAULT_CLIENT_ID_PREFIX
UNITS = UNITS_CHOICES
DEFAULT_AMI_SSM_PARAMETER = (
    "/aws/service/deeplearning/ami/x86_64/base-oss-nvidia-driver-gpu-ubuntu-24.04/latest/ami-id"
)

# Region letters, optional local-zone part, then the zone letter: us-east-1b, us-west-2-lax-1a.
_AZ_RE = re.compile(r"^[a-z]{2}(-gov)?-[a-z]+-\d+(-[a-z]+-\d+)?[a-z]$")
_AZ_ID_RE = re.compile(r"^[a-z]{3,4}\d+-az\d+$")
_INSTANCE_TYPE_RE = re.compile(
    r"^[a-z][a-z0-9-]*\d[a-z0-9-]*\.(nano|micro|small|medium|large|metal|\d*xlarge)$"
)
_AMI_ID_RE = re.compile(r"^ami-[0-9a-f]{8}([0-9a-f]{9})?$")
# Deliberately loose (SNS validates for real): one @, no spaces, a dot in the domain.
_EMAIL_RE = re.compile(r"^[^@\s]+@[^@\s]+\.[^@\s]+$")
_STACK_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9-]{0,127}$")
_TIMEZONE_RE = re.compile(r"^(UTC|[A-Za-z]+(/[A-Za-z0-9_+-]+)+)$")
# EventBridge Scheduler cron: minutes hours day-of-month month day-of-week year.
_CRON_FIELD_RE = re.compile(r"^[0-9A-Za-z*?,/#L W-]+$")
VOLUME_GB_MIN = 50
VOLUME_GB_MAX = 16384


class SettingsError(ValueError):
    """A context value is missing or unsafe; the message names the key and the `-c` to pass."""


@dataclass(frozen=True)
class TwinSettings:
    """Everything the stack needs from the person deploying it, already validated."""

    client_cidr: str
    allow_any_client: bool = False
    availability_zone: str | None = None
    instance_type: str = "g6e.2xlarge"
    volume_gb: int = 100
    devices: tuple[str, ...] = ("arm-001",)
    topic_prefix: str = "dt/lerobot"
    units: str = "auto"
    # Publish the arms as ROS 2 JointState on the host (docs/ros2.md): installs the agent's ros2 extra.
    ros2: bool = False
    record_sessions: bool = False
    ami_ssm_parameter: str = DEFAULT_AMI_SSM_PARAMETER
    ami_id: str | None = None
    termination_protection: bool = False
    auto_stop_cron: str | None = None
    auto_stop_timezone: str = "UTC"
    stack_name: str = "So101TwinStack"
    # Where the CloudWatch alarms (agent silent, arms stale, critical servo alarm) are e-mailed; empty: the
    # SNS topic only, for other subscribers.
    alarm_email: str | None = None
    # Telemetry history bucket (docs/history.md): days in S3 Standard before Standard-IA, and whether the
    # bucket survives `cdk destroy`.
    history_ia_after_days: int = 30
    retain_history: bool = True
    replace_instance: bool = False

    @property
    def instance_fingerprint(self) -> dict[str, str]:
        """The settings whose change replaces the instance (and its root disk): the replacement guard compares
        these with the deployed stack's."""
        return {
            "availabilityZone": self.availability_zone or "",
            "volumeGb": str(self.volume_gb),
            "image": self.ami_id or f"resolve:ssm:{self.ami_ssm_parameter}",
        }

    @property
    def whole_fleet(self) -> bool:
        return self.devices == ("*",)

    @classmethod
    def from_context(cls, get: Callable[[str], object]) -> TwinSettings:
        """Build from a context getter (`app.node.try_get_context`); raise SettingsError on bad input.

        `-c key=value` arrives as a string while cdk.json values keep their JSON type, so every
        parser accepts both.
        """
        _refuse_removed(get)
        allow_any = _bool(get, "allowAnyClient", False)
        ami_id = _str(get, "amiId") or None
        settings = cls(
            client_cidr=_client_cidr(_str(get, "clientCidr"), allow_any),
            allow_any_client=allow_any,
            availability_zone=_availability_zone(_str(get, "availabilityZone")),
            instance_type=_instance_type(_str(get, "instanceType") or cls.instance_type),
            volume_gb=_volume_gb(get("volumeGb")),
            devices=_devices(get("devices")),
            topic_prefix=_topic_prefix(_str(get, "topicPrefix") or cls.topic_prefix),
            units=_units(_str(get, "units") or cls.units),
            ros2=_bool(get, "ros2", False),
            record_sessions=_bool(get, "recordSessions", False),
            ami_ssm_parameter=_ami_ssm_parameter(_str(get, "amiSsmParameter") or DEFAULT_AMI_SSM_PARAMETER),
            ami_id=_ami_id(ami_id) if ami_id else None,
            termination_protection=_bool(get, "terminationProtection", False),
            auto_stop_cron=_auto_stop_cron(_str(get, "autoStopCron")),
            auto_stop_timezone=_timezone(_str(get, "autoStopTimezone") or "UTC"),
            stack_name=_stack_name(_str(get, "stackName") or cls.stack_name),
            alarm_email=_alarm_email(_str(get, "alarmEmail")),
            history_ia_after_days=_history_ia_after_days(get("historyIaAfterDays")),
            retain_history=_bool(get, "retainHistory", True),
            replace_instance=_bool(get, "replaceInstance", False),
        )
        return settings

    def check_region(self, region: str | None) -> None:
        """Refuse an AZ pin from another region (only checkable when the region is concrete)."""
        if region and self.availability_zone and not self.availability_zone.startswith(region):
            raise SettingsError(
                f"availabilityZone={self.availability_zone} is not in the stack's region {region}; "
                f"pass -c availabilityZone=<an AZ of {region} that offers {self.instance_type}>"
            )


def _refuse_removed(get: Callable[[str], object]) -> None:
    # sshAccess opened port 22 on an instance that has no key pair: nothing could log in through it.
    if get("sshAccess") not in (None, "", False, "false"):
        raise SettingsError(
            "sshAccess was removed: the host has no SSH key pair, so port 22 served nobody. Get a shell with "
            "SSM Session Manager instead (the stack output SsmSessionCommand prints the command); drop "
            "-c sshAccess=..."
        )


def _str(get: Callable[[str], object], key: str) -> str:
    value = get(key)
    if value is None:
        return ""
    if not isinstance(value, str | int | float):
        raise SettingsError(f"{key} must be a string, got {value!r}; pass -c {key}=VALUE")
    return str(value).strip()


def _bool(get: Callable[[str], object], key: str, default: bool) -> bool:
    value = get(key)
    if value is None or value == "":
        return default
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in ("true", "1", "yes"):
        return True
    if text in ("false", "0", "no"):
        return False
    raise SettingsError(f"{key}={value!r} is not a boolean; pass -c {key}=true or -c {key}=false")


def _client_cidr(value: str, allow_any: bool) -> str:
    if not value:
        raise SettingsError(
            "clientCidr is required: the DCV port opens to this range only. Pass your public IP, "
            "e.g. cdk deploy -c clientCidr=203.0.113.7/32 (find it with: curl -s "
            "https://checkip.amazonaws.com)"
        )
    if "/" not in value:
        raise SettingsError(f"clientCidr={value} has no prefix length; pass -c clientCidr={value}/32")
    try:
        network = ipaddress.ip_network(value, strict=True)
    except ValueError as exc:
        try:
            loose = ipaddress.ip_network(value, strict=False)
        except ValueError:
            raise SettingsError(
                f"clientCidr={value} is not a CIDR ({exc}); pass e.g. -c clientCidr=203.0.113.7/32"
            ) from None
        raise SettingsError(
            f"clientCidr={value} has host bits set; pass -c clientCidr={loose} "
            f"or the single address -c clientCidr={value.split('/', maxsplit=1)[0]}/{loose.max_prefixlen}"
        ) from None
    if network.version == 6:
        # The VPC has no IPv6 CIDR and the Elastic IP is IPv4: an IPv6 rule would admit nobody.
        raise SettingsError(
            f"clientCidr={value} is IPv6, but the twin host is reachable over IPv4 only (the VPC has no IPv6 "
            "range and the Elastic IP is IPv4); pass your public IPv4 address, e.g. -c "
            "clientCidr=203.0.113.7/32 (find it with: curl -s -4 https://checkip.amazonaws.com)"
        )
    if network.prefixlen == 0 and not allow_any:
        raise SettingsError(
            f"clientCidr={value} would open the DCV desktop to the whole internet; pass your own address "
            "(-c clientCidr=203.0.113.7/32), or, if you really mean it, add -c allowAnyClient=true"
        )
    return str(network)


def _availability_zone(value: str) -> str | None:
    if not value:
        return None
    if _AZ_ID_RE.match(value):
        raise SettingsError(
            f"availabilityZone={value} is a zone ID; pass the zone name instead, e.g. -c "
            "availabilityZone=us-east-1b "
            "(aws ec2 describe-availability-zones shows both)"
        )
    if not _AZ_RE.match(value):
        raise SettingsError(
            f"availabilityZone={value} is not an availability zone name; pass e.g. -c "
            "availabilityZone=us-east-1b "
            "(one that offers the instance type: aws ec2 describe-instance-type-offerings "
            "--location-type availability-zone --filters Name=instance-type,Values=g6e.2xlarge)"
        )
    return value


def _instance_type(value: str) -> str:
    if not _INSTANCE_TYPE_RE.match(value):
        raise SettingsError(
            f"instanceType={value} is not an EC2 instance type; pass e.g. -c instanceType=g6e.2xlarge"
        )
    return value


def _volume_gb(value: object) -> int:
    if value is None or value == "":
        return TwinSettings.volume_gb
    try:
        size = int(str(value).strip())
    except ValueError:
        raise SettingsError(f"volumeGb={value!r} is not a whole number; pass e.g. -c volumeGb=100") from None
    if not VOLUME_GB_MIN <= size <= VOLUME_GB_MAX:
        raise SettingsError(
            f"volumeGb={size} is outside {VOLUME_GB_MIN}..{VOLUME_GB_MAX} (the GPU AMI alone needs tens "
            "of GB; gp3 tops out at 16 TiB); pass e.g. -c volumeGb=100"
        )
    return size


def _history_ia_after_days(value: object) -> int:
    if value is None or value == "":
        return TwinSettings.history_ia_after_days
    try:
        days = int(str(value))
    except ValueError:
        raise SettingsError(
            f"historyIaAfterDays={value!r} is not a whole number; pass e.g. -c historyIaAfterDays=30"
        ) from None
    # S3 moves objects to Standard-IA no earlier than 30 days after they were written.
    if not 30 <= days <= 3650:
        raise SettingsError(
            f"historyIaAfterDays={days} is outside 30..3650 (S3 refuses a Standard-IA transition before 30 "
            "days); pass e.g. -c historyIaAfterDays=30"
        )
    return days


def _devices(value: object) -> tuple[str, ...]:
    if value is None or value == "":
        return TwinSettings.devices
    items = value if isinstance(value, list) else str(value).split(",")
    devices = tuple(str(item).strip() for item in items if str(item).strip())
    if not devices:
        raise SettingsError("devices is empty; pass -c devices=arm-001 (comma-separated) or -c devices='*'")
    if ALL_DEVICES in devices:
        if len(devices) > 1:
            raise SettingsError(
                f"devices={','.join(devices)} mixes '*' with names; pass -c devices='*' for the whole fleet "
                "or list the names only"
            )
        return (ALL_DEVICES,)
    for device in devices:
        problem = policy_device_id_problem(device)
        if problem is not None:
            raise SettingsError(
                f"device id {device!r} is not usable: {problem}; pass e.g. -c devices=arm-001,arm-002"
            )
    if len(set(devices)) != len(devices):
        raise SettingsError(f"devices={','.join(devices)} lists a device twice; list each once")
    return devices


def _topic_prefix(value: str) -> str:
    problem = topic_prefix_problem(value)
    if problem is not None:
        raise SettingsError(f"topicPrefix={value!r}: {problem}; pass e.g. -c topicPrefix=dt/lerobot")
    return value


def _units(value: str) -> str:
    if value not in UNITS:
        raise SettingsError(f"units={value} is not one of {', '.join(UNITS)}; pass e.g. -c units=auto")
    return value


def _ami_ssm_parameter(value: str) -> str:
    if not value.startswith("/") or " " in value:
        raise SettingsError(
            f"amiSsmParameter={value} is not an SSM parameter path; pass e.g. -c amiSsmParameter="
            f"{DEFAULT_AMI_SSM_PARAMETER} or an AMI with -c amiId=ami-0123456789abcdef0"
        )
    return value


def _ami_id(value: str) -> str:
    if not _AMI_ID_RE.match(value):
        raise SettingsError(f"amiId={value} is not an AMI ID; pass e.g. -c amiId=ami-0123456789abcdef0")
    return value


def _auto_stop_cron(value: str) -> str | None:
    if not value:
        return None
    body = value[5:-1] if value.startswith("cron(") and value.endswith(")") else value
    fields = body.split()
    example = "-c autoStopCron='0 20 * * ? *' (every day 20:00 in autoStopTimezone)"
    if len(fields) != 6 or not all(_CRON_FIELD_RE.match(field) for field in fields):
        raise SettingsError(
            f"autoStopCron={value!r} is not an EventBridge Scheduler cron expression (six fields: "
            f"minutes hours day-of-month month day-of-week year); pass e.g. {example}"
        )
    day_of_month, day_of_week = fields[2], fields[4]
    # Scheduler rejects a cron that constrains both day fields; one of them must be '?'.
    if (day_of_month == "?") == (day_of_week == "?"):
        raise SettingsError(
            f"autoStopCron={value!r}: exactly one of day-of-month and day-of-week must be '?'; pass e.g. "
            f"{example}"
        )
    return f"cron({' '.join(fields)})"


def _timezone(value: str) -> str:
    if not _TIMEZONE_RE.match(value):
        raise SettingsError(
            f"autoStopTimezone={value} is not an IANA zone; pass e.g. -c autoStopTimezone=UTC"
        )
    return value


def _stack_name(value: str) -> str:
    if not _STACK_NAME_RE.match(value):
        raise SettingsError(
            f"stackName={value} is not a CloudFormation stack name; pass e.g. -c stackName=So101TwinStack"
        )
    return value


def _alarm_email(value: str) -> str | None:
    if not value:
        return None
    if not _EMAIL_RE.match(value):
        raise SettingsError(
            f"alarmEmail={value} is not an e-mail address; pass e.g. -c alarmEmail=ops@example.com "
            "(or leave it empty to subscribe to the alarm topic yourself)"
        )
    return value
