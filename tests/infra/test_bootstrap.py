"""The whole first boot, an in-place update, the checks after a start and every failing boot the deploy must
name, run for real against a stand-in host.

The scripts are the ones the synthesized template carries: the UserData text and the deployment parameter
are taken from the template and resolved as CloudFormation would (tests/infra/hostsim.py), the State
Manager association's commands likewise; the assets are the ones the synth staged, with two files swapped
because a test runs offline: the agent asset's dependency lock pins a small local wheel instead of the
agent's dependencies from PyPI, and the scripts asset's releases.env pins the test release the CDN stand-in
serves (a DCV tarball of the real layout whose packages are signed, like the CloudWatch agent package, by
throw-away keys: every signature check is real gpg). What stands in for the system tools, and what each
encodes, is described in hostsim.py. Nothing here reaches AWS or the network.
"""

from __future__ import annotations

import grp
import json
import os
import re
import shutil
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from stacks import monitoring

from .hostsim import (
    ALARM_TOPIC_ARN,
    APT_UNITS,
    BOOT_ID,
    HANDLE_URL,
    HISTORY_BUCKET,
    INSTANCE_ID,
    LOG_GROUP,
    OLD_PASSWORD,
    PASSWORD,
    REGION,
    SECRET_ARN,
    STACK_NAME,
    HostSim,
    TestSigner,
    black_viewer_png,
    dpkg_lock_held,
    lock_text,
    lock_wheels,
    make_cdn,
    resolve,
    tree_digest,
    uniform_png,
    with_lock,
    zip_dir,
)
from .synth import REPO_ROOT, Synth

# 600 s, not the suite's 300: pytest-timeout counts a test's fixtures in its budget, and whichever of this
# module's tests comes first (a random order) pays the session's cdk synth and the host sim's first boot,
# about 20 s of CPU. A stress run at a load average of 15-21 on two cores stretched that past 300 s once;
# a hang still ends here.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

USERDATA = REPO_ROOT / "userdata"


def refs_for(synth: Synth) -> dict[str, str]:
    """Ref values of the named resources the host's scripts see."""
    values = {}
    for logical_id, resource in synth.json["Resources"].items():
        if resource["Type"] == "AWS::SecretsManager::Secret":
            values[logical_id] = SECRET_ARN
        elif resource["Type"] == "AWS::Logs::LogGroup" and "AgentLogGroup" in logical_id:
            values[logical_id] = LOG_GROUP
        elif resource["Type"] == "AWS::CloudFormation::WaitConditionHandle":
            values[logical_id] = HANDLE_URL
        elif resource["Type"] == "AWS::S3::Bucket" and logical_id.startswith("History"):
            values[logical_id] = HISTORY_BUCKET
        elif resource["Type"] == "AWS::SNS::Topic":
            values[logical_id] = ALARM_TOPIC_ARN
    return values


class Deployed:
    """What a deploy of `synth` puts in front of the host: UserData, parameter, association, S3 objects."""

    def __init__(self, synth: Synth, workdir: Path, pins: str) -> None:
        refs = refs_for(synth)
        instance_id, instance = next(iter(synth.resources("AWS::EC2::Instance").items()))
        self.logical_id = instance_id
        self.user_data = resolve(instance["Properties"]["UserData"], refs)
        self.parameter = resolve(synth.one("AWS::SSM::Parameter")["Properties"]["Value"], refs)
        commands = synth.one("AWS::SSM::Association")["Properties"]["Parameters"]["commands"]
        self.update_script = "\n".join(resolve(commands, refs)) + "\n"
        self.settings = dict(line.split("=", 1) for line in self.parameter.splitlines())
        self.version = self.settings["DEPLOYMENT_VERSION"]
        outdir = Path(synth.stack.node.root.outdir)
        agent_dir = next(p for p in outdir.glob("asset.*") if (p / "pyproject.toml").exists())
        scripts_dir = next(p for p in outdir.glob("asset.*") if (p / "bootstrap.sh").exists())
        workdir.mkdir(parents=True, exist_ok=True)
        agent = with_lock(agent_dir, workdir / "agent", lock_text(lock_wheels(workdir / "wheels")))
        scripts = workdir / "scripts"
        shutil.copytree(scripts_dir, scripts)
        assert (scripts / "releases.env").is_file(), "the scripts asset must carry the pins"
        (scripts / "releases.env").write_text(pins)
        self.s3 = {
            self.settings["AGENT_URL"].removeprefix("s3://"): zip_dir(agent, workdir / "agent.zip"),
            self.settings["SCRIPTS_URL"].removeprefix("s3://"): zip_dir(scripts, workdir / "scripts.zip"),
        }


