"""Deployment settings: read once, validated in one place.

Where a value comes from, the last one winning (docs/deploy.md, "Settings"):

1. the default here (`TwinSettings`' field defaults, the one place they are written);
2. the deployer's settings file, `twin.settings.toml` at the repository root (or the file that
   `-c settingsFile=...` names): the settings a deployment keeps, so every later `cdk deploy` and
   `cdk destroy` repeats them without flags;
3. CDK context (`-c key=value`): an override for one run.

cdk.json holds no setting (only CDK's feature flags), so any context value of a setting's name is the
deployer's `-c`. Every refusal says what to write instead, because the person reading it is at a terminal
running `cdk deploy` and wants the fix, not a stack trace.
"""

from __future__ import annotations

import difflib
import ipaddress
import math
import re
import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

from twin.core.topics import ALL_DEVICES, TopicError, check_deployed_devices, topic_prefix_problem

# The agent's own rules (pure modules, no MuJoCo or awscrt), so the stack accepts exactly what the agent it
# deploys accepts: device ids and the topic prefix (twin.core.topics), units, and the client id prefix the
# IAM policy scopes iot:Connect to.
from twin.core.units import UNITS_CHOICES
from twin.transport.broker import MAX_CONNECTIONS_LIMIT, agent_client_id_prefix
from twin.transport.plan import (
    DEFAULT_MAX_CONNECTIONS,
    IOT_PUBLISHES_PER_CONNECTION,
    SAFETY_MARGIN,
    devices_per_connection,
)

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
# EC2 families with NVIDIA GPUs on x86_64 that the DLAMI's OSS NVIDIA driver serves (its release notes list
# the supported instances): the boot's `gpu` step fails on any other type, more than ten minutes into a deploy
# (after the packages), and rolls it back. Checked at synth, so that mistake costs nothing.
NVIDIA_FAMILIES = ("g4dn", "g5", "g6", "g6e", "g7e", "gr6", "p4d", "p4de", "p5", "p5e", "p5en", "p6-b200")
_AMI_ID_RE = re.compile(r"^ami-[0-9a-f]{8}([0-9a-f]{9})?$")
# Deliberately loose (SNS validates for real): one @, no spaces, a dot in the domain.
_EMAIL_RE = re.compile(r"^[^@\s]+@[^@\s]+\.[^@\s]+$")
_STACK_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9-]{0,127}$")
_TIMEZONE_RE = re.compile(r"^(UTC|[A-Za-z]+(/[A-Za-z0-9_+-]+)+)$")
# EventBridge Scheduler cron: minutes hours day-of-month month day-of-week year.
_CRON_FIELD_RE = re.compile(r"^[0-9A-Za-z*?,/#L W-]+$")
# DCV's [connectivity] idle-timeout is in minutes, 0 for never; a week is the most the stack writes.
DCV_IDLE_TIMEOUT_MAX = 7 * 24 * 60
VOLUME_GB_MIN = 50
VOLUME_GB_MAX = 16384
HOST_GENERATION_MAX = 9999
# One arm must fit one connection's planned budget.
ARM_RATE_HZ_MAX = IOT_PUBLISHES_PER_CONNECTION * SAFETY_MARGIN
# The host role allows each listed device's topic filter and topic by name, and IAM bounds a role's policies
# (10,240 characters inline, ten managed policies of 6,144): 150 listed devices of any id length fit with room
# to spare (tests/infra/test_stack.py checks the synthesized role at this bound against those quotas).
MAX_LISTED_DEVICES = 150
# The edge's default publish rate (telemetry contract), and the arms at it one IoT Core connection carries
# as the agent plans it (8): the figure the refusals below work their fixes out with.
DEFAULT_ARM_RATE_HZ = 10.0
_ARMS_PER_CONNECTION = (
    devices_per_connection(DEFAULT_ARM_RATE_HZ, IOT_PUBLISHES_PER_CONNECTION, iot=True) or 1
)


