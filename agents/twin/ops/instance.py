"""Start, stop and inspect the cloud twin host deployed by the CDK stack.

`TwinInstance` reads the stack's CloudFormation outputs (`InstanceId`, `DcvUrl`, `DeploymentVersion`, ...)
and events, starts or stops the EC2 instance, waits for the state with the EC2 waiters, and runs commands on
the host through SSM Run Command (`run_on_host`): the agent's health (its `/healthz` listens on 127.0.0.1
only, so it can only be asked from the instance) with the deployment version the host runs, the verdict of
the checks the host runs after every start (`start_verdict`), and the host checks of `twin instance check`
(twin.ops.instance_check). `dcv_password` reads the DCV login password from the secret the stack names.

Everything that can go wrong for a reason the user can fix is raised as a `TwinInstanceError` subclass whose
message says what to do; the `twin instance` command maps each class to its own exit code:

- `AwsSetupError` (3): no credentials, no region, or credentials AWS rejects.
- `StackNotFoundError` (4): the stack is not deployed in that account and region.
- `StackOutputsError` (5): the stack exists but lacks an output this code needs.
- `InsufficientCapacityError` (6): EC2 has no capacity for the instance type in its Availability Zone.
- `WaitError` (7): the instance did not reach the wanted state in time, or left the path to it.
- `AwsCallError` (1): any other AWS error, with its code and message.

Agent health never raises: when SSM cannot ask (agent not registered yet, instance stopped, no permission) the
result is an `AgentHealth` with state "unknown" and the reason.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import re
import time
import tomllib
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from twin.core.aws import missing_profile_hint, region_or_env
from twin.service.config import DEFAULT_AGENT_URL

if TYPE_CHECKING:
    import boto3

    from twin.ops.deployed_settings import DeployedSettings
    from twin.ops.port_forward import PortForward

log = logging.getLogger(__name__)

DEFAULT_STACK_NAME = "So101TwinStack"
STACK_ENV_VAR = "SO101_TWIN_STACK"
# EC2 starts no instance in these states again: the stack needs a new host (TwinInstance.new_host_advice).
TERMINATED_STATES = ("shutting-down", "terminated")
# EC2's answer for an instance it does not know, e.g. one terminated more than about an hour ago.
INSTANCE_NOT_FOUND = "InvalidInstanceID.NotFound"
# The deployment's settings file (stacks/settings.py reads it for `cdk deploy`): its stackName is the default.
SETTINGS_FILE = "twin.settings.toml"
# The -c flag that confirms a deploy which replaces the host (stacks/replacement_guard.py, CONFIRM_FLAG).
REPLACE_FLAG = "replaceInstance"

# Output keys of the CDK stack (stacks/); InstanceId and DcvUrl are the ones this module cannot work without.
OUTPUT_INSTANCE_ID = "InstanceId"
OUTPUT_DCV_URL = "DcvUrl"
OUTPUT_IOT_ENDPOINT = "IotEndpoint"
OUTPUT_DCV_PASSWORD_SECRET = "DcvPasswordSecret"
OUTPUT_SSM_SESSION_COMMAND = "SsmSessionCommand"
OUTPUT_DEPLOYMENT_VERSION = "DeploymentVersion"
OUTPUT_UPDATE_ASSOCIATION = "UpdateAssociationId"
OUTPUT_HOST_LOG_GROUP = "HostLogGroup"
OUTPUT_SETTINGS = "Settings"
OUTPUT_CALIBRATION_URI = "CalibrationUri"
REQUIRED_OUTPUTS = (OUTPUT_INSTANCE_ID, OUTPUT_DCV_URL)
# The codes AWS answers a caller whose policies do not allow the call with.
ACCESS_DENIED = ("AccessDeniedException", "AccessDenied")

HEALTH_URL = f"{DEFAULT_AGENT_URL}/healthz"
# The body goes to stdout and the HTTP status is appended as the last three characters; curl prints 000 when
# nothing answers, which is how "agent not running" is told apart from "agent unhealthy".
HEALTH_COMMAND = f"curl -s -o /dev/stdout -w '%{{http_code}}' {HEALTH_URL}"
# The deployment version the host runs (written by userdata/bootstrap.sh after a verified boot or update),
# printed as the first line so one Run Command answers both.
DEPLOYED_VERSION_FILE = "/var/lib/so101-twin/deployed-version"
VERSION_COMMAND = f"printf 'version=%s\\n' \"$(cat {DEPLOYED_VERSION_FILE} 2>/dev/null || echo none)\""
STATUS_COMMANDS = [VERSION_COMMAND, HEALTH_COMMAND]

# After every start, so101-twin-start.service runs the host checks (userdata/host-check.sh --on-start) and
# writes their verdict, headed by the id of the boot it belongs to; asking for the current boot id in the same
# command tells this start's verdict from the previous one's.
LAST_START_FILE = "/var/lib/so101-twin/last-start"
START_VERDICT_COMMANDS = [
    "printf 'boot=%s\\n' \"$(cat /proc/sys/kernel/random/boot_id)\"",
    f"cat {LAST_START_FILE} 2>/dev/null || true",
]
PASS = "PASS"
FAIL = "FAIL"

# get_command_invocation states after which the output will not change any more.
_SSM_PENDING = frozenset({"Pending", "InProgress", "Delayed"})

HEALTHY = "healthy"
UNHEALTHY = "unhealthy"
UNKNOWN = "unknown"

G6E_OFFERINGS_COMMAND = (
    "aws ec2 describe-instance-type-offerings --location-type availability-zone "
    "--filters Name=instance-type,Values={instance_type} --region {region}"
)


def settings_file(start: Path | None = None) -> Path | None:
    """The deployment's settings file: twin.settings.toml in `start` (the current directory) or the nearest
    directory above it, up to the checkout's root (the directory with cdk.json, where `cdk deploy` runs). A
    command run from docs/ acts on the stack `cdk deploy` made, not on one of the default name."""
    here = (start or Path.cwd()).resolve()
    for directory in (here, *here.parents):
        if (directory / SETTINGS_FILE).is_file():
            return directory / SETTINGS_FILE
        if (directory / "cdk.json").is_file():
            return None
    return None


def default_stack_name() -> str:
    """The stack to act on when none is given: $SO101_TWIN_STACK, else the `stackName` of the deployment's
    settings file (settings_file), else `So101TwinStack`."""
    named = os.environ.get(STACK_ENV_VAR)
    if named:
        return named
    path = settings_file()
    try:
        with open(path or SETTINGS_FILE, "rb") as fh:
            value = tomllib.load(fh).get("stackName")
    except (OSError, tomllib.TOMLDecodeError):
        value = None
    return value if isinstance(value, str) and value.strip() else DEFAULT_STACK_NAME


class TwinInstanceError(Exception):
    """A problem the user can act on; `str(exc)` says what to do."""


class AwsSetupError(TwinInstanceError):
    """No usable credentials or region."""


class StackNotFoundError(TwinInstanceError):
    """The stack is not deployed in this account and region."""


class StackOutputsError(TwinInstanceError):
    """The stack lacks an output this module needs."""


class InsufficientCapacityError(TwinInstanceError):
    """EC2 could not start the instance for lack of capacity in its Availability Zone."""


class WaitError(TwinInstanceError):
    """The instance did not reach the wanted state."""


class AwsCallError(TwinInstanceError):
    """Any other AWS error."""


class InstanceGoneError(AwsCallError):
    """The stack's instance is unknown to EC2: terminated more than about an hour ago."""