@pytest.fixture(scope="module")
def release(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    dcv_key, cloudwatch_key = TestSigner("dcv-test"), TestSigner("cloudwatch-test")
    try:
        yield make_cdn(tmp_path_factory.mktemp("cdn"), dcv_key, cloudwatch_key)
    finally:
        dcv_key.close()
        cloudwatch_key.close()


@pytest.fixture(scope="module")
def deployed(
    synth_default: Synth, release: dict[str, Any], tmp_path_factory: pytest.TempPathFactory
) -> Deployed:
    return Deployed(synth_default, tmp_path_factory.mktemp("deployed"), release["pins"])


def new_host(base: Path, deployed: Deployed, release: dict[str, Any], **options: Any) -> HostSim:
    host = HostSim(
        base,
        parameter=deployed.parameter,
        user_data=deployed.user_data,
        s3=deployed.s3,
        cdn=release["dir"],
        **options,
    )
    lock_wheels(host.sim / "wheels")
    return host


def first_boot(host: HostSim, deployed: Deployed) -> subprocess.CompletedProcess[str]:
    script = host.sim / "user-data-as-launched.sh"
    script.write_text(deployed.user_data)
    return host.run(script)


@pytest.fixture(scope="module")
def booted(
    deployed: Deployed, release: dict[str, Any], tmp_path_factory: pytest.TempPathFactory
) -> tuple[HostSim, subprocess.CompletedProcess[str]]:
    host = new_host(tmp_path_factory.mktemp("host"), deployed, release)
    result = first_boot(host, deployed)
    return host, result


def copy_of(host: HostSim, tmp_path: Path) -> HostSim:
    shutil.copytree(host.root.parent, tmp_path / "host", symlinks=True)
    return HostSim.attach(tmp_path / "host")


def failure_reason(host: HostSim) -> str:
    posts = host.handle_posts()
    assert [p["Status"] for p in posts] == ["FAILURE"], posts
    assert any("--status FAILURE" in s for s in host.signals())
    assert not (host.root / "var/lib/so101-twin/deployed-version").exists()
    return posts[0]["Reason"]


def apt_restored(host: HostSim) -> None:
    """Automatic updates are back as the boot found them, whatever its outcome."""
    assert not [unit for unit in APT_UNITS if host.masked(unit)]
    assert host.active("apt-daily.timer") and host.active("apt-daily-upgrade.timer")
    assert not (host.root / "var/lib/so101-twin/apt-held").exists()


# --- the release stand-in is realistic ---------------------------------------------------------------------


def test_the_dcv_tarball_stand_in_is_realistic_and_breaks_tar_head_under_pipefail(release) -> None:
    """Several MB, several members in one versioned directory: enough that `tar -t | head -1` (the old
    bootstrap's way to find the directory) dies of SIGPIPE under pipefail, as reproduced with GNU tar.

    Whether `head` has gone by the time tar lists its second member is up to the scheduler (tar has
    megabytes to decompress in between, but a loaded machine can run it first), so the test does not run
    that race: it shows that tar lists more than one member and that tar, writing a member's name to a
    pipe whose reader has gone, is killed by SIGPIPE, which pipefail turns into the boot's failure."""
    tarball = release["tarball"]
    assert tarball.stat().st_size > 5_000_000
    listing = subprocess.run(["tar", "-tzf", str(tarball)], capture_output=True, text=True, check=True)
    assert len(listing.stdout.splitlines()) >= 5
    read_end, write_end = os.pipe()
    os.close(read_end)  # what `head -1` leaves once it has its line
    try:
        old = subprocess.run(
            ["tar", "-tzf", str(tarball)], stdout=write_end, stderr=subprocess.PIPE, check=False
        )
    finally:
        os.close(write_end)
    assert old.returncode == -signal.SIGPIPE, (old.returncode, old.stderr)


# --- first boot --------------------------------------------------------------------------------------------


def test_first_boot_succeeds_and_signals_success_after_verifying(booted, deployed: Deployed) -> None:
    host, result = booted
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    signals = host.signals()
    assert len(signals) == 1
    assert "--status SUCCESS" in signals[0]
    assert f"--stack-name {STACK_NAME}" in signals[0]
    assert f"--logical-resource-id {deployed.logical_id}" in signals[0]
    assert f"--unique-id {INSTANCE_ID}" in signals[0]
    posts = host.handle_posts()
    assert [p["Status"] for p in posts] == ["SUCCESS"]
    assert posts[0]["UniqueId"] == INSTANCE_ID
    assert host.file("/var/lib/so101-twin/deployed-version").strip() == deployed.version
    log = host.file("/var/log/so101-twin-bootstrap.log")
    for check in (
        "x-on-gpu: Xorg runs on NVIDIA L40S, 580.95.05; OpenGL on :0: NVIDIA L40S/PCIe/SSE2 (NVIDIA",
        "dcv-session: console session owned by ubuntu; DCV listens on TCP 8443 and UDP 8443 (QUIC)",
        "agent: connected and subscribed",
        "viewer: twin view runs in ubuntu's desktop session (the same process for 120 s)",
        "screen: the console shows a desktop (1280x720",
        "the viewer drawn in its window (1320x750 at +300+180)",
    ):
        assert check in log
    # The capture a person would have seen is kept on the host.
    assert (host.root / "var/lib/so101-twin/console.png").stat().st_size > 1000
    # The signal is the very last thing the boot does; just before it, once the host is verified, a silent
    # agent starts to page (the alarm is created with its actions off, so the install does not).
    calls = host.calls()
    assert calls[-1].startswith("aws cloudformation signal-resource")
    assert host.armed() == [f"{STACK_NAME}-AgentSilent"]
    arm = next(i for i, c in enumerate(calls) if c.startswith("aws cloudwatch enable-alarm-actions"))
    assert f"--region {REGION}" in calls[arm]
    assert log.index("step verify: done") < log.index(f"alarm {STACK_NAME}-AgentSilent armed")


def test_steps_run_in_order_apt_held_first_x_before_dcv(booted) -> None:
    host, _ = booted
    calls = host.calls()

    def first(prefix: str) -> int:
        return next(i for i, c in enumerate(calls) if c.startswith(prefix))

    def last(prefix: str) -> int:
        return max(i for i, c in enumerate(calls) if c.startswith(prefix))

    # Automatic updates are stopped and masked (until reboot only) before anything touches dpkg, and come
    # back after the last install, before the signal.
    mask = first("systemctl mask --runtime")
    assert all(unit in calls[mask] for unit in APT_UNITS)
    assert first("systemctl stop apt-daily.timer") < mask < first("apt-get")
    unmask = first("systemctl unmask --runtime")
    assert last("apt-get") < unmask < first("aws cloudformation signal-resource")
    assert "systemctl start apt-daily.timer apt-daily-upgrade.timer unattended-upgrades.service" in calls
    apt_restored(host)
    # CloudWatch from the first installing step: configured before any package is installed.
    desktop = [i for i, c in enumerate(calls) if c.startswith("apt-get") and "ubuntu-desktop-minimal" in c]
    assert first("amazon-cloudwatch-agent-ctl -a fetch-config") < desktop[0]
    assert first("systemctl restart gdm3") < first("systemctl restart dcvserver")
    assert first("nvidia-xconfig") < first("systemctl restart gdm3")
    log = host.file("/var/log/so101-twin-bootstrap.log")
    steps = re.findall(r"step (\w+): done", log)
    assert steps == [
        "apt",
        "logs",
        "packages",
        "gpu",
        "agent",
        "desktop",
        "password",
        "dcv",
        "display",
        "verify",
        "alarms",
    ]
    # The log holds the UserData's own first line: the file the CloudWatch agent ships from its beginning.
    assert log.splitlines()[0].startswith("so101-twin user-data: boot start")
    cw = json.loads(host.file("/opt/aws/amazon-cloudwatch-agent/etc/so101-twin.json"))
    files = cw["logs"]["logs_collected"]["files"]["collect_list"]
    assert {f["file_path"] for f in files} >= {
        "/var/log/so101-twin-bootstrap.log",
        "/var/log/so101-twin-agent.log",
        "/var/log/so101-twin-start.log",
        "/var/log/so101-twin-host-emf.log",
    }
    assert {f["log_group_name"] for f in files} == {LOG_GROUP}


def test_every_download_is_bounded_and_verified(booted) -> None:
    host, _ = booted
    calls = host.calls()
    downloads = [c for c in calls if c.startswith("curl") and " -o " in c and "127.0.0.1" not in c]
    assert len(downloads) >= 5
    for call in downloads:
        assert "--max-time" in call and "--retry" in call, call
    assert all(
        "--max-time" in c for c in calls if c.startswith("curl") and "cloudformation-waitcondition" in c
    )
    # DCV: the pinned release's versioned tarball, never the moving "latest" alias.
    assert any("/2025.0/Servers/nice-dcv-2025.0-20103-ubuntu2404-x86_64.tgz" in c for c in downloads)
    assert not any("nice-dcv-ubuntu2404-x86_64.tgz" in c for c in calls)
    log = host.file("/var/log/so101-twin-bootstrap.log")
    assert "CloudWatch agent package: signature by" in log
    assert "DCV tarball SHA-256 and package signatures by" in log
    assert all(
        " --cli-read-timeout " in c for c in calls if c.startswith(("aws s3", "aws ssm", "aws secrets"))
    )


def test_desktop_is_installed_with_recommends_and_x_may_run_as_root(booted) -> None:
    host, _ = booted
    calls = host.calls()
    desktop = next(c for c in calls if c.startswith("apt-get") and "ubuntu-desktop-minimal" in c)
    assert "--install-recommends" in desktop and "xserver-xorg-legacy" in desktop and "gdm3" in desktop
    assert (host.root / "usr/lib/xorg/Xorg.wrap").exists()
    wrapper = host.file("/etc/X11/Xwrapper.config")
    assert "needs_root_rights=yes" in wrapper


def test_headless_nvidia_x_config_uses_the_drivers_own_module(booted) -> None:
    host, _ = booted
    xorg = host.file("/etc/X11/xorg.conf")
    assert '"nvidia"' in xorg
    assert '"AllowEmptyInitialConfiguration" "True"' in xorg
    assert "Virtual     4096 2160" in xorg
    calls = host.calls()
    # The DLAMI's driver brings its Xorg module: nothing is installed over it.
    assert not [c for c in calls if "xserver-xorg-video-nvidia" in c or c.startswith("apt-cache")]
    nvx = next(c for c in calls if c.startswith("nvidia-xconfig"))
    assert "--allow-empty-initial-configuration" in nvx and "--virtual=4096x2160" in nvx


def test_desktop_is_quiet_owned_by_the_user_and_not_an_administrator(booted) -> None:
    host, _ = booted
    gdm = host.file("/etc/gdm3/custom.conf")
    assert "WaylandEnable=false" in gdm and "AutomaticLogin=ubuntu" in gdm
    schema = host.file("/usr/share/glib-2.0/schemas/90_so101-twin.gschema.override")
    assert "idle-delay=0" in schema and "lock-enabled=false" in schema
    assert host.file("/home/ubuntu/.config/gnome-initial-setup-done").strip() == "yes"
    autostart = host.file("/home/ubuntu/.config/autostart/so101-twin-view.desktop")
    assert "Exec=/opt/so101-twin/bin/twin-view-supervised" in autostart
    calls = host.calls()
    chowns = [i for i, c in enumerate(calls) if c == f"chown -R ubuntu: {host.root}/home/ubuntu/.config"]
    assert chowns, "~/.config was never handed to the desktop user"
    # Handed over after the last file was written into it (the desktop step writes last).
    assert chowns[-1] > max(i for i, c in enumerate(calls) if c.startswith("glib-compile-schemas"))
    # The DCV login is not root: no sudo, no lxd, no NOPASSWD rule.
    assert host.groups("ubuntu") == ["ubuntu", "adm"]
    assert "ubuntu ALL" not in host.file("/etc/sudoers.d/90-cloud-init-users")


def test_the_desktop_gets_a_browser_for_the_console_launcher(booted) -> None:
    """The desktop install brings no browser (ubuntu-desktop-minimal recommends none since Ubuntu 21.10; its
    Firefox is a snap the installer seeds): the boot installs the snap, and the launcher opens the command it
    put in /snap/bin."""
    host, _ = booted
    calls = host.calls()
    desktop = next(i for i, c in enumerate(calls) if "ubuntu-desktop-minimal" in c)
    browser = calls.index("snap install firefox")
    # A fresh instance's snapd may still be seeding, when an install fails "too early for operation".
    assert desktop < calls.index("snap wait system seed.loaded") < browser
    policies = json.loads(host.file("/etc/firefox/policies/policies.json"))["policies"]
    assert policies["DontCheckDefaultBrowser"] is True and policies["OverrideFirstRunPage"] == ""
    launcher = host.file("/home/ubuntu/Desktop/so101-twin-console.desktop")
    assert launcher == host.file("/home/ubuntu/.local/share/applications/so101-twin-console.desktop")
    exec_line = next(line for line in launcher.splitlines() if line.startswith("Exec="))
    command = exec_line.removeprefix("Exec=").split()[0]
    assert os.access(host.root / command.lstrip("/"), os.X_OK), f"{command} was not installed by the boot"


def test_dcv_config_password_at_awscurrent_and_start_ordering(booted, deployed: Deployed) -> None:
    host, _ = booted
    conf = host.file("/etc/dcv/dcv.conf")
    assert 'owner = "ubuntu"' in conf and "create-session = true" in conf
    assert "web-client-max-head-resolution = (4096, 2160)" in conf
    # An untouched viewer is never disconnected (the stack's dcvIdleTimeoutMinutes, 0 by default; DCV's own
    # default would end it after 60 minutes).
    assert deployed.settings["DCV_IDLE_TIMEOUT"] == "0"
    connectivity = conf.split("[connectivity]\n", 1)[1].split("\n[", 1)[0]
    assert "\nidle-timeout = 0\n" in connectivity
    # The desktop stays unlocked when the last client disconnects: DCV's own lock off (its default locks),
    # GNOME's too (disable-lock-screen), each where its program reads it.
    security = conf.split("[security]\n", 1)[1].split("\n[", 1)[0]
    assert "\nos-auto-lock = false\n" in security
    schema = host.file("/usr/share/glib-2.0/schemas/90_so101-twin.gschema.override")
    assert "[org.gnome.desktop.lockdown]\ndisable-lock-screen=true\n" in schema
    # The version staged AWSCURRENT, not the first in the map (AWSPREVIOUS here).
    assert (host.sim / "chpasswd.log").read_text() == f"chpasswd user=ubuntu password={PASSWORD}\n"
    log = host.file("/var/log/so101-twin-bootstrap.log")
    assert PASSWORD not in log and OLD_PASSWORD not in log
    assert any("get-secret-value" in c and "--version-id v-2" in c for c in host.calls())
    dropin = host.file("/etc/systemd/system/dcvserver.service.d/10-so101-twin.conf")
    assert "After=display-manager.service" in dropin
    unit = host.file("/etc/systemd/system/so101-twin-start.service")
    assert "Type=oneshot" in unit
    assert "ExecStart=/bin/bash /opt/so101-twin/userdata/host-check.sh --on-start" in unit
    assert (
        "After=network-online.target display-manager.service dcvserver.service so101-twin-agent.service"
        in unit
    )
    assert "systemctl enable so101-twin-start.service" in host.calls()
    # The start waits for network-online.target; Ubuntu 24.04 can hold that 2 min, which AWS's DLAMI sample
    # cuts (cfn/DLAMI-Ubuntu-NICE-DCV.yaml, a systemd-networkd-wait-online drop-in with a --timeout).
    wait = host.file("/etc/systemd/system/systemd-networkd-wait-online.service.d/so101-twin.conf")
    assert wait.splitlines()[-2:] == [
        "ExecStart=",
        "ExecStart=/usr/lib/systemd/systemd-networkd-wait-online --timeout=30",
    ]


def test_agent_config_and_its_own_user(booted, deployed: Deployed) -> None:
    import tomllib

    host, _ = booted
    config = tomllib.loads(host.file("/etc/so101-twin/agent.toml"))
    assert config["telemetry"]["devices"] == ["arm-001"]
    assert config["broker"]["region"] == "us-east-1"
    # USD recording is off unless recordSessions=true.
    assert config["twin"]["record_dir"] == ""
    assert deployed.settings["RECORD_SESSIONS"] == "false"
    # Main's history bucket and ros2 setting reach the agent through the same parameter.
    assert config["history"] == {"uri": f"s3://{HISTORY_BUCKET}/history", "region": "us-east-1"}
    # ... and so do the arms' calibrations, the alarm topic and the host agent's own client id prefix.
    assert config["telemetry"]["calibrations"] == f"s3://{HISTORY_BUCKET}/calibration"
    assert config["alerts"]["topic_arn"] == deployed.settings["ALERT_TOPIC_ARN"] == ALARM_TOPIC_ARN
    assert config["alerts"]["warnings"] is False
    assert config["broker"]["client_id_prefix"] == "so101-twin-So101TwinStack-"
    assert config["ros2"] == {"enabled": False}
    assert config["cloudwatch"]["emf_file"] == "/var/log/so101-twin/emf.log"
    assert (host.sim / "users" / "so101-twin").exists()
    assert "User=so101-twin\n" in host.file("/etc/systemd/system/so101-twin-agent.service")
    # The operator's own file: the first boot saved it to the stack's bucket (through the deployment
    # parameter's HOST_STATE_URI), a path unit saves it at every change, and the saver's lines reach the
    # agent's log file, which CloudWatch follows.
    saved = host.sim / "s3" / HISTORY_BUCKET / "host" / "agent.local.toml"
    assert saved.read_text() == host.file("/etc/so101-twin/agent.local.toml")
    assert "PathChanged=/etc/so101-twin/agent.local.toml\n" in host.file(
        "/etc/systemd/system/so101-twin-local-config.path"
    )
    rules = host.file("/etc/rsyslog.d/30-so101-twin.conf")
    assert ':programname, isequal, "so101-twin-local-config" /var/log/so101-twin-agent.log' in rules
    # The servo alarm state's copy: under this host's id, saved whenever the agent writes its state file.
    assert (
        f"ExecStart=/bin/bash /opt/so101-twin/userdata/save-alarm-state.sh s3://{HISTORY_BUCKET}/host/alarm-state/"
        in host.file("/etc/systemd/system/so101-twin-alarm-state.service")
    )
    assert "PathChanged=/var/lib/so101-twin-agent/state.json\n" in host.file(
        "/etc/systemd/system/so101-twin-alarm-state.path"
    )
    assert ':programname, isequal, "so101-twin-alarm-state" /var/log/so101-twin-agent.log' in rules
    # The lock was installed (its probe wheel is in the venv).
    probe = subprocess.run(
        [
            str(host.root / "opt/so101-twin/venv/bin/python"),
            "-c",
            "import so101_twin_lock_probe as p; print(p.LOCKED)",
        ],
        capture_output=True,
        text=True,
        check=False,
        timeout=60,
    )
    assert probe.stdout.strip() == "from requirements/host.txt", probe.stderr


def test_the_hosts_logs_are_rotated_every_hour_and_past_maxsize(booted, tmp_path: Path) -> None:
    """logrotate's own daily run judges maxsize once a day: an agent logging an error flood outgrew it many
    times before. Ours runs every hour on a state of its own; the real logrotate, given the config the boot
    wrote (its logs moved under tmp_path), rotates a log past maxsize at its first run and leaves the rest."""
    host, _ = booted
    assert not (host.root / "etc/logrotate.d/so101-twin").exists()  # the daily run's copy is gone
    assert "OnCalendar=hourly\n" in host.file("/etc/systemd/system/so101-twin-logrotate.timer")
    run = "/usr/sbin/logrotate --state /var/lib/so101-twin/logrotate.status /etc/so101-twin/logrotate.conf"
    assert f"ExecStart={run}\n" in host.file("/etc/systemd/system/so101-twin-logrotate.service")
    assert "systemctl enable --now so101-twin-logrotate.timer" in host.calls()
    logs = tmp_path / "log"
    logs.mkdir()
    # As Ubuntu's /var/log, root:syslog 0775 (adm here: every Debian has it): logrotate refuses a directory
    # writable by a group other than root's unless its config says whom to rotate as (`su`).
    os.chown(logs, 0, grp.getgrnam("adm").gr_gid)
    logs.chmod(0o775)
    config = tmp_path / "logrotate.conf"
    config.write_text(host.file("/etc/so101-twin/logrotate.conf").replace("/var/log/", f"{logs}/"))
    flooded, quiet = logs / "so101-twin-agent.log", logs / "so101-twin-bootstrap.log"
    with flooded.open("wb") as f:
        f.truncate(51 << 20)  # past maxsize 50M, in a day of the week
    quiet.write_text("booted\n")
    rotated = subprocess.run(
        ["logrotate", "--state", str(tmp_path / "state"), str(config)],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert rotated.returncode == 0, rotated.stderr
    assert (logs / "so101-twin-agent.log.1.gz").exists() and flooded.stat().st_size == 0  # copytruncate
    assert quiet.read_text() == "booted\n" and not (logs / "so101-twin-bootstrap.log.1.gz").exists()


def test_host_check_reports_every_line(booted, tmp_path: Path) -> None:
    # On a copy: the module's booted host is shared, and this run's calls would land after the boot's signal.
    source, _ = booted
    host = copy_of(source, tmp_path)
    result = host.run(host.root / "opt/so101-twin/userdata/host-check.sh")
    assert result.returncode == 0, result.stdout + result.stderr
    lines = [line.split("\t") for line in result.stdout.splitlines()]
    status = {name: state for name, state, _ in lines}
    assert status == {
        "x-on-gpu": "OK",
        "dcv-session": "OK",
        "agent": "OK",
        "telemetry": "WARN",
        "calibration": "OK",
        "viewer": "OK",
        "screen": "OK",
        "version": "OK",
    }
    details = {name: detail for name, _, detail in lines}
    assert "arm-001 OFFLINE 0.0 Hz, never seen" in details["telemetry"]


LLVMPIPE = (
    "name of display: :0\n"
    "display: :0  screen: 0\n"
    "direct rendering: Yes\n"
    "OpenGL vendor string: Mesa\n"
    "OpenGL renderer string: llvmpipe (LLVM 20.1.2, 256 bits)\n"
    "OpenGL core profile version string: 4.5 (Core Profile) Mesa 25.0.7-0ubuntu0.24.04.2\n"
)


def test_host_check_fails_x_on_gpu_when_opengl_on_x_is_not_nvidias(booted, tmp_path: Path) -> None:
    """nvidia-smi lists Xorg, yet X's OpenGL is Mesa's software renderer (what AWS's DCV guide checks with
    glxinfo on :0): the x-on-gpu line fails and names what renders instead."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    (host.sim / "glx").write_text(LLVMPIPE)
    result = host.run(host.root / "opt/so101-twin/userdata/host-check.sh")
    assert result.returncode == 1, result.stdout + result.stderr
    lines = {
        name: (state, detail) for name, state, detail in (ln.split("\t") for ln in result.stdout.splitlines())
    }
    state, detail = lines["x-on-gpu"]
    assert state == "FAIL"
    assert detail.startswith("Xorg runs on NVIDIA L40S, 580.95.05, but OpenGL on :0 is rendered by llvmpipe")
    assert "(Mesa), not NVIDIA's driver" in detail


def test_host_check_passes_x_on_gpu_saying_so_when_x_cannot_be_asked_about_opengl(
    booted, tmp_path: Path
) -> None:
    """X runs on the GPU (nvidia-smi lists it) but its OpenGL could not be asked about: here no Xorg gives an
    -auth file, so glxinfo is refused. Only a renderer seen not to be NVIDIA's fails: a guess about a host's
    X authority must not fail every boot. The line says what it could not ask."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    cmdline = host.root / "proc/1234/cmdline"
    cmdline.write_bytes(cmdline.read_bytes().replace(b"-auth\0", b"-noauth\0"))
    result = host.run(host.root / "opt/so101-twin/userdata/host-check.sh")
    lines = {
        name: (state, detail) for name, state, detail in (ln.split("\t") for ln in result.stdout.splitlines())
    }
    state, detail = lines["x-on-gpu"]
    assert state == "OK", detail
    assert detail == (
        "Xorg runs on NVIDIA L40S, 580.95.05; not asked what renders OpenGL: no Xorg process gives an "
        "-auth file"
    ), detail
    # Nor where the viewer's window is: the capture is judged as a whole, and the line says so.
    state, detail = lines["screen"]
    assert state == "OK", detail
    assert "not asked where the viewer's window is: no Xorg process gives an -auth file" in detail, detail


def check_lines(host: HostSim) -> dict[str, tuple[str, str]]:
    """host-check.sh's lines on `host`: NAME -> (OK|WARN|FAIL, detail)."""
    result = host.run(host.root / "opt/so101-twin/userdata/host-check.sh")
    return {
        name: (state, detail) for name, state, detail in (ln.split("\t") for ln in result.stdout.splitlines())
    }


def test_host_check_fails_the_dcv_line_when_nothing_listens_on_dcvs_web_port(booted, tmp_path: Path) -> None:
    """The console session exists, yet no browser could reach it: nothing listens on TCP 8443 beyond
    loopback (another web port in dcv.conf, DCV's web frontend failing, bound to 127.0.0.1). UDP 8443 missing
    alone is only noted: no QUIC, and the browser streams over TCP. ss failing is said as such."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    unreachable = (
        "console session owned by ubuntu, but nothing listens on TCP 8443 beyond loopback, DCV's web port: "
        "no browser can connect (dcv.conf [connectivity] web-port; journalctl -u dcvserver, "
        "/var/log/dcv/server.log)"
    )
    for listing in ("0.0.0.0:8080      0.0.0.0:*", "127.0.0.1:8443      0.0.0.0:*", "[::1]:8443      [::]:*"):
        (host.sim / "ss-tcp").write_text(f"LISTEN 0      10               {listing}\n")
        assert check_lines(host)["dcv-session"] == ("FAIL", unreachable), listing
    # Any address beyond loopback is reachable: all of IPv4's, all of both stacks', one interface's.
    for listing in ("*:8443      *:*", "10.0.1.23%ens5:8443      0.0.0.0:*"):
        (host.sim / "ss-tcp").write_text(f"LISTEN 0      10               {listing}\n")
        assert check_lines(host)["dcv-session"][0] == "OK", listing
    (host.sim / "fail" / "ss").touch()
    assert check_lines(host)["dcv-session"] == (
        "OK",
        "console session owned by ubuntu; not told whether DCV listens on 8443: ss failed: ss: failing on "
        "purpose (test)",
    )
    (host.sim / "fail" / "ss").unlink()
    (host.sim / "ss-tcp").unlink()
    (host.sim / "ss-udp").write_text("")
    state, detail = check_lines(host)["dcv-session"]
    assert (state, detail) == (
        "OK",
        "console session owned by ubuntu; DCV listens on TCP 8443, not on UDP 8443: no QUIC, browsers stream "
        "over TCP (dcv.conf enable-quic-frontend)",
    )


def test_host_check_fails_the_dcv_line_when_another_process_holds_its_port(booted, tmp_path: Path) -> None:
    """A listener on TCP 8443 passed whoever it was: another server there is what a browser reaches. The
    process ss names must be in dcvserver.service's cgroup (by unit, not by name); a socket ss names no
    process for is not judged."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    assert check_lines(host)["dcv-session"][0] == "OK"  # dcvserver's own, in its unit
    (host.root / "proc/777").mkdir()
    (host.root / "proc/777/cgroup").write_text("0::/system.slice/nginx.service\n")
    (host.sim / "ss-tcp").write_text(
        'LISTEN 0      511               0.0.0.0:8443      0.0.0.0:*    users:(("nginx",pid=777,fd=6))\n'
    )
    assert check_lines(host)["dcv-session"] == (
        "FAIL",
        "console session owned by ubuntu, but TCP 8443 is held by nginx (pid 777), not by DCV's server "
        "(dcvserver.service): a browser reaches it instead; stop it or move it to another port (ss -ltnp), "
        "then restart dcvserver",
    )
    # A process gone since ss answered (DCV restarting): not judged, so not called another server.
    (host.root / "proc/777/cgroup").unlink()
    assert check_lines(host)["dcv-session"][0] == "OK"
    # The same process moved into DCV's unit (a name is no proof either way): DCV's.
    (host.root / "proc/777/cgroup").write_text("0::/system.slice/dcvserver.service\n")
    assert check_lines(host)["dcv-session"][0] == "OK"
    (host.sim / "ss-tcp").write_text("LISTEN 0      511               0.0.0.0:8443      0.0.0.0:*\n")
    assert check_lines(host)["dcv-session"][0] == "OK"


def test_host_check_fails_the_screen_when_the_viewers_window_is_black(booted, tmp_path: Path) -> None:
    """A desktop drawn around a black viewer window (MuJoCo drawing nothing) passed as "a desktop": the
    window xwininfo finds on :0 is cut from the capture, scaled as the capture is, and judged on its own."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    black_viewer_png(host.sim / "screen.png")
    state, detail = check_lines(host)["screen"]
    assert state == "FAIL", detail
    assert detail.startswith(
        "the viewer's window (1320x750 at +300+180) shows one flat colour (#000000 over 100.0%): MuJoCo draws"
        " nothing in it (its log: journalctl _UID=$(id -u ubuntu) | grep twin-view; capture kept in"
    ), detail
    assert "xwininfo -root -tree" in host.calls()


def test_host_check_finds_a_viewer_window_partly_off_the_screen(booted, tmp_path: Path) -> None:
    """xwininfo prints an offset left of or above the screen as +-N: such a window is found, and judged on
    the part of it on the screen."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    (host.sim / "xwin-tree").write_text(
        "     1 child:\n"
        '     0x2200007 "MuJoCo : so101": ("MuJoCo" "MuJoCo")  1620x930+-300+-180  +-300+-180\n'
    )
    state, detail = check_lines(host)["screen"]
    # On the screen: 0..1320 x 0..750 of 1920x1080, the capture's 0..880 x 0..500 (its desktop bar and the
    # left of the window stand-in): drawn.
    assert state == "OK", detail
    assert "the viewer drawn in its window (1620x930 at -300-180)" in detail, detail


def test_host_check_fails_the_screen_when_the_viewers_window_is_not_shown(booted, tmp_path: Path) -> None:
    """X's tree lists a window whether it is shown or not: a minimised or withdrawn viewer window, judged by
    what the capture shows at its place, passed. Its map state is asked, and only a shown one is judged."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    (host.sim / "xwin-map").mkdir()
    (host.sim / "xwin-map" / "0x2200007").write_text("IsUnMapped")
    state, detail = check_lines(host)["screen"]
    assert (state, detail.split(" (capture")[0]) == (
        "FAIL",
        "twin view runs, but its MuJoCo window is not shown on :0 (X says IsUnMapped: minimised or withdrawn;"
        " restore it in the DCV session)",
    ), detail
    assert "xwininfo -id 0x2200007" in host.calls()
    # A second viewer window, shown and smaller, is the one judged (a restarted viewer beside a stale one).
    (host.sim / "xwin-tree").write_text(
        "     2 children:\n"
        '     0x2200007 "MuJoCo : so101": ("MuJoCo" "MuJoCo")  1620x930+0+0  +0+0\n'
        '     0x2400007 "MuJoCo : so101": ("MuJoCo" "MuJoCo")  1320x750+6+30  +300+180\n'
    )
    state, detail = check_lines(host)["screen"]
    assert state == "OK", detail
    assert "the viewer drawn in its window (1320x750 at +300+180)" in detail, detail


def test_host_check_fails_the_screen_when_no_viewer_window_is_on_x(booted, tmp_path: Path) -> None:
    """twin view runs (its line passes) but no MuJoCo window is on :0 (opened on another display, or none):
    what a person would see has no twin in it."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    (host.sim / "xwin-tree").write_text(
        '     1 child:\n     0x1a00003 "Terminal": ("gnome-terminal" "Terminal")  800x600+0+0  +0+0\n'
    )
    lines = check_lines(host)
    assert lines["viewer"][0] == "OK"
    state, detail = lines["screen"]
    assert (state, detail.split(" (capture")[0]) == ("FAIL", "no MuJoCo window is on X's display :0"), detail