class SettingsError(ValueError):
    """A setting is unknown, or its value is unsafe; the message names the key and what to write."""


# The settings file at the repository root; `-c settingsFile=PATH` names another (relative to the root).
SETTINGS_FILE = "twin.settings.toml"
SETTINGS_FILE_KEY = "settingsFile"
# Confirmations for one deploy, never kept: in the settings file they would confirm every later deploy too.
ONE_RUN_KEYS = frozenset({"replaceInstance"})


class Source(StrEnum):
    """Where a setting's value came from."""

    DEFAULT = "default"
    FILE = "file"
    CONTEXT = "-c"


@dataclass(frozen=True)
class TwinSettings:
    """Everything the stack needs from the person deploying it, already validated."""

    # None until given: synth still builds (so `cdk destroy` needs no flags), but `cdk deploy` refuses
    # (`deploy_blockers`).
    client_cidr: str | None = None
    allow_any_client: bool = False
    # Minutes without input before DCV disconnects a client (its [connectivity] idle-timeout); 0: never.
    # DCV's own default is 60, but the twin is watched for hours without being touched.
    dcv_idle_timeout_minutes: int = 0
    availability_zone: str | None = None
    instance_type: str = "g6e.2xlarge"
    volume_gb: int = 100
    devices: tuple[str, ...] = ("arm-001",)
    # The arms' publish rate, and the whole fleet's connection bound: what the IAM policy's client ids and
    # the agent's connection pool are sized for (docs/scaling.md).
    arm_rate_hz: float = DEFAULT_ARM_RATE_HZ
    max_connections: int = DEFAULT_MAX_CONNECTIONS
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
    # Where alarms are e-mailed (the host's servo alarms and the CloudWatch alarms); empty: the SNS topic
    # only, for other subscribers.
    alarm_email: str | None = None
    # Servo alarms of warning severity are e-mailed too (critical ones always are; docs/servo-health.md).
    alarm_warnings: bool = False
    # Telemetry history bucket (docs/history.md): days in S3 Standard before Standard-IA, and whether the
    # bucket survives `cdk destroy`.
    history_ia_after_days: int = 30
    retain_history: bool = True
    # Which host the stack runs: part of the instance's construct id, so a new value is a new instance (the
    # way back from a terminated one, which no deploy of unchanged settings replaces). At 1, the first
    # host's id, so upgrading so101-twin replaces no deployed host.
    host_generation: int = 1
    replace_instance: bool = False

    @property
    def instance_fingerprint(self) -> dict[str, str]:
        """The settings whose change replaces the instance (and its root disk): the replacement guard compares
        these with the deployed stack's."""
        fingerprint = {
            "availabilityZone": self.availability_zone or "",
            "volumeGb": str(self.volume_gb),
            "image": self.ami_id or f"resolve:ssm:{self.ami_ssm_parameter}",
        }
        # Left out at the first host, so a stack deployed before the setting existed compares equal.
        if self.host_generation != TwinSettings.host_generation:
            fingerprint["hostGeneration"] = str(self.host_generation)
        return fingerprint

    @property
    def whole_fleet(self) -> bool:
        return self.devices == ("*",)

    @property
    def client_id_prefix(self) -> str:
        """The twin host agent's client ids and shared-subscription group, `so101-twin-<stack name>-`: its
        own, so an agent on a laptop (named for its host) never splits the fleet with it, and two stacks in
        one account never collide. The IAM policy allows exactly these client ids."""
        return agent_client_id_prefix(self.stack_name)

    def deploy_blockers(self) -> list[str]:
        """What stops `cdk deploy` (but not `cdk destroy`, which needs no settings): the app turns each into
        an error annotation, which the CDK CLI refuses to deploy or synthesize."""
        if self.client_cidr is None:
            return [
                "clientCidr is required: the DCV port opens to this range only. Write your public IP into "
                f'{SETTINGS_FILE} (clientCidr = "203.0.113.7/32") or pass it once, e.g. cdk deploy -c '
                "clientCidr=203.0.113.7/32 (find it with: curl -s https://checkip.amazonaws.com)"
            ]
        return []

    def file_values(self) -> dict[str, Any]:
        """Every setting as the settings file writes it (TOML types, empty string for "not set")."""
        values: dict[str, Any] = {}
        for key, name in SETTING_FIELDS.items():
            value = getattr(self, name)
            if value is None:
                value = ""
            elif isinstance(value, tuple):
                value = list(value)
            values[key] = value
        return values

    @classmethod
    def from_context(cls, get: Callable[[str], object]) -> TwinSettings:
        """Build from a getter of setting values (CDK context, or `resolve`'s merge of the settings file and
        context); raise SettingsError on bad input.

        `-c key=value` arrives as a string while the settings file's values keep their TOML type, so every
        parser accepts both.
        """
        _refuse_removed(get)
        allow_any = _bool(get, "allowAnyClient", False)
        ami_id = _str(get, "amiId") or None
        settings = cls(
            client_cidr=_client_cidr(_str(get, "clientCidr"), allow_any),
            allow_any_client=allow_any,
            dcv_idle_timeout_minutes=_dcv_idle_timeout_minutes(get("dcvIdleTimeoutMinutes")),
            availability_zone=_availability_zone(_str(get, "availabilityZone")),
            instance_type=_instance_type(_str(get, "instanceType") or cls.instance_type),
            volume_gb=_volume_gb(get("volumeGb")),
            devices=_devices(get("devices")),
            arm_rate_hz=_arm_rate_hz(get("armRateHz")),
            max_connections=_max_connections(get("maxConnections")),
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
            alarm_warnings=_bool(get, "alarmWarnings", False),
            history_ia_after_days=_history_ia_after_days(get("historyIaAfterDays")),
            retain_history=_bool(get, "retainHistory", True),
            host_generation=_host_generation(get("hostGeneration")),
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


# Setting key (as in the settings file and -c) -> TwinSettings field, in the order docs/deploy.md lists them.
SETTING_FIELDS: dict[str, str] = {
    "clientCidr": "client_cidr",
    "allowAnyClient": "allow_any_client",
    "dcvIdleTimeoutMinutes": "dcv_idle_timeout_minutes",
    "stackName": "stack_name",
    "devices": "devices",
    "armRateHz": "arm_rate_hz",
    "maxConnections": "max_connections",
    "topicPrefix": "topic_prefix",
    "units": "units",
    "alarmEmail": "alarm_email",
    "alarmWarnings": "alarm_warnings",
    "instanceType": "instance_type",
    "availabilityZone": "availability_zone",
    "volumeGb": "volume_gb",
    "amiSsmParameter": "ami_ssm_parameter",
    "amiId": "ami_id",
    "terminationProtection": "termination_protection",
    "hostGeneration": "host_generation",
    "autoStopCron": "auto_stop_cron",
    "autoStopTimezone": "auto_stop_timezone",
    "ros2": "ros2",
    "recordSessions": "record_sessions",
    "historyIaAfterDays": "history_ia_after_days",
    "retainHistory": "retain_history",
    "replaceInstance": "replace_instance",
}
# The settings a deployment keeps (the file's keys, the deployed stack's Settings output).
KEPT_KEYS: tuple[str, ...] = tuple(k for k in SETTING_FIELDS if k not in ONE_RUN_KEYS)


@dataclass(frozen=True)
class ResolvedSettings:
    """The validated settings, where each came from, and the settings file that was read (None: none)."""

    settings: TwinSettings
    sources: Mapping[str, Source]
    settings_file: Path | None

    @property
    def given(self) -> dict[str, str]:
        """Kept settings that were written down (file or -c), with where: what the Settings output records."""
        return {k: str(s) for k, s in self.sources.items() if s is not Source.DEFAULT and k in KEPT_KEYS}


def settings_file_path(root: Path, get: Callable[[str], object]) -> tuple[Path, bool]:
    """The settings file to read and whether the deployer named it (then it must exist)."""
    named = get(SETTINGS_FILE_KEY)
    if named in (None, ""):
        return root / SETTINGS_FILE, False
    path = Path(str(named)).expanduser()
    return (path if path.is_absolute() else root / path), True


def read_settings_file(path: Path, *, required: bool = False) -> dict[str, Any]:
    """The settings file's values by key ({} when it is absent and not required); SettingsError names an
    unknown key, a table where a value belongs, or a one-run flag written down."""
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        if required:
            raise SettingsError(
                f"{SETTINGS_FILE_KEY}={path} does not exist; pass an existing file or drop "
                f"-c {SETTINGS_FILE_KEY}"
            ) from None
        return {}
    except tomllib.TOMLDecodeError as exc:
        raise SettingsError(f"{path} is not valid TOML: {exc}") from None
    except OSError as exc:
        raise SettingsError(f"{path} cannot be read: {exc}") from None
    for key, value in data.items():
        if key in ONE_RUN_KEYS:
            raise SettingsError(
                f"{path}: {key} confirms one deploy and is never kept; remove it from the file and pass "
                f"-c {key}=true with the deploy it confirms"
            )
        if key not in SETTING_FIELDS:
            raise SettingsError(
                f"{path}: unknown setting '{key}'; {_closest(key)}the settings are: {', '.join(KEPT_KEYS)} "
                "(docs/deploy.md, Settings)"
            )
        if isinstance(value, dict):
            raise SettingsError(f"{path}: {key} must be a value, not a table")
    return data


def _closest(key: str) -> str:
    """ "did you mean 'devices'? " for an unknown key close to a setting's name (a file's or a -c one); for a
    calibration key, where the arms' calibrations go instead."""
    if "calibration" in key.lower():
        # Each arm's is a file of its own, pushed to the stack's bucket; no deploy carries them.
        return (
            "the arms' calibrations are not a stack setting: push each arm's file with `twin calibration "
            "push ARM FILE` (docs/deploy.md, the CalibrationUri output); "
        )
    close = difflib.get_close_matches(key, list(SETTING_FIELDS), n=1)
    return f"did you mean '{close[0]}'? " if close else ""


# A context key that looks like one of ours: CDK's own keys hold ':', '-', '/' or start with '@'.
_OUR_SHAPE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


def check_context_keys(keys: Iterable[str]) -> None:
    """SettingsError for a `-c` key shaped like a setting that is none (`-c device=arm-1`): CDK keeps any key
    it is given, so the deploy would run without it and nothing would say so."""
    known = {*SETTING_FIELDS, SETTINGS_FILE_KEY, *ONE_RUN_KEYS}
    for key in sorted(keys):
        if _OUR_SHAPE.match(key) and key not in known:
            raise SettingsError(
                f"-c {key}: unknown setting; {_closest(key)}the settings are: {', '.join(KEPT_KEYS)}, and "
                f"{', '.join(sorted(ONE_RUN_KEYS))} for one deploy (docs/deploy.md, Settings)"
            )


def resolve(
    get_context: Callable[[str], object], file_values: Mapping[str, Any], settings_file: Path | None = None
) -> ResolvedSettings:
    """Merge the settings file with context (`-c` wins), validate, and say where each value came from."""
    sources: dict[str, Source] = {}
    for key in SETTING_FIELDS:
        if get_context(key) is not None:
            sources[key] = Source.CONTEXT
        elif key in file_values:
            sources[key] = Source.FILE
        else:
            sources[key] = Source.DEFAULT

    def get(key: str) -> object:
        value = get_context(key)
        return value if value is not None else file_values.get(key)

    try:
        settings = TwinSettings.from_context(get)
    except SettingsError as exc:
        # The messages start with the key; say when the bad value is the file's, so the fix goes there.
        match = re.match(r"[a-zA-Z0-9]+", str(exc))
        if match and sources.get(match.group(0)) is Source.FILE and settings_file is not None:
            raise SettingsError(_in_file(str(exc), match.group(0), settings_file)) from None
        raise
    return ResolvedSettings(settings, sources, settings_file if file_values else None)


def _in_file(message: str, key: str, settings_file: Path) -> str:
    """A bad value's message when the value is the settings file's: the fix goes in the file (a walk was told
    to "pass -c devices=..." for a list it had written in the file, which stays wrong for the next deploy)."""
    problem, sep, flag = message.partition("; pass ")
    if not sep:
        return f"{message} (it is set in {settings_file})"
    return f"{problem}: correct {key} in {settings_file} (or, for one deploy only, pass {flag})"


def default_values() -> dict[str, Any]:
    """Every kept setting's default, as the settings file writes it."""
    values = TwinSettings().file_values()
    return {k: values[k] for k in KEPT_KEYS}


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


def _client_cidr(value: str, allow_any: bool) -> str | None:
    if not value:
        return None  # TwinSettings.deploy_blockers says what to pass
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
    family = value.split(".", 1)[0]
    if family not in NVIDIA_FAMILIES:
        raise SettingsError(
            f"instanceType={value} has no NVIDIA GPU the host's image drives ({family} is not one of "
            f"{', '.join(NVIDIA_FAMILIES)}): the twin's desktop renders on it and the first boot checks for "
            "it, so the deploy would fail and roll back; pass e.g. -c instanceType=g6e.2xlarge"
        )
    return value


def _whole(
    key: str, value: object, default: int, *, example: int, bounds: tuple[int, int]
) -> tuple[int, bool]:
    """`value` as a whole number (`default` when not given) and whether it lies in `bounds` (inclusive);
    SettingsError, naming `key` and an example, when it is not a whole number."""
    if value is None or value == "":
        return default, True
    try:
        # A settings file's 16.0 is the whole number its "16" and -c's 16 are.
        number = int(value) if isinstance(value, float) and value.is_integer() else int(str(value).strip())
    except ValueError:
        raise SettingsError(f"{key}={value!r} is not a whole number; pass e.g. -c {key}={example}") from None
    return number, bounds[0] <= number <= bounds[1]


def _volume_gb(value: object) -> int:
    size, inside = _whole(
        "volumeGb", value, TwinSettings.volume_gb, example=100, bounds=(VOLUME_GB_MIN, VOLUME_GB_MAX)
    )
    if not inside:
        raise SettingsError(
            f"volumeGb={size} is outside {VOLUME_GB_MIN}..{VOLUME_GB_MAX} (the GPU AMI alone needs tens "
            "of GB; gp3 tops out at 16 TiB); pass e.g. -c volumeGb=100"
        )
    return size


def _dcv_idle_timeout_minutes(value: object) -> int:
    minutes, inside = _whole(
        "dcvIdleTimeoutMinutes",
        value,
        TwinSettings.dcv_idle_timeout_minutes,
        example=0,
        bounds=(0, DCV_IDLE_TIMEOUT_MAX),
    )
    if not inside:
        raise SettingsError(
            f"dcvIdleTimeoutMinutes={minutes} is outside 0..{DCV_IDLE_TIMEOUT_MAX} (minutes without input "
            "before DCV disconnects a client; 0: never); pass e.g. -c dcvIdleTimeoutMinutes=0"
        )
    return minutes


def _history_ia_after_days(value: object) -> int:
    # S3 moves objects to Standard-IA no earlier than 30 days after they were written.
    days, inside = _whole(
        "historyIaAfterDays", value, TwinSettings.history_ia_after_days, example=30, bounds=(30, 3650)
    )
    if not inside:
        raise SettingsError(
            f"historyIaAfterDays={days} is outside 30..3650 (S3 refuses a Standard-IA transition before 30 "
            "days); pass e.g. -c historyIaAfterDays=30"
        )
    return days


def _host_generation(value: object) -> int:
    generation, inside = _whole(
        "hostGeneration", value, TwinSettings.host_generation, example=2, bounds=(1, HOST_GENERATION_MAX)
    )
    if not inside:
        raise SettingsError(
            f"hostGeneration={generation} is outside 1..{HOST_GENERATION_MAX} (1 is the stack's first host; "
            "raise it by one to build a new host in place of the deployed one); pass e.g. -c hostGeneration=2"
        )
    return generation


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
    try:
        # Each deployable (a calibration file's name, part of an IAM ARN), once, and no two differing only
        # in case: a new deployment's list, so refusing costs nothing a host had.
        check_deployed_devices(devices)
    except TopicError as exc:
        raise SettingsError(f"devices: {exc}; pass e.g. -c devices=arm-001,arm-002") from None
    if len(devices) > MAX_LISTED_DEVICES:
        raise SettingsError(
            f"devices lists {len(devices)} arms; the host's IAM role can name at most {MAX_LISTED_DEVICES} "
            f"(IAM's size quotas on a role's policies). {_fleet_instead(len(devices))} (docs/scaling.md)"
        )
    return devices


def _fleet_instead(arms: int) -> str:
    """What carries `arms` instead of a list: the whole fleet over enough connections (at the edge's default
    10 Hz, 8 arms a connection), or past the agent's bound, more than one host."""
    per_connection = _ARMS_PER_CONNECTION
    needed = math.ceil(arms / per_connection)
    if needed > MAX_CONNECTIONS_LIMIT:
        return (
            f"{arms} arms at 10 Hz need {needed} connections, more than one host's {MAX_CONNECTIONS_LIMIT}: "
            "mirror them from several stacks (each its devices, or its topicPrefix), docs/scale-out.md"
        )
    return (
        f'Mirror them as the whole fleet instead, with enough connections: devices = ["*"] and '
        f"maxConnections = {needed} in the settings file ({per_connection} arms at 10 Hz a connection; "
        "-c devices='*' -c maxConnections=... for one deploy)"
    )


def _arm_rate_hz(value: object) -> float:
    if value is None or value == "":
        return TwinSettings.arm_rate_hz
    try:
        rate = float(str(value).strip())
    except ValueError:
        raise SettingsError(f"armRateHz={value!r} is not a number; pass e.g. -c armRateHz=10") from None
    if not 0 < rate <= ARM_RATE_HZ_MAX:
        raise SettingsError(
            f"armRateHz={value} is outside (0, {ARM_RATE_HZ_MAX:g}]: one arm must fit in one IoT Core "
            f"connection's planned {ARM_RATE_HZ_MAX:g} messages a second; pass the rate the edge publishes "
            "at, e.g. -c armRateHz=10"
        )
    return rate


def _max_connections(value: object) -> int:
    count, inside = _whole(
        "maxConnections", value, TwinSettings.max_connections, example=8, bounds=(1, MAX_CONNECTIONS_LIMIT)
    )
    if count < 1:
        raise SettingsError(f"maxConnections={count} is below 1; pass e.g. -c maxConnections=8")
    if not inside:
        raise SettingsError(
            f"maxConnections={count} is above {MAX_CONNECTIONS_LIMIT}, the agent's bound for the whole "
            f"fleet (about {MAX_CONNECTIONS_LIMIT * _ARMS_PER_CONNECTION} arms at 10 Hz; past it a fleet "
            "wants an IoT rule into Kinesis, docs/scale-out.md); pass e.g. -c maxConnections=8, or list the "
            "devices (at most "
            f"{MAX_LISTED_DEVICES})"
        )
    return count


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
