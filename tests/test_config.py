"""Agent config: TOML, flag overrides, eager validation with messages naming key, value and fix."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
from twin.core.alarms import AlarmKind, AlarmThresholds
from twin.core.modes import TwinMode
from twin.core.units import Units
from twin.service import events
from twin.service.config import (
    AgentConfig,
    ConfigError,
    HistorySection,
    config_from_mapping,
    load_config,
)

REPO = Path(__file__).resolve().parents[1]

EVERY_KEY_TOML = """
[broker]
url = "iot"
region = ""
endpoint = ""
client_id_prefix = ""
ca_file = ""
[telemetry]
topic_prefix = "dt/lerobot"
devices = ["*"]
units = "auto"
calibration = ""
[twin]
mode = "kinematic"
model = ""
record_dir = ""
[health]
expected_rate_hz = 10.0
stale_periods = 3
offline_after_s = 10.0
[http]
listen = "127.0.0.1:8080"
[log]
level = "INFO"
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "agent.toml"
    path.write_text(text)
    return path


def test_defaults_match_the_agreed_file(tmp_path: Path) -> None:
    # The keys the host's config file has always carried (docs/agent.md, "Configuration reference"): every
    # one must load, and mean the defaults.
    assert load_config(write(tmp_path, EVERY_KEY_TOML)) == AgentConfig()
    assert load_config(None) == AgentConfig()


def test_example_config_loads() -> None:
    config = load_config(REPO / "examples" / "agent.toml")
    assert config.http.host == "127.0.0.1"
    # Every key of the example is its default: the whole fleet, IoT Core's own per-connection budget.
    assert config == AgentConfig()
    assert config.telemetry.all_devices
    assert (config.broker.per_connection_limit, config.broker.max_connections) == (0, 8)
    assert config.history == HistorySection()  # the example lists the defaults
    # The example spells out every [rerun] key at its default.
    assert config.rerun == AgentConfig().rerun


def test_history_section_defaults_match_the_writers() -> None:
    from twin.output.history import HistorySettings
    from twin.output.history_feed import WRITER_NICE

    section, writer = HistorySection(), HistorySettings(uri="x")
    for key in ("commit_every_s", "commit_every_rows", "max_buffer_rows", "queue_max", "maintain_every_s"):
        assert getattr(section, key) == getattr(writer, key), key
    assert section.vacuum_retention_hours == writer.vacuum_retention_hours
    assert section.keep_days == writer.keep_days == 0  # an upgrade deletes no one's history
    assert section.writer_nice == WRITER_NICE
    assert not section.enabled


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        ('[history]\nuri = "gs://b/h"', "is not a directory or s3://bucket/prefix"),
        ('[history]\nuri = "s3:///h"', "names no bucket"),
        # A slash short: read as a URI it sent deltalake to the metadata service before a vague error.
        ('[history]\nuri = "s3:/b/h"', "lacks the '//' after 's3:', as in s3://bucket/prefix"),
        ('[history]\nuri = "h"\ncommit_every_s = 0', "history.commit_every_s = 0.0 must be greater than 0"),
        ('[history]\nuri = "h"\nmax_buffer_rows = 10', "must be at least commit_every_rows"),
        ('[history]\nuri = "h"\nurl = "x"', "unknown key 'history.url'"),
        ('[history]\nuri = "h"\nwriter_nice = -1', "history.writer_nice = -1 must be from 0"),
        ('[history]\nuri = "h"\nwriter_nice = 20', "history.writer_nice = 20 must be from 0"),
        ('[history]\nuri = "h"\nkeep_days = -1', "history.keep_days = -1 must be at least 0"),
        (
            '[history]\nuri = "h"\nvacuum_retention_hours = -1',
            "history.vacuum_retention_hours = -1.0 must be at least 0 (0 = files replaced go at once)",
        ),
        (
            '[history]\nuri = "h"\nmaintain_every_s = -1',
            "history.maintain_every_s = -1.0 must be at least 0 (0 = never)",
        ),
        ('[history]\nuri = "h"\nkeep_days = 1.5', "history.keep_days = 1.5 must be a whole number"),
        ('[history]\nuri = "h"\nkeep_days = "30"', "history.keep_days = '30' must be a whole number"),
    ],
)
def test_history_settings_are_checked(tmp_path: Path, toml: str, message: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_config(write(tmp_path, toml))


@pytest.mark.parametrize("capacity", [0, 99, 100_001, -5])
def test_the_event_store_capacity_is_checked(tmp_path: Path, capacity: int) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, f"[twin]\nevents_capacity = {capacity}\n"))
    assert str(info.value).startswith(f"twin.events_capacity = {capacity} is outside 100..100000; set it")