def test_host_check_says_not_that_the_viewer_runs_when_it_does_not(booted, tmp_path: Path) -> None:
    """`twin instance check` runs the screen line whatever the viewer line found: with no viewer (and so no
    MuJoCo window on :0) the screen line fails for the missing window, without saying twin view runs."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    (host.sim / "state" / "viewer").unlink()
    (host.sim / "xwin-tree").write_text(
        '     1 child:\n     0x1a00003 "Terminal": ("gnome-terminal" "Terminal")  800x600+0+0  +0+0\n'
    )
    lines = check_lines(host)
    assert lines["viewer"][0] == "FAIL" and "twin view is not running" in lines["viewer"][1], lines["viewer"]
    state, detail = lines["screen"]
    assert state == "FAIL" and "no MuJoCo window is on X's display :0" in detail, detail
    assert "twin view runs" not in detail, detail


def test_host_check_fails_the_agent_line_when_iot_core_refuses_a_filter(booted, tmp_path: Path) -> None:
    """One filter refused, another granted: the agent is connected and has a subscription, yet the refused
    filter's arms are never heard, and the check says which filter and which right."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    refused = "dt/lerobot/arm-002/telemetry"
    served = host.sim / "agent" / "state.json"  # what the host's agent answers on /state
    state = json.loads(served.read_text())
    state["agent"]["broker"]["connections"] = [{"index": 0, "state": "refused", "refused": [refused]}]
    served.write_text(json.dumps(state))
    result = host.run(host.root / "opt/so101-twin/userdata/host-check.sh")
    lines = [line.split("\t") for line in result.stdout.splitlines()]
    status, detail = next((state, detail) for name, state, detail in lines if name == "agent")
    assert status == "FAIL", detail
    assert (
        f"IoT Core refuses the subscription to {refused} (the role must allow iot:Subscribe on it)" in detail
    )


