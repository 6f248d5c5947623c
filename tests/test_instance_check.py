"""`twin instance check` (twin.ops.instance_check) and the version in `twin instance status`.

AWS cannot be reached from here. moto stands in for CloudFormation, EC2 and SSM (a small stack whose outputs
reference a moto instance, as the CDK stack's do). What moto cannot do is injected at the botocore level and
said so at each place: the first boot's signal events (moto records no CreationPolicy signals), and the output
of Run Command on the host (moto executes nothing). That output is not made up: it is what the real
`userdata/host-check.sh` prints (or `host-check.sh --on-start` writes, for `twin instance start`), run here
against a stand-in host (tests/infra/hostsim.py: a temporary root with stand-ins for nvidia-smi, dcv,
systemctl, pgrep, ps and curl), and the commands that bring the console capture back are run for real on a
local copy of it. The DCV port check makes a real TLS handshake with a local server that has a self-signed
certificate, like DCV's; a closed port stands for a blocked one.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import re
import socket
import ssl
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import boto3
import botocore.client
import botocore.exceptions
import pytest
from conftest import AWS_TEST_REGION
from infra.hostsim import BOOT_ID, HostSim
from moto import mock_aws
from twin.cli import main
from twin.cli.commands import instance as cmd
from twin.core.health import DeviceStatus, HealthSnapshot
from twin.ops import instance as lib
from twin.ops import instance_check as chk
from twin.service.state import AgentInfo, AgentState, BrokerState, DeviceState, HealthReport

REGION = AWS_TEST_REGION
REPO = Path(__file__).resolve().parents[1]
VERSION = "a63e23774290"


# --- a DCV-like TLS port on loopback ------------------------------------------------------------------------


def self_signed(tmp: Path) -> tuple[Path, Path]:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "dcv-stand-in")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=1))
        .not_valid_after(now + datetime.timedelta(days=1))
        .sign(key, hashes.SHA256())
    )
    cert_path, key_path = tmp / "cert.pem", tmp / "key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    return cert_path, key_path


@pytest.fixture
def dcv_port(tmp_path: Path) -> Iterator[int]:
    """A TLS listener on 127.0.0.1 that completes handshakes, then closes."""
    cert, key = self_signed(tmp_path)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(cert, key)
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(0.2)
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            try:
                with context.wrap_socket(conn, server_side=True):
                    pass
            except (ssl.SSLError, OSError):
                pass

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield server.getsockname()[1]
    finally:
        stop.set()
        thread.join(timeout=5)
        server.close()


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --- the stand-in host's own answer -------------------------------------------------------------------------


def stand_in_host(
    tmp: Path, *, deployed: str = VERSION, viewer: bool = True, x: bool = True, uncalibrated: bool = False
) -> HostSim:
    """A stand-in host in the given state, its agent serving the documents the real agent would."""
    host = HostSim(tmp / "host")
    for marker, on in (("xorg", x), ("viewer", viewer)):
        if on:
            (host.sim / "state" / marker).touch()
    (host.sim / "state" / "console").write_text("ubuntu\n")
    (host.sim / "services").mkdir(exist_ok=True)
    (host.sim / "services" / "so101-twin-agent").touch()
    # DCV runs (it listens on 8443, the ss stand-in says), as its console session shows.
    (host.sim / "services" / "dcvserver").touch()
    (host.root / "etc/so101-twin").mkdir(parents=True, exist_ok=True)
    (host.root / "etc/so101-twin/deployment.env").write_text(
        f"DESKTOP_USER=ubuntu\nDEPLOYMENT_VERSION={deployed}\n"
    )
    (host.root / "var/lib/so101-twin").mkdir(parents=True, exist_ok=True)
    (host.root / "var/lib/so101-twin/deployed-version").write_text(deployed + "\n")
    (host.root / "var/lib/so101-twin/last-run").write_text(
        "2026-11-23T10:00:00+00:00 boot SUCCESS verified\n"
    )
    venv_bin = host.root / "opt/so101-twin/venv/bin"
    venv_bin.mkdir(parents=True)
    # The test venv's interpreter, with its packages (Pillow for the screen check), as the host venv's.
    (venv_bin / "python").write_text(f'#!/bin/sh\nexec {sys.executable} "$@"\n')
    (venv_bin / "python").chmod(0o755)
    # The documents the agent itself would serve, built from its own typed state (twin.service.state).
    online = DeviceStatus.ONLINE
    state = AgentState(
        agent=AgentInfo(
            running=True,
            topic_filters=("dt/lerobot/arm-001/telemetry",),
            broker=BrokerState(url="iot", connected=True, subscribes=1, messages=420),
        ),
        devices={
            "arm-001": DeviceState(
                device_id="arm-001",
                health=HealthSnapshot(status=online, age_s=0.04, rate_hz=10.0),
                uncalibrated=uncalibrated,
            )
        },
    )
    health = HealthReport(status="ok", running=True, broker_connected=True, devices={"arm-001": online})
    (host.sim / "agent" / "state.json").write_bytes(state.to_json())
    (host.sim / "agent" / "healthz.json").write_bytes(health.to_json())
    return host


def host_check_output(tmp: Path, **state: Any) -> str:
    """What userdata/host-check.sh prints on a host in the given state (run for real on a stand-in host)."""
    host = stand_in_host(tmp, **state)
    result = host.run(REPO / "userdata" / "host-check.sh")
    assert result.stdout, result.stderr
    return result.stdout


def start_verdict_output(tmp: Path, **state: Any) -> str:
    """What START_VERDICT_COMMANDS print on a host whose start checks (host-check.sh --on-start) have run."""
    host = stand_in_host(tmp, **state)
    host.run(REPO / "userdata" / "host-check.sh", "--on-start")
    last_start = (host.root / "var/lib/so101-twin/last-start").read_text()
    return f"boot={BOOT_ID}\n{last_start}"


# --- moto stack ---------------------------------------------------------------------------------------------


def template(dcv_url: str) -> dict:
    return {
        "Resources": {
            "Host": {
                "Type": "AWS::EC2::Instance",
                "Properties": {"ImageId": "ami-12c6146b", "InstanceType": "g6e.2xlarge"},
            },
        },
        "Outputs": {
            "InstanceId": {"Value": {"Ref": "Host"}},
            "DcvUrl": {"Value": dcv_url},
            "DeploymentVersion": {"Value": VERSION},
            "UpdateAssociationId": {"Value": "0b1c2d3e-0000-4000-8000-000000000009"},
        },
    }


def deploy(dcv_url: str) -> dict[str, str]:
    cfn = boto3.client("cloudformation", region_name=REGION)
    cfn.create_stack(StackName=lib.DEFAULT_STACK_NAME, TemplateBody=json.dumps(template(dcv_url)))
    outputs = cfn.describe_stacks(StackName=lib.DEFAULT_STACK_NAME)["Stacks"][0]["Outputs"]
    return {o["OutputKey"]: o["OutputValue"] for o in outputs}


def stopped(outputs: dict[str, str]) -> None:
    """The deployed host stopped (moto's instance runs from the start), so `start` has a start to check."""
    ec2 = boto3.client("ec2", region_name=REGION)
    ec2.stop_instances(InstanceIds=[outputs["InstanceId"]])


SIGNAL_SUCCESS = {
    "ResourceType": "AWS::EC2::Instance",
    "LogicalResourceId": "HostInstance2C59A3BE",
    "ResourceStatus": "CREATE_IN_PROGRESS",
    "ResourceStatusReason": "Received SUCCESS signal with UniqueId i-0123456789abcdef0",
}
WAIT_FAILED = {
    "ResourceType": "AWS::CloudFormation::WaitCondition",
    "LogicalResourceId": "HostBootWait",
    "ResourceStatus": "CREATE_FAILED",
    "ResourceStatusReason": "WaitCondition received failed message: 'step display failed (exit 1): X did not "
    "start on the GPU: no Xorg process; last log lines: ...' for uniqueId: i-0123456789abcdef0",
}


def intercept(monkeypatch: pytest.MonkeyPatch, handlers: dict) -> None:
    """Route chosen AWS operations through `handler(original, params)`; everything else reaches moto."""
    original = botocore.client.BaseClient._make_api_call

    def patched(self, operation_name, api_params):
        if operation_name in handlers:
            return handlers[operation_name](lambda: original(self, operation_name, api_params), api_params)
        return original(self, operation_name, api_params)

    monkeypatch.setattr(botocore.client.BaseClient, "_make_api_call", patched)


def with_events(*extra: dict):
    """moto's own stack events plus the signal events it cannot produce (stand-ins)."""

    def handler(call, _params):
        response = call()
        response["StackEvents"] = list(extra) + response.get("StackEvents", [])
        return response

    return handler


def host_answers(stdout: str, status: str = "Success"):
    """SSM's GetCommandInvocation as the host would answer (moto runs nothing on an instance)."""

    def handler(call, params):
        response = call()
        response.update({"Status": status, "StandardOutputContent": stdout, "StandardErrorContent": ""})
        return response

    return handler


def run_check(capsys) -> tuple[int, str]:
    code = main(["instance", "check"])
    return code, capsys.readouterr().out


def table(out: str) -> dict[str, tuple[str, str]]:
    rows = {}
    for line in out.splitlines()[1:]:
        if not line.strip() or line.startswith(("fixes:", "  ", "verdict:")):
            break
        name, status, detail = re.split(r"\s{2,}", line, maxsplit=2)
        rows[name] = (status, detail)
    return rows


# --- the whole command -------------------------------------------------------------------------------------


def test_a_working_twin_passes_every_check(aws_env, dcv_port, tmp_path, monkeypatch, capsys):
    stdout = host_check_output(tmp_path)
    with mock_aws():
        deploy(f"https://127.0.0.1:{dcv_port}/#console")
        intercept(
            monkeypatch,
            {
                "DescribeStackEvents": with_events(SIGNAL_SUCCESS),
                "GetCommandInvocation": host_answers(stdout),
            },
        )
        code, out = run_check(capsys)
        sent = boto3.client("ssm", region_name=REGION).list_commands()["Commands"][-1]
    assert code == cmd.EXIT_OK, out
    rows = table(out)
    assert list(rows) == [
        "stack",
        "boot signal",
        "instance",
        "dcv port",
        "x-on-gpu",
        "dcv-session",
        "agent",
        "telemetry",
        "calibration",
        "viewer",
        "screen",
        "version",
    ]
    assert {name: status for name, (status, _) in rows.items()} == dict.fromkeys(rows, "OK")
    assert rows["dcv port"][1].startswith(f"127.0.0.1:{dcv_port} completes a TLS handshake from here (TLSv1.")
    # Its certificate's fingerprint, to compare with the host's: a proxy completes a handshake too.
    der = ssl.PEM_cert_to_DER_cert((tmp_path / "cert.pem").read_text())
    fingerprint = ":".join(f"{b:02X}" for b in hashlib.sha256(der).digest())
    assert f"its certificate's SHA-256 is {fingerprint}: the same as `sudo dcv list-endpoints -j`" in out
    assert "arm-001 ONLINE 10.0 Hz, last message 0.0 s ago" in rows["telemetry"][1]
    assert f"host runs {VERSION}, the stack's current deployment" in rows["version"][1]
    assert out.rstrip().endswith("verdict: the twin works (12 checks OK)")
    assert sent["Parameters"]["commands"] == [chk.HOST_CHECK_COMMAND]


def test_failing_lines_get_a_fix_and_the_verdict_fails(aws_env, tmp_path, monkeypatch, capsys):
    stdout = host_check_output(tmp_path, deployed="0ld0ld0ld0ld", viewer=False)
    with mock_aws():
        deploy(f"https://127.0.0.1:{closed_port()}/#console")
        intercept(
            monkeypatch,
            {
                "DescribeStackEvents": with_events(SIGNAL_SUCCESS),
                "GetCommandInvocation": host_answers(stdout, "Failed"),
            },
        )
        code, out = run_check(capsys)
    assert code == cmd.EXIT_CHECK_FAILED
    rows = table(out)
    assert rows["dcv port"][0] == "FAIL" and "ConnectionRefusedError" in rows["dcv port"][1]
    assert rows["viewer"][0] == "FAIL"
    assert rows["screen"][0] == "OK"
    assert rows["version"] == (
        "FAIL",
        f"host runs 0ld0ld0ld0ld, the stack asks for {VERSION} (last run: "
        "2026-11-23T10:00:00+00:00 boot SUCCESS verified)",
    )
    fixes = out.split("fixes:", 1)[1]
    assert (
        "dcv port: DCV admits only clientCidr" in fixes
        and 'clientCidr = "<it>/32" into twin.settings.toml' in fixes
    )
    assert "viewer: the viewer starts at the desktop login and must keep running" in fixes
    assert "aws ssm start-associations-once --association-ids 0b1c2d3e-0000-4000-8000-000000000009" in fixes
    assert "verdict: the twin does not work: 3 failing check(s): dcv port, viewer, version" in out


def test_an_arm_without_calibration_is_a_warning_with_the_command(
    aws_env, dcv_port, tmp_path, monkeypatch, capsys
):
    stdout = host_check_output(tmp_path, uncalibrated=True)
    with mock_aws():
        deploy(f"https://127.0.0.1:{dcv_port}/#console")
        intercept(
            monkeypatch,
            {
                "DescribeStackEvents": with_events(SIGNAL_SUCCESS),
                "GetCommandInvocation": host_answers(stdout),
            },
        )
        code, out = run_check(capsys)
    assert code == cmd.EXIT_OK  # a warning: the twin works, with the nominal arm's angles
    rows = table(out)
    assert rows["calibration"] == (
        "WARN",
        "arm-001 has no calibration: the nominal SO-101's zero and range, not the arm's",
    )
    assert "calibration: push each arm's LeRobot calibration: twin calibration push ARM FILE" in out


def test_a_failed_boot_shows_the_reason_from_the_wait_condition(
    aws_env, dcv_port, tmp_path, monkeypatch, capsys
):
    stdout = host_check_output(tmp_path, x=False)
    with mock_aws():
        deploy(f"https://127.0.0.1:{dcv_port}/#console")
        intercept(
            monkeypatch,
            {"DescribeStackEvents": with_events(WAIT_FAILED), "GetCommandInvocation": host_answers(stdout)},
        )
        code, out = run_check(capsys)
    assert code == cmd.EXIT_CHECK_FAILED
    rows = table(out)
    assert rows["boot signal"][0] == "FAIL"
    assert "step display failed (exit 1): X did not start on the GPU" in rows["boot signal"][1]
    assert rows["x-on-gpu"][0] == "FAIL" and "no Xorg process" in rows["x-on-gpu"][1]


def test_a_stopped_instance_skips_the_host(aws_env, dcv_port, monkeypatch, capsys):
    with mock_aws():
        outputs = deploy(f"https://127.0.0.1:{dcv_port}/#console")
        boto3.client("ec2", region_name=REGION).stop_instances(InstanceIds=[outputs["InstanceId"]])
        intercept(monkeypatch, {"DescribeStackEvents": with_events(SIGNAL_SUCCESS)})
        code, out = run_check(capsys)
    assert code == cmd.EXIT_CHECK_FAILED
    rows = table(out)
    assert rows["instance"][0] == "FAIL"
    assert rows["dcv port"][0] == "SKIP" and rows["host"][0] == "SKIP"
    assert "instance: start it: twin instance start" in out


def forgotten_by_ec2(call, params):
    """EC2's answer about an instance terminated over an hour ago (moto lists a terminated one for good)."""
    (instance_id,) = params["InstanceIds"]
    error = {
        "Code": "InvalidInstanceID.NotFound",
        "Message": f"The instance ID '{instance_id}' does not exist",
    }
    raise botocore.exceptions.ClientError({"Error": error}, "DescribeInstances")


@pytest.mark.parametrize("listed", [True, False], ids=["listed", "forgotten-by-ec2"])
def test_a_terminated_instance_fails_the_check_with_the_way_to_a_new_host(
    aws_env, dcv_port, monkeypatch, capsys, listed
):
    """It once was a warning, "check again in a minute", and the verdict said the twin works. An hour after
    the termination EC2 no longer lists it: the check said only an AWS error then, with no table."""
    handlers: dict[str, Any] = {"DescribeStackEvents": with_events(SIGNAL_SUCCESS)}
    if not listed:
        handlers["DescribeInstances"] = forgotten_by_ec2
    with mock_aws():
        outputs = deploy(f"https://127.0.0.1:{dcv_port}/#console")
        boto3.client("ec2", region_name=REGION).terminate_instances(InstanceIds=[outputs["InstanceId"]])
        intercept(monkeypatch, handlers)
        code, out = run_check(capsys)
    assert code == cmd.EXIT_CHECK_FAILED
    rows = table(out)
    assert rows["instance"] == ("FAIL", f"{outputs['InstanceId']} terminated: EC2 never starts it again")
    # This stack publishes no Settings output (older than hostGeneration): its first host, so 2; and no
    # pointer to `twin instance settings`, which fails on such a stack.
    assert "instance: Build a new host in its place: raise hostGeneration by one in twin.settings.toml" in out
    assert "(write hostGeneration = 2 if it is not there)" in out and "instance settings" not in out, out
    assert "and run `cdk deploy -c replaceInstance=true`" in out
    assert "the twin works" not in out


def test_an_unregistered_ssm_agent_is_one_clear_line(aws_env, dcv_port, monkeypatch, capsys):
    from botocore.exceptions import ClientError

    def unregistered(_call, params):
        raise ClientError({"Error": {"Code": "InvalidInstanceId", "Message": "not valid"}}, "SendCommand")

    with mock_aws():
        deploy(f"https://127.0.0.1:{dcv_port}/#console")
        intercept(
            monkeypatch, {"DescribeStackEvents": with_events(SIGNAL_SUCCESS), "SendCommand": unregistered}
        )
        code, out = run_check(capsys)
    assert code == cmd.EXIT_CHECK_FAILED
    assert table(out)["host"] == ("FAIL", "the SSM agent has not registered yet")


# --- status shows the version ------------------------------------------------------------------------------


def test_status_shows_the_version_the_host_runs(aws_env, dcv_port, monkeypatch, capsys):
    body = json.dumps({"status": "ok", "devices": {"arm-001": "ONLINE"}})
    with mock_aws():
        deploy(f"https://127.0.0.1:{dcv_port}/#console")
        intercept(monkeypatch, {"GetCommandInvocation": host_answers(f"version={VERSION}\n{body}200")})
        assert main(["instance", "status"]) == 0
        out = capsys.readouterr().out
        sent = boto3.client("ssm", region_name=REGION).list_commands()["Commands"][-1]
    assert "agent healthy: arm-001=ONLINE" in out
    assert f"version: {VERSION} (the stack's current deployment)" in out
    assert sent["Parameters"]["commands"] == lib.STATUS_COMMANDS


def test_status_says_when_the_host_is_behind(aws_env, dcv_port, monkeypatch, capsys):
    with mock_aws():
        deploy(f"https://127.0.0.1:{dcv_port}/#console")
        intercept(monkeypatch, {"GetCommandInvocation": host_answers("version=0ld0ld0ld0ld\n000", "Failed")})
        assert main(["instance", "status"]) == 0
        out = capsys.readouterr().out
    assert f"the host runs 0ld0ld0ld0ld, the stack asks for {VERSION}: the in-place update is pending" in out


# --- the pieces ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("status", "expected"),
    [
        ("CREATE_COMPLETE", chk.OK),
        ("UPDATE_COMPLETE", chk.OK),
        ("UPDATE_ROLLBACK_COMPLETE", chk.WARN),
        ("UPDATE_IN_PROGRESS", chk.WARN),
        ("ROLLBACK_COMPLETE", chk.FAIL),
        ("CREATE_FAILED", chk.FAIL),
    ],
)
def test_stack_status_lines(status: str, expected: str) -> None:
    line = chk.check_stack(status, "")
    assert line.status == expected
    assert bool(line.fix) == (expected != chk.OK)