def test_the_event_store_capacity_is_read(tmp_path: Path) -> None:
    assert AgentConfig().twin.events_capacity == 20_000 == events.DEFAULT_CAPACITY
    assert load_config(write(tmp_path, "[twin]\nevents_capacity = 5000\n")).twin.events_capacity == 5000


def test_history_flag_turns_it_on(tmp_path: Path) -> None:
    config = load_config(None, {"history.uri": str(tmp_path / "h")})
    assert config.history.enabled and config.history.uri == str(tmp_path / "h")


def test_rerun_is_off_unless_saving_or_serving(tmp_path: Path) -> None:
    assert not AgentConfig().rerun.enabled
    config = load_config(
        write(tmp_path, '[rerun]\nsave = "out/fleet.rrd"\nmax_rate_hz = 5\nmemory_limit = "2GiB"\n'),
        {"rerun.serve": True, "rerun.web_port": 0},
    )
    assert config.rerun.enabled and config.rerun.serve
    assert (config.rerun.save, config.rerun.max_rate_hz, config.rerun.web_port) == ("out/fleet.rrd", 5.0, 0)
    assert config.rerun.memory_limit == "2GiB"
    # `twin run` passes None for flags it was not given: the file's value stays.
    assert load_config(write(tmp_path, "[rerun]\nserve = true\n"), {"rerun.serve": None}).rerun.serve


@pytest.mark.parametrize(
    ("values", "needle"),
    [
        ({"broker.per_connection_limit": -1}, "per_connection_limit"),
        ({"broker.max_connections": 0}, "max_connections"),
        ({"broker.max_connections": 65}, "max_connections"),
    ],
)
def test_pool_settings_are_checked(values: dict[str, object], needle: str) -> None:
    with pytest.raises(ConfigError, match=needle):
        load_config(None, values)


def test_values_and_derived_properties(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        """
[broker]
url = "mqtt://127.0.0.1:18830"
[telemetry]
devices = ["*"]
units = "ticks"
[health]
expected_rate_hz = 20
stale_periods = 4
offline_after_s = 2
[http]
listen = "0.0.0.0:9000"
[log]
level = "debug"
""",
    )
    config = load_config(path)
    assert config.broker.url == "mqtt://127.0.0.1:18830"
    assert config.telemetry.all_devices
    assert config.health.stale_after_s == pytest.approx(0.2)
    assert isinstance(config.health.expected_rate_hz, float)
    assert (config.http.host, config.http.port) == ("0.0.0.0", 9000)
    assert config.log.level == "DEBUG"
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.broker.url = "iot"  # type: ignore[misc]


def test_flags_override_file(tmp_path: Path) -> None:
    path = write(tmp_path, '[broker]\nurl = "mqtt://127.0.0.1:1883"\n[telemetry]\nunits = "degrees"\n')
    config = load_config(
        path,
        {
            "broker.url": "mqtts://broker.example:8883",
            "telemetry.units": "ticks",
            "telemetry.devices": "arm-001, arm-002",
            "http.listen": "127.0.0.1:0",
            "twin.mode": None,  # an unset flag leaves the file's (here the default) value
        },
    )
    assert config.broker.url == "mqtts://broker.example:8883"
    assert config.telemetry.units == "ticks"
    assert config.telemetry.devices == ("arm-001", "arm-002")
    assert config.http.port == 0
    assert config.twin.mode == "kinematic"