# --- after every start --------------------------------------------------------------------------------------


def test_after_a_reboot_dcv_is_put_on_x_and_the_checks_report(booted, tmp_path: Path) -> None:
    """A reboot: GDM's X came up after DCV, so DCV has no console session. The start unit restarts DCV once
    X runs, re-runs the checks, writes the verdict of this boot and its metric, and gives back apt's timers
    left masked by a run that was killed."""
    source, result = booted
    assert result.returncode == 0
    host = copy_of(source, tmp_path)
    (host.sim / "state" / "console").unlink()  # dcvserver started before X
    (host.root / "var/lib/so101-twin/apt-held").write_text("apt-daily.timer\n")
    (host.sim / "services" / "apt-daily.timer").unlink()
    (host.sim / "masked").mkdir(exist_ok=True)
    (host.sim / "masked" / "apt-daily.timer").write_text("1\n")
    calls_before = len(host.calls())
    run = host.run(host.root / "opt/so101-twin/userdata/host-check.sh", "--on-start", AGENT_NAME=STACK_NAME)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    new_calls = host.calls()[calls_before:]
    assert "systemctl restart dcvserver" in new_calls
    last_start = host.file("/var/lib/so101-twin/last-start").splitlines()
    assert last_start[0].startswith(f"boot={BOOT_ID} ")
    assert (
        " PASS X on the GPU, DCV console session listening on 8443, agent subscribed, viewer stable, desktop"
        " and viewer drawn on screen" in last_start[0]
    )
    assert {line.split("\t")[0] for line in last_start[1:]} == {
        "x-on-gpu",
        "dcv-session",
        "agent",
        "telemetry",
        "calibration",
        "viewer",
        "screen",
    }
    assert "verdict: PASS" in host.file("/var/log/so101-twin-start.log")
    metric = json.loads(host.file("/var/log/so101-twin-host-emf.log").splitlines()[-1])
    assert metric[monitoring.HOST_CHECKS_FAILED] == 0 and metric["Agent"] == STACK_NAME
    assert metric["_aws"]["CloudWatchMetrics"][0]["Namespace"] == "SO101Twin"
    assert host.active("apt-daily.timer") and not host.masked("apt-daily.timer")
    # Every start turns the silent alarm's actions on again (a deploy may have turned them off).
    assert host.armed() == [f"{STACK_NAME}-AgentSilent"] * 2