@dataclass(frozen=True)
class StackOutputs:
    instance_id: str
    dcv_url: str
    iot_endpoint: str | None = None
    dcv_password_secret: str | None = None
    ssm_session_command: str | None = None
    deployment_version: str | None = None
    update_association_id: str | None = None
    host_log_group: str | None = None
    # The settings the stack was deployed with, as JSON (twin.ops.deployed_settings reads it).
    settings: str | None = None
    # Where the arms' calibrations are kept (s3://<bucket>/calibration; `twin calibration`).
    calibration_uri: str | None = None


@dataclass(frozen=True)
class AgentHealth:
    """What the agent's /healthz said, or why it could not be asked."""

    state: str  # HEALTHY, UNHEALTHY or UNKNOWN
    reason: str
    http_status: int | None = None
    body: Any = None
    # The deployment version the host runs ("none" before its first verified boot), when it could be asked.
    host_version: str | None = None

    @property
    def healthy(self) -> bool:
        return self.state == HEALTHY

    def describe(self) -> str:
        if self.state == UNKNOWN:
            return f"agent health unknown: {self.reason}"
        return f"agent {self.state}: {self.reason}"


@dataclass(frozen=True)
class InstanceStatus:
    instance_id: str
    state: str
    instance_type: str
    availability_zone: str | None
    dcv_url: str
    health: AgentHealth | None = field(default=None)
    expected_version: str | None = None

    @property
    def host_version(self) -> str | None:
        return self.health.host_version if self.health is not None else None


