"""Settings as code: twin.settings.toml holds a deployment's settings, `-c` overrides it for one run, and a
deploy never silently resets a setting it was not given (the deployed stack's Settings output is compared).
The deployed stack is read through a reader of its outputs, as stacks/deployed.py reads it from AWS.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from twin.ops.deployed_settings import DeployedSettings, parse_deployed_settings

from stacks.settings import (
    KEPT_KEYS,
    SettingsError,
    Source,
    check_context_keys,
    default_values,
    read_settings_file,
    resolve,
)
from stacks.settings_guard import SETTINGS_OUTPUT, parse_settings_output, settings_output, silent_resets

from .synth import CLIENT_CIDR, REPO_ROOT, annotations, app_stack, normalise, synthesize

FILE_SETTINGS = {
    "clientCidr": "198.51.100.0/24",
    "stackName": "FiveArms",
    "devices": ["arm-001", "arm-002", "arm-003", "arm-004", "arm-005"],
    "alarmEmail": "robots@example.com",
    "alarmWarnings": True,
    "volumeGb": 150,
    "recordSessions": True,
    "autoStopCron": "0 20 * * ? *",
}


def settings_toml(values: dict[str, Any], given: dict[str, str] | None = None) -> str:
    """A settings file as `twin instance settings` writes it (every key given unless `given` says)."""
    return DeployedSettings(values, given if given is not None else dict.fromkeys(values, "file")).to_toml()


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def file_with(tmp_path: Path, values: dict[str, Any]) -> Path:
    return write(tmp_path / "twin.settings.toml", settings_toml(values))


# --- the file --------------------------------------------------------------------------------------------


def test_an_absent_file_is_no_settings_unless_named(tmp_path: Path) -> None:
    assert read_settings_file(tmp_path / "twin.settings.toml") == {}
    with pytest.raises(SettingsError, match="does not exist"):
        read_settings_file(tmp_path / "mine.toml", required=True)


def test_an_unknown_key_is_refused_with_the_closest_name(tmp_path: Path) -> None:
    path = write(tmp_path / "s.toml", 'clientCidr = "203.0.113.7/32"\ndevice = ["arm-001"]\n')
    with pytest.raises(SettingsError, match=r"unknown setting 'device'; did you mean 'devices'\?"):
        read_settings_file(path)
    # A walk put its arms' calibrations here: they are pushed, not deployed, and the error says so.
    path = write(tmp_path / "s.toml", 'clientCidr = "203.0.113.7/32"\ncalibrations = "cal/"\n')
    with pytest.raises(SettingsError, match=r"not a stack setting: push each arm's file with `twin"):
        read_settings_file(path)


@pytest.mark.parametrize(("key", "hint"), [("device", "did you mean 'devices'? "), ("gpuType", "")])
def test_an_unknown_context_key_is_refused_with_the_closest_name(tmp_path: Path, key: str, hint: str) -> None:
    """A deploy walk ran `cdk synth -c device=arm-1`: CDK keeps any key, so the synth passed without it."""
    with pytest.raises(SettingsError) as info:
        app_stack(tmp_path, reader=lambda _stack, _region: None, clientCidr=CLIENT_CIDR, **{key: "x"})
    assert str(info.value).startswith(f"-c {key}: unknown setting; {hint}the settings are: clientCidr")


def test_cdks_own_context_keys_are_not_settings() -> None:
    check_context_keys(
        [
            "@aws-cdk/core:newStyleStackSynthesis",
            "aws:cdk:enable-path-metadata",
            "acknowledged-issue-numbers",
            "availability-zones:account=111111111111:region=us-east-1",
            "clientCidr",
            "replaceInstance",
            "settingsFile",
        ]
    )


def test_a_one_run_confirmation_is_never_kept(tmp_path: Path) -> None:
    path = write(tmp_path / "s.toml", "replaceInstance = true\n")
    with pytest.raises(SettingsError, match="-c replaceInstance=true with the deploy it confirms"):
        read_settings_file(path)


@pytest.mark.parametrize(("text", "problem"), [("devices = [", "not valid TOML"), ("[devices]\n", "a table")])
def test_a_broken_file_says_what_is_wrong(tmp_path: Path, text: str, problem: str) -> None:
    with pytest.raises(SettingsError, match=problem):
        read_settings_file(write(tmp_path / "s.toml", text))


def test_a_bad_value_in_the_file_names_the_file(tmp_path: Path) -> None:
    path = file_with(tmp_path, {"clientCidr": CLIENT_CIDR, "volumeGb": 10})
    # The fix goes in the file: -c would fix one deploy and leave the file wrong for the next.
    with pytest.raises(SettingsError) as caught:
        resolve({}.get, read_settings_file(path), path)
    assert re.fullmatch(
        r"volumeGb=10 is outside 50\.\.16384 \(.*\): correct volumeGb in \S*twin\.settings\.toml "
        r"\(or, for one deploy only, pass e\.g\. -c volumeGb=100\)",
        str(caught.value),
    ), caught.value
    # A bad device id too (a walk found its message did not start with the key, so the file went unnamed).
    path = file_with(tmp_path, {"clientCidr": CLIENT_CIDR, "devices": ["arm/left"]})
    message = r"^devices: device id 'arm/left' .*: correct devices in .*\.toml \(or, for one"
    with pytest.raises(SettingsError, match=message):
        resolve({}.get, read_settings_file(path), path)


# --- precedence ------------------------------------------------------------------------------------------


def test_context_overrides_the_file_which_overrides_the_defaults(tmp_path: Path) -> None:
    path = file_with(tmp_path, FILE_SETTINGS)
    context = {"volumeGb": "200", "alarmEmail": ""}
    resolved = resolve(context.get, read_settings_file(path), path)
    s = resolved.settings
    assert s.devices == tuple(FILE_SETTINGS["devices"]) and s.stack_name == "FiveArms"
    assert s.volume_gb == 200
    # An empty -c value is given too: it clears the file's e-mail for this run.
    assert s.alarm_email is None
    assert s.instance_type == "g6e.2xlarge"
    assert resolved.sources["devices"] is Source.FILE
    assert resolved.sources["volumeGb"] is Source.CONTEXT
    assert resolved.sources["instanceType"] is Source.DEFAULT
    assert resolved.given == {**{k: "file" for k in FILE_SETTINGS}, "volumeGb": "-c", "alarmEmail": "-c"}


def test_the_deployed_settings_print_as_a_file_that_reads_back_the_same(tmp_path: Path) -> None:
    """`twin instance settings` (twin.ops.deployed_settings) prints the Settings output as a settings file;
    read back through the stack's own loader it gives the deployed settings, with the same sources."""
    resolved = resolve({"units": "ticks", "devices": "*"}.get, FILE_SETTINGS)
    printed = parse_deployed_settings(settings_output(resolved), "FiveArms").to_toml(header="FiveArms")
    path = write(tmp_path / "twin.settings.toml", printed)
    again = resolve({}.get, read_settings_file(path), path)
    assert again.settings == resolved.settings
    assert again.given == {k: "file" for k in resolved.given}
    # Every kept key is there in the documented order (defaults commented out); a one-run flag never is.
    keys = [line.lstrip("# ").split(" = ")[0] for line in printed.splitlines() if " = " in line]
    assert keys == list(KEPT_KEYS)
    assert "replaceInstance" not in printed
    assert 'units = "ticks"  # given with -c' in printed
    assert '# instanceType = "g6e.2xlarge"  # default' in printed.splitlines()