def test_boot_signal_without_events_is_a_warning_not_a_pass() -> None:
    assert chk.check_boot_signal([]).status == chk.WARN
    timeout = {
        "ResourceType": "AWS::EC2::Instance",
        "ResourceStatus": "CREATE_FAILED",
        "ResourceStatusReason": "Failed to receive 1 resource signal(s) within the specified duration",
    }
    assert chk.check_boot_signal([timeout]).status == chk.FAIL


def test_the_newest_boots_signal_decides_not_an_older_failure() -> None:
    """Events come newest first. A host built again after a failed boot (a raised hostGeneration, a deploy
    after a rollback) leaves that failure among the recent events: the newer SUCCESS is the verdict, and a
    failure after an older SUCCESS is the verdict, with the reason its wait condition carried."""
    failure_signal = {
        "ResourceType": "AWS::EC2::Instance",
        "ResourceStatus": "CREATE_FAILED",
        "ResourceStatusReason": "Received FAILURE signal with UniqueId i-0123456789abcdef0",
    }
    rebuilt = chk.check_boot_signal([SIGNAL_SUCCESS, failure_signal, WAIT_FAILED])
    assert (rebuilt.status, rebuilt.fix) == (chk.OK, ""), rebuilt
    broke = chk.check_boot_signal([failure_signal, WAIT_FAILED, SIGNAL_SUCCESS])
    assert broke.status == chk.FAIL and broke.detail == WAIT_FAILED["ResourceStatusReason"], broke
    assert (
        chk.check_boot_signal([failure_signal, SIGNAL_SUCCESS]).detail
        == failure_signal["ResourceStatusReason"]
    )
    # A review: the wait condition's message quotes the boot's last log lines, often "timed out after N s
    # waiting for ...": taken for a boot's end, it lost the step's name. On either side of its signal.
    quoted = dict(WAIT_FAILED)
    quoted["ResourceStatusReason"] = WAIT_FAILED["ResourceStatusReason"].replace(
        "last log lines: ...", "last log lines: timed out after 60 s waiting for Xorg"
    )
    orders = ([quoted, failure_signal], [failure_signal, quoted], [failure_signal, quoted, SIGNAL_SUCCESS])
    for events in orders:
        said = chk.check_boot_signal(events)
        assert said.status == chk.FAIL and said.detail == quoted["ResourceStatusReason"], (events, said)
    # An old boot's failure after its own signal, then a newer SUCCESS: the SUCCESS decides.
    assert chk.check_boot_signal([SIGNAL_SUCCESS, quoted, failure_signal]).status == chk.OK