def test_a_start_whose_silent_alarm_cannot_be_armed_still_checks_and_says_why(booted, tmp_path: Path) -> None:
    """The role lacks cloudwatch:EnableAlarmActions: the start's checks run and pass as before, and the log
    names the alarm, the consequence and the missing right."""
    source, result = booted
    assert result.returncode == 0
    host = copy_of(source, tmp_path)
    host.fail("cloudwatch")
    run = host.run(host.root / "opt/so101-twin/userdata/host-check.sh", "--on-start", AGENT_NAME=STACK_NAME)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    log = host.file("/var/log/so101-twin-start.log")
    assert f"could not turn on the actions of alarm {STACK_NAME}-AgentSilent" in log
    assert "AccessDenied" in log and "cloudwatch:EnableAlarmActions" in log
    assert "verdict: PASS" in log
    assert host.armed() == [f"{STACK_NAME}-AgentSilent"]  # the first boot's only


def path_without(tool: str, host: HostSim, tmp_path: Path) -> str:
    """The PATH host.run gives, with every directory holding `tool` stood in for by one of links to the
    rest of its programs: the host's stand-in gone and this machine's own not found either."""
    directories = []
    for entry in host.env()["PATH"].split(os.pathsep):
        folder = Path(entry)
        if not (folder / tool).exists():
            directories.append(entry)
            continue
        mirror = tmp_path / f"without-{tool}-{len(directories)}"
        mirror.mkdir()
        for program in folder.iterdir():
            if program.name != tool:
                (mirror / program.name).symlink_to(program)
        directories.append(str(mirror))
    return os.pathsep.join(directories)