@dataclass(frozen=True)
class StartVerdict:
    """The host checks after a start: PASS, FAIL, or UNKNOWN when no verdict of this boot came in time."""

    state: str
    summary: str
    # The host-check lines (NAME<TAB>OK|WARN|FAIL<TAB>detail) the verdict was made from.
    lines: tuple[str, ...] = ()

    def describe(self) -> str:
        if self.state == UNKNOWN:
            return f"start checks: no verdict: {self.summary}"
        return f"start checks: {self.state}: {self.summary}"


def parse_start_verdict(stdout: str) -> StartVerdict | None:
    """Interpret START_VERDICT_COMMANDS' output; None while the verdict on the host is not this boot's."""
    lines = stdout.strip().splitlines()
    if len(lines) < 2 or not lines[0].startswith("boot="):
        return None
    boot = lines[0].removeprefix("boot=").strip()
    # "boot=<id> <time> PASS|FAIL <summary>"
    head = lines[1].split(" ", 3)
    if len(head) < 3 or head[0] != f"boot={boot}" or head[2] not in (PASS, FAIL):
        return None
    return StartVerdict(head[2], head[3] if len(head) > 3 else "", tuple(lines[2:]))


@dataclass(frozen=True)
class HostCommand:
    """The outcome of a Run Command on the host: its status and output, or why it could not run."""

    status: str
    stdout: str = ""
    stderr: str = ""
    problem: str | None = None  # set when SSM could not run it or it did not finish


def _device_summary(body: Any) -> str:
    """One line per device from the agent's JSON; tolerant of its shape so new fields never break the CLI."""
    if not isinstance(body, dict):
        return ""
    devices = body.get("devices")
    items: Iterable[tuple[object, object]]
    if isinstance(devices, dict):
        items = devices.items()
    elif isinstance(devices, list):
        items = [(d.get("device_id") or d.get("id") or "?", d) for d in devices if isinstance(d, dict)]
    else:
        return str(body.get("status", ""))
    parts = []
    for name, value in items:
        shown = value
        if isinstance(value, dict):
            shown = value.get("status") or value.get("state") or json.dumps(value, sort_keys=True)
        parts.append(f"{name}={shown}")
    return ", ".join(parts)


def parse_health_output(stdout: str) -> AgentHealth:
    """Interpret the output of STATUS_COMMANDS (or HEALTH_COMMAND alone): an optional `version=...` line, then
    the /healthz body followed by the 3-digit HTTP status."""
    text = stdout.strip()
    host_version = None
    if text.startswith("version="):
        first, _, text = text.partition("\n")
        host_version = first.removeprefix("version=").strip() or None
        text = text.strip()
    health = _parse_health(text)
    return dataclasses.replace(health, host_version=host_version) if host_version else health


def _parse_health(text: str) -> AgentHealth:
    match = re.fullmatch(r"(.*?)(\d{3})", text, flags=re.DOTALL)
    if match is None:
        shown = text[:200] or "nothing"
        return AgentHealth(UNKNOWN, f"the health check printed no HTTP status (got {shown!r})")
    raw_body, status = match.group(1).strip(), int(match.group(2))
    if status == 0:
        return AgentHealth(
            UNHEALTHY,
            f"nothing answers on {HEALTH_URL}: the twin agent service is not running or still starting",
            http_status=0,
        )
    try:
        body: Any = json.loads(raw_body) if raw_body else None
    except json.JSONDecodeError:
        body = raw_body
    summary = _device_summary(body)
    if status == 200:
        return AgentHealth(HEALTHY, summary or "HTTP 200", http_status=status, body=body)
    reason = f"HTTP {status}" + (f" ({summary})" if summary else "")
    return AgentHealth(UNHEALTHY, reason, http_status=status, body=body)