@pytest.mark.parametrize(
    ("toml", "must_mention"),
    [
        ("[health]\noffline_after = 5.0\n", ["health.offline_after", "offline_after_s"]),
        ("[helth]\n", ["[helth]", "health"]),
        ('[telemetry]\nunits = "degree"\n', ["telemetry.units", "'degree'", "degrees"]),
        ('[twin]\nmode = "physic"\n', ["twin.mode", "physics"]),
        ('[broker]\nurl = "http://x:1"\n', ["broker.url", "http://x:1", "mqtt://host:port"]),
        ('[broker]\nurl = "mqtt://h:99999"\n', ["broker.url", "port"]),
        ("[health]\nexpected_rate_hz = 0\n", ["health.expected_rate_hz", "greater than 0"]),
        ('[health]\nexpected_rate_hz = "10"\n', ["health.expected_rate_hz", "'10'", "number"]),
        ("[health]\nstale_periods = true\n", ["health.stale_periods", "number"]),
        ("[health]\noffline_after_s = 0.2\n", ["health.offline_after_s", "stale"]),
        ('[http]\nlisten = "8080"\n', ["http.listen", "HOST:PORT"]),
        (
            '[http]\nallowed_hosts = ["twin.example:8080"]\n',
            ["http.allowed_hosts", "twin.example:8080", "port"],
        ),
        ('[http]\nallowed_hosts = ["*"]\n', ["http.allowed_hosts", "'*'", "wildcard"]),
        ("[http]\nmax_connections = 0\n", ["http.max_connections", "1..10000"]),
        ("[http]\nmax_body_bytes = 10\n", ["http.max_body_bytes", "1024"]),
        ("[http]\ntimeout_s = 0\n", ["http.timeout_s", "greater than 0"]),
        ("[http]\nconsole_rate_hz = 50\n", ["http.console_rate_hz", "stream_rate_hz"]),
        ("[http]\nsession_gap_s = -1\n", ["http.session_gap_s", "greater than 0"]),
        ('[telemetry]\ndevices = ["arm/1"]\n', ["telemetry.devices", "arm/1"]),
        ('[telemetry]\ndevices = ["*", "arm-001"]\n', ["telemetry.devices", "*"]),
        ("[telemetry]\ndevices = []\n", ["telemetry.devices", "fleet"]),
        ('[telemetry]\ntopic_prefix = "dt/+/x"\n', ["telemetry.topic_prefix", "wildcards"]),
        ('[telemetry]\ncalibration = "/nope/cal.json"\n', ["telemetry.calibration", "/nope/cal.json"]),
        ('[log]\nlevel = "LOUD"\n', ["log.level", "LOUD", "INFO"]),
        ('[broker]\nca_file = "/nope.pem"\n', ["broker.ca_file", "/nope.pem"]),
        ("broker = 3\n", ["[broker]", "table"]),
        ('[rerun]\nsave = "fleet.txt"\n', ["rerun.save", "fleet.txt", ".rrd"]),
        ('[rerun]\nmemory_limit = "lots"\n', ["rerun.memory_limit", "'lots'", "512MiB"]),
        ("[rerun]\nmax_rate_hz = 0\n", ["rerun.max_rate_hz", "greater than 0"]),
        ("[rerun]\nburst_s = -1\n", ["rerun.burst_s", "-1.0", "greater than 0", "burst_s = 5.0"]),
        ("[rerun]\nmesh_faces_far = 10\n", ["rerun.mesh_faces_far", "10", "at least 100"]),
        ("[rerun]\nserve = 1\n", ["rerun.serve", "true or false"]),
        ("[rerun]\nweb_port = 70000\n", ["rerun.web_port", "0..65535"]),
        ("[rerun]\nserve = true\ngrpc_port = 9000\nweb_port = 9000\n", ["rerun.grpc_port", "different"]),
        ("[rerun]\nsave_to = 1\n", ["rerun.save_to", "save"]),
        # A key given in another section's place: where it belongs.
        ('[telemetry]\nstate_file = "s.json"\n', ["telemetry.state_file", "a key of [twin]"]),
        # A directory where one file for every arm goes: the key for each arm's own.
        ('[telemetry]\ncalibration = "/tmp"\n', ["is a directory", "telemetry.calibrations = '/tmp'"]),
    ],
)
def test_bad_values_name_key_value_and_fix(tmp_path: Path, toml: str, must_mention: list[str]) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, toml))
    for text in must_mention:
        assert text in str(info.value)


def test_bad_flag_is_reported_like_a_bad_key() -> None:
    with pytest.raises(ConfigError, match=r"telemetry\.units = 'radians'"):
        load_config(None, {"telemetry.units": "radians"})


def test_file_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found") as missing:
        load_config(tmp_path / "missing.toml")
    # The fix fits `twin config check FILE` as well as `twin run --config FILE`.
    assert "`twin config example > FILE`" in str(missing.value) and "--config" not in str(missing.value)
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(write(tmp_path, "[broker\n"))