def test_a_start_without_ss_claims_no_dcv_port_in_its_verdict(booted, tmp_path: Path) -> None:
    """Without ss (iproute2), or with an ss that fails, no check learnt whether DCV listens on 8443: the
    verdict of a start that passes says what was verified, not that port."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    no_ss = path_without("ss", host, tmp_path)
    run = host.run(host.root / "opt/so101-twin/userdata/host-check.sh", "--on-start", PATH=no_ss)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    head = host.file("/var/lib/so101-twin/last-start").splitlines()[0]
    assert (
        " PASS X on the GPU, DCV console session (not asked whether DCV listens on 8443: no ss), agent "
        "subscribed, viewer stable, desktop and viewer drawn on screen" in head
    ), head
    assert "listening on 8443" not in head
    # ss there but failing: no more told.
    host.fail("ss")
    run = host.run(host.root / "opt/so101-twin/userdata/host-check.sh", "--on-start")
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    head = host.file("/var/lib/so101-twin/last-start").splitlines()[0]
    told = " PASS X on the GPU, DCV console session (not told whether DCV listens on 8443: ss failed), "
    assert told in head, head


def test_start_checks_fail_and_say_so_when_the_viewer_crash_loops(booted, tmp_path: Path) -> None:
    source, _ = booted
    host = copy_of(source, tmp_path)
    (host.sim / "viewer-mode").write_text("crashloop")
    run = host.run(host.root / "opt/so101-twin/userdata/host-check.sh", "--on-start")
    assert run.returncode == 1
    head = host.file("/var/lib/so101-twin/last-start").splitlines()[0]
    assert f"boot={BOOT_ID} " in head and " FAIL viewer: twin view keeps restarting" in head
    metric = json.loads(host.file("/var/log/so101-twin-host-emf.log").splitlines()[-1])
    assert metric[monitoring.HOST_CHECKS_FAILED] == 1


# --- second run: the update path changes nothing -----------------------------------------------------------


REFETCHED = (
    "opt/so101-twin/agent-src",
    "opt/so101-twin/userdata",
    "opt/so101-twin/agent-src.zip",
    "opt/so101-twin/userdata.zip",
    "etc/so101-twin/deployment.env",
    "var/log/",
    "var/lib/so101-twin/last-run",
    "var/lib/so101-twin/run.lock",
    # Each verify captures the console anew.
    "var/lib/so101-twin/console.png",
    "run/so101-twin/",
)


def stable(digest: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in digest.items() if not k.startswith(REFETCHED)}


def run_association(host: HostSim, script_text: str) -> subprocess.CompletedProcess[str]:
    script = host.sim / "association.sh"
    script.write_text(script_text)
    # AWS-RunShellScript runs the commands with sh.
    return subprocess.run(
        ["sh", str(script)], env=host.env(), capture_output=True, text=True, timeout=600, check=False
    )


def test_second_run_through_the_association_changes_nothing(
    booted, deployed: Deployed, tmp_path: Path
) -> None:
    source, result = booted
    assert result.returncode == 0
    host = copy_of(source, tmp_path)
    before = tree_digest(host.root)
    calls_before = len(host.calls())
    rerun = run_association(host, deployed.update_script)
    assert rerun.returncode == 0, rerun.stdout[-4000:] + rerun.stderr[-2000:]
    after = tree_digest(host.root)
    changed = sorted(k for k in set(before) | set(after) if stable(before).get(k) != stable(after).get(k))
    assert changed == []
    new_calls = host.calls()[calls_before:]
    assert not [c for c in new_calls if " install " in c or c.startswith(("nvidia-xconfig", "chpasswd"))]
    assert not [c for c in new_calls if c.startswith("systemctl restart")]
    assert not [c for c in new_calls if "signal-resource" in c], (
        "an update must not signal the CreationPolicy"
    )
    assert len(host.handle_posts()) == 1
    # An update holds apt still too, and gives it back.
    assert any(c.startswith("systemctl mask --runtime") for c in new_calls)
    apt_restored(host)
    log = host.file("/var/log/so101-twin-bootstrap.log")
    assert f"update of deployment {deployed.version}" in log
    assert "install-agent: " in log and "done (changed=0)" in log


def test_an_update_keeps_the_operators_own_settings_and_rewrites_the_generated_config(
    booted, deployed: Deployed, tmp_path: Path
) -> None:
    """What docs/deploy.md promises of a redeploy, through the whole update (the association runs the
    UserData again): agent.local.toml comes out as the operator left it, and saved to the bucket; an edit of
    the generated agent.toml is undone."""
    source, result = booted
    assert result.returncode == 0
    host = copy_of(source, tmp_path)
    local = host.root / "etc/so101-twin/agent.local.toml"
    mine = "# my lab's servos run warm\n[alarms]\ntemperature_warning_c = 58.0\n"
    local.write_text(mine)
    generated = host.root / "etc/so101-twin/agent.toml"
    as_deployed = generated.read_text()
    generated.write_text(as_deployed.replace('units = "', 'units = "degrees" # "'))
    assert generated.read_text() != as_deployed  # an edit the next deploy undoes
    rerun = run_association(host, deployed.update_script)
    assert rerun.returncode == 0, rerun.stdout[-4000:] + rerun.stderr[-2000:]
    assert local.read_text() == mine
    assert (host.sim / "s3" / HISTORY_BUCKET / "host" / "agent.local.toml").read_text() == mine
    assert generated.read_text() == as_deployed


def test_an_update_with_a_new_dcv_idle_timeout_rewrites_dcv_conf_and_restarts_dcv(
    booted, deployed: Deployed, tmp_path: Path
) -> None:
    """dcvIdleTimeoutMinutes changed: the association's run writes it into dcv.conf and restarts DCV alone,
    which attaches its console session to the X that runs; GDM is not restarted (that would end the desktop
    and the viewer in it)."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    parameter = host.sim / "parameter"
    parameter.write_text(parameter.read_text().replace("DCV_IDLE_TIMEOUT=0", "DCV_IDLE_TIMEOUT=90"))
    calls_before = len(host.calls())
    rerun = run_association(host, deployed.update_script)
    assert rerun.returncode == 0, rerun.stdout[-4000:] + rerun.stderr[-2000:]
    conf = host.file("/etc/dcv/dcv.conf")
    assert "\nidle-timeout = 90\n" in conf.split("[connectivity]\n", 1)[1].split("\n[", 1)[0]
    new_calls = host.calls()[calls_before:]
    assert "systemctl restart dcvserver" in new_calls and "systemctl restart gdm3" not in new_calls, new_calls
    assert (host.sim / "state" / "console").read_text().strip() == "ubuntu"


