"""`twin instance console`: the agent's port on the host, forwarded to this machine through Session Manager.

AWS cannot be reached from here. moto stands in for CloudFormation and EC2 (the stack's outputs, the
instance's state); moto has no StartSession or TerminateSession, so those two calls are answered at the
botocore level with the shape AWS answers them in, and recorded. AWS's Session Manager plugin (which would
open a WebSocket to AWS) is stood in for by a small program first on PATH that checks it was handed the
session the way the AWS CLI hands it, listens on the local port it was given and relays each connection to
a local HTTP server that plays the agent's port on the host; it logs what it was given and when it ends.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import stat
import sys
import textwrap
import threading
import urllib.request
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import boto3
import botocore.client
import pytest
from conftest import AWS_TEST_REGION, wait_for
from moto import mock_aws
from test_instance import TEMPLATE
from twin.cli import main
from twin.cli.commands import instance as cmd
from twin.ops import instance as lib
from twin.ops import port_forward

SESSION = {
    "SessionId": "twin-user-0a1b2c3d4e5f67890",
    "TokenValue": "AAEAAWbPfTm7-session-token-for-the-plugin-only",
    "StreamUrl": f"wss://ssmmessages.{AWS_TEST_REGION}.amazonaws.com/v1/data-channel/twin-user-0a1b2c3d4e5f67890",
}
CONSOLE_PAGE = b"<!doctype html><title>so101-twin console</title>"

# The stand-in plugin: the AWS CLI's calling convention checked, then a loopback relay to SIM_FORWARD_TO.
PLUGIN = textwrap.dedent(
    """\
    #!{python}
    import json, os, signal, socket, sys, threading
    log = open(os.environ["SIM_PLUGIN_LOG"], "a", buffering=1)
    if sys.argv[1:] == ["--version"]:
        print(os.environ.get("SIM_PLUGIN_VERSION", "1.2.707.0")); sys.exit(0)
    if len(sys.argv) != 7 or sys.argv[3] != "StartSession":
        print("usage: session-manager-plugin RESPONSE REGION StartSession PROFILE PARAMETERS ENDPOINT")
        sys.exit(2)
    handed = sys.argv[1]
    session = json.loads(os.environ[handed] if handed == "AWS_SSM_START_SESSION_RESPONSE" else handed)
    request = json.loads(sys.argv[5])
    log.write(json.dumps({{"argv": sys.argv[1:], "session": session, "request": request}}) + "\\n")
    if os.environ.get("SIM_PLUGIN_FAIL"):
        print("An error occurred (TargetNotConnected) when calling the StartSession operation: offline")
        sys.exit(255)
    port = int(request["Parameters"]["localPortNumber"][0])
    host, _, target = os.environ["SIM_FORWARD_TO"].rpartition(":")
    def ended(*_):
        log.write("terminated\\n"); os._exit(0)
    signal.signal(signal.SIGTERM, ended)
    server = socket.create_server(("127.0.0.1", port))
    print("Starting session with SessionId: " + session["SessionId"])
    print("Port %d opened for sessionId %s." % (port, session["SessionId"]))
    print("Waiting for connections...", flush=True)
    def pipe(a, b):
        try:
            while data := a.recv(65536):
                b.sendall(data)
        except OSError:
            pass
        finally:
            b.close()
    while True:
        client, _ = server.accept()
        upstream = socket.create_connection((host, int(target)))
        threading.Thread(target=pipe, args=(client, upstream), daemon=True).start()
        threading.Thread(target=pipe, args=(upstream, client), daemon=True).start()
    """
)


class _Agent(BaseHTTPRequestHandler):
    def do_GET(self) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(CONSOLE_PAGE)))
        self.end_headers()
        self.wfile.write(CONSOLE_PAGE)

    def log_message(self, *_args: object) -> None:
        pass


@pytest.fixture
def stack(aws_env):
    """The deployed twin stack in moto (tests/test_instance.py's template): yields its outputs."""
    with mock_aws():
        cfn = boto3.client("cloudformation", region_name=AWS_TEST_REGION)
        cfn.create_stack(StackName=lib.DEFAULT_STACK_NAME, TemplateBody=json.dumps(TEMPLATE))
        outputs = cfn.describe_stacks(StackName=lib.DEFAULT_STACK_NAME)["Stacks"][0]["Outputs"]
        yield {o["OutputKey"]: o["OutputValue"] for o in outputs}


@pytest.fixture
def host_port():
    """An HTTP server playing the agent's port 8080 on the host."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Agent)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server.server_address[1]
    server.shutdown()
    server.server_close()


@pytest.fixture
def plugin(
    request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, host_port: int
) -> Path:
    """The stand-in plugin first on PATH (of the version a test parametrizes it with); returns its log."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    path = bin_dir / port_forward.PLUGIN
    path.write_text(PLUGIN.format(python=sys.executable))
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    log = tmp_path / "plugin.log"
    log.touch()
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("SIM_PLUGIN_LOG", str(log))
    monkeypatch.setenv("SIM_FORWARD_TO", f"127.0.0.1:{host_port}")
    monkeypatch.setenv("SIM_PLUGIN_VERSION", getattr(request, "param", "1.2.707.0"))
    return log


@pytest.fixture
def sessions(monkeypatch: pytest.MonkeyPatch) -> dict[str, list[dict]]:
    """StartSession and TerminateSession answered as AWS answers them (moto has neither); the requests."""
    calls: dict[str, list[dict]] = {"StartSession": [], "TerminateSession": []}
    original = botocore.client.BaseClient._make_api_call

    def patched(self, operation_name, api_params):
        if operation_name == "StartSession":
            calls[operation_name].append(api_params)
            return dict(SESSION)
        if operation_name == "TerminateSession":
            calls[operation_name].append(api_params)
            return {"SessionId": api_params["SessionId"]}
        return original(self, operation_name, api_params)

    monkeypatch.setattr(botocore.client.BaseClient, "_make_api_call", patched)
    return calls


def plugin_log(log: Path) -> list[str]:
    return log.read_text().splitlines()


def listening_port(log: Path) -> int | None:
    lines = plugin_log(log)
    if not lines:
        return None
    port = int(json.loads(lines[0])["request"]["Parameters"]["localPortNumber"][0])
    with socket.socket() as probe:
        return port if probe.connect_ex(("127.0.0.1", port)) == 0 else None


def run_console(args: list[str], log: Path) -> tuple[int, bytes | None]:
    """`twin instance console ARGS` in this (main) thread, as a user runs it: a second thread waits for the
    forward, fetches the console through it, then presses Ctrl-C (SIGINT to this process)."""
    fetched: list[bytes] = []

    def user() -> None:
        try:
            port = wait_for(lambda: listening_port(log), 60, "the plugin to listen")
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as response:
                fetched.append(response.read())
        finally:
            os.kill(os.getpid(), signal.SIGINT)

    helper = threading.Thread(target=user, daemon=True)
    helper.start()
    code = main(["instance", "console", *args])
    helper.join(60)
    return code, fetched[0] if fetched else None


@pytest.mark.slow
@pytest.mark.parametrize("plugin", ["1.2.707.0", "1.2.497.0"], indirect=True)
def test_console_forwards_the_agents_port_and_ends_the_session(stack, plugin, sessions, capsys):
    code, page = run_console(["--port", "0", "--no-browser"], plugin)
    out = capsys.readouterr().out
    assert code == 0, out
    assert page == CONSOLE_PAGE  # the host's port, through the forward
    (start,) = sessions["StartSession"]
    port = int(start["Parameters"]["localPortNumber"][0])
    assert start == {
        "Target": stack["InstanceId"],
        "DocumentName": "AWS-StartPortForwardingSession",
        "Parameters": {"portNumber": ["8080"], "localPortNumber": [str(port)]},
    }
    assert f"console: http://127.0.0.1:{port}/" in out
    assert f"port 8080 of {stack['InstanceId']}" in out and SESSION["SessionId"] in out
    record = json.loads(plugin_log(plugin)[0])
    handed, region, verb, profile, _request, endpoint = record["argv"]
    assert record["session"] == SESSION and json.loads(json.dumps(start)) == record["request"]
    assert (region, verb, profile, endpoint) == (
        AWS_TEST_REGION,
        "StartSession",
        "",
        f"https://ssm.{AWS_TEST_REGION}.amazonaws.com",
    )
    if os.environ["SIM_PLUGIN_VERSION"] == "1.2.707.0":
        # A newer plugin gets the session in the environment: the token stays out of the process list.
        assert handed == port_forward.RESPONSE_ENV
    else:
        assert json.loads(handed) == SESSION
    # Ctrl-C ended the plugin and the session.
    assert plugin_log(plugin)[-1] == "terminated"
    assert sessions["TerminateSession"] == [{"SessionId": SESSION["SessionId"]}]
    assert "console: session ended" in out


def test_without_the_plugin_it_says_how_to_install_it_and_opens_no_session(
    stack,
    sessions,
    capsys,
    monkeypatch,
    tmp_path,
):
    empty = tmp_path / "empty-bin"
    empty.mkdir()
    monkeypatch.setenv("PATH", str(empty))
    assert main(["instance", "console", "--no-browser"]) == cmd.EXIT_SETUP
    err = capsys.readouterr().err
    assert "the Session Manager plugin (session-manager-plugin) is not installed or not on PATH" in err
    assert port_forward.PLUGIN_INSTALL_URL in err and "sudo dpkg -i session-manager-plugin.deb" in err
    assert sessions["StartSession"] == []


def test_a_terminated_instance_is_not_told_to_start(stack, plugin, sessions, capsys):
    boto3.client("ec2", region_name=AWS_TEST_REGION).terminate_instances(InstanceIds=[stack["InstanceId"]])
    assert main(["instance", "console", "--no-browser"]) == cmd.EXIT_AWS
    err = capsys.readouterr().err
    assert "is terminated. Build a new host in its place: write hostGeneration = 2" in err, err
    assert "twin instance start" not in err, err
    assert sessions["StartSession"] == []


def test_a_stopped_instance_is_named_with_the_way_out(stack, plugin, sessions, capsys):
    boto3.client("ec2", region_name=AWS_TEST_REGION).stop_instances(InstanceIds=[stack["InstanceId"]])
    assert main(["instance", "console", "--no-browser"]) == cmd.EXIT_WAIT
    assert "is stopped: start it with `twin instance start`" in capsys.readouterr().err
    assert sessions["StartSession"] == []


def test_a_local_port_in_use_is_named_before_any_session(stack, plugin, sessions, capsys):
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        assert main(["instance", "console", "--port", str(port), "--no-browser"]) == cmd.EXIT_AWS
    assert f"local port {port} is in use" in capsys.readouterr().err
    assert sessions["StartSession"] == []


@pytest.mark.slow
def test_a_plugin_that_fails_is_reported_and_its_session_ended(
    stack,
    plugin,
    sessions,
    capsys,
    monkeypatch,
):
    monkeypatch.setenv("SIM_PLUGIN_FAIL", "1")
    assert main(["instance", "console", "--port", "0", "--no-browser"]) == cmd.EXIT_AWS
    err = capsys.readouterr().err
    assert "did not open port" in err and "TargetNotConnected" in err
    assert sessions["TerminateSession"] == [{"SessionId": SESSION["SessionId"]}]