def test_unparseable_host_output_is_ignored_line_by_line() -> None:
    lines = chk.parse_host_check("garbage\nagent\tOK\tconnected\nx\tMAYBE\ty\n", None, None)
    assert [(line.name, line.status) for line in lines] == [("agent", "OK")]


# --- the verdict of the checks after a start ---------------------------------------------------------------


def test_start_waits_for_the_hosts_own_checks_and_prints_their_verdict(
    aws_env, dcv_port, tmp_path, monkeypatch, capsys
):
    stdout = start_verdict_output(tmp_path)
    with mock_aws():
        stopped(deploy(f"https://127.0.0.1:{dcv_port}/#console"))
        intercept(monkeypatch, {"GetCommandInvocation": host_answers(stdout)})
        code = main(["instance", "start", "--timeout", "60"])
        out = capsys.readouterr().out
        sent = boto3.client("ssm", region_name=REGION).list_commands()["Commands"][-1]
    assert code == cmd.EXIT_OK, out
    assert "start checks: PASS: X on the GPU, DCV console session listening on 8443, agent subscribed" in out
    assert sent["Parameters"]["commands"] == lib.START_VERDICT_COMMANDS


def test_start_fails_with_the_failing_checks_and_their_fixes(
    aws_env, dcv_port, tmp_path, monkeypatch, capsys
):
    stdout = start_verdict_output(tmp_path, viewer=False)
    with mock_aws():
        stopped(deploy(f"https://127.0.0.1:{dcv_port}/#console"))
        intercept(monkeypatch, {"GetCommandInvocation": host_answers(stdout)})
        code = main(["instance", "start", "--timeout", "60"])
        out = capsys.readouterr().out
    assert code == cmd.EXIT_CHECK_FAILED, out
    assert "start checks: FAIL: viewer: twin view is not running" in out
    assert "  viewer: twin view is not running in ubuntu's session" in out
    assert "    fix: the viewer starts at the desktop login" in out
    # The screen is not even captured without a viewer that ran its 20 s.
    assert "  screen: not captured" in out