def test_an_update_that_upgrades_dcv_keeps_the_boots_dcv_conf_without_asking(
    booted, deployed: Deployed, tmp_path: Path
) -> None:
    """A new DCV release pinned in releases.env reaches a running host through the update: dpkg would ask
    what to do with dcv.conf (the boot's, not the package's) and, with no terminal to answer, fail the
    package. apt tells it to keep the file on the host (the boot rewrites it anyway)."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    (host.sim / "dpkg" / "nice-dcv-server").write_text("2024.0.19030-1\n")
    conf = host.file("/etc/dcv/dcv.conf")
    calls_before = len(host.calls())
    rerun = run_association(host, deployed.update_script)
    assert rerun.returncode == 0, rerun.stdout[-4000:] + rerun.stderr[-2000:]
    installs = [c for c in host.calls()[calls_before:] if "nice-dcv-server_" in c]
    assert installs and all("Dpkg::Options::=--force-confold" in c for c in installs), installs
    assert host.file("/etc/dcv/dcv.conf") == conf
    assert (host.sim / "dpkg" / "nice-dcv-server").read_text().startswith("2025.0.")


def test_an_idle_timeout_past_the_stacks_bound_is_refused_by_the_boot_too(
    booted, deployed: Deployed, tmp_path: Path
) -> None:
    """A hand-edited deployment parameter gets past the stack's check: the boot holds the same bound
    (0..10080 minutes) and says so, and dcv.conf keeps what it had."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    parameter = host.sim / "parameter"
    parameter.write_text(parameter.read_text().replace("DCV_IDLE_TIMEOUT=0", "DCV_IDLE_TIMEOUT=20000"))
    rerun = run_association(host, deployed.update_script)
    assert rerun.returncode != 0
    assert "DCV_IDLE_TIMEOUT=20000 is not 0..10080 minutes" in rerun.stdout + rerun.stderr
    assert "\nidle-timeout = 0\n" in host.file("/etc/dcv/dcv.conf")


def test_update_waits_for_the_parameter_to_show_its_version(
    booted, deployed: Deployed, tmp_path: Path
) -> None:
    """An association run for a newer version than the parameter shows fails instead of installing the old."""
    source, _ = booted
    host = copy_of(source, tmp_path)
    rerun = run_association(host, deployed.update_script.replace(deployed.version, "0123456789ab"))
    assert rerun.returncode != 0
    assert "want version 0123456789ab" in rerun.stdout
    assert host.file("/var/lib/so101-twin/deployed-version").strip() == deployed.version


# --- failing boots name their step -------------------------------------------------------------------------


def test_no_nvidia_driver_is_a_failure_of_the_gpu_step(tmp_path: Path, deployed: Deployed, release) -> None:
    host = new_host(tmp_path, deployed, release, gpu_driver=False)
    result = first_boot(host, deployed)
    assert result.returncode != 0
    reason = failure_reason(host)
    assert reason.startswith("step gpu failed (exit 1): no NVIDIA driver: the instance has an NVIDIA GPU")
    assert "nvidia-smi is missing" in reason
    # No dummy X instead: nothing after the failing step ran.
    assert not [c for c in host.calls() if c.startswith(("dcv ", "nvidia-xconfig")) or "restart gdm3" in c]
    assert not (host.root / "etc/X11/xorg.conf").exists()
    assert "FAILURE" in host.file("/var/lib/so101-twin/last-run")
    apt_restored(host)


def _password_step_failed(tmp_path: Path, deployed: Deployed, release, switch: str) -> tuple[HostSim, str]:
    """A first boot whose DCV password secret is broken as the stand-in's `switch` says: it fails, and no
    password was set (chpasswd never ran); the host and the failure's reason."""
    host = new_host(tmp_path, deployed, release)
    host.fail(switch)
    result = first_boot(host, deployed)
    assert result.returncode != 0
    assert not (host.sim / "chpasswd.log").exists()
    return host, failure_reason(host)