def test_choices_load_as_their_enums() -> None:
    config = load_config(None, {"telemetry.units": "range100", "twin.mode": "physics"})
    assert config.telemetry.units is Units.RANGE100 and config.twin.mode is TwinMode.PHYSICS
    assert AgentConfig().telemetry.units is Units.AUTO and AgentConfig().twin.mode is TwinMode.KINEMATIC
    with pytest.raises(ConfigError, match=r"twin\.mode = 3 is not one of kinematic, physics"):
        load_config(None, {"twin.mode": 3})


def test_to_dict_round_trips() -> None:
    config = load_config(None, {"telemetry.devices": ["a", "b"], "broker.url": "mqtt://127.0.0.1:1"})
    assert config_from_mapping(config.to_dict()) == config


def test_alarms_and_cloudwatch_sections() -> None:
    from twin.service.config import ConfigError, load_config

    config = load_config(
        None,
        {
            "alarms.temperature_warning_c": 58.0,
            "alarms.servo_version": "12v",
            "cloudwatch.emf_file": "/var/log/so101-twin/emf.log",
            "cloudwatch.agent_name": "So101TwinStack",
        },
    )
    assert config.alarms.temperature_warning_c == 58.0
    assert config.alarms.servo.stall_torque_nm > 2.9
    assert config.cloudwatch.interval_s == 60.0
    # Any interval that divides 60, the tests' half second too.
    for seconds in (30.0, 20.0, 15.0, 10.0, 1.0, 0.5, 0.1):
        assert load_config(None, {"cloudwatch.interval_s": seconds}).cloudwatch.interval_s == seconds
    for overrides, words in [
        ({"alarms.temperature_warning_clear_c": 61.0}, ["[alarms]", "hysteresis"]),
        ({"alarms.servo_version": "24v"}, ["[alarms]", "7.4v"]),
        ({"alarms.overload": 80}, ["alarms.overload", "overload_percent"]),
        ({"cloudwatch.interval_s": 0.0}, ["cloudwatch.interval_s", "greater than 0"]),
        # The stack's per-minute alarms: a 45 s interval gives minutes one document or two (MessagesRefused
        # weighed 45 s of Rejects against 60 s of messages), a 120 s one minutes with none.
        ({"cloudwatch.interval_s": 45.0}, ["cloudwatch.interval_s = 45.0", "divide 60", "30, 20"]),
        ({"cloudwatch.interval_s": 120.0}, ["cloudwatch.interval_s = 120.0", "divide 60", "set one of 60"]),
        ({"cloudwatch.interval_s": 0.7}, ["cloudwatch.interval_s = 0.7", "divide 60"]),
    ]:
        with pytest.raises(ConfigError) as info:
            load_config(None, overrides)
        for word in words:
            assert word in str(info.value), (overrides, str(info.value))


def test_a_wrong_emf_interval_is_told_every_whole_interval_that_divides_60() -> None:
    """The advice was a hand list that left 12 and 6 out."""
    with pytest.raises(ConfigError, match=r"set one of ([\d, ]+) \(60") as info:
        load_config(None, {"cloudwatch.interval_s": 45.0})
    advice = re.search(r"set one of ([\d, ]+) \(60", str(info.value))
    assert advice is not None
    named = [int(s) for s in advice.group(1).split(", ")]
    assert named == sorted((s for s in range(1, 61) if 60 % s == 0), reverse=True)
    for seconds in named:
        assert load_config(None, {"cloudwatch.interval_s": float(seconds)}).cloudwatch.interval_s == seconds


_RULE_KEYS = {
    ("over_temperature", False): ("temperature_warning_c", "temperature_warning_clear_c"),
    ("over_temperature_critical", False): ("temperature_critical_c", "temperature_critical_clear_c"),
    ("over_current", False): ("current_a", "current_clear_a"),
    ("over_current", True): ("gripper_current_a", "gripper_current_clear_a"),
    ("overload", False): ("overload_percent", "overload_clear_percent"),
    ("overload", True): ("gripper_overload_percent", "gripper_overload_clear_percent"),
    ("model_mismatch", False): ("mismatch_percent", "mismatch_clear_percent"),
}