class TwinInstance:
    """The twin host of one deployed stack. Clients are built on first use unless injected (tests, reuse)."""

    def __init__(
        self,
        stack_name: str | None = None,
        *,
        region: str | None = None,
        session: boto3.session.Session | None = None,
        cloudformation: Any = None,
        ec2: Any = None,
        ssm: Any = None,
        poll_interval_s: float = 15.0,
        health_poll_interval_s: float = 2.0,
    ) -> None:
        self.stack_name = stack_name or default_stack_name()
        self._region = region
        self._session = session
        self._clients: dict[str, Any] = {"cloudformation": cloudformation, "ec2": ec2, "ssm": ssm}
        self._outputs: StackOutputs | None = None
        self._stack: dict[str, Any] | None = None
        self.poll_interval_s = poll_interval_s
        self.health_poll_interval_s = health_poll_interval_s

    # --- clients -----------------------------------------------------------------------------------

    def _client(self, service: Literal["cloudformation", "ec2", "ssm", "secretsmanager"]) -> Any:
        client = self._clients.get(service)
        if client is None:
            with self._aws(f"create the {service} client"):
                if self._session is None:
                    import boto3  # noqa: PLC0415 - keeps `twin --help` free of boto3's import time

                    self._session = boto3.session.Session(region_name=region_or_env(self._region))
                client = self._session.client(service)
            self._clients[service] = client
        return client

    @property
    def region(self) -> str:
        for client in self._clients.values():
            if client is not None:
                return client.meta.region_name
        if self._session is not None and self._session.region_name:
            return self._session.region_name
        return self._region or "(no region)"

    @contextmanager
    def _aws(self, action: str) -> Iterator[None]:
        """Turn botocore's exceptions for setup problems into messages that say how to fix them."""
        from botocore.exceptions import (  # noqa: PLC0415
            ClientError,
            EndpointConnectionError,
            NoCredentialsError,
            NoRegionError,
            PartialCredentialsError,
            ProfileNotFound,
        )

        try:
            yield
        except ProfileNotFound as exc:
            raise AwsSetupError(missing_profile_hint(exc)) from exc
        except NoRegionError as exc:
            raise AwsSetupError(
                "no AWS region configured: pass --region (e.g. --region us-east-1), set AWS_REGION, "
                "or run `aws configure`"
            ) from exc
        except (NoCredentialsError, PartialCredentialsError) as exc:
            raise AwsSetupError(
                f"no AWS credentials found ({exc}): run `aws configure` or `aws sso login`, set AWS_PROFILE, "
                "or export AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY"
            ) from exc
        except EndpointConnectionError as exc:
            raise AwsCallError(f"could not {action}: {exc} (check the region and the network)") from exc
        except ClientError as exc:
            code = exc.response.get("Error", {}).get("Code", "")
            message = exc.response.get("Error", {}).get("Message", str(exc))
            if code in {
                "ExpiredToken",
                "ExpiredTokenException",
                "InvalidClientTokenId",
                "UnrecognizedClientException",
                "AuthFailure",
                "SignatureDoesNotMatch",
            }:
                raise AwsSetupError(
                    f"AWS rejected the credentials ({code}: {message}): refresh them "
                    "(`aws sso login` or `aws configure`) and retry"
                ) from exc
            raise AwsCallError(f"could not {action}: {code}: {message}") from exc

    # --- stack -------------------------------------------------------------------------------------

    def stack_description(self) -> dict[str, Any]:
        """The stack as DescribeStacks returns it (status, outputs, ...), read once per object."""
        if self._stack is not None:
            return self._stack
        from botocore.exceptions import ClientError  # noqa: PLC0415

        cfn = self._client("cloudformation")
        # Our own errors pass through _aws untouched; only botocore's are translated there.
        with self._aws(f"read stack {self.stack_name}"):
            try:
                response = cfn.describe_stacks(StackName=self.stack_name)
            except ClientError as exc:
                error = exc.response.get("Error", {})
                if error.get("Code") == "ValidationError" and "does not exist" in error.get("Message", ""):
                    raise StackNotFoundError(self._stack_missing_message()) from exc
                raise
        stacks = response.get("Stacks", [])
        if not stacks:
            raise StackNotFoundError(self._stack_missing_message())
        self._stack = stacks[0]
        return self._stack

    def outputs(self) -> StackOutputs:
        """The stack's outputs, read once per object."""
        if self._outputs is not None:
            return self._outputs
        stack = self.stack_description()
        values = {o["OutputKey"]: o.get("OutputValue", "") for o in stack.get("Outputs", [])}
        missing = [key for key in REQUIRED_OUTPUTS if not values.get(key)]
        if missing:
            raise StackOutputsError(
                f"stack {self.stack_name} in {self.region} ({stack.get('StackStatus', '?')}) has no output "
                f"{', '.join(missing)}; it is not the twin stack or its deploy did not finish: redeploy with "
                "`cdk deploy` or pass the right --stack"
            )
        self._outputs = StackOutputs(
            instance_id=values[OUTPUT_INSTANCE_ID],
            dcv_url=values[OUTPUT_DCV_URL],
            iot_endpoint=values.get(OUTPUT_IOT_ENDPOINT),
            dcv_password_secret=values.get(OUTPUT_DCV_PASSWORD_SECRET),
            ssm_session_command=values.get(OUTPUT_SSM_SESSION_COMMAND),
            deployment_version=values.get(OUTPUT_DEPLOYMENT_VERSION),
            update_association_id=values.get(OUTPUT_UPDATE_ASSOCIATION),
            host_log_group=values.get(OUTPUT_HOST_LOG_GROUP),
            settings=values.get(OUTPUT_SETTINGS),
            calibration_uri=values.get(OUTPUT_CALIBRATION_URI),
        )
        log.debug("stack %s outputs: %s", self.stack_name, self._outputs)
        return self._outputs

    def stack_events(self, max_pages: int = 3) -> list[dict[str, Any]]:
        """The stack's most recent events, newest first (a few pages: enough to reach the last deploy)."""
        events: list[dict[str, Any]] = []
        token = None
        cfn = self._client("cloudformation")
        with self._aws(f"read the events of stack {self.stack_name}"):
            for _ in range(max_pages):
                kwargs = {"StackName": self.stack_name, **({"NextToken": token} if token else {})}
                page = cfn.describe_stack_events(**kwargs)
                events += page.get("StackEvents", [])
                token = page.get("NextToken")
                if not token:
                    break
        return events

    def _stack_missing_message(self) -> str:
        where = ""
        if self.stack_name == DEFAULT_STACK_NAME and settings_file() is None:
            # The name no file gave: a settings file elsewhere may name the stack that was deployed.
            where = (
                f" (the default name: no {SETTINGS_FILE} in {Path.cwd()} or above it; run from the checkout "
                "you deployed from)"
            )
        return (
            f"stack {self.stack_name} not found in {self.region}{where}: deploy it with "
            "`cdk deploy` (docs/deploy.md) or pass --stack, or --region if it was deployed to another region"
        )

    def url(self) -> str:
        """The DCV browser URL (stable across stop/start because it is built from the Elastic IP)."""
        return self.outputs().dcv_url

    def dcv_password(self) -> str:
        """The DCV password: the current (AWSCURRENT) version of the secret in the DcvPasswordSecret output.

        The host applies a version only when its setup runs (the first boot and each in-place update), so a
        version put into the secret since then is printed here but refused by DCV until the next update.
        """
        from botocore.exceptions import ClientError  # noqa: PLC0415

        secret = self.outputs().dcv_password_secret
        if not secret:
            raise StackOutputsError(
                f"stack {self.stack_name} in {self.region} has no output {OUTPUT_DCV_PASSWORD_SECRET}; it is "
                "not the twin stack or its deploy did not finish: redeploy with `cdk deploy` or pass the "
                "right --stack"
            )
        client = self._client("secretsmanager")
        with self._aws(f"read the DCV password secret {secret}"):
            try:
                value = client.get_secret_value(SecretId=secret)
            except ClientError as exc:
                error = _secret_error(exc, secret)
                if error is None:
                    raise
                raise error from exc
        if "SecretString" not in value:
            raise AwsCallError(
                f"the DCV password secret {secret} holds binary data, not the text password the stack "
                "generates: it was changed outside the stack; put the password back as text with `aws "
                f"secretsmanager put-secret-value --secret-id {secret} --secret-string ...`, then run the "
                "host's update (docs/deploy.md, Log in), which fails its password step until then"
            )
        return str(value["SecretString"])

    def settings(self) -> DeployedSettings:
        """The settings the stack was deployed with; StackOutputsError when it does not publish them."""
        from twin.ops.deployed_settings import DeployedSettingsError, parse_deployed_settings  # noqa: PLC0415

        try:
            return parse_deployed_settings(self.outputs().settings, self.stack_name)
        except DeployedSettingsError as exc:
            raise StackOutputsError(str(exc)) from exc

    # --- instance ----------------------------------------------------------------------------------

    def describe_instance(self) -> dict[str, Any]:
        """The instance as DescribeInstances returns it."""
        return self._describe()

    def _describe(self) -> dict[str, Any]:
        from botocore.exceptions import ClientError  # noqa: PLC0415

        instance_id = self.outputs().instance_id
        with self._aws(f"describe instance {instance_id}"):
            try:
                reservations = self._client("ec2").describe_instances(InstanceIds=[instance_id])
            except ClientError as exc:
                if exc.response.get("Error", {}).get("Code") == INSTANCE_NOT_FOUND:
                    raise self._gone(instance_id) from exc
                raise
        instances = [i for r in reservations["Reservations"] for i in r.get("Instances", [])]
        if not instances:
            raise self._gone(instance_id)
        return instances[0]

    def _gone(self, instance_id: str) -> InstanceGoneError:
        """The stack's instance unknown to EC2: terminated more than about an hour ago (EC2 lists a terminated
        instance for about that long, and an account's cleanup may be noticed days later)."""
        return InstanceGoneError(
            f"instance {instance_id} of stack {self.stack_name} no longer exists: it was terminated, and EC2 "
            f"forgets a terminated instance about an hour later. {self.new_host_advice()}"
        )

    def state(self) -> str:
        return self._describe()["State"]["Name"]

    def start(self, wait: bool = True, timeout_s: float = 900.0) -> str:
        """Start the instance; with `wait`, return once it is running. Returns the state last seen."""
        from botocore.exceptions import ClientError  # noqa: PLC0415

        instance_id = self.outputs().instance_id
        log.info("starting %s", instance_id)
        with self._aws(f"start instance {instance_id}"):
            try:
                response = self._client("ec2").start_instances(InstanceIds=[instance_id])
            except ClientError as exc:
                code = exc.response.get("Error", {}).get("Code")
                if code == "InsufficientInstanceCapacity":
                    raise self._capacity_error(exc) from exc
                if code == "IncorrectInstanceState":
                    raise self._not_now("start", "stopped") from exc
                raise
        state = response["StartingInstances"][0]["CurrentState"]["Name"]
        if wait:
            self._wait("instance_running", "running", timeout_s)
            state = "running"
        return state

    def stop(self, wait: bool = True, timeout_s: float = 900.0) -> str:
        """Stop the instance (EBS and the Elastic IP stay); with `wait`, return once it is stopped."""
        from botocore.exceptions import ClientError  # noqa: PLC0415

        instance_id = self.outputs().instance_id
        log.info("stopping %s", instance_id)
        with self._aws(f"stop instance {instance_id}"):
            try:
                response = self._client("ec2").stop_instances(InstanceIds=[instance_id])
            except ClientError as exc:
                code = exc.response.get("Error", {}).get("Code")
                if code == "IncorrectInstanceState":
                    raise self._not_now("stop", "running") from exc
                if code == INSTANCE_NOT_FOUND:
                    raise self._gone(instance_id) from exc
                raise
        state = response["StoppingInstances"][0]["CurrentState"]["Name"]
        if wait:
            self._wait("instance_stopped", "stopped", timeout_s)
            state = "stopped"
        return state

    def _not_now(self, action: str, ready: str) -> AwsCallError:
        """EC2's IncorrectInstanceState for `action` (start, stop) as what to do: it refuses to stop an
        instance still starting (pending) and to start one still stopping; `ready`: the state to wait for."""
        done = {"start": "started", "stop": "stopped"}[action]
        instance_id, state = self.outputs().instance_id, self.state()
        if state in TERMINATED_STATES:
            # Waiting would never end: EC2 starts and stops no terminated instance.
            return AwsCallError(
                f"instance {instance_id} cannot be {done}: it is {state}, and EC2 never starts or stops "
                f"a terminated instance. {self.new_host_advice()}"
            )
        return AwsCallError(
            f"instance {instance_id} cannot be {done} now ({state}): wait until it "
            f"is {ready} (`twin instance status`), then {action} it again"
        )

    def new_host_advice(self) -> str:
        """How to build a host in place of a terminated one, with the deployed stack's next hostGeneration:
        a deploy of unchanged settings does nothing, since CloudFormation does not see that it is gone."""
        generation = self._next_generation()
        write = (
            f"write hostGeneration = {generation} into {SETTINGS_FILE}"
            if generation is not None
            # No readable Settings output: a stack from before hostGeneration (its first host), unless the
            # output's version is one this agent cannot read. `twin instance settings` would fail alike.
            else f"raise hostGeneration by one in {SETTINGS_FILE} (write hostGeneration = 2 if it is not "
            "there)"
        )
        return (
            f"Build a new host in its place: {write} and run `cdk deploy -c replaceInstance=true` (about 15 "
            "minutes). It keeps the DCV address and password, and takes from the stack's bucket the history, "
            "the calibrations, the servo alarms and your agent.local.toml; what was only on the old disk "
            '(USD recordings, the console\'s Events list) is gone: docs/deploy.md, "A terminated host"'
        )

    def _next_generation(self) -> int | None:
        """The deployed hostGeneration plus one; None when the stack's Settings output cannot say."""
        try:
            value = self.settings().values.get("hostGeneration", 1)
        except TwinInstanceError:
            return None
        return value + 1 if isinstance(value, int) and not isinstance(value, bool) else None

    def _capacity_error(self, exc: Exception) -> InsufficientCapacityError:
        try:
            described = self._describe()
            instance_type = described.get("InstanceType", "g6e.2xlarge")
            zone = described.get("Placement", {}).get("AvailabilityZone", "its Availability Zone")
        except TwinInstanceError:
            instance_type, zone = "g6e.2xlarge", "its Availability Zone"
        offerings = G6E_OFFERINGS_COMMAND.format(instance_type=instance_type, region=self.region)
        return InsufficientCapacityError(
            f"AWS has no {instance_type} capacity in {zone} right now (InsufficientInstanceCapacity): "
            f"that Availability Zone's {instance_type} capacity is exhausted. Retry in a few minutes, or "
            f"move the host to another zone that offers {instance_type} (list them with `{offerings}`): "
            f'write availabilityZone = "<zone>" into {SETTINGS_FILE} and run '
            f"`cdk deploy -c {REPLACE_FLAG}=true`, which builds a new host there (about 15 minutes; the "
            'replacement guard refuses the move without it: docs/deploy.md, "Changes that replace the '
            'instance"). '
            f"Detail: {exc}"
        )

    def _wait(self, waiter_name: str, target: str, timeout_s: float) -> None:
        from botocore.exceptions import WaiterError  # noqa: PLC0415

        instance_id = self.outputs().instance_id
        delay = max(1, min(int(self.poll_interval_s), int(timeout_s) or 1))
        attempts = max(1, math.ceil(timeout_s / delay))
        log.info("waiting up to %.0f s for %s to be %s", timeout_s, instance_id, target)
        try:
            with self._aws(f"wait for instance {instance_id}"):
                self._client("ec2").get_waiter(waiter_name).wait(
                    InstanceIds=[instance_id], WaiterConfig={"Delay": delay, "MaxAttempts": attempts}
                )
        except WaiterError as exc:
            try:
                now = self.state()
            except TwinInstanceError:
                now = "unknown"
            if "Max attempts exceeded" in str(exc):
                raise WaitError(
                    f"instance {instance_id} was not {target} after {timeout_s:.0f} s (now {now}): "
                    "check again with `twin instance status` or pass a longer --timeout"
                ) from exc
            raise WaitError(f"instance {instance_id} will not become {target}: it is {now} ({exc})") from exc

    # --- health ------------------------------------------------------------------------------------

    def run_on_host(self, commands: list[str], comment: str, timeout_s: float = 60.0) -> HostCommand:
        """Run shell commands on the host through SSM Run Command and wait for them; never raises.

        `problem` says why when SSM could not run them or they did not finish within `timeout_s`.
        """
        from botocore.exceptions import BotoCoreError, ClientError  # noqa: PLC0415

        instance_id = self.outputs().instance_id
        ssm = self._client("ssm")
        try:
            sent = ssm.send_command(
                InstanceIds=[instance_id],
                DocumentName="AWS-RunShellScript",
                Comment=comment,
                Parameters={"commands": commands},
                TimeoutSeconds=max(30, math.ceil(timeout_s)),
            )
        except ClientError as exc:
            error = exc.response.get("Error", {})
            if error.get("Code") == "InvalidInstanceId":
                # SSM says this both before the agent's first registration and while it is offline.
                return HostCommand("NotSent", problem="the SSM agent has not registered yet")
            return HostCommand(
                "NotSent",
                problem=f"SSM could not run the check ({error.get('Code')}: {error.get('Message')})",
            )
        except BotoCoreError as exc:
            return HostCommand("NotSent", problem=f"SSM could not run the check ({exc})")
        command_id = sent["Command"]["CommandId"]
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                invocation = ssm.get_command_invocation(CommandId=command_id, InstanceId=instance_id)
            except ClientError as exc:
                # The invocation appears a moment after send_command returns.
                if exc.response.get("Error", {}).get("Code") != "InvocationDoesNotExist":
                    return HostCommand("Lost", problem=f"SSM lost the check ({exc})")
                invocation = {"Status": "Pending"}
            except BotoCoreError as exc:
                return HostCommand("Lost", problem=f"SSM lost the check ({exc})")
            status = invocation.get("Status", "Pending")
            if status not in _SSM_PENDING:
                break
            if time.monotonic() >= deadline:
                return HostCommand(
                    status,
                    problem=f"the check did not finish within {timeout_s:.0f} s (the host may still be "
                    "booting: ask again with `twin instance status`)",
                )
            time.sleep(self.health_poll_interval_s)
        stdout = invocation.get("StandardOutputContent", "")
        stderr = invocation.get("StandardErrorContent", "")
        # A command that exits non-zero (curl with nothing listening) still printed something: keep it.
        if status not in {"Success", "Failed"} and not stdout.strip():
            return HostCommand(status, stdout, stderr, problem=f"the check ended {status}")
        return HostCommand(status, stdout, stderr)

    def health(self, timeout_s: float = 60.0) -> AgentHealth:
        """Ask the agent's /healthz (and the deployed version) through SSM Run Command; never raises."""
        result = self.run_on_host(STATUS_COMMANDS, "twin instance: agent /healthz", timeout_s)
        if result.problem:
            return AgentHealth(UNKNOWN, result.problem)
        return parse_health_output(result.stdout)

    def start_verdict(self, timeout_s: float = 900.0) -> StartVerdict:
        """Wait for the verdict of the host checks of this boot (so101-twin-start.service); never raises."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = max(0.0, deadline - time.monotonic())
            result = self.run_on_host(
                START_VERDICT_COMMANDS,
                "twin instance start: verdict of the start checks",
                min(60.0, remaining),
            )
            verdict = None if result.problem else parse_start_verdict(result.stdout)
            if verdict is not None:
                return verdict
            waiting = result.problem or "the start checks have not finished yet"
            if time.monotonic() >= deadline:
                return StartVerdict(
                    UNKNOWN,
                    f"none within {timeout_s:.0f} s ({waiting}); ask again with `twin instance check`, "
                    f"or read {LAST_START_FILE} and `journalctl -u so101-twin-start` on the host",
                )
            log.info("start checks: %s", waiting)
            time.sleep(min(self.poll_interval_s, max(0.0, deadline - time.monotonic())))

    # --- a port of the host here ---------------------------------------------------------------------

    def forward_port(self, remote_port: int, local_port: int, *, plugin: str | None = None) -> PortForward:
        """`remote_port` of the running host on this machine's 127.0.0.1:`local_port`, through Session
        Manager and its plugin (twin.ops.port_forward); `close()` the result to end it."""
        from twin.ops.port_forward import find_plugin, start_port_forward  # noqa: PLC0415

        path = plugin or find_plugin()  # before any AWS call: a missing plugin leaves no session behind
        instance_id = self.outputs().instance_id
        state = self.state()
        if state in TERMINATED_STATES:
            # "Start it" would fail alike: EC2 starts no terminated instance.
            raise AwsCallError(f"instance {instance_id} is {state}. {self.new_host_advice()}")
        if state != "running":
            raise WaitError(
                f"instance {instance_id} is {state}: start it with `twin instance start`, then run this again"
            )
        with self._aws(f"start a Session Manager session to {instance_id}"):
            return start_port_forward(
                self._client("ssm"),
                instance_id=instance_id,
                remote_port=remote_port,
                local_port=local_port,
                profile=os.environ.get("AWS_PROFILE", ""),
                plugin=path,
            )

    def status(self, check_health: bool = True, health_timeout_s: float = 60.0) -> InstanceStatus:
        """State, type, URL and (when running and asked) agent health."""
        described = self._describe()
        state = described["State"]["Name"]
        health = None
        if check_health:
            if state == "running":
                health = self.health(health_timeout_s)
            else:
                health = AgentHealth(UNKNOWN, f"the instance is {state}")
        return InstanceStatus(
            instance_id=described["InstanceId"],
            state=state,
            instance_type=described.get("InstanceType", "?"),
            availability_zone=described.get("Placement", {}).get("AvailabilityZone"),
            dcv_url=self.url(),
            health=health,
            expected_version=self.outputs().deployment_version,
        )


def _secret_error(exc: Any, secret: str) -> AwsCallError | None:
    """Our message for the ClientError `exc` of GetSecretValue on `secret`, with AWS's own message (an
    explicit deny, a permissions boundary or a KMS refusal all arrive as AccessDenied and differ only
    there); None leaves `exc` to the generic translation."""
    error = exc.response.get("Error", {})
    code, message = error.get("Code", ""), error.get("Message", "")
    if code in ACCESS_DENIED:
        return AwsCallError(
            f"not allowed to read the DCV password secret {secret} ({code}: {message}): use credentials "
            f"allowed secretsmanager:GetSecretValue on {secret}"
        )
    if code == "InvalidRequestException" and "delet" in message.lower():  # AWS: "marked for deletion"
        return AwsCallError(
            f"the DCV password secret {secret} is scheduled for deletion ({code}: {message}): restore it "
            f"with `aws secretsmanager restore-secret --secret-id {secret}`"
        )
    if code == "ResourceNotFoundException":
        # CloudFormation does not notice a resource deleted behind its back: a plain deploy keeps it gone.
        return AwsCallError(
            f"the DCV password secret {secret} no longer exists ({code}: {message}): it was deleted outside "
            "the stack, and `cdk deploy` does not recreate it; `cdk destroy` then `cdk deploy` makes a new "
            "one (docs/deploy.md, Destroy, says what is kept)"
        )
    return None