def test_a_binary_password_secret_is_a_failure_of_the_password_step_not_a_password(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    """A secret put back as binary has no SecretString: read as text it printed "None", which chpasswd made
    the DCV login's password."""
    _, reason = _password_step_failed(tmp_path, deployed, release, "secret")
    assert reason.startswith(
        "step password failed (exit 1): the DCV password secret's AWSCURRENT version v-2 holds no text"
    ), reason
    assert "put-secret-value --secret-string" in reason


def test_a_password_secret_deleted_outside_the_stack_fails_the_password_step_with_aws_reason_and_fix(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    """A walk: the step said "the DCV password secret has no AWSCURRENT version" for a secret that was gone,
    which named neither that nor the fix."""
    host, reason = _password_step_failed(tmp_path, deployed, release, "secret-gone")
    assert reason.startswith(
        f"step password failed (exit 1): the DCV password secret {SECRET_ARN} no longer exists"
        " (describe-secret: An error occurred (ResourceNotFoundException) when calling the DescribeSecret"
        " operation: Secrets Manager can't find the specified secret.)"
    ), reason
    assert "cdk destroy then cdk deploy makes a new one" in reason, reason
    # The AWS CLI's error comes between newlines: the record of the run stays one line.
    assert len(host.file("/var/lib/so101-twin/last-run").splitlines()) == 1


def test_a_password_secret_scheduled_for_deletion_fails_the_password_step_saying_restore_it(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    host, reason = _password_step_failed(tmp_path, deployed, release, "secret-deleting")
    assert reason.startswith(
        f"step password failed (exit 1): the DCV password secret {SECRET_ARN} is scheduled for deletion"
        " (2026-12-01T10:00:00+00:00"
    ), reason
    assert f"aws secretsmanager restore-secret --secret-id {SECRET_ARN}, then run the update" in reason
    assert not [c for c in host.calls() if "get-secret-value" in c]


def test_an_update_whose_password_is_set_still_fails_on_a_secret_scheduled_for_deletion(
    booted, deployed: Deployed, tmp_path: Path
) -> None:
    """The password stamp matches the secret's version, so the update would change nothing; yet after the
    recovery window the password is gone for good, so the update says so now, and its later steps wait."""
    source, result = booted
    assert result.returncode == 0
    host = copy_of(source, tmp_path)
    assert host.file("/var/lib/so101-twin/password.version").strip() == "v-2"
    host.fail("secret-deleting")
    calls_before = len(host.calls())
    rerun = run_association(host, deployed.update_script)
    assert rerun.returncode != 0
    last_run = host.file("/var/lib/so101-twin/last-run")
    assert " update FAILURE step password failed (exit 1): " in last_run, last_run
    assert f"restore-secret --secret-id {SECRET_ARN}, then run the update" in last_run, last_run
    assert not [c for c in host.calls()[calls_before:] if "get-secret-value" in c or c.startswith("chpasswd")]
    # The chain stops at the password: docs/deploy.md says the update's later steps wait for the restore.
    log = host.file("/var/log/so101-twin-bootstrap.log")
    update_log = log.split(f"update of deployment {deployed.version}")[-1]
    assert "step password: start" in update_log and "step dcv: start" not in update_log


def test_no_nvidia_xconfig_is_a_named_failure_of_the_desktop_step(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    """The driver came without nvidia-xconfig and apt's package brought none: the desktop step says so and
    what to use, instead of failing on a command not found with no reason."""
    host = new_host(tmp_path, deployed, release)
    (host.bin / "nvidia-xconfig").unlink()
    result = first_boot(host, deployed)
    assert result.returncode != 0
    reason = failure_reason(host)
    assert reason.startswith("step desktop failed (exit 1): nvidia-xconfig is missing"), reason
    assert "DLAMI Base OSS NVIDIA" in reason
    assert not (host.root / "etc/X11/xorg.conf").exists()
    apt_restored(host)


def test_a_held_dpkg_lock_is_a_failure_of_the_apt_step(tmp_path: Path, deployed: Deployed, release) -> None:
    """A process that keeps the dpkg lock (an fcntl lock, as apt and dpkg take it) past the wait."""
    host = new_host(tmp_path, deployed, release)
    with dpkg_lock_held(host.root / "var/lib/dpkg/lock-frontend") as pid:
        result = first_boot(host, deployed)
    assert result.returncode != 0
    reason = failure_reason(host)
    assert reason.startswith(f"step apt failed (exit 1): the dpkg lock is still held by {pid} (python")
    assert "on /var/lib/dpkg/lock-frontend after 300 s" in reason
    # Nothing was installed, and the timers are back.
    assert not [c for c in host.calls() if c.startswith("apt-get")]
    apt_restored(host)


def test_a_uniform_screen_is_a_failure_of_the_verify_step(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    host = new_host(tmp_path, deployed, release)
    uniform_png(host.sim / "screen.png")
    result = first_boot(host, deployed)
    assert result.returncode != 0
    reason = failure_reason(host)
    assert reason.startswith(
        "step verify failed (exit 1): screen: the console shows one flat colour (#000000"
    )
    assert "viewer:" not in reason.split("; last log lines:")[0]
    # A boot that failed never armed the silent alarm (the stack rolls back).
    assert host.armed() == []
    apt_restored(host)


def test_an_active_ufw_lets_dcv_in_and_an_inactive_one_is_left_alone(
    booted, tmp_path: Path, deployed: Deployed, release
) -> None:
    """An AMI with ufw on would drop DCV's port after the security group let it in, while every check on the
    host passed: the boot opens 8443 over TCP and UDP, as AWS's DLAMI sample does, and only then."""
    default, _ = booted
    assert not [c for c in default.calls() if c.startswith("ufw allow")]
    host = new_host(tmp_path, deployed, release)
    (host.sim / "ufw-active").touch()
    result = first_boot(host, deployed)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    allowed = [c for c in host.calls() if c.startswith("ufw allow")]
    assert allowed == ["ufw allow 8443/tcp", "ufw allow 8443/udp"], allowed
    assert (
        "ufw is active: opened 8443/udp for DCV"
        in (host.root / "var/log/so101-twin-bootstrap.log").read_text()
    )
    # ufw keeps its rules: an update finds them there and adds none.
    rerun = run_association(host, deployed.update_script)
    assert rerun.returncode == 0, rerun.stdout[-3000:] + rerun.stderr[-3000:]
    assert [c for c in host.calls() if c.startswith("ufw allow")] == allowed


def test_x_whose_opengl_is_software_is_a_failure_of_the_display_step(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    host = new_host(tmp_path, deployed, release)
    (host.sim / "glx").write_text(LLVMPIPE)
    result = first_boot(host, deployed)
    assert result.returncode != 0
    reason = failure_reason(host)
    assert reason.startswith("step display failed (exit 1): X did not start on the GPU: Xorg runs on NVIDIA")
    assert "OpenGL on :0 is rendered by llvmpipe (LLVM 20.1.2, 256 bits) (Mesa)" in reason
    # X was asked with the authority file of its own command line, as root has to.
    assert "glxinfo -B" in host.calls()
    apt_restored(host)


def test_a_crash_looping_viewer_is_a_failure_of_the_verify_step(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    host = new_host(tmp_path, deployed, release)
    (host.sim / "viewer-mode").write_text("crashloop")
    result = first_boot(host, deployed)
    assert result.returncode != 0
    reason = failure_reason(host)
    assert reason.startswith("step verify failed (exit 1): viewer: twin view keeps restarting")
    assert "its process is 3 s old" in reason
    # Looked at again and again, a new process each time: never the same one for 20 s.
    assert int((host.sim / "viewer-starts").read_text()) > 5
    apt_restored(host)


def test_a_missing_xorg_module_of_another_version_is_not_installed(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    """Ubuntu's module package pins its libraries: one of another version than the driver would replace it."""
    host = new_host(tmp_path, deployed, release, xorg_module=False)
    (host.sim / "apt-candidate").mkdir()
    (host.sim / "apt-candidate" / "xserver-xorg-video-nvidia-580-server").write_text("580.126.09-0ubuntu1\n")
    result = first_boot(host, deployed)
    assert result.returncode != 0
    reason = failure_reason(host)
    assert reason.startswith("step gpu failed (exit 1): the NVIDIA Xorg module nvidia_drv.so is missing")
    assert "580.126.09-0ubuntu1, not the installed driver's 580.95.05-0ubuntu0.24.04.2" in reason
    assert not [c for c in host.calls() if c.startswith("apt-get") and "xserver-xorg-video-nvidia" in c]


def test_a_failing_download_before_bootstrap_signals_failure(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    host = new_host(tmp_path, deployed, release)
    for obj in (host.sim / "s3").rglob("*.zip"):
        obj.unlink()
    result = first_boot(host, deployed)
    assert result.returncode != 0
    posts = host.handle_posts()
    assert [p["Status"] for p in posts] == ["FAILURE"]
    assert posts[0]["Reason"].startswith("step fetch failed")
    assert "does not exist" in posts[0]["Reason"]
    assert any(
        "--status FAILURE" in s and "--unique-id i-0123456789abcdef0-fetch" in s for s in host.signals()
    )


def test_an_unguarded_command_failing_inside_a_step_function_is_caught(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    """No `|| die` around it: set -E carries the ERR trap into the step's function (the old script lacked it,
    so a failure inside a function ended the boot silently)."""
    host = new_host(tmp_path, deployed, release)
    host.fail("dpkg")
    result = first_boot(host, deployed)
    assert result.returncode != 0
    reason = failure_reason(host)
    assert reason.startswith("step logs failed (exit 1); last log lines:")
    assert "dpkg: failing on purpose" in reason


def test_an_incomplete_deployment_parameter_fails_the_settings_step(
    tmp_path: Path, deployed: Deployed, release
) -> None:
    host = new_host(tmp_path, deployed, release)
    (host.sim / "parameter").write_text(
        "\n".join(line for line in deployed.parameter.splitlines() if not line.startswith("DEVICES="))
    )
    result = first_boot(host, deployed)
    assert result.returncode != 0
    reason = failure_reason(host)
    assert reason.startswith("step settings failed (exit 1): ")
    assert "has no DEVICES: the stack's deployment parameter is incomplete" in reason