# --- the silent-reset guard ------------------------------------------------------------------------------


def deployed_as(values: dict[str, Any], given: dict[str, str]) -> tuple[dict[str, Any], dict[str, str]]:
    return {**default_values(), **values}, given


def test_a_setting_dropped_from_the_file_is_a_reset() -> None:
    values, given = deployed_as({"devices": ["arm-002"]}, {"devices": "file"})
    resets = silent_resets(values, given, resolve({}.get, {"clientCidr": CLIENT_CIDR}))
    assert resets == ["devices: arm-002 (twin.settings.toml) -> arm-001 (default)"]


def test_a_c_value_not_repeated_is_a_reset_even_when_the_file_has_another() -> None:
    values, given = deployed_as({"alarmEmail": "me@example.com"}, {"alarmEmail": "-c"})
    assert silent_resets(values, given, resolve({}.get, {"clientCidr": CLIENT_CIDR})) == [
        "alarmEmail: me@example.com (-c) -> (not set) (default)"
    ]
    in_file = resolve({}.get, {"clientCidr": CLIENT_CIDR, "alarmEmail": "team@example.com"})
    assert silent_resets(values, given, in_file) == [
        "alarmEmail: me@example.com (-c) -> team@example.com (twin.settings.toml)"
    ]


def test_changes_written_down_are_on_purpose() -> None:
    values, given = deployed_as({"devices": ["arm-002"]}, {"devices": "file"})
    edited = resolve({}.get, {"clientCidr": CLIENT_CIDR, "devices": ["arm-003"]})
    assert silent_resets(values, given, edited) == []
    flagged = resolve({"devices": "arm-001"}.get, {"clientCidr": CLIENT_CIDR})
    assert silent_resets(values, given, flagged) == []


def test_unchanged_values_and_changed_defaults_are_not_resets() -> None:
    same = resolve({}.get, {"clientCidr": CLIENT_CIDR, "devices": "arm-002"})
    values, given = deployed_as({"devices": ["arm-002"]}, {"devices": "-c"})
    assert silent_resets(values, given, same) == []
    # A default that changed with a new version of the project is not the deployer's setting.
    values, given = deployed_as({"volumeGb": 80}, {})
    assert silent_resets(values, given, resolve({}.get, {"clientCidr": CLIENT_CIDR})) == []