def test_a_verdict_of_an_earlier_boot_is_not_this_starts(aws_env, dcv_port, tmp_path, monkeypatch) -> None:
    """The host still shows the verdict of the boot before the stop: `start` waits for a new one."""
    earlier = start_verdict_output(tmp_path).replace(f"boot={BOOT_ID}\n", "boot=0a0a0a0a-new-boot\n", 1)
    assert lib.parse_start_verdict(earlier) is None
    assert lib.parse_start_verdict(start_verdict_output(tmp_path / "again")).state == lib.PASS
    with mock_aws():
        deploy(f"https://127.0.0.1:{dcv_port}/#console")
        intercept(monkeypatch, {"GetCommandInvocation": host_answers(earlier)})
        twin = lib.TwinInstance(poll_interval_s=0.01, health_poll_interval_s=0.01)
        verdict = twin.start_verdict(timeout_s=0.5)
    assert verdict.state == lib.UNKNOWN
    assert "none within 0 s (the start checks have not finished yet)" in verdict.summary


# --- the console capture comes back ------------------------------------------------------------------------


def host_runs(answer):
    """SendCommand and GetCommandInvocation as the host would serve them: `answer(commands)` is the output of
    the commands sent (moto records commands but runs nothing)."""
    sent: dict[str, list[str]] = {}

    def record(call, params):
        response = call()
        sent[response["Command"]["CommandId"]] = params["Parameters"]["commands"]
        return response

    def on_the_host(call, params):
        response = call()
        stdout = answer(sent[params["CommandId"]])
        response.update({"Status": "Success", "StandardOutputContent": stdout, "StandardErrorContent": ""})
        return response

    return {"SendCommand": record, "GetCommandInvocation": on_the_host}, sent


