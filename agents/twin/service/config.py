"""The agent's configuration: one typed, frozen object loaded once from a TOML file plus flag overrides.

Every value is validated when the file is loaded, not when it is first used, so a bad deployment fails at
start-up with a message that names the key, the bad value and the fix. Unknown sections and keys are
errors too: a misspelt key (`offline_after` for `offline_after_s`) would otherwise leave the default
silently in force. The key names are the contract with the CDK UserData that renders this file on the
instance (docs/configuration.md).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

from twin.core.alarms import AlarmThresholds
from twin.core.health import HealthThresholds
from twin.core.locations import location_problem
from twin.core.modes import TwinMode
from twin.core.topics import (
    ALL_DEVICES,
    DEFAULT_TOPIC_PREFIX,
    TopicError,
    check_devices,
    check_topic_prefix,
    listed_device_notes,
)
from twin.core.units import MAX_PAYLOAD_BYTES, Units
from twin.output.rerun_settings import RerunSettings, RerunSettingsError
from twin.output.ros2 import Ros2Error, Ros2Settings
from twin.robot.calibration import leader_problem, load_calibration
from twin.transport.broker import IOT, BrokerConfig, BrokerConfigError
from twin.transport.plan import (
    IOT_PUBLISHES_PER_CONNECTION,
    SAFETY_MARGIN,
    PoolSettings,
    default_limit,
    devices_per_connection,
)

RECORD_FORMAT_CHOICES: tuple[str, ...] = ("usdc", "usda")
LOG_LEVELS: tuple[str, ...] = ("DEBUG", "INFO", "WARNING", "ERROR")
# The agent's HTTP API (state, metrics, health): loopback only by default, because it has no authentication.
# The viewer, `twin instance` (health through SSM) and the instance's config all point here.
DEFAULT_HTTP_HOST = "127.0.0.1"
DEFAULT_HTTP_PORT = 8080
DEFAULT_AGENT_URL = f"http://{DEFAULT_HTTP_HOST}:{DEFAULT_HTTP_PORT}"
# More worker processes than this is a typo, not a fleet (docs/scaling.md, "Workers").
MAX_WORKERS = 64
# [twin] events_capacity by default: service.events.DEFAULT_CAPACITY (a test holds the two equal). Not
# imported from there: reading a config imports no third-party package (events needs msgspec), which
# `twin --help` and the host's config checks rely on (tests/infra install the package with none).
DEFAULT_EVENTS_CAPACITY = 20_000
# [twin] events_capacity: below this a store holds too few to page through or to count a session's alarms;
# above it the Sessions page and the exports (which read at most 100,000 events) would see a part of it.
MIN_EVENTS_CAPACITY = 100
MAX_EVENTS_CAPACITY = 100_000
# The largest payload cap a config may set (the default is IoT Core's 128 KiB).
MAX_PAYLOAD_LIMIT_BYTES = 1 << 20
# twin.output.alerts.MAX_FLUSH_S, as a plain number so loading a config imports no output module.
MAX_ALERT_FLUSH_S = 9.5
# Linux's lowest priority (the largest nice value).
MAX_NICE = 19
_SNS_ARN_RE = re.compile(r"^arn:aws[a-z-]*:sns:[a-z0-9-]+:\d{12}:[A-Za-z0-9_-]{1,256}(\.fifo)?$")


class ConfigError(ValueError):
    """A configuration value is missing, unknown or invalid; the message says which key and how to fix it."""


# The [broker] section is the subscriber's broker settings themselves: one definition, validated as loaded.
BrokerSection = BrokerConfig


@dataclass(frozen=True)
class TelemetrySection:
    topic_prefix: str = DEFAULT_TOPIC_PREFIX
    # The whole fleet under the prefix by default: a new user pointing the agent at a broker sees every arm.
    devices: tuple[str, ...] = (ALL_DEVICES,)
    units: Units = Units.AUTO
    # One LeRobot calibration file for every arm without its own (empty: the nominal SO-101).
    calibration: str = ""
    # Where each arm's own calibration is kept, as <device>.json: a directory or s3://bucket/prefix (the
    # stack renders its bucket's calibration/ prefix); empty: none. Watched every calibration_poll_s
    # (twin.service.calibrations).
    calibrations: str = ""
    calibration_poll_s: float = 30.0
    max_payload_bytes: int = MAX_PAYLOAD_BYTES
    # One host mirrors about this many arms, and the account's default IoT Core publish quota carries as many
    # at 10 Hz; a device counts once it has sent valid telemetry (service.admission).
    max_devices: int = 2000
    # An arm silent this long (OFFLINE), with no alarm waiting for a person, is forgotten as an operator would
    # forget it (its place in max_devices goes to a new arm); 0: never (twin.service.agent, long_offline).
    forget_offline_after_s: float = 0.0
    # An arm silent this long is forgotten even with alarms no person has seen, each named in a WARNING
    # event: else a fleet whose arms leave with an alarm up fills max_devices for good; 0: never.
    forget_unseen_after_s: float = 0.0

    @property
    def all_devices(self) -> bool:
        return self.devices == (ALL_DEVICES,)


@dataclass(frozen=True)
class TwinSection:
    mode: TwinMode = TwinMode.KINEMATIC
    model: str = ""
    record_dir: str = ""
    # usdc by default: a binary layer saves incrementally, while a text layer is rewritten whole on every
    # flush, which grows to most of a second per save after an hour of recording (docs/robot-model.md).
    record_format: str = "usdc"
    physics_rate_hz: float = 200.0
    record_flush_s: float = 2.0
    # Processes that mirror the fleet, each a share of the devices (docs/scaling.md, "Workers"); 0 = one per
    # usable core for the whole fleet, fewer for a small listed one (twin.service.workerstart.worker_count).
    workers: int = 0
    # The recording rotates to a new session file once its file reaches record_max_mb or it is
    # record_max_age_s old, and the oldest session files in record_dir are deleted while they take more than
    # record_budget_mb together (docs/agent.md, "Bounds"). A USD stage also lives in memory while it records:
    # rotation bounds that too.
    record_max_mb: float = 256.0
    record_max_age_s: float = 3600.0
    record_budget_mb: float = 4096.0
    # Each arm is recorded at most this often (samples a second; the rest are counted as skipped): authoring
    # a USD sample costs about a millisecond, so a large fleet at 10 Hz is more than one thread can record.
    record_rate_hz: float = 10.0
    # Where the agent keeps the servo alarms a restart must not forget (ACTIVE, ACKNOWLEDGED, LATCHED;
    # service.persist): a file under the service's state directory on the host; "" = not kept.
    state_file: str = ""
    # Where the agent's events are appended, to be read back at its next start (service.event_journal): the
    # Events page and the sessions' alarm counts over a restart; "" = kept in memory only.
    events_file: str = ""
    # How many events the agent's store keeps, and each worker's (service.events): about 300 bytes each. The
    # alarms, calibration, agent, worker and broker events keep half of it from the status, rejected and
    # twin events' floods, and the last four a twentieth of it from an alarm flood.
    events_capacity: int = DEFAULT_EVENTS_CAPACITY
    # How long `stop` may take in all: the workers handle what is queued and flush their sinks (history's
    # last commit) within it, and are killed after it. systemd's TimeoutStopSec must be longer.
    shutdown_budget_s: float = 60.0


# The [health] section is the health thresholds themselves: one definition, used as loaded.
HealthSection = HealthThresholds


@dataclass(frozen=True)
class HttpSection:
    """The HTTP API and the operator console (docs/http-api.md, docs/console.md)."""

    listen: str = f"{DEFAULT_HTTP_HOST}:{DEFAULT_HTTP_PORT}"
    stream_rate_hz: float = 30.0
    # Host names (or addresses) the server answers to besides the loopback ones: a page that reaches it
    # under any other name (DNS rebinding) is refused. Add the name a non-loopback listener is reached by.
    allowed_hosts: tuple[str, ...] = ()
    # At most this many connections at once (more get 503): viewers, scrapes and console tabs are a handful.
    max_connections: int = 64
    # A request head or body that stalls, or a client that stops reading, is cut off after this long.
    timeout_s: float = 10.0
    # The largest request body accepted (the one POST takes none).
    max_body_bytes: int = 65536
    # How often the console's pages are updated (the fleet summary, an arm's page, the events tail).
    console_rate_hz: float = 2.0
    # A device's telemetry history splits into sessions at gaps longer than this (the Sessions page).
    session_gap_s: float = 30.0
    # The Sessions page's files kept on disk for the next request, at most this much in all (MB).
    session_files_mb: int = 1024

    @property
    def host(self) -> str:
        return _split_listen(self.listen)[0]

    @property
    def port(self) -> int:
        return _split_listen(self.listen)[1]


@dataclass(frozen=True)
class HistorySection:
    """Telemetry history in Delta Lake (docs/history.md); `uri` empty = off. The defaults are
    twin.output.history.HistorySettings' (tests/test_config.py keeps the two in step)."""

    uri: str = ""
    region: str = ""
    commit_every_s: float = 10.0
    commit_every_rows: int = 50_000
    max_buffer_rows: int = 200_000
    queue_max: int = 30_000
    maintain_every_s: float = 3600.0
    vacuum_retention_hours: float = 24.0
    # Days of history kept; 0 = all (the default, so an upgrade removes no one's rows).
    keep_days: int = 0
    # How much nicer than the mirrors the writer process runs (twin.output.history_feed.WRITER_NICE says why
    # 5; a host with cores to spare may run it at 0).
    writer_nice: int = 5

    @property
    def enabled(self) -> bool:
        return bool(self.uri.strip())