def test_the_output_round_trips() -> None:
    resolved = resolve({"units": "ticks"}.get, FILE_SETTINGS)
    values, given = parse_settings_output(settings_output(resolved))
    assert values == {k: v for k, v in resolved.settings.file_values().items() if k in KEPT_KEYS}
    assert given == resolved.given
    assert silent_resets(values, given, resolved) == []


# --- through the app -------------------------------------------------------------------------------------


def test_the_app_refuses_a_reset_and_says_how_to_keep_it(tmp_path: Path) -> None:
    deployed = resolve({"devices": "arm-007"}.get, {"clientCidr": CLIENT_CIDR})
    outputs = {SETTINGS_OUTPUT: settings_output(deployed)}
    stack = app_stack(tmp_path, reader=lambda _n, _r: outputs, clientCidr=CLIENT_CIDR)
    (error,) = annotations(stack, "error")
    assert "devices: arm-007 (-c) -> arm-001 (default)" in error
    assert "twin.settings.toml" in error and "twin instance settings" in error


def test_destroy_context_needs_no_settings_but_deploy_does(tmp_path: Path) -> None:
    """No file and no -c (what `cdk destroy` gets): the app still synthesizes, and its one error is what a
    deploy needs; the CDK CLI stops `cdk deploy` and `cdk synth` on it, not `cdk destroy`."""
    stack = app_stack(tmp_path, reader=lambda _n, _r: None, account=None)
    (error,) = annotations(stack, "error")
    assert error.startswith("clientCidr is required")
    template = json.loads((tmp_path / f"{stack.artifact_id}.template.json").read_text())
    groups = [r for r in template["Resources"].values() if r["Type"] == "AWS::EC2::SecurityGroup"]
    assert groups and all("SecurityGroupIngress" not in g["Properties"] for g in groups)


def test_a_deploy_without_c_reproduces_the_settings_file(tmp_path: Path) -> None:
    """The template from the settings file alone is the one the same values give as -c, and its Settings
    output records the file's values as given in the file."""
    path = file_with(tmp_path, FILE_SETTINGS)
    from_file = synthesize(tmp_path / "file", settings_file=path, clientCidr=None)
    as_flags = {
        k: ",".join(v) if isinstance(v, list) else str(v).lower() if isinstance(v, bool) else str(v)
        for k, v in FILE_SETTINGS.items()
    }
    from_flags = synthesize(tmp_path / "flags", **as_flags)

    def shape(template: dict[str, Any]) -> dict[str, Any]:
        t = normalise(template)
        t["Outputs"].pop(SETTINGS_OUTPUT)
        return t

    assert shape(from_file.json) == shape(from_flags.json)
    values, given = parse_settings_output(from_file.json["Outputs"][SETTINGS_OUTPUT]["Value"])
    assert {k: values[k] for k in FILE_SETTINGS} == {**FILE_SETTINGS, "autoStopCron": "cron(0 20 * * ? *)"}
    assert given == {k: "file" for k in FILE_SETTINGS}
    # What the settings reach: the stack's name, the arms the role may read, the e-mail, the disk.
    assert from_file.stack.stack_name == "FiveArms"
    topics = json.dumps(from_file.resources("AWS::IAM::Policy"))
    assert all(f"dt/lerobot/arm-00{i}/telemetry" in topics for i in range(1, 6))
    assert from_file.one("AWS::SNS::Subscription")["Properties"]["Endpoint"] == "robots@example.com"
    (volume,) = from_file.one("AWS::EC2::Instance")["Properties"]["BlockDeviceMappings"]
    assert volume["Ebs"]["VolumeSize"] == 150


def test_the_example_file_names_every_setting_and_uncommented_is_valid(tmp_path: Path) -> None:
    example = REPO_ROOT / "twin.settings.example.toml"
    assert read_settings_file(example) == {"clientCidr": ""}
    # A setting's line, live or commented out: `[# ]key = value`.
    lines = [m.group(1) for m in re.finditer(r"^(?:# )?([a-z][A-Za-z0-9]* = .*)$", example.read_text(), re.M)]
    assert [line.split(" = ")[0] for line in lines] == list(KEPT_KEYS)
    # Every line uncommented, with an address: a file that deploys.
    live = "\n".join(lines).replace('clientCidr = ""', f'clientCidr = "{CLIENT_CIDR}"')
    path = write(tmp_path / "twin.settings.toml", live)
    resolved = resolve({}.get, read_settings_file(path), path)
    assert resolved.settings.deploy_blockers() == []
    assert resolved.settings.auto_stop_timezone == "Europe/Berlin"