def test_check_brings_the_console_capture_back(aws_env, dcv_port, tmp_path, monkeypatch, capsys):
    """The capture host-check.sh just took, in pieces that fit Run Command's output, checked by SHA-256."""
    host = stand_in_host(tmp_path)
    checked = host.run(REPO / "userdata" / "host-check.sh")
    capture = host.root / "var/lib/so101-twin/console.png"
    # Bigger than one piece, as a real desktop's capture is.
    capture.write_bytes(capture.read_bytes() + bytes(range(256)) * 200)

    def answer(commands: list[str]) -> str:
        if commands == [chk.HOST_CHECK_COMMAND]:
            return checked.stdout
        # The capture's size and pieces: run for real against the stand-in host's files.
        script = "\n".join(commands).replace("/var/lib/so101-twin/", f"{host.root}/var/lib/so101-twin/")
        stdout = subprocess.run(
            ["bash", "-c", script], capture_output=True, text=True, check=True, timeout=60
        ).stdout
        assert len(stdout) <= 24_000, "Run Command would cut this output"
        return stdout

    handlers, sent = host_runs(answer)
    target = tmp_path / "console.png"
    with mock_aws():
        deploy(f"https://127.0.0.1:{dcv_port}/#console")
        intercept(monkeypatch, {"DescribeStackEvents": with_events(SIGNAL_SUCCESS), **handlers})
        code = main(["instance", "check", "--screenshot", str(target)])
        out = capsys.readouterr().out
    assert code == cmd.EXIT_OK, out
    assert target.read_bytes() == capture.read_bytes()
    size = capture.stat().st_size
    assert size > chk.SCREENSHOT_CHUNK_BYTES
    captured = int(capture.stat().st_mtime)
    assert table(out)["screenshot"] == ("OK", f"saved {target} ({size} bytes, captured at epoch {captured})")
    # The host checks, the size, then one command per piece.
    assert len(sent) == 2 + -(-size // chk.SCREENSHOT_CHUNK_BYTES)


def test_a_missing_capture_is_a_failing_line_not_a_crash(aws_env, dcv_port, tmp_path, monkeypatch, capsys):
    stdout = host_check_output(tmp_path)
    handlers, _ = host_runs(lambda commands: stdout if commands == [chk.HOST_CHECK_COMMAND] else "missing\n")
    with mock_aws():
        deploy(f"https://127.0.0.1:{dcv_port}/#console")
        intercept(monkeypatch, {"DescribeStackEvents": with_events(SIGNAL_SUCCESS), **handlers})
        code = main(["instance", "check", "--screenshot", str(tmp_path / "x.png")])
        out = capsys.readouterr().out
    assert code == cmd.EXIT_CHECK_FAILED
    assert table(out)["screenshot"] == (
        "FAIL",
        "no capture to fetch from /var/lib/so101-twin/console.png (missing)",
    )
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize(
    ("detail", "fix_part"),
    [
        # verify_host, when no viewer ran its 20 s: nothing was captured, so nothing on the console is known.
        ("not captured: no viewer ran 20 s", "fix the viewer line first"),
        ("dcv get-screenshot of the console session failed: no such session", "see the dcv-session line"),
        (
            "the viewer's window (1280x720 at +0+0) shows one flat colour (#000000 over 100.0%): MuJoCo "
            "draws nothing in it",
            "'The viewer's window is black'",
        ),
        (
            "twin view runs, but its MuJoCo window is not shown on :0 (X says IsUnMapped: minimised or "
            "withdrawn)",
            "'The viewer's window is black'",
        ),
        ("no MuJoCo window is on X's display :0", "'The viewer's window is black'"),
        # A review: a capture the check could not judge got the flat console's fix.
        ("could not analyse the capture: ModuleNotFoundError: PIL", "could not judge it"),
        (
            "the console shows one flat colour (#000000 over 100.0% of 1280x720): no desktop is drawn",
            "'The console is black or blank'",
        ),
    ],
)
def test_a_failing_screen_line_gets_the_fix_for_what_it_saw(detail: str, fix_part: str) -> None:
    """The screen line fails for a flat console, a black, hidden or missing viewer window, a failed capture,
    or no capture at all: each gets its own fix, not the flat console's."""
    (line,) = chk.parse_host_check(f"screen\tFAIL\t{detail}\n", None, None)
    assert fix_part in line.fix, line.fix
    flat_console = "one flat colour:" in line.fix
    assert flat_console == detail.startswith("the console shows one flat colour"), line.fix