# The servo error's levels are fixed (any error bit raises, none clears): no keys of its own to get wrong.
@pytest.mark.parametrize("kind", [k for k in AlarmKind if k is not AlarmKind.SERVO_ERROR])
@pytest.mark.parametrize("joint", ["shoulder_pan", "gripper"])
def test_a_rule_without_hysteresis_names_the_two_keys_to_change(kind: AlarmKind, joint: str) -> None:
    """A raise value moved to its clear value (docs once gave `temperature_warning_c = 55.0` alone, the
    default clear value) stopped the host's agent with the rule's kind but not the key to change."""
    from twin.service.config import ConfigError, load_config

    defaults = AlarmThresholds()
    rule = defaults.rule(kind, joint)
    raised, cleared = _RULE_KEYS.get((str(kind), joint == "gripper"), _RULE_KEYS[str(kind), False])
    assert (getattr(defaults, raised), getattr(defaults, cleared)) == (rule.raise_at, rule.clear_at)
    with pytest.raises(ConfigError) as info:
        load_config(None, {f"alarms.{raised}": rule.clear_at})
    text = str(info.value)
    assert f"({cleared})" in text and f"{rule.clear_at:g}, {raised})" in text, text
    assert f"set {cleared} below {raised}" in text, text


def test_a_warning_above_the_critical_temperature_is_refused() -> None:
    from twin.service.config import ConfigError, load_config

    with pytest.raises(ConfigError) as info:
        load_config(None, {"alarms.temperature_warning_c": 500.0, "alarms.temperature_warning_clear_c": 55.0})
    assert "temperature_warning_c (500) is not below temperature_critical_c (65)" in str(info.value)


def test_ros2_section_is_the_bridge_settings_and_names_its_keys(tmp_path: Path) -> None:
    config = load_config(
        write(
            tmp_path,
            """
[telemetry]
devices = ["arm-001"]
[ros2]
enabled = true
topic = "/joint_states"
joint_names = ["so_arm101_usd"]
velocity = false
peers = ["10.0.1.23"]
""",
        )
    )
    assert config.ros2.enabled and config.ros2.fixed_topic
    assert config.ros2.ros_joint_names[0] == "Rotation"
    assert config.to_dict()["ros2"]["peers"] == ["10.0.1.23"]
    # The flag --ros2 is the override ros2.enabled; the section is off by default.
    assert not load_config(None).ros2.enabled
    assert load_config(None, {"ros2.enabled": True}).ros2.enabled
    with pytest.raises(ConfigError, match=r"ros2\.joint_names = \['isaac'\] must be one preset"):
        load_config(None, {"ros2.joint_names": "isaac"})
    with pytest.raises(ConfigError, match=r"unknown key 'ros2\.topics'; did you mean 'topic'"):
        load_config(None, {"ros2.topics": "/x"})


def test_a_fixed_ros2_topic_for_several_devices_is_refused() -> None:
    overrides = {"ros2.enabled": True, "ros2.topic": "/joint_states", "telemetry.devices": "arm-001,arm-002"}
    with pytest.raises(ConfigError, match=r"one topic for 2 devices.*/\{arm\}/joint_states"):
        load_config(None, overrides)
    # Off, or one arm, or a pattern with {arm}: fine.
    load_config(None, {**overrides, "ros2.enabled": False})
    load_config(None, {**overrides, "telemetry.devices": "arm-001"})
    load_config(None, {**overrides, "ros2.topic": "/twin/{arm}/joint_states"})


@pytest.mark.parametrize(("key", "example"), [("state_file", "state.json"), ("events_file", "events.jsonl")])
def test_a_state_file_under_a_file_is_refused_with_a_path_that_works(
    tmp_path: Path, key: str, example: str
) -> None:
    (tmp_path / "agent.toml").write_text("")
    with pytest.raises(ConfigError) as info:
        load_config(None, {f"twin.{key}": str(tmp_path / "agent.toml" / "sub" / example)})
    said = str(info.value)
    assert f"{str(tmp_path / 'agent.toml')!r} is a file, not a directory" in said, said
    assert f"e.g. {str(tmp_path / example)!r}" in said, said


def test_a_list_of_more_arms_than_max_devices_is_refused() -> None:
    """A walk listed 10,001 ids: accepted (max_devices bounded only the whole fleet), 1,251 connections."""
    from twin.service.config import ConfigError, load_config

    arms = [f"arm-{i:05d}" for i in range(11)]
    with pytest.raises(ConfigError) as info:
        load_config(None, {"telemetry.devices": arms, "telemetry.max_devices": 10})
    assert "telemetry.devices lists 11 arms, more than telemetry.max_devices = 10" in str(info.value)
    assert load_config(None, {"telemetry.devices": arms[:10], "telemetry.max_devices": 10})
