"""A port of the twin host on this machine's loopback, through Session Manager: what `aws ssm start-session
--document-name AWS-StartPortForwardingSession` does, without the AWS CLI.

SSM's StartSession opens the session; AWS's Session Manager plugin (`session-manager-plugin`, a program of
its own that the AWS CLI runs too) carries it: it listens on the local port and tunnels each connection over
the session's WebSocket to the port on the instance, whose SSM agent dials out, so nothing opens in the
security group. The session is handed to the plugin the way the AWS CLI hands it
(aws/aws-cli `awscli/customizations/sessionmanager.py`): the StartSession response as JSON, in the
environment variable AWS_SSM_START_SESSION_RESPONSE for plugins newer than 1.2.497.0 (on the command line
before), then the region, "StartSession", the profile, the request's parameters as JSON, and the SSM
endpoint. The plugin runs in a session of its own, so Ctrl-C reaches this program, which ends the plugin
and the SSM session itself.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from typing import Any

from twin.ops.instance import AwsSetupError, TwinInstanceError

log = logging.getLogger(__name__)

PLUGIN = "session-manager-plugin"
DOCUMENT = "AWS-StartPortForwardingSession"
PLUGIN_INSTALL_URL = "https://docs.aws.amazon.com/systems-manager/latest/userguide/session-manager-working-with-install-plugin.html"
RESPONSE_ENV = "AWS_SSM_START_SESSION_RESPONSE"
# The last plugin that takes the response only on its command line (the AWS CLI's own rule).
LAST_PLUGIN_VERSION_WITHOUT_ENV = (1, 2, 497, 0)
LOOPBACK = "127.0.0.1"


class PortForwardError(TwinInstanceError):
    """The forward could not start or ended; the message says why and what to do."""


class PluginMissingError(AwsSetupError):
    """No Session Manager plugin on PATH: part of the AWS setup, like credentials."""


def find_plugin(name: str = PLUGIN) -> str:
    """The plugin's path; PluginMissingError saying how to install it when it is not on PATH."""
    path = shutil.which(name)
    if path is None:
        raise PluginMissingError(
            f"the Session Manager plugin ({name}) is not installed or not on PATH; it carries the port "
            f"forward, as it does for `aws ssm start-session`. Install it as {PLUGIN_INSTALL_URL} says "
            "(Debian/Ubuntu: its session-manager-plugin.deb and `sudo dpkg -i session-manager-plugin.deb`; "
            "macOS: `brew install --cask session-manager-plugin`), check with `session-manager-plugin "
            "--version`, then run this again"
        )
    return path


def plugin_version(path: str) -> tuple[int, ...] | None:
    """The plugin's version (`--version`), or None when it prints none that parses."""
    try:
        out = subprocess.run(
            [path, "--version"], capture_output=True, text=True, timeout=20, check=False
        ).stdout.strip()
        return tuple(int(part) for part in out.split("."))
    except (OSError, ValueError, subprocess.TimeoutExpired):
        return None


def local_port_free(port: int) -> int:
    """`port` if nothing listens on it here (0: a free one); PortForwardError naming the way out if taken."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((LOOPBACK, port))
        except OSError as exc:
            raise PortForwardError(
                f"local port {port} is in use ({exc.strerror}): pass another with --port, or --port 0 for "
                "any free one"
            ) from exc
        return int(probe.getsockname()[1])


class PortForward:
    """A running forward of `remote_port` on the instance to `local_port` on this machine's loopback."""

    def __init__(
        self,
        ssm: Any,
        session_id: str,
        instance_id: str,
        *,
        remote_port: int,
        local_port: int,
        process: Any,
    ) -> None:
        self._ssm = ssm
        self.session_id = session_id
        self.instance_id = instance_id
        self.remote_port = remote_port
        self.local_port = local_port
        self.process = process
        self._lines: list[str] = []
        self._reader = threading.Thread(target=self._read, name="ssm-plugin-output", daemon=True)
        self._reader.start()
        self._closed = False

    @property
    def url(self) -> str:
        return f"http://{LOOPBACK}:{self.local_port}/"

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    @property
    def output(self) -> str:
        """What the plugin printed so far (its errors say why a session failed)."""
        return "\n".join(self._lines[-20:])

    def _read(self) -> None:
        for raw in self.process.stdout:
            line = raw.rstrip()
            if line:
                self._lines.append(line)
                log.debug("session-manager-plugin: %s", line)

    def wait_ready(self, timeout_s: float) -> bool:
        """Until the local port accepts connections (True), or the plugin exits or time runs out (False)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.alive:
            with contextlib.suppress(OSError), socket.create_connection((LOOPBACK, self.local_port), 1.0):
                return True
            time.sleep(0.2)
        return False

    def close(self) -> None:
        """End the plugin (SIGTERM, then SIGKILL) and the SSM session; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        if self.alive:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait(5)
        self._reader.join(5)
        try:
            self._ssm.terminate_session(SessionId=self.session_id)
        except Exception as exc:  # the session ends by itself when its plugin is gone; say so and go on
            log.warning("could not end SSM session %s (%s); it ends when idle", self.session_id, exc)


def start_port_forward(
    ssm: Any,
    *,
    instance_id: str,
    remote_port: int,
    local_port: int,
    profile: str = "",
    plugin: str | None = None,
) -> PortForward:
    """Start the session and its plugin; the caller waits with `wait_ready` and ends it with `close`.

    The plugin is found before any AWS call (PluginMissingError), so a missing one leaves no session open.
    Errors of the StartSession call itself (botocore's) reach the caller unchanged.
    """
    path = plugin or find_plugin()
    local_port = local_port_free(local_port)
    parameters = {
        "Target": instance_id,
        "DocumentName": DOCUMENT,
        "Parameters": {"portNumber": [str(remote_port)], "localPortNumber": [str(local_port)]},
    }
    response = ssm.start_session(**parameters)
    argv, env = _plugin_invocation(path, ssm, response, parameters, profile=profile)
    try:
        process = subprocess.Popen(
            argv,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
    except OSError as exc:
        ssm.terminate_session(SessionId=response["SessionId"])
        raise PortForwardError(f"could not run {path}: {exc}") from exc
    log.info(
        "session %s: %s port %d on 127.0.0.1:%d", response["SessionId"], instance_id, remote_port, local_port
    )
    return PortForward(
        ssm,
        response["SessionId"],
        instance_id,
        remote_port=remote_port,
        local_port=local_port,
        process=process,
    )


def _plugin_invocation(
    path: str, ssm: Any, response: dict[str, Any], parameters: dict[str, Any], *, profile: str
) -> tuple[list[str], dict[str, str]]:
    """The plugin's command line and environment: the session handed over the way the AWS CLI hands it
    (module doc)."""
    session = json.dumps(
        {key: response[key] for key in ("SessionId", "TokenValue", "StreamUrl")}, separators=(",", ":")
    )
    env = dict(os.environ)
    version = plugin_version(path)
    handed = session
    if version is not None and version > LAST_PLUGIN_VERSION_WITHOUT_ENV:
        # The token stays out of the process list.
        env[RESPONSE_ENV] = session
        handed = RESPONSE_ENV
    argv = [
        path,
        handed,
        ssm.meta.region_name,
        "StartSession",
        profile,
        json.dumps(parameters),
        ssm.meta.endpoint_url,
    ]
    return argv, env