@dataclass(frozen=True)
class LogSection:
    level: str = "INFO"


# The [alarms] section is the servo alarm thresholds themselves (docs/servo-health.md lists every key).
AlarmsSection = AlarmThresholds


@dataclass(frozen=True)
class CloudWatchSection:
    """CloudWatch metrics as Embedded Metric Format lines (docs/servo-health.md); off while emf_file is empty.

    `agent_name` is the metrics' Agent dimension: the stack renders its own name here, and its alarms watch
    that value.
    """

    emf_file: str = ""
    agent_name: str = "so101-twin"
    interval_s: float = 60.0


@dataclass(frozen=True)
class AlertsSection:
    """Servo alarm transitions sent to an SNS topic, batched and rate-limited (twin.output.alerts;
    docs/servo-health.md, "Alarm e-mails"); off while topic_arn is empty. The twin host's config names the
    stack's alarm topic."""

    topic_arn: str = ""
    region: str = ""
    # Critical alarms are always sent; warnings too when this is true (the stack's alarmWarnings).
    warnings: bool = False
    flush_s: float = 5.0
    max_per_hour: int = 30
    burst: int = 10

    @property
    def enabled(self) -> bool:
        return bool(self.topic_arn.strip())


# The [ros2] section is the ROS 2 bridge's settings themselves (docs/ros2.md); they validate themselves.
Ros2Section = Ros2Settings

