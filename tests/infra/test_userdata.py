"""The UserData scripts: shellcheck, the rendered UserData, a real run of the agent installer, and the
helpers every script shares (the deployment parameter's allow-list, the signature checks).

The installer runs against a temporary ROOT with the exact agent asset the synth staged (the same zip
content the instance downloads), building a real venv and pip-installing the real package, offline: its
dependency lock is swapped for one that pins a small local wheel (tests/infra/hostsim.py, `with_lock`).
"""

from __future__ import annotations

import functools
import json
import os
import re
import shutil
import subprocess
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest

from stacks import monitoring, twin_host

from .hostsim import (
    HostSim,
    TestSigner,
    dpkg_lock_held,
    lock_text,
    lock_wheels,
    make_deb,
    tree_digest,
    with_lock,
)
from .synth import REPO_ROOT, Synth

USERDATA = REPO_ROOT / "userdata"
SCRIPTS = sorted(USERDATA.glob("*.sh"))


def test_shellcheck_is_clean() -> None:
    assert {p.name for p in SCRIPTS} == {
        "user-data.sh",
        "update.sh",
        "bootstrap.sh",
        "install-agent.sh",
        "lib.sh",
        "host-check.sh",
        "view-supervisor.sh",
        "save-local-config.sh",
        "save-alarm-state.sh",
    }
    shellcheck = shutil.which("shellcheck")
    if shellcheck is None:
        pytest.fail("shellcheck is missing: `make setup` installs it (apt package shellcheck)")
    result = subprocess.run([shellcheck, *map(str, SCRIPTS)], capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout


# --- no reader that exits early under pipefail ------------------------------------------------------------

# A reader that may stop before its writer is done: under `set -o pipefail` the writer then dies of SIGPIPE
# (status 141) and `set -e` ends the script (the old `tar -tzf ... | head -1`).
_EARLY_READER = re.compile(
    r"^\s*(head\b|grep\s+(-\w*[qlLm]\w*|--quiet|--silent|--max-count|--files-with)|sed\s+(-n\s+)?['\"]?\d*q|"
    r"awk\b.*\bexit\b|read\b|line\b)"
)


def early_exit_pipes(text: str) -> list[str]:
    """Lines of a shell script that pipe into a reader that can exit before its input ends."""
    found = []
    joined = re.sub(r"\\\n\s*", " ", text)
    for line in joined.splitlines():
        code = line.split(" #", 1)[0]
        if code.lstrip().startswith("#"):
            continue
        # Split on single pipes, not on `||`.
        segments = re.split(r"(?<!\|)\|(?!\|)", code)
        if any(_EARLY_READER.match(segment) for segment in segments[1:]):
            found.append(line.strip())
    return found


def test_the_pipe_check_catches_the_old_bugs() -> None:
    """The check must find what the old bootstrap did, or it proves nothing."""
    old = (
        'dir="$(tar -tzf "$work/$tarball" | head -1 | cut -d/ -f1)"\n'
        'dpkg-query -W -f=\'${Status}\' "$pkg" 2>/dev/null | grep -q "install ok installed" || x\n'
        "id -nG dcv 2>/dev/null | grep -qw video || usermod -aG video dcv\n"
        "nvidia-smi -L 2>/dev/null | \\\n  grep -m1 GPU\n"
    )
    assert len(early_exit_pipes(old)) == 4
    fine = "a || b\nfind . -print0 | sort -z | xargs -0 sha256sum | sha256sum\n# x | head\n"
    assert early_exit_pipes(fine) == []


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_no_script_pipes_into_an_early_exiting_reader(script: Path) -> None:
    assert early_exit_pipes(script.read_text()) == []


# --- templates -------------------------------------------------------------------------------------------


def test_render_fills_every_placeholder_and_refuses_gaps() -> None:
    values = {
        "REGION": "us-east-1",
        "STACK_NAME": "So101TwinStack",
        "RESOURCE": "HostInstance2C59A3BE",
        "PARAMETER": "/so101-twin/So101TwinStack/deployment",
        "HANDLE_URL": "https://cloudformation-waitcondition-us-east-1.s3.amazonaws.com/x",
    }
    text = twin_host.render_user_data(values)
    assert "@@" not in text
    assert len(text.encode()) < 16 * 1024
    with pytest.raises(KeyError, match="HANDLE_URL"):
        twin_host.render_user_data({k: v for k, v in values.items() if k != "HANDLE_URL"})
    with pytest.raises(KeyError, match="NOPE"):
        twin_host.render_user_data({**values, "NOPE": "x"})
    commands = twin_host.render_update_commands("0123456789ab")
    assert "export SO101_TWIN_EXPECTED_VERSION='0123456789ab'" in commands
    assert not [line for line in commands if "@@" in line]


def test_bootstrap_never_traces_or_prints_the_password() -> None:
    text = (USERDATA / "bootstrap.sh").read_text()
    assert "set -x" not in text
    assert "chpasswd" in text
    # The secret only flows into chpasswd's stdin.
    secret_lines = [line for line in text.splitlines() if "$secret" in line or "${secret}" in line]
    assert secret_lines == ['  printf \'%s:%s\\n\' "$DESKTOP_USER" "$secret" | chpasswd']


def agent_asset_dir(synth: Synth) -> Path:
    dirs = [p for p in Path(synth.stack.node.root.outdir).glob("asset.*") if (p / "pyproject.toml").exists()]
    assert len(dirs) == 1
    return dirs[0]


def run_installer(root: Path, source: Path, **env: str) -> subprocess.CompletedProcess[str]:
    host = HostSim(root.parent / f"{root.name}-sim")
    lock_wheels(host.sim / "wheels")
    full_env = {
        **host.env(),
        "ROOT": str(root),
        "AGENT_SRC": str(source),
        "AWS_REGION": "eu-central-1",
        "TOPIC_PREFIX": "dt/lerobot",
        "DEVICES": "arm-001, arm-002",
        "UNITS": "ticks",
        "AGENT_NAME": "LabTwin",
        "CLIENT_ID_PREFIX": "so101-twin-",
        "DESKTOP_USER": "ubuntu",
        "HISTORY_URI": "s3://twin-history-bucket/history",
        "CALIBRATIONS_URI": "s3://twin-history-bucket/calibration",
        "HOST_STATE_URI": "s3://twin-history-bucket/host",
        **env,
    }
    return subprocess.run(
        ["bash", str(USERDATA / "install-agent.sh")],
        env=full_env,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )


@pytest.fixture(scope="module")
def locked_source(synth_default: Synth, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthesized agent asset with a lock pinning the local probe wheel."""
    work = tmp_path_factory.mktemp("locked")
    return with_lock(agent_asset_dir(synth_default), work / "agent", lock_text(lock_wheels(work / "w")))


@pytest.fixture(scope="module")
def installed(locked_source: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("root")
    source = locked_source
    result = run_installer(root, source)
    assert result.returncode == 0, result.stdout + result.stderr
    return root, source


def test_installer_writes_the_agent_config_from_the_settings(installed: tuple[Path, Path]) -> None:
    root, _ = installed
    path = root / "etc/so101-twin/agent.toml"
    config = tomllib.loads(path.read_text())
    assert config["broker"]["url"] == "iot"
    assert config["broker"]["region"] == "eu-central-1"
    assert config["broker"]["client_id_prefix"] == "so101-twin-"
    assert config["telemetry"] == {
        "topic_prefix": "dt/lerobot",
        "devices": ["arm-001", "arm-002"],
        "units": "ticks",
        "calibration": "",
        "calibrations": "s3://twin-history-bucket/calibration",
    }
    assert path.read_text().startswith("# GENERATED by userdata/install-agent.sh")
    # No recording unless the stack says recordSessions=true: it would grow without bound.
    assert config["twin"]["record_dir"] == ""
    assert config["ros2"] == {"enabled": False}
    # The agent's own loader accepts it (same schema as `twin run --config`).
    from twin.service.config import load_config

    loaded = load_config(path)
    assert list(loaded.telemetry.devices) == ["arm-001", "arm-002"]
    assert loaded.broker.url == "iot"
    # Without the stack's armRateHz and maxConnections (an older deployment parameter), the defaults.
    assert (loaded.broker.max_connections, loaded.health.expected_rate_hz) == (8, 10.0)
    # CloudWatch metrics go to the file the CloudWatch agent follows, named for the stack's alarms.
    from twin.output.emf import DEFAULT_EMF_FILE

    assert (loaded.cloudwatch.emf_file, loaded.cloudwatch.agent_name) == (DEFAULT_EMF_FILE, "LabTwin")
    # History goes to the stack's bucket, in the instance's region.
    assert (loaded.history.uri, loaded.history.region) == ("s3://twin-history-bucket/history", "eu-central-1")
    assert loaded.history.enabled
    unit = (root / "etc/systemd/system/so101-twin-agent.service").read_text()
    assert "LogsDirectory=so101-twin\n" in unit


def unit_directives(text: str) -> dict[str, list[str]]:
    directives: dict[str, list[str]] = {}
    for line in text.splitlines():
        if "=" in line and not line.startswith("#"):
            key, value = line.split("=", 1)
            directives.setdefault(key, []).append(value)
    return directives


def test_installer_writes_the_service_and_the_viewer_autostart(installed: tuple[Path, Path]) -> None:
    root, _ = installed
    unit = (root / "etc/systemd/system/so101-twin-agent.service").read_text()
    assert (
        "ExecStart=/opt/so101-twin/venv/bin/twin run --config /etc/so101-twin/agent.toml "
        "--config /etc/so101-twin/agent.local.toml\n"
    ) in unit
    assert "Restart=always" in unit
    assert "Environment=MUJOCO_GL=egl" in unit
    assert "WantedBy=multi-user.target" in unit
    desktop = (root / "home/ubuntu/.config/autostart/so101-twin-view.desktop").read_text()
    assert "Exec=/opt/so101-twin/bin/twin-view-supervised" in desktop
    assert "Type=Application" in desktop
    supervisor = root / "opt/so101-twin/bin/twin-view-supervised"
    assert supervisor.read_text() == (USERDATA / "view-supervisor.sh").read_text()
    assert os.access(supervisor, os.X_OK)
    assert not (root / "var/lib/so101-twin-agent/sessions").exists()


def test_installer_writes_the_console_launcher(installed: tuple[Path, Path]) -> None:
    """The operator console one click away on the DCV desktop: a launcher in the applications and on the
    desktop opening the agent's own address, both valid desktop entries (desktop-file-validate, the
    freedesktop.org reference validator), and the login-time mark that lets the desktop icon launch."""
    from twin.service.config import DEFAULT_AGENT_URL

    root, _ = installed
    home = root / "home/ubuntu"
    apps = home / ".local/share/applications/so101-twin-console.desktop"
    desktop = home / "Desktop/so101-twin-console.desktop"
    trust = home / ".config/autostart/so101-twin-console-trust.desktop"
    assert apps.read_text() == desktop.read_text()
    assert os.access(apps, os.X_OK) and os.access(desktop, os.X_OK)  # the desktop launches only these
    entry = unit_directives(desktop.read_text())
    assert entry["Type"] == ["Application"] and entry["Terminal"] == ["false"]
    assert entry["Exec"] == [f"/snap/bin/firefox --new-window {DEFAULT_AGENT_URL}/"]
    config = tomllib.loads((root / "etc/so101-twin/agent.toml").read_text())
    assert f"http://{config['http']['listen']}" == DEFAULT_AGENT_URL
    assert unit_directives(trust.read_text())["Exec"] == [
        "gio set /home/ubuntu/Desktop/so101-twin-console.desktop metadata::trusted true"
    ]
    validator = shutil.which("desktop-file-validate")
    assert validator, "desktop-file-validate is missing: make setup installs desktop-file-utils"
    for path in (apps, desktop, trust):
        result = subprocess.run(
            [validator, str(path)], capture_output=True, text=True, timeout=30, check=False
        )
        assert result.returncode == 0 and "error" not in result.stdout, result.stdout + result.stderr


def test_the_agent_runs_as_its_own_user_in_a_sandbox(installed: tuple[Path, Path]) -> None:
    """It parses untrusted MQTT payloads with native parsers: no root, no capabilities, a read-only system."""
    from twin.cli.commands.run import EXIT_CONFIG

    root, _ = installed
    directives = unit_directives((root / "etc/systemd/system/so101-twin-agent.service").read_text())
    assert directives["User"] == ["so101-twin"] and directives["Group"] == ["so101-twin"]
    for key, value in {
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "PrivateTmp": "yes",
        "ProtectHome": "yes",
        "CapabilityBoundingSet": "",
        "AmbientCapabilities": "",
        "RestrictSUIDSGID": "yes",
    }.items():
        assert directives[key] == [value], key
    # Writable: its state and its EMF log, nothing else.
    assert directives["ReadWritePaths"] == ["-/var/lib/so101-twin-agent -/var/log/so101-twin"]
    assert directives["StateDirectory"] == ["so101-twin-agent"] and directives["LogsDirectory"] == [
        "so101-twin"
    ]
    # A configuration error (`twin run` exits EXIT_CONFIG) is not restarted every 5 s forever.
    assert directives["RestartPreventExitStatus"] == [str(EXIT_CONFIG)]
    # systemd waits longer than the agent's own shutdown budget (its workers flush history within it), and
    # the files that keep acknowledged and latched alarms and the events lie in the one directory it may
    # write.
    from twin.service.config import load_config

    config = load_config(root / "etc/so101-twin/agent.toml")
    (timeout,) = directives["TimeoutStopSec"]
    assert int(timeout) >= config.twin.shutdown_budget_s + 15
    assert Path(config.twin.state_file).parent == Path("/var/lib/so101-twin-agent")
    assert Path(config.twin.events_file).parent == Path("/var/lib/so101-twin-agent")
    # No device restriction: EGL needs /dev/nvidia* (ProtectClock= or PrivateDevices= would hide them).
    assert not {"PrivateDevices", "ProtectClock", "DeviceAllow"} & set(directives)


def test_systemd_knows_when_the_agent_is_up_and_when_it_is_stuck(installed: tuple[Path, Path]) -> None:
    """`twin run` notifies systemd (twin.service.systemd): ready once it serves, so what is ordered after the
    unit finds it up, and alive from its main thread, so one stuck is killed and started again."""
    from twin.service.shards import START_TIMEOUT_S

    root, _ = installed
    directives = unit_directives((root / "etc/systemd/system/so101-twin-agent.service").read_text())
    assert directives["Type"] == ["notify"] and directives["NotifyAccess"] == ["main"]
    assert directives["Restart"] == ["always"]
    # The agent pings every second, from its main loop: the interval leaves room for a slow turn of it.
    (watchdog,) = directives["WatchdogSec"]
    assert int(watchdog) >= 8
    # Its workers' start may take START_TIMEOUT_S; a start that takes longer is killed and tried again.
    (start,) = directives["TimeoutStartSec"]
    assert int(start) > START_TIMEOUT_S
    # The installer does not wait for READY=1 (a restart of a notify unit would): the host check says it.
    calls = HostSim.attach(root.parent / f"{root.name}-sim").calls()
    assert "systemctl restart --no-block so101-twin-agent.service" in calls, calls


def test_the_unit_is_valid_for_systemd(installed: tuple[Path, Path], tmp_path: Path) -> None:
    """systemd's own parser reads the units without a complaint about any directive."""
    systemd_analyze = shutil.which("systemd-analyze")
    if systemd_analyze is None:
        pytest.fail("systemd-analyze is missing (package systemd)")
    root, _ = installed
    names = (
        "so101-twin-agent.service",
        "so101-twin-local-config.service",
        "so101-twin-local-config.path",
        "so101-twin-alarm-state.service",
        "so101-twin-alarm-state.path",
    )
    units = [tmp_path / name for name in names]
    for unit in units:
        # The venv's twin lives under the test's root: point ExecStart there so only the directives are
        # judged.
        text = (root / "etc/systemd/system" / unit.name).read_text()
        unit.write_text(text.replace("=/opt/so101-twin/venv/", f"={root}/opt/so101-twin/venv/"))
    result = subprocess.run(
        [systemd_analyze, "verify", "--man=no", *map(str, units)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    complaints = [
        line
        for line in (result.stdout + result.stderr).splitlines()
        if any(name in line for name in names)
        and any(word in line for word in ("Unknown", "Invalid", "Failed to parse", "Refusing", "bad unit"))
    ]
    assert complaints == []


def test_installer_installs_the_real_package_with_the_robot_model(installed: tuple[Path, Path]) -> None:
    root, _ = installed
    venv_python = root / "opt/so101-twin/venv/bin/python"
    # Every mesh file the installed MJCF names is installed beside it (this venv has no mujoco to load it).
    probe = (
        "import twin, twin_robots, pathlib, xml.etree.ElementTree as et; "
        "d = pathlib.Path(twin_robots.__file__).parent / 'so101'; "
        "x = et.parse(d / 'so101.xml').getroot(); "
        "mesh_dir = d / x.find('compiler').get('meshdir'); "
        "files = [m.get('file') for m in x.iter('mesh')]; "
        "print(pathlib.Path(twin.__file__).parent.parent.name, (d / 'scene.xml').is_file(), len(files), "
        "all((mesh_dir / f).is_file() for f in files), (d / 'meshes' / 'NOTICE').is_file())"
    )
    out = subprocess.run(
        [str(venv_python), "-c", probe], capture_output=True, text=True, check=True, timeout=60
    )
    # Installed into the venv's site-packages (not the repo checkout), model files and part meshes included.
    assert out.stdout.split() == ["site-packages", "True", "13", "True", "True"]
    help_ = subprocess.run(
        [str(root / "opt/so101-twin/venv/bin/twin"), "--help"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert help_.returncode == 0
    assert "run" in help_.stdout
    # The benchmark and the demo (the layers bench and rig) are not shipped; asking for them there says why
    # instead of a traceback.
    for command in (["bench", "fidelity", "--seconds", "1"], ["demo", "--seconds", "1"]):
        tool = subprocess.run(
            [str(root / "opt/so101-twin/venv/bin/twin"), *command],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert tool.returncode == 1, command
        assert "development tooling" in tool.stderr and "Traceback" not in tool.stderr, tool.stderr
    site = next((root / "opt/so101-twin/venv/lib").glob("python3*/site-packages"))
    assert {p.name for p in (site / "twin").iterdir() if p.is_dir()} >= {"edge", "ops", "cli"}
    assert not [name for name in ("rig", "bench") if (site / "twin" / name).exists()]


def test_second_run_changes_nothing(installed: tuple[Path, Path]) -> None:
    root, source = installed
    before = host_state(root)
    result = run_installer(root, source)
    assert result.returncode == 0, result.stderr
    assert "changed=0" in result.stdout
    assert "installing" not in result.stdout
    assert host_state(root) == before


def test_changed_settings_rewrite_only_the_config(installed: tuple[Path, Path], tmp_path: Path) -> None:
    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    before = host_state(root)
    result = run_installer(
        root,
        installed[1],
        DEVICES="*",
        UNITS="auto",
        RECORD_SESSIONS="true",
        ARM_RATE_HZ="2.5",
        MAX_CONNECTIONS="24",
    )
    assert result.returncode == 0, result.stderr
    after = host_state(root)
    changed = sorted(k for k in after if before.get(k) != after[k])
    assert changed == ["etc/so101-twin/agent.toml"]
    config = tomllib.loads((root / "etc/so101-twin/agent.toml").read_text())
    assert config["telemetry"]["devices"] == ["*"]
    # The stack's armRateHz and maxConnections: the pool is planned as the role's client ids are.
    from twin.service.config import load_config

    loaded = load_config(root / "etc/so101-twin/agent.toml")
    assert (loaded.broker.max_connections, loaded.health.expected_rate_hz) == (24, 2.5)
    assert config["twin"]["record_dir"] == "/var/lib/so101-twin-agent/sessions"
    assert (root / "var/lib/so101-twin-agent/sessions").is_dir()


def test_the_operators_own_file_survives_every_deploy(installed: tuple[Path, Path], tmp_path: Path) -> None:
    """The generated config is rewritten by every deploy; agent.local.toml is created once and never written
    again, and the agent reads it after the generated one, key by key."""
    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    local = root / "etc/so101-twin/agent.local.toml"
    assert tomllib.loads(local.read_text()) == {}  # comments only, to start with
    from twin.service.config import config_notes, load_config

    # Its example, uncommented, is one the agent starts with (55.0 was refused: it is the clear level).
    example = re.sub(r"(?m)^# (\[\w+\]|\w+ = .*)$", r"\1", local.read_text())
    assert tomllib.loads(example)["alarms"], example
    local.write_text(example)
    load_config([root / "etc/so101-twin/agent.toml", local])
    # A stack setting overruled here is said, with the fix (a walk: a third arm added to the stack's
    # settings was never mirrored, the local file's devices winning without a word).
    local.write_text('[telemetry]\ndevices = ["arm-001"]\n')
    configs = [root / "etc/so101-twin/agent.toml", local]
    (note,) = config_notes(configs, load_config(configs))
    assert f"{local} sets [telemetry] devices = ['arm-001'] over" in note and "twin.settings.toml" in note
    local.write_text("[alarms]\ntemperature_warning_c = 52.0\ntemperature_warning_clear_c = 48.0\n")
    result = run_installer(root, installed[1], DEVICES="arm-001,arm-002,arm-003")
    assert result.returncode == 0, result.stderr
    assert "temperature_warning_c = 52.0" in local.read_text()
    loaded = load_config([root / "etc/so101-twin/agent.toml", local])
    assert loaded.alarms.temperature_warning_c == 52.0
    assert list(loaded.telemetry.devices) == ["arm-001", "arm-002", "arm-003"]


def host_state(root: Path) -> dict[str, str]:
    """tree_digest of the host without its logs: each run appends to them (the saver's metric line at every
    install), and "a re-run changes nothing" is about what the host runs, not what it has recorded."""
    return {k: v for k, v in tree_digest(root).items() if not k.startswith("var/log/")}


SAVED_LOCAL = "twin-history-bucket/host/agent.local.toml"
SAVER = USERDATA / "save-local-config.sh"


def not_saved_metric(root: Path, name: str = monitoring.LOCAL_CONFIG_NOT_SAVED) -> tuple[float, str]:
    """The last `name` a saver wrote on the host at `root` (userdata/lib.sh, emit_host_metrics), with its
    Agent dimension: what the stack's alarm of that name watches."""
    lines = (root / "var/log/so101-twin-host-emf.log").read_text().splitlines()
    documents = [json.loads(line) for line in lines]
    last = [d for d in documents if name in d][-1]
    (directive,) = last["_aws"]["CloudWatchMetrics"]
    assert directive["Namespace"] == monitoring.NAMESPACE and directive["Dimensions"] == [["Agent"]]
    return last[name], last["Agent"]


def _new_host(installed: tuple[Path, Path], tmp_path: Path, saved: str | None) -> Path:
    """A host that replaces the installed one: its disk as the installer left it but without the operator's
    file (what a first boot finds), and the stack's bucket holding `saved` as that file's copy."""
    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    (root / "etc/so101-twin/agent.local.toml").unlink()
    (root / "var/lib/so101-twin/host-id").unlink()  # made at a disk's first install
    if saved is not None:
        copy = tmp_path / "root-sim" / "sim" / "s3" / SAVED_LOCAL
        copy.parent.mkdir(parents=True)
        copy.write_text(saved)
    return root


def test_the_operators_file_is_saved_whenever_it_changes_and_a_new_host_starts_with_it(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    """A change that replaces the instance (a new disk) keeps the operator's agent.local.toml: the host saves
    it to the stack's bucket at every install and, through a path unit, at every change; a new host's
    install puts it back before the agent starts."""
    root, _ = installed
    saver = (root / "etc/systemd/system/so101-twin-local-config.service").read_text()
    assert (
        "ExecStart=/bin/bash /opt/so101-twin/userdata/save-local-config.sh "
        "s3://twin-history-bucket/host/agent.local.toml\n"
    ) in saver
    assert "Type=oneshot" in saver and "Environment=AWS_REGION=eu-central-1 AGENT_NAME=LabTwin\n" in saver
    watch = (root / "etc/systemd/system/so101-twin-local-config.path").read_text()
    assert "PathChanged=/etc/so101-twin/agent.local.toml\n" in watch and "WantedBy=multi-user.target" in watch
    # The installer saved the new file at once (the bucket held none, so the host wrote the default).
    saved = root.parent / f"{root.name}-sim" / "sim" / "s3" / SAVED_LOCAL
    assert saved.read_text() == (root / "etc/so101-twin/agent.local.toml").read_text()
    assert not_saved_metric(root) == (0, "LabTwin")

    # The operator edits the file; systemd's path unit runs the saver, as here.
    edited = tmp_path / "edited"
    shutil.copytree(root, edited / "root", symlinks=True)
    local = edited / "root/etc/so101-twin/agent.local.toml"
    local.write_text("[alarms]\ntemperature_warning_c = 52.0\ntemperature_warning_clear_c = 48.0\n")
    host = HostSim(edited / "sim")
    result = host.run(SAVER, f"s3://{SAVED_LOCAL}", ROOT=str(edited / "root"), AGENT_NAME="LabTwin")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "saved /etc/so101-twin/agent.local.toml to s3://" in result.stdout
    assert not_saved_metric(edited / "root") == (0, "LabTwin")
    kept = (host.sim / "s3" / SAVED_LOCAL).read_text()
    assert kept == local.read_text()

    # A new host (the bucket has the copy): its file is the operator's, and the agent reads it.
    new_root = _new_host(installed, tmp_path / "new", kept)
    result = run_installer(new_root, installed[1])
    assert result.returncode == 0, result.stdout + result.stderr
    assert (
        "restored /etc/so101-twin/agent.local.toml from s3://twin-history-bucket/host/agent.local.toml"
        in (result.stdout)
    )
    restored = new_root / "etc/so101-twin/agent.local.toml"
    assert restored.read_text() == kept
    # On disk before its rename, and the rename too: an empty file after a power cut would be saved over
    # the bucket's copy, the operator's only one.
    synced = [c for c in HostSim(new_root.parent / f"{new_root.name}-sim").calls() if c.startswith("sync ")]
    config_dir = restored.parent
    assert any(c.startswith(f"sync {config_dir}/.so101-twin.") for c in synced), synced
    assert f"sync {config_dir}" in synced, synced
    assert oct(restored.stat().st_mode & 0o777) == "0o644"
    from twin.service.config import load_config

    loaded = load_config([new_root / "etc/so101-twin/agent.toml", restored])
    assert loaded.alarms.temperature_warning_c == 52.0


def test_a_change_made_while_the_file_is_saved_is_saved_too(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    """systemd does not start the saver again for a change made while it runs (the path unit's start merges
    into the running job), so the saver itself uploads again when the file changed during its upload."""
    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    local = root / "etc/so101-twin/agent.local.toml"
    local.write_text("[alarms]\ntemperature_warning_c = 52.0\ntemperature_warning_clear_c = 48.0\n")
    host = HostSim(tmp_path / "host")
    second = "[alarms]\ntemperature_warning_c = 51.0\ntemperature_warning_clear_c = 48.0\n"
    hook = host.sim / "on-upload"
    hook.write_text(f"#!/usr/bin/env bash\nprintf '%s' '{second}' > '{local}'\n")
    hook.chmod(0o755)
    result = host.run(USERDATA / "save-local-config.sh", f"s3://{SAVED_LOCAL}", ROOT=str(root))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "changed while it was saved; saving it again" in result.stdout
    assert (host.sim / "s3" / SAVED_LOCAL).read_text() == second == local.read_text()
    uploads = [c for c in host.calls() if c.startswith("aws s3 cp")]
    assert len(uploads) == 2, uploads


def test_an_upload_that_fails_says_what_to_check_and_pages_until_a_save_succeeds(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    """The bucket refuses the upload: the saver fails with the reason and the fix in the agent's log, and
    writes the metric that pages (LocalConfigNotSaved = 1); the next save that succeeds writes 0."""
    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    local = root / "etc/so101-twin/agent.local.toml"
    local.write_text("[alarms]\ntemperature_warning_c = 52.0\ntemperature_warning_clear_c = 48.0\n")
    host = HostSim(tmp_path / "host")
    host.fail("s3")  # the bucket refuses this role (tests/infra/hostsim.py, the aws stand-in)
    result = host.run(SAVER, f"s3://{SAVED_LOCAL}", ROOT=str(root), AGENT_NAME="Lab")
    assert result.returncode == 1, result.stdout + result.stderr
    out = result.stdout + result.stderr
    assert "Forbidden" in out, out  # the AWS CLI's own error, in the unit's journal
    assert "not saved: /etc/so101-twin/agent.local.toml could not be uploaded to s3://" in out, out
    assert "s3:PutObject" in out and "systemctl start so101-twin-local-config" in out, out
    assert not_saved_metric(root) == (1, "Lab")
    assert not (host.sim / "s3" / SAVED_LOCAL).exists()

    (host.sim / "fail" / "s3").unlink()
    result = host.run(SAVER, f"s3://{SAVED_LOCAL}", ROOT=str(root), AGENT_NAME="Lab")
    assert result.returncode == 0, result.stdout + result.stderr
    assert (host.sim / "s3" / SAVED_LOCAL).read_text() == local.read_text()
    assert not_saved_metric(root) == (0, "Lab")


def test_a_file_the_agent_cannot_start_with_is_not_saved_over_the_last_good_copy(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    """An edit with a typo is saved by the path unit at once; the bucket keeps no versions, so the operator's
    last good settings were gone, and a host that replaced this one started with no agent. Such a file is
    checked as the agent reads it, left unsaved with the problem and the fix, and pages until corrected."""
    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    local = root / "etc/so101-twin/agent.local.toml"
    good = "[alarms]\ntemperature_warning_c = 52.0\ntemperature_warning_clear_c = 48.0\n"
    host = HostSim(tmp_path / "host")
    local.write_text(good)
    assert host.run(SAVER, f"s3://{SAVED_LOCAL}", ROOT=str(root)).returncode == 0
    for typo in ("[alarms\ntemperature_warning_c = 52.0\n", "[alarms]\ntemperature_warning = 52.0\n"):
        local.write_text(typo)
        result = host.run(SAVER, f"s3://{SAVED_LOCAL}", ROOT=str(root), AGENT_NAME="Lab")
        out = result.stdout + result.stderr
        assert result.returncode == 1, out
        assert "not saved: /etc/so101-twin/agent.local.toml is not a config the agent can start with" in out
        assert "twin config check /etc/so101-twin/agent.toml /etc/so101-twin/agent.local.toml" in out, out
        assert (host.sim / "s3" / SAVED_LOCAL).read_text() == good
        assert not_saved_metric(root) == (1, "Lab")
    assert "temperature_warning" in out, out  # the agent's own words on what is wrong
    # The agent's venv broken (a deploy replacing it): not said to be the operator's typo, and not saved.
    twin = root / "opt/so101-twin/venv/bin/twin"
    twin.unlink()
    twin.write_text("#!/bin/sh\necho 'ModuleNotFoundError: No module named twin' >&2\nexit 1\n")
    twin.chmod(0o755)
    local.write_text(good.replace("52.0", "53.0"))
    result = host.run(SAVER, f"s3://{SAVED_LOCAL}", ROOT=str(root), AGENT_NAME="Lab")
    out = result.stdout + result.stderr
    assert result.returncode == 1 and "could not be checked" in out and "No module named twin" in out, out
    assert "not a config the agent can start with" not in out, out
    assert (host.sim / "s3" / SAVED_LOCAL).read_text() == good and not_saved_metric(root) == (1, "Lab")
    shutil.copy2(installed[0] / "opt/so101-twin/venv/bin/twin", twin)
    local.write_text(good.replace("52.0", "51.0"))
    assert host.run(SAVER, f"s3://{SAVED_LOCAL}", ROOT=str(root), AGENT_NAME="Lab").returncode == 0
    assert (host.sim / "s3" / SAVED_LOCAL).read_text() == local.read_text()
    assert not_saved_metric(root) == (0, "Lab")


def test_a_file_made_invalid_while_it_is_saved_is_not_saved(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    """The saver uploads again a change made during its upload (the path unit does not start it again): the
    file checked must be the file uploaded, so a typo saved meanwhile is checked in turn and refused, not
    uploaded over the good copy unchecked with the metric at 0."""
    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    local = root / "etc/so101-twin/agent.local.toml"
    good = "[alarms]\ntemperature_warning_c = 52.0\ntemperature_warning_clear_c = 48.0\n"
    local.write_text(good)
    host = HostSim(tmp_path / "host")
    assert host.run(SAVER, f"s3://{SAVED_LOCAL}", ROOT=str(root)).returncode == 0
    typo = "[alarms]\ntemperature_warning = 51.0\n"
    hook = host.sim / "on-upload"
    hook.write_text(f"#!/usr/bin/env bash\nprintf '%s' '{typo}' > '{local}'\n")
    hook.chmod(0o755)
    local.write_text(good.replace("52.0", "53.0"))
    result = host.run(SAVER, f"s3://{SAVED_LOCAL}", ROOT=str(root), AGENT_NAME="Lab")
    out = result.stdout + result.stderr
    assert result.returncode == 1, out
    assert "not saved: /etc/so101-twin/agent.local.toml is not a config the agent can start with" in out
    # The agent's words name the operator's file, not the copy checked.
    assert "/etc/so101-twin/agent.local.toml)" in out and "so101-twin-local-config." not in out, out
    assert (host.sim / "s3" / SAVED_LOCAL).read_text() == good.replace("52.0", "53.0")
    assert not_saved_metric(root) == (1, "Lab")


SAVED_ALARMS = "twin-history-bucket/host/alarm-state"
ALARM_SAVER = USERDATA / "save-alarm-state.sh"
AGENT_STATE_FILE = "var/lib/so101-twin-agent/state.json"


def write_alarm_state(path: Path, *, joint: str, wall: float) -> None:
    """The agent's state file as its running agent writes it (`stopped` false): `joint`'s over-temperature
    alarm LATCHED and the gripper's ACKNOWLEDGED."""
    from twin.core.alarms import AlarmKind, AlarmRecord, AlarmState
    from twin.service.persist import StateFile

    records = [
        AlarmRecord(
            "arm-001", joint, AlarmKind.OVER_TEMPERATURE, AlarmState.LATCHED, 100.0, False, 2, 66.0, "hot"
        ),
        AlarmRecord(
            "arm-001", "gripper", AlarmKind.OVERLOAD, AlarmState.ACKNOWLEDGED, 90.0, True, 1, 95.0, "x"
        ),
    ]
    assert StateFile(path).save(records, now_mono=110.0, now_wall=wall)


def test_a_new_host_starts_with_the_servo_alarms_of_the_host_it_replaces(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    """Acknowledged and latched servo alarms survive a change that replaces the instance: each host saves
    the agent's state file under its own id whenever the agent writes it, and a new disk's first install
    adopts the copy written last, before its agent first runs."""
    root, source = installed
    host_id = (root / "var/lib/so101-twin/host-id").read_text().strip()
    assert re.fullmatch(r"\d{8}T\d{6}Z-[0-9a-f]{8}", host_id), host_id
    saver = (root / "etc/systemd/system/so101-twin-alarm-state.service").read_text()
    assert f"ExecStart=/bin/bash /opt/so101-twin/userdata/save-alarm-state.sh s3://{SAVED_ALARMS}/\n" in saver
    watch = (root / "etc/systemd/system/so101-twin-alarm-state.path").read_text()
    assert "PathChanged=/var/lib/so101-twin-agent/state.json\n" in watch
    assert (
        'state_file = "/var/lib/so101-twin-agent/state.json"'
        in (root / "etc/so101-twin/agent.toml").read_text()
    )

    # The running agent writes its file; the path unit runs the saver, as here.
    old = tmp_path / "old"
    shutil.copytree(root, old / "root", symlinks=True)
    write_alarm_state(old / "root" / AGENT_STATE_FILE, joint="elbow_flex", wall=time.time())
    host = HostSim(old / "sim")
    result = host.run(ALARM_SAVER, f"s3://{SAVED_ALARMS}/", ROOT=str(old / "root"), AGENT_NAME="LabTwin")
    assert result.returncode == 0, result.stdout + result.stderr
    saved = host.sim / "s3" / SAVED_ALARMS / f"{host_id}.json"
    assert (
        f"saved /var/lib/so101-twin-agent/state.json to s3://{SAVED_ALARMS}/{host_id}.json" in result.stdout
    )
    assert saved.read_text() == (old / "root" / AGENT_STATE_FILE).read_text()

    # A new host. The bucket holds that copy and an older host's (a first boot that failed and was rolled
    # back writes a greater host id, but only once: the copy written last is the one in service).
    new_root = _new_host(installed, tmp_path / "new", None)
    bucket = tmp_path / "new" / "root-sim" / "sim" / "s3" / SAVED_ALARMS
    bucket.mkdir(parents=True)
    shutil.copy(saved, bucket / f"{host_id}.json")
    rolled_back = bucket / "29990101T000000Z-0000beef.json"
    write_alarm_state(rolled_back, joint="wrist_roll", wall=time.time() - 7200)
    os.utime(rolled_back, (time.time() - 3600, time.time() - 3600))
    result = run_installer(new_root, source)
    assert result.returncode == 0, result.stdout + result.stderr
    expected = f"servo alarm state adopted from s3://{SAVED_ALARMS}/{host_id}.json (2 alarms)"
    assert expected in result.stdout, result.stdout
    adopted = json.loads((new_root / AGENT_STATE_FILE).read_text())
    assert (
        "stopped" not in adopted
    )  # another host's run: this host's agent reports no unclean stop of its own
    assert adopted["alarms"] == json.loads(saved.read_text())["alarms"]
    from twin.service.persist import StateFile

    back = StateFile(new_root / AGENT_STATE_FILE).load(now_mono=5.0, now_wall=time.time())
    assert sorted((r.joint, str(r.state)) for r in back) == [
        ("elbow_flex", "LATCHED"),
        ("gripper", "ACKNOWLEDGED"),
    ]
    # The new host saves its own copy under its own id; the old host's stays as it was.
    new_id = (new_root / "var/lib/so101-twin/host-id").read_text().strip()
    assert new_id != host_id
    assert (bucket / f"{new_id}.json").read_text() == (new_root / AGENT_STATE_FILE).read_text()
    assert not_saved_metric(new_root, monitoring.ALARM_STATE_NOT_SAVED) == (0, "LabTwin")

    # Adopted once, at the disk's first install: a deploy later leaves the agent's own file alone.
    write_alarm_state(bucket / "30000101T000000Z-00000001.json", joint="shoulder_pan", wall=time.time())
    before = (new_root / AGENT_STATE_FILE).read_text()
    assert run_installer(new_root, source).returncode == 0
    assert (new_root / AGENT_STATE_FILE).read_text() == before


def test_the_alarm_state_is_uploaded_at_most_once_a_wait_and_ends_as_the_file_is(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    """The agent may rewrite its state file every second while alarms flap across a fleet: after an upload
    the saver waits, and uploads again only if the file changed meanwhile (a start asked for during its run
    merges into it, so the wait must look itself)."""
    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    state = root / AGENT_STATE_FILE
    write_alarm_state(state, joint="elbow_flex", wall=time.time())
    host = HostSim(tmp_path / "host")
    hook = host.sim / "on-sleep"
    later = tmp_path / "later.json"
    write_alarm_state(later, joint="wrist_flex", wall=time.time())
    hook.write_text(f"#!/usr/bin/env bash\ncp '{later}' '{state}'\n")
    hook.chmod(0o755)
    result = host.run(ALARM_SAVER, f"s3://{SAVED_ALARMS}/", ROOT=str(root), SAVE_EVERY_S="30")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "state.json changed since; saving it again" in result.stdout
    uploads = [c for c in host.calls() if c.startswith("aws s3 cp")]
    sleeps = [c for c in host.calls() if c.startswith("sleep")]
    assert len(uploads) == 2 and sleeps == ["sleep 30", "sleep 30"], host.calls()
    host_id = (root / "var/lib/so101-twin/host-id").read_text().strip()
    assert (host.sim / "s3" / SAVED_ALARMS / f"{host_id}.json").read_text() == later.read_text()


def test_a_saved_copy_that_cannot_be_read_is_never_overwritten_and_is_restored_later(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    """The bucket refuses the new host for a while: the agent starts with a placeholder, which is not saved
    over the operator's copy; the next install (a deploy) puts the copy in place."""
    settings = "[alarms]\ntemperature_warning_c = 50.0\ntemperature_warning_clear_c = 46.0\n"
    root = _new_host(installed, tmp_path, settings)
    host = HostSim.attach(tmp_path / "root-sim")
    (host.sim / "fail").mkdir(parents=True)
    host.fail("s3")  # the bucket refuses this role (tests/infra/hostsim.py, the aws stand-in)
    result = run_installer(root, installed[1])
    assert result.returncode == 0, result.stdout + result.stderr
    out = result.stdout
    assert "could not look for the saved /etc/so101-twin/agent.local.toml at s3://" in out, out
    assert "AccessDenied" in out and "is a placeholder until the saved copy can be read" in out, out
    assert "not saved: /etc/so101-twin/agent.local.toml is the placeholder" in out, out
    assert (
        "could not look for the servo alarm state saved at s3://twin-history-bucket/host/alarm-state/" in out
    )
    assert "the servo alarms of the host this one replaces are not carried over" in out, out
    assert not (root / AGENT_STATE_FILE).exists()
    local = root / "etc/so101-twin/agent.local.toml"
    assert tomllib.loads(local.read_text()) == {}  # the agent starts with no setting of it
    assert (host.sim / "s3" / SAVED_LOCAL).read_text() == settings  # the copy stays as it was
    # The host runs without the operator's settings: that pages (stacks/monitoring.py) until it is mended.
    assert not_saved_metric(root) == (1, "LabTwin")

    (host.sim / "fail" / "s3").unlink()
    result = run_installer(root, installed[1])
    assert result.returncode == 0, result.stdout + result.stderr
    assert local.read_text() == settings
    assert "restored /etc/so101-twin/agent.local.toml" in result.stdout
    assert not_saved_metric(root) == (0, "LabTwin")


def test_an_edited_placeholder_is_the_operators_and_stays(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    """Once the operator edits the placeholder it is theirs: a later install neither restores over it nor
    saves it while it still carries the placeholder's line (the saver says how to keep it)."""
    root = _new_host(installed, tmp_path, "[alarms]\ntemperature_warning_c = 50.0\n")
    host = HostSim.attach(tmp_path / "root-sim")
    (host.sim / "fail").mkdir(parents=True)
    host.fail("s3")  # the bucket refuses this role (tests/infra/hostsim.py, the aws stand-in)
    assert run_installer(root, installed[1]).returncode == 0
    local = root / "etc/so101-twin/agent.local.toml"
    local.write_text(local.read_text() + "[twin]\nshutdown_budget_s = 30.0\n")
    (host.sim / "fail" / "s3").unlink()
    result = run_installer(root, installed[1])
    assert result.returncode == 0, result.stdout + result.stderr
    assert "shutdown_budget_s = 30.0" in local.read_text()
    assert "delete its line" in result.stdout
    assert (host.sim / "s3" / SAVED_LOCAL).read_text() == "[alarms]\ntemperature_warning_c = 50.0\n"


def test_two_arms_decode_each_with_its_own_calibration_on_the_installed_host(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    """Done when: two arms calibrated differently, each decoded with its own, on the host config the installer
    produced. The agent runs as the unit's ExecStart says (the venv's `twin` swapped for this checkout's),
    pointed at a local mosquitto; the stack's bucket is moto's S3 server (AWS cannot be reached from here),
    which `twin calibration push` fills."""
    import json

    from conftest import Publisher, get_state, wait_for
    from moto_s3 import MotoS3
    from twin.rig.mosquitto import MosquittoBroker

    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    # What a deploy cannot know about this test machine goes where an operator's own settings go.
    (root / "etc/so101-twin/agent.local.toml").write_text(
        f'[cloudwatch]\nemf_file = "{tmp_path / "emf.log"}"\n[history]\nuri = ""\n'
    )
    example = REPO_ROOT / "robots/so101/calibration/so101_follower_example.json"
    moved = json.loads(example.read_text())
    moved["shoulder_pan"]["range_min"] += 150
    moved["shoulder_pan"]["range_max"] += 150
    (tmp_path / "arm-002.json").write_text(json.dumps(moved))
    s3 = MotoS3(bucket="twin-history-bucket")
    broker = MosquittoBroker(workdir=tmp_path / "mosquitto")
    broker.start()
    aws = {
        **os.environ,
        "AWS_ENDPOINT_URL": s3.endpoint,
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_EC2_METADATA_DISABLED": "true",
    }
    twin = str(REPO_ROOT / ".venv/bin/twin")
    agent = None
    publisher = None
    try:
        store = "s3://twin-history-bucket/calibration"
        for arm, path in (("arm-001", example), ("arm-002", tmp_path / "arm-002.json")):
            pushed = subprocess.run(
                [twin, "calibration", "push", arm, str(path), "--store", store, "--region", "eu-central-1"],
                env=aws,
                capture_output=True,
                text=True,
                timeout=120,
                check=False,
            )
            assert pushed.returncode == 0, pushed.stderr
        unit = (root / "etc/systemd/system/so101-twin-agent.service").read_text()
        (exec_start,) = [
            line.removeprefix("ExecStart=") for line in unit.splitlines() if line.startswith("ExecStart=")
        ]
        argv = [
            twin if a.endswith("/bin/twin") else f"{root}{a}" if a.startswith("/etc/") else a
            for a in exec_start.split()
        ]
        agent, base = _start_own_agent([*argv, "--broker", broker.url], {**aws, "MUJOCO_GL": "egl"})
        publisher = Publisher(broker.url)

        def both_shown() -> bool:
            ts = int(time.time() * 1000)
            for arm in ("arm-001", "arm-002"):
                joints = {
                    n: {"position": p}
                    for n, p in zip(
                        (
                            "shoulder_pan",
                            "shoulder_lift",
                            "elbow_flex",
                            "wrist_flex",
                            "wrist_roll",
                            "gripper",
                        ),
                        (2048, 1800, 2200, 2100, 2048, 2500),
                        strict=True,
                    )
                }
                publisher.publish(
                    arm, json.dumps({"device_id": arm, "timestamp": ts, "joints": joints}).encode()
                )
            try:
                devices = get_state(base).devices
            except OSError:
                return False
            return all(devices.get(a) and devices[a].joints_rad for a in ("arm-001", "arm-002"))

        wait_for(lambda: agent.poll() is None and both_shown(), 120, "both arms mirrored", interval=0.2)
        devices = get_state(base).devices
        k = 2 * 3.141592653589793 / 4095
        # shoulder_pan at 2048 ticks: (2048 - the middle of the arm's own calibrated range) * K.
        assert devices["arm-001"].joints_rad["shoulder_pan"] == pytest.approx((2048 - 2036) * k, abs=1e-9)
        assert devices["arm-002"].joints_rad["shoulder_pan"] == pytest.approx((2048 - 2186) * k, abs=1e-9)
        assert devices["arm-001"].calibration == f"{store}/arm-001.json"
        assert devices["arm-002"].calibration == f"{store}/arm-002.json"
        assert not devices["arm-001"].uncalibrated and not devices["arm-002"].uncalibrated
    finally:
        if publisher is not None:
            publisher.close()
        if agent is not None:
            agent.terminate()
            _, err = agent.communicate(timeout=60)
            assert agent.returncode == 0, err[-3000:]
        broker.stop()
        s3.close()


def _start_own_agent(argv: list[str], env: dict[str, str]) -> tuple[subprocess.Popen[str], str]:
    """`argv` with `--http` on a port picked free; started again on another port when another process took
    that one before the agent bound it (the agent exits saying so), so the test never polls a server that is
    not its agent (twin.rig.local.await_own_http, as the rig's agents are started)."""
    from twin.rig.local import await_own_http, port_taken
    from twin.rig.mosquitto import free_port

    said = ""
    for _ in range(3):
        port = free_port()
        agent = subprocess.Popen(
            [*argv, "--http", f"127.0.0.1:{port}"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        said = await_own_http(agent, port, functools.partial(_stderr_of, agent), where="its stderr") or ""
        if agent.poll() is None:
            return agent, f"http://127.0.0.1:{port}"
        if not port_taken(said, port):
            raise AssertionError(f"the agent exited with {agent.returncode}: {said[-3000:]}")
    raise AssertionError(f"three ports picked free were taken before the agent bound them: {said[-3000:]}")


def _stderr_of(process: subprocess.Popen[str]) -> str:
    return process.stderr.read() if process.stderr is not None else ""


def test_ros2_enables_the_bridge_from_the_lock_it_already_has(
    installed: tuple[Path, Path], tmp_path: Path
) -> None:
    root = tmp_path / "root"
    shutil.copytree(installed[0], root, symlinks=True)
    before = host_state(root)
    result = run_installer(root, installed[1], ROS2="true")
    assert result.returncode == 0, result.stderr
    # The lock holds the ros2 extra's packages already: only the config changes, pip does not run again.
    assert "installing" not in result.stdout
    after = host_state(root)
    assert sorted(k for k in after if before.get(k) != after[k]) == ["etc/so101-twin/agent.toml"]
    from twin.service.config import load_config

    loaded = load_config(root / "etc/so101-twin/agent.toml")
    assert loaded.ros2.enabled
    assert loaded.ros2.topic == "/{arm}/joint_states"


@pytest.mark.parametrize(
    ("env", "message"),
    [
        ({"UNITS": "radians"}, "UNITS=radians"),
        ({"ROS2": "yes"}, "ROS2=yes is not true or false"),
        ({"AGENT_SRC": "/nonexistent"}, "no pyproject.toml"),
        ({"RECORD_SESSIONS": "yes"}, "RECORD_SESSIONS=yes is not true or false"),
        ({"ARM_RATE_HZ": "10 Hz"}, "ARM_RATE_HZ=10 Hz is not a number"),
        ({"MAX_CONNECTIONS": "08"}, "MAX_CONNECTIONS=08 is not a whole number above 0"),
    ],
)
def test_installer_refuses_bad_input(tmp_path: Path, env: dict[str, str], message: str) -> None:
    result = run_installer(tmp_path / "root", REPO_ROOT, **env)
    assert result.returncode == 2
    assert message in result.stderr
    assert not (tmp_path / "root" / "etc").exists()


def test_installer_refuses_a_source_without_the_lock(tmp_path: Path) -> None:
    source = tmp_path / "agent"
    source.mkdir()
    shutil.copy(REPO_ROOT / "pyproject.toml", source / "pyproject.toml")
    result = run_installer(tmp_path / "root", source)
    assert result.returncode == 2
    assert "has no requirements/host.txt, the hashed dependency lock" in result.stderr
    assert not (tmp_path / "root" / "opt").exists()


def test_installer_installs_only_what_the_lock_hashes(locked_source: Path, tmp_path: Path) -> None:
    """A wheel that is not the one the lock hashed is refused by pip (--require-hashes), and nothing else
    is fetched: the agent is built with --no-index and --no-build-isolation."""
    text = (USERDATA / "install-agent.sh").read_text()
    assert '--require-hashes --no-deps $PIP_ARGS -r "$AGENT_SRC/$LOCK"' in text
    assert '--no-deps --no-build-isolation --no-index $PIP_ARGS "$build"' in text
    source = tmp_path / "agent"
    shutil.copytree(locked_source, source)
    lock = source / "requirements" / "host.txt"
    lock.write_text(re.sub(r"sha256:[0-9a-f]{64}", "sha256:" + "0" * 64, lock.read_text()))
    result = run_installer(tmp_path / "root", source)
    assert result.returncode != 0
    assert "DO NOT MATCH THE HASHES" in result.stderr
    assert not (tmp_path / "root/opt/so101-twin/venv/.so101-twin-source.sha256").exists()


def test_boot_hands_every_installer_setting_from_the_deployment_parameter(synth_all_options: Synth) -> None:
    """Each setting install-agent.sh reads that the stack puts in the deployment parameter (ROS2,
    HISTORY_URI, RECORD_SESSIONS, ...) is passed on by bootstrap.sh's agent step; one left out would be
    silently replaced by the installer's default on the host."""

    def text_of(value: object) -> str:  # the literal parts of a Fn::Join, with their real newlines
        if isinstance(value, str):
            return value
        if isinstance(value, list):
            return "".join(text_of(v) for v in value)
        if isinstance(value, dict):
            return "".join(text_of(v) for v in value.values())
        return ""

    parameter = text_of(synth_all_options.one("AWS::SSM::Parameter")["Properties"]["Value"])
    stack_keys = set(re.findall(r"^([A-Z][A-Z0-9_]*)=", parameter, re.M))
    installer_keys = set(
        re.findall(r'^([A-Z][A-Z0-9_]*)="\$\{\1:-', (USERDATA / "install-agent.sh").read_text(), re.M)
    )
    bootstrap = (USERDATA / "bootstrap.sh").read_text()
    step = re.search(r"^step_agent\(\) \{\n(.*?)^\}", bootstrap, re.S | re.M)
    assert step is not None
    passed = set(re.findall(r"\b([A-Z][A-Z0-9_]*)=", step.group(1)))
    wanted = stack_keys & installer_keys
    assert {"ROS2", "HISTORY_URI", "RECORD_SESSIONS", "AGENT_NAME", "DEVICES"} <= wanted
    assert wanted <= passed, f"step_agent does not pass {sorted(wanted - passed)}"


def test_host_scripts_use_the_agents_http_address(installed: tuple[Path, Path]) -> None:
    """install-agent.sh writes the agent's listen address and host-check.sh (the boot's verify step and
    `twin instance check`) asks it for /healthz: both must be the one the agent package defines."""
    from twin.service.config import DEFAULT_AGENT_URL, DEFAULT_HTTP_HOST, DEFAULT_HTTP_PORT

    config = tomllib.loads((installed[0] / "etc/so101-twin/agent.toml").read_text())
    assert config["http"]["listen"] == f"{DEFAULT_HTTP_HOST}:{DEFAULT_HTTP_PORT}"
    check = subprocess.run(
        [
            "bash",
            "-c",
            'unset AGENT_HTTP; . "$1"; printf %s "$AGENT_HTTP"',
            "-",
            str(USERDATA / "host-check.sh"),
        ],
        capture_output=True,
        text=True,
        check=True,
        timeout=30,
    )
    assert check.stdout == DEFAULT_AGENT_URL


def test_cloudwatch_agent_ships_the_emf_file_the_agent_writes() -> None:
    """The CloudWatch agent config in bootstrap.sh, rendered as the shell would, follows the EMF file."""
    import json
    import re

    from twin.output.emf import DEFAULT_EMF_FILE

    text = (USERDATA / "bootstrap.sh").read_text()
    assert f"local EMF_FILE={DEFAULT_EMF_FILE}\n" in text
    config = re.search(
        r"write_file /opt/aws/amazon-cloudwatch-agent/etc/so101-twin.json 0644 <<JSON\n(.*?)\nJSON\n",
        text,
        re.S,
    )
    assert config is not None
    rendered = (
        config.group(1).replace("${LOG_GROUP}", "/so101-twin/S/host").replace("${EMF_FILE}", DEFAULT_EMF_FILE)
    )
    files = json.loads(rendered)["logs"]["logs_collected"]["files"]["collect_list"]
    emf = [f for f in files if f["file_path"] == DEFAULT_EMF_FILE]
    assert emf == [
        {
            "file_path": DEFAULT_EMF_FILE,
            "log_group_name": "/so101-twin/S/host",
            "log_stream_name": "{instance_id}/emf",
        }
    ]


# --- the viewer supervisor ---------------------------------------------------------------------------------


def fake_viewer(root: Path, body: str) -> Path:
    """A stand-in `twin` in the venv: the supervisor's only job is to keep whatever that is running."""
    twin = root / "opt/so101-twin/venv/bin/twin"
    twin.parent.mkdir(parents=True, exist_ok=True)
    twin.write_text(f'#!/usr/bin/env bash\necho "$*" >>{root}/starts\n{body}\n')
    twin.chmod(0o755)
    return twin


def test_supervisor_restarts_a_viewer_that_dies(tmp_path: Path) -> None:
    fake_viewer(tmp_path, "exit 3")
    result = subprocess.run(
        ["bash", str(USERDATA / "view-supervisor.sh")],
        env={**os.environ, "ROOT": str(tmp_path), "VIEW_POLL_S": "0.05", "VIEW_MAX_STARTS": "3"},
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "starts").read_text() == "view\nview\nview\n"
    assert result.stderr.count("twin view exited with status 3") == 3


def test_supervisor_restarts_the_viewer_when_the_agent_package_changes(tmp_path: Path) -> None:
    fake_viewer(tmp_path, "exec sleep 30")
    stamp = tmp_path / "opt/so101-twin/venv/.so101-twin-source.sha256"
    stamp.write_text("old\n")
    proc = subprocess.Popen(
        ["bash", str(USERDATA / "view-supervisor.sh")],
        env={**os.environ, "ROOT": str(tmp_path), "VIEW_POLL_S": "0.05", "VIEW_MAX_STARTS": "2"},
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 20
        while not (tmp_path / "starts").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        stamp.write_text("new\n")
        # The second start is killed by the test's end; wait for it to appear.
        while (tmp_path / "starts").read_text().count("view") < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert (tmp_path / "starts").read_text() == "view\nview\n"
    finally:
        proc.terminate()
        _, stderr = proc.communicate(timeout=20)
    assert "the agent package changed; restarting the viewer" in stderr


# --- the helpers every script shares -----------------------------------------------------------------------


def lib_call(script: str, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    """Source userdata/lib.sh and run `script` (bash) with `args` as $1..."""
    return subprocess.run(
        ["bash", "-c", f'set -Eeuo pipefail; . "{USERDATA}/lib.sh"; {script}', "-", *args],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_the_deployment_parameter_gives_only_the_keys_the_host_takes(
    synth_all_options: Synth, tmp_path: Path
) -> None:
    """Whoever can write the parameter must not reach the next root bootstrap's environment."""

    def text_of(value: object) -> str:
        if isinstance(value, str):
            return value
        if isinstance(value, list):
            return "".join(text_of(v) for v in value)
        if isinstance(value, dict):
            return "".join(text_of(v) for v in value.values())
        return ""

    parameter = text_of(synth_all_options.one("AWS::SSM::Parameter")["Properties"]["Value"])
    stack_keys = set(re.findall(r"^([A-Z][A-Z0-9_]*)=", parameter, re.M))
    allowed = lib_call('printf "%s\\n" "${DEPLOYMENT_KEYS[@]}"').stdout.split()
    assert stack_keys == set(allowed)
    env_file = tmp_path / "deployment.env"
    env_file.write_text(
        "DEVICES=arm-001\nLD_PRELOAD=/tmp/evil.so\nPIP_INDEX_URL=http://203.0.113.9/simple\nPATH=/tmp/evil\n"
        "lowercase=x\n# a comment\n\nUNITS=ticks\n"
    )
    shown = lib_call(
        'load_env "$1"; printf "%s|%s|%s|%s\\n" "$DEVICES" "$UNITS" "${PIP_INDEX_URL:-unset}" '
        '"${LD_PRELOAD:-unset}"',
        str(env_file),
        PATH=os.environ["PATH"],
    )
    assert shown.returncode == 0, shown.stderr
    assert shown.stdout.splitlines()[-1] == "arm-001|ticks|unset|unset"
    for key in ("LD_PRELOAD", "PIP_INDEX_URL", "PATH", "lowercase"):
        assert f"ignoring {key} in {env_file}: not a setting this host takes" in shown.stdout


@pytest.fixture(scope="module")
def signer() -> Iterator[TestSigner]:
    key = TestSigner("helper-test")
    try:
        yield key
    finally:
        key.close()


def test_verify_deb_checks_the_builder_signature_and_every_member(signer: TestSigner, tmp_path: Path) -> None:
    key = tmp_path / "key.asc"
    key.write_bytes(signer.public_key())
    good = make_deb(tmp_path / "good_1_amd64.deb", "good", b"payload" * 1000, signer)
    ok = lib_call('verify_deb "$1" "$2" "$3"', str(key), signer.fingerprint, str(good), TMPDIR=str(tmp_path))
    assert ok.returncode == 0, ok.stderr
    # A member changed after signing.
    tampered = tmp_path / "tampered"
    tampered.mkdir()
    subprocess.run(["ar", "x", str(good)], cwd=tampered, check=True)
    (tampered / "data.tar.xz").write_bytes(b"payload" * 999 + b"evil" * 2)
    bad = tmp_path / "bad_1_amd64.deb"
    names = ["debian-binary", "control.tar.gz", "data.tar.xz", "_gpgbuilder"]
    subprocess.run(["ar", "rcD", str(bad), *names], cwd=tampered, check=True)
    refused = lib_call(
        'verify_deb "$1" "$2" "$3"', str(key), signer.fingerprint, str(bad), TMPDIR=str(tmp_path)
    )
    assert refused.returncode == 1
    assert "member data.tar.xz does not match its signed checksums" in refused.stderr
    # No builder signature at all.
    unsigned = make_deb(tmp_path / "unsigned_1_amd64.deb", "unsigned", b"x", None)
    refused = lib_call(
        'verify_deb "$1" "$2" "$3"', str(key), signer.fingerprint, str(unsigned), TMPDIR=str(tmp_path)
    )
    assert refused.returncode == 1 and "carries no builder signature" in refused.stderr
    # Signed, but the key served next to it is not the pinned one.
    refused = lib_call('verify_deb "$1" "$2" "$3"', str(key), "0" * 40, str(good), TMPDIR=str(tmp_path))
    assert (
        refused.returncode == 1 and f"has fingerprint {signer.fingerprint}, not the pinned" in refused.stderr
    )


def signed_package(signer: TestSigner, where: Path) -> tuple[Path, Path, Path]:
    """(the signer's public key file, a package, its detached signature), written under `where`."""
    key = where / "key.asc"
    key.write_bytes(signer.public_key())
    package = where / "agent.deb"
    package.write_bytes(b"Package: amazon-cloudwatch-agent\n")
    sig = where / "agent.deb.sig"
    sig.write_bytes(signer.detach_sign(package.read_bytes()))
    return key, package, sig


def verify_detached(
    key: Path, fingerprint: str, sig: Path, package: Path, tmp: Path
) -> subprocess.CompletedProcess[str]:
    return lib_call('verify_detached "$@"', str(key), fingerprint, str(sig), str(package), TMPDIR=str(tmp))


def test_verify_detached_needs_the_pinned_key(signer: TestSigner, tmp_path: Path) -> None:
    key, package, sig = signed_package(signer, tmp_path)
    ok = verify_detached(key, signer.fingerprint, sig, package, tmp_path)
    assert ok.returncode == 0, ok.stderr
    package.write_bytes(b"Package: something-else\n")
    refused = verify_detached(key, signer.fingerprint, sig, package, tmp_path)
    assert refused.returncode == 1 and "no valid signature by" in refused.stderr


def test_signatures_verify_under_a_temporary_directory_too_long_for_an_agent_socket(
    signer: TestSigner, tmp_path: Path
) -> None:
    """The keyrings are made under TMPDIR; a gpg-agent's socket in one must fit 108 bytes. No agent is
    started (--no-autostart), so a long TMPDIR (a test runner's, a host's) does not fail the import."""
    long_tmp = tmp_path / ("t" * 90)
    long_tmp.mkdir()
    key, package, sig = signed_package(signer, tmp_path)
    ok = verify_detached(key, signer.fingerprint, sig, package, long_tmp)
    assert ok.returncode == 0, ok.stderr
    good = make_deb(tmp_path / "good_1_amd64.deb", "good", b"payload" * 100, signer)
    ok = lib_call('verify_deb "$1" "$2" "$3"', str(key), signer.fingerprint, str(good), TMPDIR=str(long_tmp))
    assert ok.returncode == 0, ok.stderr
    # A key file that is no key: refused, saying what gpg said.
    garbage = tmp_path / "garbage.asc"
    garbage.write_text("<html>Access Denied</html>\n")
    refused = verify_detached(garbage, signer.fingerprint, sig, package, long_tmp)
    assert refused.returncode == 1
    assert f"gpg could not import {garbage}: " in refused.stderr and "no valid OpenPGP data" in refused.stderr
    assert list(long_tmp.iterdir()) == []  # the keyrings and work directories are gone, refused or not


def test_the_pinned_downloads_are_one_well_formed_file_in_the_scripts_asset(synth_default: Synth) -> None:
    text = (USERDATA / "releases.env").read_text()
    pins = dict(line.split("=", 1) for line in text.splitlines() if line and not line.startswith("#"))
    assert re.fullmatch(r"\d{4}\.\d+-\d+", pins["DCV_VERSION"])
    assert re.fullmatch(r"[0-9a-f]{64}", pins["DCV_SHA256_UBUNTU2404_X86_64"])
    assert re.fullmatch(r"[0-9A-F]{40}", pins["DCV_KEY_FINGERPRINT"])
    assert re.fullmatch(r"[0-9A-F]{40}", pins["CLOUDWATCH_KEY_FINGERPRINT"])
    # Nothing else names a DCV release: the version and its hash live in this file only.
    for script in SCRIPTS:
        assert pins["DCV_VERSION"] not in script.read_text(), script.name
    outdir = Path(synth_default.stack.node.root.outdir)
    shipped = next(p for p in outdir.glob("asset.*") if (p / "bootstrap.sh").exists())
    assert (shipped / "releases.env").read_text() == text


def test_the_dpkg_lock_probe_names_the_holder(tmp_path: Path) -> None:
    lock = tmp_path / "var/lib/dpkg/lock-frontend"
    lock.parent.mkdir(parents=True)
    lock.touch()
    free = lib_call("dpkg_lock_holder", ROOT=str(tmp_path))
    assert free.returncode == 0 and free.stdout == ""
    with dpkg_lock_held(lock) as pid:
        held = lib_call("dpkg_lock_holder", ROOT=str(tmp_path))
    assert re.fullmatch(rf"{pid} \(python[\d.]*\) on /var/lib/dpkg/lock-frontend", held.stdout.strip())
