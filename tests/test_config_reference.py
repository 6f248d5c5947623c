"""One schema, one truth: docs/configuration.md and examples/agent.toml are what the loader's own sections
generate (`make config-docs`), every key has its meaning written once, and the example is every key at its
default. Fails when a key is added, renamed or given a new default without the files following."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path

from twin.cli import main
from twin.service import config as cfg
from twin.service.config_reference import KEY_DOCS, SECTION_DOCS, keys, render_example, render_reference

REPO = Path(__file__).resolve().parents[1]
REFERENCE = REPO / "docs/configuration.md"
FIX = "the config changed: run `make config-docs` and commit docs/configuration.md and examples/agent.toml"


def loader_keys() -> set[str]:
    return {f"{name}.{f.name}" for name, cls in cfg._SECTIONS.items() for f in dataclasses.fields(cls)}


def test_every_key_has_its_meaning_written_once() -> None:
    assert set(KEY_DOCS) == loader_keys()
    assert set(SECTION_DOCS) == set(cfg._SECTIONS)
    assert all(text.strip() for text in KEY_DOCS.values())


def test_the_reference_is_what_the_loader_generates() -> None:
    assert REFERENCE.read_text() == render_reference(), FIX


def test_the_example_is_what_the_loader_generates() -> None:
    assert (REPO / "examples" / "agent.toml").read_text() == render_example(), FIX


def test_the_example_has_every_key_at_its_default() -> None:
    data = tomllib.loads(render_example())
    assert {f"{s}.{k}" for s, values in data.items() for k in values} == loader_keys()
    loaded = cfg.load_config(REPO / "examples" / "agent.toml").to_dict()
    defaults = cfg.AgentConfig().to_dict()
    for section, values in defaults.items():
        for key, default in values.items():
            got = loaded[section][key]
            if isinstance(default, float):
                assert math.isclose(got, default, rel_tol=1e-9), f"{section}.{key}"
            else:
                assert got == default, f"{section}.{key}"


def test_the_reference_names_every_key_with_its_default() -> None:
    text = render_reference()
    for key in keys():
        assert f"## `[{key.section}]`" in text
        assert f"| `{key.name}` | {key.type} |" in text


def test_each_keys_type_is_the_type_of_its_value_in_toml() -> None:
    # The list keys (telemetry.devices, http.allowed_hosts, ...) were typed "string" in the reference.
    names = {bool: "boolean", int: "integer", float: "number", str: "string", list: "list of strings"}
    example = tomllib.loads(render_example())
    for key in keys():
        assert key.type == names[type(example[key.section][key.name])], key.dotted


def test_twin_config_prints_both_and_checks_files(tmp_path: Path, capsys) -> None:
    assert main(["config", "example"]) == 0
    assert capsys.readouterr().out == render_example()
    assert main(["config", "reference"]) == 0
    assert capsys.readouterr().out == render_reference()
    assert main(["config", "check", str(REPO / "examples" / "agent.toml")]) == 0
    bad = tmp_path / "bad.toml"
    bad.write_text("[history]\ntarget_file_mb = 128\n")
    assert main(["config", "check", str(bad)]) == 2
    assert "unknown key 'history.target_file_mb'" in capsys.readouterr().err


def test_config_check_notes_one_arms_calibration_for_several_and_a_key_a_later_file_overrules(
    tmp_path: Path, capsys
) -> None:
    """A walk: the single-file `calibration` was used for both of an owner's arms, one of them then 22 degrees
    off while shown as calibrated, and nothing said so; a later file overruled a key without a word."""
    example = REPO / "robots" / "so101" / "calibration" / "so101_follower_example.json"
    first, second = tmp_path / "agent.toml", tmp_path / "agent.local.toml"
    first.write_text(f'[telemetry]\ndevices = ["alpha-01", "bravo-02"]\ncalibration = "{example}"\n')
    second.write_text('[telemetry]\ndevices = ["alpha-01", "bravo-02"]\nunits = "ticks"\n')
    assert main(["config", "check", str(first), str(second)]) == 0  # valid: the notes do not stop it
    out = capsys.readouterr().out
    (note,) = [line for line in out.splitlines() if line.startswith("note: ")]
    assert "one arm's LeRobot file, used here for all 2 listed arms" in note, out
    assert "twin calibration push ARM FILE --store DIR" in note
    # A later file setting a key to the same value is no note; to another value it is, with both files named.
    second.write_text('[telemetry]\ndevices = ["alpha-01"]\n')
    assert main(["config", "check", str(first), str(second)]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note: ")]
    assert len(notes) == 1, notes  # one arm now: its own file is fine
    assert (
        f"{second} sets [telemetry] devices = ['alpha-01'] over {first}'s ['alpha-01', 'bravo-02']"
        in notes[0]
    )
    # A store beside it: the file is the fallback of arms without their own, a choice, not a slip.
    first.write_text(f'[telemetry]\ncalibration = "{example}"\ncalibrations = "{tmp_path}"\n')
    assert main(["config", "check", str(first)]) == 0
    assert "note:" not in capsys.readouterr().out


def test_config_check_says_the_rate_the_arms_are_expected_at(tmp_path: Path, capsys) -> None:
    """A walk: 300 edges at 2 Hz read 80 % loss and flapped STALE, and nothing said 10 Hz was expected."""
    config = tmp_path / "agent.toml"
    config.write_text("[health]\nexpected_rate_hz = 2\n")
    assert main(["config", "check", str(config)]) == 0
    (line,) = [line for line in capsys.readouterr().out.splitlines() if line.startswith("health: ")]
    assert line.startswith("health: each arm expected at 2 Hz ([health] expected_rate_hz), STALE after 1.5 s")


def check_notes(tmp_path: Path, capsys, text: str) -> list[str]:
    """The notes `twin config check` prints for a config file holding `text` (which it takes: exit 0)."""
    config = tmp_path / "agent.toml"
    config.write_text(text)
    assert main(["config", "check", str(config)]) == 0
    return [line for line in capsys.readouterr().out.splitlines() if line.startswith("note: ")]


def test_config_check_notes_a_servo_error_alarm_that_watches_no_bit(tmp_path: Path, capsys) -> None:
    """A walk set `servo_error_bits = []`: "a valid agent config", and the alarm was off without a word."""
    (note,) = check_notes(tmp_path, capsys, "[alarms]\nservo_error_bits = []\n")
    assert "servo_error_bits is empty: no servo error is ever raised" in note
    assert check_notes(tmp_path, capsys, '[alarms]\nservo_error_bits = ["voltage"]\n') == []


def test_config_check_notes_a_per_connection_limit_the_broker_will_not_honour(tmp_path: Path, capsys) -> None:
    """A walk behind the quota proxy: a limit above IoT Core's 100/s, and one below an arm's rate, were both
    planned without a word, and the broker discarded the excess."""
    iot = '[broker]\nurl = "iot"\nregion = "eu-west-1"\n'
    (note,) = check_notes(tmp_path, capsys, iot + "per_connection_limit = 1000\n")
    assert "per_connection_limit = 1000 is above IoT Core's 100 publishes a second" in note
    local = '[broker]\nurl = "mqtt://127.0.0.1:1883"\nper_connection_limit = 5\n'
    (note,) = check_notes(tmp_path, capsys, local)
    assert "per_connection_limit = 5 carries less than one arm at 10 Hz" in note
    assert check_notes(tmp_path, capsys, iot + "per_connection_limit = 100\n") == []
    # IoT Core's own budget, which no setting raises: the rate is what can be wrong.
    (note,) = check_notes(tmp_path, capsys, iot + "[health]\nexpected_rate_hz = 200.0\n")
    assert "expected_rate_hz = 200 is more than the pool plans for one IoT Core connection" in note, note
    assert "IoT Core discards what passes 100 a second" in note and "raise the limit" not in note, note
    # Within IoT Core's 100, nothing is discarded: only the margin is gone.
    (note,) = check_notes(tmp_path, capsys, iot + "[health]\nexpected_rate_hz = 90.0\n")
    assert "within its 100 a second, with none of the margin" in note and "discards" not in note, note
    assert check_notes(tmp_path, capsys, iot + "[health]\nexpected_rate_hz = 80.0\n") == []
    # A limit set by hand on IoT Core: the rate is named, not a limit no setting can raise.
    (note,) = check_notes(
        tmp_path, capsys, iot + "per_connection_limit = 100\n[health]\nexpected_rate_hz = 200.0\n"
    )
    assert "expected_rate_hz = 200" in note and "raise the limit" not in note, note
    above, rate_note = check_notes(
        tmp_path, capsys, iot + "per_connection_limit = 200\n[health]\nexpected_rate_hz = 200.0\n"
    )
    assert "leave it 0" in above and "discards what passes 100 a second" in rate_note, (above, rate_note)
    # One set below IoT Core's by hand can be raised, up to it.
    (note,) = check_notes(
        tmp_path, capsys, iot + "per_connection_limit = 50\n[health]\nexpected_rate_hz = 50.0\n"
    )
    assert "per_connection_limit = 50 carries less than one arm at 50 Hz" in note, note


def test_config_check_shows_the_connections_a_broker_policy_must_allow(tmp_path: Path, capsys) -> None:
    """A walk compared the agent's plan with the stack's role through the Python API: `twin config check`
    showed nothing of it. It shows the connections and the client id indexes they take."""

    def plan(text: str) -> str:
        config = tmp_path / "agent.toml"
        config.write_text(text)
        assert main(["config", "check", str(config)]) == 0
        (line,) = [x for x in capsys.readouterr().out.splitlines() if x.startswith("connections: ")]
        return line

    iot = '[broker]\nurl = "iot"\nregion = "eu-west-1"\n'
    arms = ", ".join(f'"arm-{i:03d}"' for i in range(120))
    listed = plan(iot + f"[telemetry]\ndevices = [{arms}]\n[health]\nexpected_rate_hz = 5.0\n")
    assert listed == (
        "connections: 8 for 120 listed arm(s) at 5 Hz (16 a connection, 80 of its 100 msg/s planned); "
        "client id indexes 0 to 7"
    )
    fleet = plan(iot + 'max_connections = 50\n[telemetry]\ndevices = ["*"]\n')
    assert fleet.startswith("connections: 1 to 50 for the whole fleet (broker.max_connections)")
    # A walk's operator of 40 arms read "about 8 arms" as what the whole pool carries.
    assert fleet.endswith("about 8 arms at 10 Hz, so about 400 arms in all; client id indexes 0 to 49")
    fleet_at = iot + 'max_connections = 50\n[telemetry]\ndevices = ["*"]\n[health]\n'
    fast = plan(fleet_at + "expected_rate_hz = 200.0\n")
    assert "msg/s, less than one arm at 200 Hz, so about 50 arms in all;" in fast, fast
    local = plan('[broker]\nurl = "mqtt://127.0.0.1:1883"\n')
    assert local == "connections: 1 (the broker has no per-connection limit); client id index 0"


def test_no_default_prints_a_float_tail() -> None:
    """A default computed as a share of a servo figure printed as 2.1125000000000003 in the reference and in
    `twin config`: a person copying it reads a number nobody chose."""
    tails = [k.dotted for k in keys() if isinstance(k.default, float) and len(repr(k.default)) > 12]
    assert tails == [], tails