# The [rerun] section is the Rerun sink's settings themselves (off unless `save` or `serve`; docs/web.md).
RerunSection = RerunSettings


@dataclass(frozen=True)
class AgentConfig:
    broker: BrokerSection = field(default_factory=BrokerSection)
    telemetry: TelemetrySection = field(default_factory=TelemetrySection)
    twin: TwinSection = field(default_factory=TwinSection)
    health: HealthSection = field(default_factory=HealthSection)
    http: HttpSection = field(default_factory=HttpSection)
    history: HistorySection = field(default_factory=HistorySection)
    log: LogSection = field(default_factory=LogSection)
    alarms: AlarmsSection = field(default_factory=AlarmsSection)
    cloudwatch: CloudWatchSection = field(default_factory=CloudWatchSection)
    alerts: AlertsSection = field(default_factory=AlertsSection)
    ros2: Ros2Section = field(default_factory=Ros2Section)
    rerun: RerunSection = field(default_factory=RerunSection)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """The effective configuration as TOML-shaped sections (logged at start-up, served nowhere)."""
        out = dataclasses.asdict(self)
        out["telemetry"]["devices"] = list(self.telemetry.devices)
        out["ros2"]["joint_names"] = list(self.ros2.joint_names)
        out["ros2"]["peers"] = list(self.ros2.peers)
        return out


_SECTIONS: dict[str, type] = {
    "broker": BrokerSection,
    "telemetry": TelemetrySection,
    "twin": TwinSection,
    "health": HealthSection,
    "http": HttpSection,
    "history": HistorySection,
    "log": LogSection,
    "alarms": AlarmsSection,
    "cloudwatch": CloudWatchSection,
    "alerts": AlertsSection,
    "ros2": Ros2Section,
    "rerun": RerunSection,
}


def _suggest(name: str, choices: list[str]) -> str:
    close = difflib.get_close_matches(name, choices, n=1)
    return f"did you mean '{close[0]}'? " if close else ""


def _file_in_the_way(path: Path) -> Path | None:
    """The nearest existing ancestor of `path` when it is not a directory (the file cannot be made there)."""
    for parent in path.absolute().parents:
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


def _elsewhere(key: str) -> str:
    """Where a key given in the wrong section belongs ("" when no section has it)."""
    homes = [name for name, cls in _SECTIONS.items() if key in {f.name for f in dataclasses.fields(cls)}]
    return f"'{key}' is a key of [{'], ['.join(homes)}]; " if homes else ""


def _split_listen(listen: str) -> tuple[str, int]:
    host, sep, port_text = listen.rpartition(":")
    if not sep or not host or not port_text.isdigit():
        raise ConfigError(
            f"http.listen = {listen!r} is not HOST:PORT; use e.g. '{DEFAULT_HTTP_HOST}:{DEFAULT_HTTP_PORT}' "
            "(port 0 picks a free port)"
        )
    port = int(port_text)
    if not 0 <= port <= 65535:
        raise ConfigError(f"http.listen = {listen!r}: port {port} is outside 0..65535")
    return host.strip("[]"), port


# What each choice means, after the list of choices in the message for a value that is none of them.
_CHOICE_HINTS: dict[str, str] = {
    "telemetry.units": "ticks for raw servo positions, degrees or range100 for LeRobot-normalised ones, "
    "auto to infer per device",
    "twin.mode": "kinematic mirrors the measured pose, physics drives a simulated arm toward it",
}


def _expect_type(key: str, value: Any, default: Any) -> Any:
    """Coerce TOML/flag values to the type of the field's default, refusing anything surprising."""
    short = key.rsplit(".", maxsplit=1)[-1]
    if isinstance(default, Enum):
        return _expect_choice(key, value, type(default))
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{key} = {value!r} must be true or false")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key} = {value!r} must be a whole number, e.g. {short} = {default}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key} = {value!r} must be a number, e.g. {short} = {default}")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{key} = {value!r} must be a finite number")
        return value
    if isinstance(default, tuple):
        if isinstance(value, str):
            # A flag or a hand-written `devices = "arm-001"`: accept a comma-separated list.
            value = [part.strip() for part in value.split(",") if part.strip()]
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f'{key} = {value!r} must be a list of strings, e.g. {short} = ["arm-001"]')
        return tuple(value)
    if not isinstance(value, str):
        raise ConfigError(f'{key} = {value!r} must be a string, e.g. {short} = "{default}"')
    return value


def _expect_choice(key: str, value: object, choices: type[Enum]) -> Enum:
    """The member of `choices` whose value `value` is; ConfigError listing the values otherwise."""
    values = [str(member.value) for member in choices]
    if isinstance(value, str):
        for member in choices:
            if member.value == value:
                return member
    suggestion = _suggest(value, values) if isinstance(value, str) else ""
    raise ConfigError(
        f"{key} = {value!r} is not one of {', '.join(values)}; {suggestion}{_CHOICE_HINTS.get(key, '')}"
    )


