"""The whole first boot, an in-place update and a failing boot, run for real against a stand-in host.

The scripts are the ones the synthesized template carries: the UserData text and the deployment parameter
are taken from the template and resolved as CloudFormation would (tests/infra/hostsim.py), the State
Manager association's commands likewise; the assets are the exact ones the synth staged. What stands in for
the system tools, and what each encodes, is described in hostsim.py. Nothing here reaches AWS or the network.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

from .hostsim import (
    HANDLE_URL,
    HISTORY_BUCKET,
    INSTANCE_ID,
    LOG_GROUP,
    SECRET_ARN,
    STACK_NAME,
    HostSim,
    make_dcv_tarball,
    resolve,
    tree_digest,
    zip_dir,
)
from .synth import REPO_ROOT, Synth

pytestmark = pytest.mark.slow

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
    return values


class Deployed:
    """What a deploy of `synth` puts in front of the host: UserData, parameter, association, S3 objects."""

    def __init__(self, synth: Synth, workdir: Path) -> None:
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
        self.s3 = {
            self.settings["AGENT_URL"].removeprefix("s3://"): zip_dir(agent_dir, workdir / "agent.zip"),
            self.settings["SCRIPTS_URL"].removeprefix("s3://"): zip_dir(scripts_dir, workdir / "scripts.zip"),
        }


@pytest.fixture(scope="module")
def dcv_tgz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_dcv_tarball(tmp_path_factory.mktemp("dcv") / "nice-dcv-ubuntu2404-x86_64.tgz")


@pytest.fixture(scope="module")
def deployed(synth_default: Synth, tmp_path_factory: pytest.TempPathFactory) -> Deployed:
    return Deployed(synth_default, tmp_path_factory.mktemp("deployed"))


def new_host(base: Path, deployed: Deployed, dcv_tgz: Path) -> HostSim:
    return HostSim(
        base, parameter=deployed.parameter, user_data=deployed.user_data, s3=deployed.s3, dcv_tgz=dcv_tgz
    )


def first_boot(host: HostSim, deployed: Deployed) -> subprocess.CompletedProcess[str]:
    script = host.sim / "user-data-as-launched.sh"
    script.write_text(deployed.user_data)
    return host.run(script)


@pytest.fixture(scope="module")
def booted(
    deployed: Deployed, dcv_tgz: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[HostSim, subprocess.CompletedProcess[str]]:
    host = new_host(tmp_path_factory.mktemp("host"), deployed, dcv_tgz)
    result = first_boot(host, deployed)
    return host, result


# --- the dcv tarball stand-in is realistic -----------------------------------------------------------------


def test_the_dcv_tarball_stand_in_is_realistic_and_breaks_tar_head_under_pipefail(dcv_tgz: Path) -> None:
    """Several MB, several members in one versioned directory: enough that `tar -t | head -1` (the old
    bootstrap's way to find the directory) dies of SIGPIPE under pipefail, as reproduced with GNU tar."""
    assert dcv_tgz.stat().st_size > 5_000_000
    listing = subprocess.run(["tar", "-tzf", str(dcv_tgz)], capture_output=True, text=True, check=True)
    assert len(listing.stdout.splitlines()) >= 5
    old = subprocess.run(
        ["bash", "-c", f"set -o pipefail; tar -tzf {dcv_tgz} | head -1"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert old.returncode == 141, (old.returncode, old.stderr)


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
        "x-on-gpu: Xorg runs on NVIDIA L40S",
        "dcv-session: console session owned by ubuntu",
        "agent: connected and subscribed",
        "viewer: twin view runs",
    ):
        assert check in log
    # The signal is the very last thing the boot does.
    calls = host.calls()
    assert calls[-1].startswith("aws cloudformation signal-resource")


def test_steps_run_in_order_logs_first_x_before_dcv(booted) -> None:
    host, _ = booted
    calls = host.calls()

    def first(prefix: str) -> int:
        return next(i for i, c in enumerate(calls) if c.startswith(prefix))

    # CloudWatch from the first step: configured before any package is installed.
    assert first("amazon-cloudwatch-agent-ctl -a fetch-config") < first(
        "apt-get -o DPkg::Lock::Timeout=600 install -y -q --no-install-recommends"
    )
    assert first("systemctl restart gdm3") < first("systemctl restart dcvserver")
    assert first("nvidia-xconfig") < first("systemctl restart gdm3")
    log = host.file("/var/log/so101-twin-bootstrap.log")
    steps = re.findall(r"step (\w+): done", log)
    assert steps == ["logs", "packages", "gpu", "agent", "desktop", "password", "dcv", "display", "verify"]
    # The log holds the UserData's own first line: the file the CloudWatch agent ships from its beginning.
    assert log.splitlines()[0].startswith("so101-twin user-data: boot start")
    cw = json.loads(host.file("/opt/aws/amazon-cloudwatch-agent/etc/so101-twin.json"))
    files = cw["logs"]["logs_collected"]["files"]["collect_list"]
    assert {f["file_path"] for f in files} >= {
        "/var/log/so101-twin-bootstrap.log",
        "/var/log/so101-twin-agent.log",
    }
    assert {f["log_group_name"] for f in files} == {LOG_GROUP}


def test_headless_nvidia_x_config(booted) -> None:
    host, _ = booted
    xorg = host.file("/etc/X11/xorg.conf")
    assert '"nvidia"' in xorg
    assert '"AllowEmptyInitialConfiguration" "True"' in xorg
    assert "Virtual     4096 2160" in xorg
    # The driver came from packages without its Xorg module: the matching flavour was installed.
    calls = host.calls()
    assert any(
        c.endswith("xserver-xorg-video-nvidia-580-server")
        for c in calls
        if c.startswith("apt-get") and " install " in c
    )
    nvx = next(c for c in calls if c.startswith("nvidia-xconfig"))
    assert "--allow-empty-initial-configuration" in nvx and "--virtual=4096x2160" in nvx


def test_desktop_is_quiet_and_owned_by_the_user(booted) -> None:
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


def test_dcv_config_and_password(booted) -> None:
    host, _ = booted
    conf = host.file("/etc/dcv/dcv.conf")
    assert 'owner = "ubuntu"' in conf and "create-session = true" in conf
    assert "web-client-max-head-resolution = (4096, 2160)" in conf
    assert (host.sim / "chpasswd.log").read_text() == "chpasswd user=ubuntu length=29\n"
    log = host.file("/var/log/so101-twin-bootstrap.log")
    assert "Gener4tedPassw0rd" not in log


def test_agent_config_from_the_deployment_parameter(booted, deployed: Deployed) -> None:
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
    assert config["ros2"] == {"enabled": False}
    assert config["cloudwatch"]["emf_file"] == "/var/log/so101-twin/emf.log"


def test_host_check_reports_every_line(booted) -> None:
    host, _ = booted
    result = host.run(host.root / "opt/so101-twin/userdata/host-check.sh")
    assert result.returncode == 0, result.stdout + result.stderr
    lines = [line.split("\t") for line in result.stdout.splitlines()]
    status = {name: state for name, state, _ in lines}
    assert status == {
        "x-on-gpu": "OK",
        "dcv-session": "OK",
        "agent": "OK",
        "telemetry": "WARN",
        "viewer": "OK",
        "version": "OK",
    }
    details = {name: detail for name, _, detail in lines}
    assert "arm-001 OFFLINE 0.0 Hz, never seen" in details["telemetry"]


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
    "run/so101-twin/",
)


def stable(digest: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in digest.items() if not k.startswith(REFETCHED)}


def test_second_run_through_the_association_changes_nothing(
    booted, deployed: Deployed, tmp_path: Path
) -> None:
    source, result = booted
    assert result.returncode == 0
    root = tmp_path / "host"
    shutil.copytree(source.root.parent, root, symlinks=True)
    host = HostSim.__new__(HostSim)
    host.root, host.sim, host.bin = root / "root", root / "sim", root / "sim" / "bin"
    before = tree_digest(host.root)
    calls_before = len(host.calls())
    script = host.sim / "association.sh"
    script.write_text(deployed.update_script)
    # AWS-RunShellScript runs the commands with sh.
    rerun = subprocess.run(
        ["sh", str(script)], env=host.env(), capture_output=True, text=True, timeout=600, check=False
    )
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
    log = host.file("/var/log/so101-twin-bootstrap.log")
    assert f"update of deployment {deployed.version}" in log
    assert "install-agent: " in log and "done (changed=0)" in log


def test_update_waits_for_the_parameter_to_show_its_version(
    booted, deployed: Deployed, tmp_path: Path
) -> None:
    """An association run for a newer version than the parameter shows fails instead of installing the old."""
    source, _ = booted
    root = tmp_path / "host"
    shutil.copytree(source.root.parent, root, symlinks=True)
    host = HostSim.__new__(HostSim)
    host.root, host.sim, host.bin = root / "root", root / "sim", root / "sim" / "bin"
    script = host.sim / "association.sh"
    script.write_text(deployed.update_script.replace(deployed.version, "0123456789ab"))
    rerun = subprocess.run(
        ["sh", str(script)], env=host.env(), capture_output=True, text=True, timeout=600, check=False
    )
    assert rerun.returncode != 0
    assert "want version 0123456789ab" in rerun.stdout
    assert host.file("/var/lib/so101-twin/deployed-version").strip() == deployed.version


# --- a failing step ----------------------------------------------------------------------------------------


def failing_boot(tmp_path: Path, deployed: Deployed, dcv_tgz: Path, tool: str) -> tuple[HostSim, Any]:
    host = new_host(tmp_path, deployed, dcv_tgz)
    host.fail(tool)
    return host, first_boot(host, deployed)


def test_a_failing_step_signals_failure_naming_the_step(
    tmp_path: Path, deployed: Deployed, dcv_tgz: Path
) -> None:
    # A broken NVIDIA driver: the gpu step fails (early, so the test stays quick).
    host, result = failing_boot(tmp_path, deployed, dcv_tgz, "nvidia-smi")
    assert result.returncode != 0
    signals = host.signals()
    assert len(signals) == 1 and "--status FAILURE" in signals[0]
    assert f"--logical-resource-id {deployed.logical_id}" in signals[0]
    posts = host.handle_posts()
    assert [p["Status"] for p in posts] == ["FAILURE"]
    reason = posts[0]["Reason"]
    assert reason.startswith(
        "step gpu failed (exit 1): nvidia-smi -L failed: the NVIDIA driver is not working"
    )
    assert "last log lines:" in reason and "nvidia-smi: failing on purpose" in reason
    # Nothing after the failing step ran, and the host does not claim the version.
    assert not [c for c in host.calls() if c.startswith(("dcv ", "nvidia-xconfig")) or "restart gdm3" in c]
    assert not (host.root / "opt/so101-twin/venv").exists()
    assert not (host.root / "var/lib/so101-twin/deployed-version").exists()
    assert "FAILURE" in host.file("/var/lib/so101-twin/last-run")


def test_a_failing_download_before_bootstrap_signals_failure(
    tmp_path: Path, deployed: Deployed, dcv_tgz: Path
) -> None:
    host = new_host(tmp_path, deployed, dcv_tgz)
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
    tmp_path: Path, deployed: Deployed, dcv_tgz: Path
) -> None:
    """No `|| die` around it: set -E carries the ERR trap into the step's function (the old script lacked it,
    so a failure inside a function ended the boot silently)."""
    host, result = failing_boot(tmp_path, deployed, dcv_tgz, "dpkg")
    assert result.returncode != 0
    posts = host.handle_posts()
    assert [p["Status"] for p in posts] == ["FAILURE"]
    assert posts[0]["Reason"].startswith("step logs failed (exit 1); last log lines:")
    assert "dpkg: failing on purpose" in posts[0]["Reason"]
    assert any("--status FAILURE" in s for s in host.signals())


def test_an_incomplete_deployment_parameter_fails_the_settings_step(
    tmp_path: Path, deployed: Deployed, dcv_tgz: Path
) -> None:
    parameter = "\n".join(line for line in deployed.parameter.splitlines() if not line.startswith("DEVICES="))
    host = HostSim(
        tmp_path, parameter=parameter, user_data=deployed.user_data, s3=deployed.s3, dcv_tgz=dcv_tgz
    )
    result = first_boot(host, deployed)
    assert result.returncode != 0
    reason = host.handle_posts()[0]["Reason"]
    assert reason.startswith("step settings failed (exit 1): ")
    assert "has no DEVICES: the stack's deployment parameter is incomplete" in reason
    assert any("--status FAILURE" in s for s in host.signals())