def _build_section(name: str, cls: type, values: Mapping[str, Any]) -> Any:
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in values.items():
        if key not in fields:
            raise ConfigError(
                f"unknown key '{name}.{key}'; {_suggest(key, list(fields)) or _elsewhere(key)}"
                f"the [{name}] keys are: {', '.join(fields)}"
            )
        default = cls()
        kwargs[key] = _expect_type(f"{name}.{key}", value, getattr(default, key))
    try:
        return cls(**kwargs)
    except (BrokerConfigError, Ros2Error) as exc:  # sections that validate themselves name their keys already
        raise ConfigError(str(exc)) from None
    except ValueError as exc:  # [alarms] validates itself; its messages name the key
        raise ConfigError(f"[{name}]: {exc}") from None


def _positive(key: str, value: float) -> None:
    if value <= 0:
        raise ConfigError(f"{key} = {value!r} must be greater than 0")


# EMF intervals (whole seconds) that put the same number of documents in every minute, for the error's
# advice: every divisor of 60, longest first, so the advice cannot leave one out.
_EMF_INTERVALS = tuple(s for s in range(60, 0, -1) if 60 % s == 0)


def _validate_emf_interval(interval_s: float) -> None:
    """The stack's alarms judge each minute (stacks/monitoring.py): MessagesRefused weighs a minute's Rejects
    (summed) against its MessagesPerSecond (averaged) times 60, and the sustained alarms need a document in
    every minute. Only an interval that divides 60 gives each minute whole intervals, all alike."""
    _positive("cloudwatch.interval_s", interval_s)
    per_minute = 60.0 / interval_s
    if abs(per_minute - round(per_minute)) > 1e-6 * per_minute:
        choices = ", ".join(str(s) for s in _EMF_INTERVALS)
        raise ConfigError(
            f"cloudwatch.interval_s = {interval_s!r} does not divide 60 s: the stack's CloudWatch alarms "
            "judge each minute, and with it some minutes get no document or a part of one (MessagesRefused "
            f"would misjudge the refused share, the sustained alarms miss minutes); set one of {choices} "
            "(60, the default, is the cheapest)"
        )


def validate(config: AgentConfig) -> AgentConfig:
    """Check every cross-field and range rule; returns the config unchanged or raises ConfigError.

    [broker] (BrokerConfig) validated itself when it was built; the other sections are checked here.
    """
    _validate_telemetry(config.telemetry)
    _validate_twin(config.twin)
    _validate_health(config.health)
    _validate_forget(config.telemetry, config.health)
    _validate_http(config.http)
    _validate_emf_interval(config.cloudwatch.interval_s)
    if config.cloudwatch.emf_file and not config.cloudwatch.agent_name:
        raise ConfigError("cloudwatch.agent_name is empty; name the agent (the stack renders its stack name)")
    _validate_history(config.history)
    _validate_alerts(config.alerts)
    if config.log.level.upper() not in LOG_LEVELS:
        raise ConfigError(f"log.level = {config.log.level!r} is not one of {', '.join(LOG_LEVELS)}")
    _validate_ros2(config.ros2, config.telemetry)
    try:
        config.rerun.validate()
    except RerunSettingsError as exc:
        raise ConfigError(str(exc)) from None
    if config.rerun.enabled and config.twin.workers > 1:
        raise ConfigError(
            f"twin.workers = {config.twin.workers} with [rerun] on: the Rerun stream is one recording from "
            "one process; set workers = 1 (or 0, which picks 1 while [rerun] is on), or turn [rerun] off"
        )
    return config


def _validate_http(h: HttpSection) -> None:
    _split_listen(h.listen)
    _positive("http.stream_rate_hz", h.stream_rate_hz)
    _positive("http.timeout_s", h.timeout_s)
    _positive("http.console_rate_hz", h.console_rate_hz)
    _positive("http.session_gap_s", h.session_gap_s)
    if not 1 <= h.session_files_mb <= 1_000_000:
        raise ConfigError(f"http.session_files_mb = {h.session_files_mb} is outside 1..1000000")
    if h.console_rate_hz > h.stream_rate_hz:
        raise ConfigError(
            f"http.console_rate_hz = {h.console_rate_hz} is above stream_rate_hz = {h.stream_rate_hz}; the "
            "console needs no more than the stream (2 is plenty for people)"
        )
    if not 1 <= h.max_connections <= 10_000:
        raise ConfigError(f"http.max_connections = {h.max_connections} is outside 1..10000")
    if not 1024 <= h.max_body_bytes <= MAX_PAYLOAD_LIMIT_BYTES:
        raise ConfigError(
            f"http.max_body_bytes = {h.max_body_bytes} is outside 1024..{MAX_PAYLOAD_LIMIT_BYTES}"
        )
    for name in h.allowed_hosts:
        if not name.strip() or any(c in name for c in "/ ,*@") or name.count(":") == 1:
            raise ConfigError(
                f"http.allowed_hosts: {name!r} is not a host name; list names or addresses without scheme, "
                'port or wildcard, e.g. allowed_hosts = ["twin.example.internal", "10.0.1.5"]'
            )


def _validate_telemetry(t: TelemetrySection) -> None:
    try:
        check_topic_prefix(t.topic_prefix)
    except TopicError as exc:
        raise ConfigError(f"telemetry.topic_prefix = {t.topic_prefix!r}: {exc}") from None
    try:
        check_devices(t.devices)
    except TopicError as exc:
        raise ConfigError(
            f'telemetry.devices = {list(t.devices)!r}: {exc}; list device ids, or ["*"] alone for the fleet'
        ) from None
    if t.calibration and Path(t.calibration).is_dir():
        raise ConfigError(
            f"telemetry.calibration = {t.calibration!r} is a directory; it names one LeRobot calibration "
            "JSON for every arm. For each arm's own file (<device>.json in a directory), set "
            f"telemetry.calibrations = {t.calibration!r} instead"
        )
    if t.calibration and not Path(t.calibration).is_file():
        raise ConfigError(
            f"telemetry.calibration = {t.calibration!r} does not exist; give the LeRobot calibration JSON "
            "(~/.cache/huggingface/lerobot/calibration/robots/so_follower/<id>.json) or leave it empty"
        )
    problem = leader_problem(t.calibration) if t.calibration else None
    if problem:
        raise ConfigError(f"telemetry.calibration = {t.calibration!r} {problem}; give that one")
    if t.calibration:
        # Read here, not only when the mirror starts: `twin config check` (and the host's saver, which runs
        # it) would call a file the agent then refuses valid, and the agent would stop after subscribing.
        try:
            load_calibration(t.calibration)
        except ValueError as exc:
            raise ConfigError(f"telemetry.calibration = {t.calibration!r}: {exc}") from None
    store = t.calibrations.strip()
    problem = location_problem(store)
    if problem:
        raise ConfigError(
            f"telemetry.calibrations = {t.calibrations!r} {problem}; e.g. "
            'calibrations = "s3://<bucket>/calibration" (or "" for none)'
        )
    if "://" not in store and store and Path(store).expanduser().is_file():
        raise ConfigError(
            f"telemetry.calibrations = {t.calibrations!r} is a file; give the directory that holds "
            "<device>.json files (one file for every arm is telemetry.calibration)"
        )
    if not 1.0 <= t.calibration_poll_s <= 3600.0:
        raise ConfigError(
            f"telemetry.calibration_poll_s = {t.calibration_poll_s:g} is outside 1..3600 seconds; e.g. 30"
        )
    if not 1024 <= t.max_payload_bytes <= MAX_PAYLOAD_LIMIT_BYTES:
        raise ConfigError(
            f"telemetry.max_payload_bytes = {t.max_payload_bytes} is outside 1024..{MAX_PAYLOAD_LIMIT_BYTES} "
            f"(IoT Core caps a message at {MAX_PAYLOAD_BYTES})"
        )

    _validate_admission(t)


def _validate_admission(t: TelemetrySection) -> None:
    if not 1 <= t.max_devices <= 10000:
        raise ConfigError(
            f"telemetry.max_devices = {t.max_devices} is outside 1..10000; it bounds how many twins a fleet "
            'subscription (devices = ["*"]) may create'
        )
    listed = 0 if t.all_devices else len(t.devices)
    if listed > t.max_devices:
        # The fleet's bound holds for a list too: a walk listed 10,001 ids and the pool planned 1,251
        # connections for them without a word.
        raise ConfigError(
            f"telemetry.devices lists {listed} arms, more than telemetry.max_devices = {t.max_devices}, the "
            "twins one agent takes on; raise max_devices (at most 10000) if one host is really to mirror "
            "them all, or split them over hosts (docs/scale-out.md)"
        )


def _validate_twin(tw: TwinSection) -> None:
    if tw.model and not Path(tw.model).is_file():
        raise ConfigError(
            f"twin.model = {tw.model!r} does not exist; give an MJCF file or leave it empty (bundled SO-101)"
        )
    if tw.record_dir and Path(tw.record_dir).exists() and not Path(tw.record_dir).is_dir():
        raise ConfigError(
            f"twin.record_dir = {tw.record_dir!r} is a file; give a directory (created if missing)"
        )
    if tw.record_format not in RECORD_FORMAT_CHOICES:
        raise ConfigError(
            f"twin.record_format = {tw.record_format!r} is not one of {', '.join(RECORD_FORMAT_CHOICES)}; "
            "usdc (binary, for long sessions) or usda (text, readable, for short ones)"
        )
    _positive("twin.physics_rate_hz", tw.physics_rate_hz)
    _positive("twin.record_flush_s", tw.record_flush_s)
    for key in ("record_max_mb", "record_max_age_s", "record_budget_mb", "record_rate_hz"):
        _positive(f"twin.{key}", getattr(tw, key))
    if tw.record_budget_mb < tw.record_max_mb:
        raise ConfigError(
            f"twin.record_budget_mb = {tw.record_budget_mb:g} is below record_max_mb = {tw.record_max_mb:g}: "
            "the budget must hold at least the session being recorded; raise it or lower record_max_mb"
        )
    for key, example in (("state_file", "state.json"), ("events_file", "events.jsonl")):
        path = getattr(tw, key)
        if path and Path(path).is_dir():
            raise ConfigError(
                f"twin.{key} = {path!r} is a directory; give a file in it, e.g. {str(Path(path) / example)!r}"
            )
        blocked = _file_in_the_way(Path(path)) if path else None
        if blocked is not None:
            raise ConfigError(
                f"twin.{key} = {path!r} cannot be made: {str(blocked)!r} is a file, not a directory; give a "
                f"path in a directory, e.g. {str(blocked.parent / example)!r}"
            )
    if not MIN_EVENTS_CAPACITY <= tw.events_capacity <= MAX_EVENTS_CAPACITY:
        raise ConfigError(
            f"twin.events_capacity = {tw.events_capacity} is outside {MIN_EVENTS_CAPACITY}.."
            f"{MAX_EVENTS_CAPACITY}; set it in that range (the default {DEFAULT_EVENTS_CAPACITY} takes about "
            "6 MB at 300 bytes an event)"
        )
    if not 10.0 <= tw.shutdown_budget_s <= 600.0:
        raise ConfigError(
            f"twin.shutdown_budget_s = {tw.shutdown_budget_s:g} is outside 10..600 seconds; the workers need "
            "time to flush history on stop, and systemd's TimeoutStopSec must cover it"
        )
    if not 0 <= tw.workers <= MAX_WORKERS:
        raise ConfigError(
            f"twin.workers = {tw.workers} is outside 0..{MAX_WORKERS}; 0 picks one per core, 1 runs "
            "everything in one process"
        )


def _validate_ros2(r: Ros2Section, t: TelemetrySection) -> None:
    # [ros2] validated itself; what is left is how it meets the device list.
    if r.enabled and r.fixed_topic and not t.all_devices and len(t.devices) > 1:
        raise ConfigError(
            f"ros2.topic = {r.topic!r} is one topic for {len(t.devices)} devices, whose messages would "
            'interleave; use a topic with {arm} (topic = "/{arm}/joint_states") or mirror one device'
        )


def _validate_health(h: HealthThresholds) -> None:
    _positive("health.expected_rate_hz", h.expected_rate_hz)
    _positive("health.stale_periods", h.stale_periods)
    _positive("health.offline_after_s", h.offline_after_s)
    _positive("health.window_s", h.window_s)
    if h.offline_after_s <= h.stale_after_s:
        raise ConfigError(
            f"health.offline_after_s = {h.offline_after_s} must be longer than the stale time "
            f"(stale_periods / expected_rate_hz = {h.stale_after_s:g} s); raise offline_after_s"
        )


def _validate_forget(t: TelemetrySection, h: HealthThresholds) -> None:
    after = t.forget_offline_after_s
    if after != 0 and not (math.isfinite(after) and after > h.offline_after_s):
        raise ConfigError(
            f"telemetry.forget_offline_after_s = {after} must be 0 (never) or longer than "
            f"health.offline_after_s = {h.offline_after_s:g} (an arm is forgotten once silent that long); "
            "e.g. 604800 for a week"
        )
    unseen = t.forget_unseen_after_s
    if unseen != 0 and not (math.isfinite(unseen) and after != 0 and unseen >= after):
        raise ConfigError(
            f"telemetry.forget_unseen_after_s = {unseen:g} must be 0 (never) or at least "
            f"telemetry.forget_offline_after_s = {after:g}, itself set (not 0): an arm with alarms no "
            "person has seen is kept longer than one without; e.g. 2592000 for 30 days"
        )


def _validate_alerts(a: AlertsSection) -> None:
    if a.enabled and not _SNS_ARN_RE.match(a.topic_arn.strip()):
        raise ConfigError(
            f"alerts.topic_arn = {a.topic_arn!r} is not an SNS topic ARN; e.g. "
            '"arn:aws:sns:us-east-1:123456789012:alarms" (the stack\'s AlarmTopic output), or "" for none'
        )
    if not 0 < a.flush_s <= MAX_ALERT_FLUSH_S:
        raise ConfigError(
            f"alerts.flush_s = {a.flush_s:g} must be in (0, {MAX_ALERT_FLUSH_S:g}]: a transition is sent on "
            "the flush after it, within 10 s"
        )
    for key in ("max_per_hour", "burst"):
        if getattr(a, key) < 1:
            raise ConfigError(f"alerts.{key} = {getattr(a, key)} must be at least 1")


def _validate_history(hs: HistorySection) -> None:
    if not hs.enabled:
        return
    uri = hs.uri.strip()
    problem = location_problem(uri)
    if problem:
        raise ConfigError(
            f'history.uri = {hs.uri!r} {problem}; e.g. uri = "out/history" or "s3://<bucket>/history"'
        )
    if "://" not in uri and Path(uri).exists() and not Path(uri).is_dir():
        raise ConfigError(f"history.uri = {hs.uri!r} is a file; give a directory (created if missing)")
    if hs.commit_every_s <= 0:
        raise ConfigError(f"history.commit_every_s = {hs.commit_every_s!r} must be greater than 0")
    for key, zero in (("maintain_every_s", "never"), ("vacuum_retention_hours", "files replaced go at once")):
        if getattr(hs, key) < 0:
            raise ConfigError(f"history.{key} = {getattr(hs, key)!r} must be at least 0 (0 = {zero})")
    for key in ("commit_every_rows", "max_buffer_rows", "queue_max"):
        if getattr(hs, key) < 1:
            raise ConfigError(f"history.{key} = {getattr(hs, key)!r} must be at least 1")
    if hs.keep_days < 0:
        raise ConfigError(
            f"history.keep_days = {hs.keep_days} must be at least 0: the whole UTC days of history kept, "
            "e.g. keep_days = 90, or keep_days = 0 to keep everything"
        )
    if hs.max_buffer_rows < hs.commit_every_rows:
        raise ConfigError(
            f"history.max_buffer_rows = {hs.max_buffer_rows} must be at least commit_every_rows = "
            f"{hs.commit_every_rows}"
        )
    if not 0 <= hs.writer_nice <= MAX_NICE:
        raise ConfigError(
            f"history.writer_nice = {hs.writer_nice} must be from 0 (the mirrors' priority) to {MAX_NICE} "
            "(the lowest): the writer may only run at a lower priority than the mirrors, never a higher one"
        )


def config_from_mapping(data: Mapping[str, Any]) -> AgentConfig:
    """Build and validate a config from TOML-shaped data ({section: {key: value}})."""
    sections: dict[str, Any] = {}
    for name, values in data.items():
        if name not in _SECTIONS:
            raise ConfigError(
                f"unknown section [{name}]; {_suggest(name, list(_SECTIONS))}"
                f"the sections are: {', '.join(_SECTIONS)}"
            )
        if not isinstance(values, Mapping):
            raise ConfigError(f"[{name}] must be a table of keys, not {values!r}")
        sections[name] = _build_section(name, _SECTIONS[name], values)
    config = AgentConfig(**sections)
    if config.log.level != config.log.level.upper():
        config = dataclasses.replace(config, log=LogSection(level=config.log.level.upper()))
    return validate(config)


def read_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError as exc:
        # Read for `twin run --config` and `twin config check` alike: the fix names neither flag.
        raise ConfigError(
            f"config file {str(path)!r} not found; check the path, or write one with "
            "`twin config example > FILE`"
        ) from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {str(path)!r} is not valid TOML: {exc}") from exc
    except OSError as exc:
        raise ConfigError(f"config file {str(path)!r} cannot be read: {exc}") from exc


def load_config(
    path: str | Path | Sequence[str | Path] | None = None, overrides: Mapping[str, Any] | None = None
) -> AgentConfig:
    """Load the TOML file (or files, or the defaults when path is None) and apply flag overrides.

    Several files are read in order, each key of a later file winning over the same key of an earlier one:
    the twin host runs with its generated config and then the operator's own file (docs/deploy.md, "What the
    instance runs"). `overrides` maps dotted keys to values, e.g. {"broker.url": "mqtt://127.0.0.1:1883"};
    None values are skipped so an argparse namespace can be passed through without filtering. Overrides win
    over the files.
    """
    paths: list[str | Path] = [] if path is None else [path] if isinstance(path, str | Path) else list(path)
    data: dict[str, Any] = {}
    for one in paths:
        for name, values in read_toml(one).items():
            target = data.get(name)
            if isinstance(values, Mapping) and isinstance(target, dict):
                target.update(values)
            else:
                data[name] = dict(values) if isinstance(values, Mapping) else values
    for dotted, value in (overrides or {}).items():
        if value is None:
            continue
        section, _, key = dotted.partition(".")
        if not key:
            raise ConfigError(f"override {dotted!r} must be 'section.key'")
        target = data.setdefault(section, {})
        if not isinstance(target, dict):
            raise ConfigError(f"[{section}] must be a table of keys, not {target!r}")
        target[key] = value
    try:
        return config_from_mapping(data)
    except ConfigError as exc:
        where = f" (in {', '.join(str(p) for p in paths)})" if paths else ""
        raise ConfigError(f"{exc}{where}") from exc


def pool_settings(config: AgentConfig) -> PoolSettings:
    """The connection pool's settings from the agent's config (the broker's budget, the fleet to plan for)."""
    t = config.telemetry
    return PoolSettings(
        prefix=t.topic_prefix,
        devices=tuple(t.devices),
        rate_hz=config.health.expected_rate_hz,
        limit=default_limit(config.broker),
        max_connections=config.broker.max_connections,
    )


def connection_plan(config: AgentConfig) -> str:
    """The connections the agent would open, and the client id indexes they take: what a broker policy
    (the stack's IAM role) must allow, for `twin config check` to show beside it."""
    settings = pool_settings(config)
    rate, limit = settings.rate_hz, settings.limit
    if limit is None:
        return "connections: 1 (the broker has no per-connection limit); client id index 0"
    iot = config.broker.url == IOT
    if settings.shared:
        k = settings.most_connections(iot=iot)
        arms = limit * SAFETY_MARGIN / rate
        # The fleet's total too: a walk's operator of 40 arms read "about 8 arms" as the pool's whole.
        each = f"about {arms:.0f} arms" if arms >= 1 else "less than one arm"
        return (
            f"connections: 1 to {k} for the whole fleet (broker.max_connections), each planned for "
            f"{limit * SAFETY_MARGIN:g} msg/s, {each} at {rate:g} Hz, so about {k * max(arms, 1):.0f} "
            f"arms in all; client id indexes 0 to {k - 1}"
        )
    k = settings.most_connections(iot=iot)
    per = devices_per_connection(rate, limit, iot=iot)
    return (
        f"connections: {k} for {len(settings.devices)} listed arm(s) at {rate:g} Hz ({per} a connection, "
        f"{limit * SAFETY_MARGIN:g} of its {limit:g} msg/s planned); client id indexes 0 to {k - 1}"
    )


def health_plan(config: AgentConfig) -> str:
    """The rate every arm is expected at and what hangs on it, for `twin config check` to show: a fleet of
    edges slower than the setting read as losing most of their messages and flapped STALE, and nothing said
    which rate the agent expected."""
    h = config.health
    return (
        f"health: each arm expected at {h.expected_rate_hz:g} Hz ([health] expected_rate_hz), STALE after "
        f"{h.stale_after_s:g} s without a valid message, OFFLINE after {h.offline_after_s:g} s; an edge "
        "publishing slower than that reads as losing messages and goes STALE between them"
    )


def config_notes(path: str | Path | Sequence[str | Path] | None, config: AgentConfig) -> list[str]:
    """What a valid config holds that a person likely did not mean, one sentence each with the fix: a key a
    later file sets over an earlier file's different value (the host runs its generated config, then the
    operator's `agent.local.toml`: a stack setting changed there is silently overruled), one arm's
    calibration file used for several arms, a listed id that cannot have a calibration of its own or
    differs from another in case alone, and a servo error alarm that watches no bit. `twin run` logs each
    as a warning; `twin config check` prints them."""
    paths: list[str | Path] = [] if path is None else [path] if isinstance(path, str | Path) else list(path)
    notes: list[str] = []
    set_by: dict[tuple[str, str], tuple[str, Any]] = {}
    for one in paths:
        for section, values in read_toml(one).items():
            if not isinstance(values, Mapping):
                continue
            for key, value in values.items():
                earlier = set_by.get((section, key))
                if earlier is not None and earlier[1] != value:
                    notes.append(
                        f"{one} sets [{section}] {key} = {_shown(value)} over {earlier[0]}'s "
                        f"{_shown(earlier[1])}: the later file wins; if the earlier one is the stack's, "
                        "change the setting there (twin.settings.toml), or take the key out of the later file"
                    )
                set_by[(section, key)] = (str(one), value)
    telemetry = config.telemetry
    notes += listed_device_notes(telemetry.devices)
    several = telemetry.devices == (ALL_DEVICES,) or len(telemetry.devices) > 1
    if telemetry.calibration and several and not telemetry.calibrations:
        arms = (
            "every arm of the fleet"
            if telemetry.devices == (ALL_DEVICES,)
            else (f"all {len(telemetry.devices)} listed arms")
        )
        notes.append(
            f"[telemetry] calibration = {telemetry.calibration!r} is one arm's LeRobot file, used here for "
            f"{arms}: each arm has its own, and another arm's puts its twin in a wrong pose. Keep each arm's "
            'in a store ([telemetry] calibrations = "DIR", then `twin calibration push ARM FILE --store '
            'DIR`; docs/agent.md, "Calibration")'
        )
    notes += _pool_notes(config)
    if config.alarms.enabled and not config.alarms.servo_error_bits:
        notes.append(
            "[alarms] servo_error_bits is empty: no servo error is ever raised, whatever the servos report; "
            "list the bits to watch, or take the key out for all six"
        )
    return notes


def _pool_notes(config: AgentConfig) -> list[str]:
    """A per-connection limit the broker will not honour, or too small for one arm (a walk behind the quota
    proxy: both planned silently, and the broker discarded the excess)."""
    limit, rate = config.broker.per_connection_limit, config.health.expected_rate_hz
    notes = []
    iot = config.broker.url == IOT
    if iot and limit > IOT_PUBLISHES_PER_CONNECTION:
        notes.append(
            f"[broker] per_connection_limit = {limit} is above IoT Core's {IOT_PUBLISHES_PER_CONNECTION} "
            "publishes a second per connection, which cannot be raised: the pool would plan too few "
            "connections and the broker discard the excess; leave it 0 (the broker's own)"
        )
    if iot and (limit == 0 or limit >= IOT_PUBLISHES_PER_CONNECTION):
        notes += _iot_rate_notes(rate)
    elif 0 < limit * SAFETY_MARGIN < rate:
        notes.append(
            f"[broker] per_connection_limit = {limit} carries less than one arm at {rate:g} Hz ([health] "
            f"expected_rate_hz) with the pool's {SAFETY_MARGIN:.0%} margin: each connection takes one arm "
            "and the broker discards the rest of its messages; raise the limit to what the broker allows"
        )
    return notes


def _iot_rate_notes(rate: float) -> list[str]:
    """An arm rate one IoT Core connection does not carry with the pool's margin at IoT Core's own budget,
    which no setting raises: the plan said "about 0 arms" a connection, and nothing why. The rate is what
    can be wrong then, not the limit (a limit set lower by hand can be raised: _pool_notes says so)."""
    limit = IOT_PUBLISHES_PER_CONNECTION
    if rate <= limit * SAFETY_MARGIN:
        return []
    lost = (
        f"and IoT Core discards what passes {limit:g} a second"
        if rate > limit
        else f"within its {limit:g} a second, with none of the margin the pool keeps"
    )
    return [
        f"[health] expected_rate_hz = {rate:g} is more than the pool plans for one IoT Core connection "
        f"({limit * SAFETY_MARGIN:g} of its {limit:g} publishes a second, which cannot be raised): each "
        f"connection takes one arm, {lost}; give the rate the edges publish at (10 Hz for the LeRobot edge)"
    ]


def _shown(value: Any) -> str:
    """A TOML value in a note, cut short when long (a devices list of a large fleet)."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
