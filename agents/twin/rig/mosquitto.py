"""A private mosquitto broker on loopback, for tests, the demo and the benchmark.

The twin talks to AWS IoT Core in production; locally the same awscrt client code talks to a mosquitto
started here with its own config in a temp dir, so nothing depends on (or disturbs) a system broker.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pwd
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

from twin.core.lifetime import die_with_parent

log = logging.getLogger(__name__)

_SEARCH_DIRS = ("/usr/sbin", "/usr/local/sbin", "/opt/homebrew/sbin")
_HOST = "127.0.0.1"


class MosquittoNotFound(RuntimeError):  # noqa: N818 - a public name: the rig, the demo and tests catch it
    """The mosquitto binary is not installed (or not on PATH / in /usr/sbin)."""


class BrokerError(RuntimeError):
    """mosquitto did not start or did not accept connections in time."""


def find_mosquitto() -> str:
    """Path of the mosquitto binary; Debian installs it in /usr/sbin, which is often not on a user's PATH."""
    found = shutil.which("mosquitto")
    if found:
        return found
    for folder in _SEARCH_DIRS:
        candidate = Path(folder) / "mosquitto"
        if candidate.is_file() and os.access(candidate, os.X_OK):
            return str(candidate)
    raise MosquittoNotFound(
        "mosquitto is not installed (looked on PATH and in " + ", ".join(_SEARCH_DIRS) + "): "
        "run `make setup` or `apt-get install mosquitto`"
    )


def free_port(host: str = _HOST) -> int:
    """A TCP port the kernel considers free right now on `host`."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def _port_accepts(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


def _port_bindable(host: str, port: int) -> bool:
    # SO_REUSEADDR as mosquitto itself sets it: TIME_WAIT leftovers then do not count as busy.
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError:
            return False
        return True


class MosquittoBroker:
    """mosquitto as a child process listening on 127.0.0.1 only, anonymous, without persistence.

    With `tls_certfile`/`tls_keyfile` the listener speaks TLS (url `mqtts://...`); `extra_config` lines are
    appended to the generated config as they are (e.g. a second listener).
    """

    def __init__(
        self,
        port: int | None = None,
        *,
        workdir: Path | None = None,
        tls_certfile: Path | None = None,
        tls_keyfile: Path | None = None,
        extra_config: str = "",
        start_timeout: float = 5.0,
    ) -> None:
        if (tls_certfile is None) != (tls_keyfile is None):
            raise ValueError("TLS needs both tls_certfile and tls_keyfile (PEM server certificate and key)")
        self.host = _HOST
        self._requested_port = port
        self.port: int = port or 0
        self._own_workdir = workdir is None
        self.workdir = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="so101-mqtt-"))
        self.tls_certfile = tls_certfile
        self.tls_keyfile = tls_keyfile
        self.extra_config = extra_config
        self.start_timeout = start_timeout
        self.log_path = self.workdir / "mosquitto.log"
        self.config_path = self.workdir / "mosquitto.conf"
        self._binary = find_mosquitto()
        self._proc: subprocess.Popen[bytes] | None = None
        self._log_file: BinaryIO | None = None

    @property
    def url(self) -> str:
        scheme = "mqtts" if self.tls_certfile else "mqtt"
        return f"{scheme}://{self.host}:{self.port}"

    @property
    def pid(self) -> int | None:
        """The broker process id while it runs (so a caller can prove it is gone afterwards)."""
        return self._proc.pid if self._proc is not None else None

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def _write_config(self) -> None:
        lines = [
            f"listener {self.port} {self.host}",
            "allow_anonymous true",
            "persistence false",
            # Telemetry is many small packets: without this, Nagle's algorithm holds them back for tens of
            # milliseconds on loopback, which the demo and the benchmark would report as network latency.
            "set_tcp_nodelay true",
            # Mosquitto drops QoS 0 messages for an online subscriber once 1,000 wait in its queue (the
            # default max_queued_messages; its log says "Outgoing messages are being dropped"), unseen by
            # the agent. A burst of a large fleet, or an agent starved of CPU for a moment, reaches that.
            # The local broker holds up to 100,000 instead (about 10 s of 1,000 arms, some 30 MB), so a
            # loss happens in the agent's mailbox, where it is counted and reported.
            "max_queued_messages 100000",
            # Started as root (CI containers), mosquitto would drop to the `mosquitto` user and lose access to
            # our private temp dir (log file, TLS key); keep it as the invoking user instead.
            f"user {pwd.getpwuid(os.geteuid()).pw_name}",
            f"log_dest file {self.log_path}",
            "log_timestamp true",
        ]
        if self.tls_certfile and self.tls_keyfile:
            lines += [f"certfile {self.tls_certfile}", f"keyfile {self.tls_keyfile}"]
        if self.extra_config:
            lines.append(self.extra_config)
        self.config_path.write_text("\n".join(lines) + "\n")

    def start(self) -> None:
        if self.running:
            return
        self.workdir.mkdir(parents=True, exist_ok=True)
        # An auto-picked port can be taken between picking and binding; then pick again.
        attempts = 1 if self._requested_port or self.port else 3
        for attempt in range(attempts):
            if not self.port:
                self.port = free_port(self.host)
            try:
                self._launch()
                return
            except BrokerError:
                if attempt == attempts - 1:
                    raise
                log.warning("mosquitto failed on port %d, retrying with another port", self.port)
                self.port = 0

    def _launch(self) -> None:
        # Checked first: with another server on the port, "accepts connections" would be a false success.
        if not _port_bindable(self.host, self.port):
            raise BrokerError(
                f"port {self.port} on {self.host} is in use by another process; pick another port"
            )
        self._write_config()
        self._log_file = open(self.log_path, "ab")  # noqa: SIM115 - lives as long as the process
        # The log is appended to across restarts: only what this launch writes after here counts.
        log_start = self._log_file.tell()
        self._proc = subprocess.Popen(
            [self._binary, "-c", str(self.config_path)],
            stdout=self._log_file,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            # A rig killed outright (a test run's timeout, kill -9) must not leave a broker on its port.
            preexec_fn=die_with_parent(),  # noqa: PLW1509 - only prctl
        )
        deadline = time.monotonic() + self.start_timeout
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:
                self._close_log()
                raise BrokerError(
                    f"mosquitto exited with code {self._proc.returncode} on port {self.port}; "
                    f"log {self.log_path}:\n{self._log_tail()}"
                )
            # "running" in our own log proves the listener is this process's: another server that took the
            # port after the check above also accepts connections, while mosquitto exits on "Address already
            # in use" a moment later.
            if self._says_running(log_start) and _port_accepts(self.host, self.port):
                log.info("mosquitto listening on %s (pid %d)", self.url, self._proc.pid)
                return
            time.sleep(0.02)
        self._terminate()
        raise BrokerError(
            f"mosquitto did not accept connections on {self.url} within {self.start_timeout:.1f} s; "
            f"log {self.log_path}:\n{self._log_tail()}"
        )

    def _says_running(self, log_start: int) -> bool:
        try:
            with open(self.log_path, "rb") as log_file:
                log_file.seek(log_start)
                return re.search(rb"mosquitto version \S+ running", log_file.read()) is not None
        except OSError:
            return False

    def _log_tail(self, lines: int = 20) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"

    def _close_log(self) -> None:
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None

    def _terminate(self, sig: int = signal.SIGTERM, timeout: float = 5.0) -> None:
        proc = self._proc
        if proc is None:
            return
        if proc.poll() is None:
            proc.send_signal(sig)
            try:
                proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                log.warning("mosquitto pid %d ignored signal %d, killing it", proc.pid, sig)
                proc.kill()
                proc.wait(timeout=timeout)
        self._proc = None
        self._close_log()

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after 5 s. Idempotent."""
        self._terminate(signal.SIGTERM)

    def kill(self) -> None:
        """SIGKILL: a crash as clients see it (no clean close of their sockets by the broker)."""
        self._terminate(signal.SIGKILL)

    def restart(self, *, hard: bool = False, port_free_timeout: float = 5.0) -> None:
        """Stop (or with `hard`, kill) and start again on the same port once the port is free."""
        if hard:
            self.kill()
        else:
            self.stop()
        deadline = time.monotonic() + port_free_timeout
        while not _port_bindable(self.host, self.port):
            if time.monotonic() > deadline:
                raise BrokerError(
                    f"port {self.port} still busy {port_free_timeout:.0f} s after stopping mosquitto"
                )
            time.sleep(0.05)
        self._launch()

    def close(self) -> None:
        """Stop and remove the private temp dir (when this object created it)."""
        self.stop()
        if self._own_workdir:
            with contextlib.suppress(OSError):
                shutil.rmtree(self.workdir)

    def __enter__(self) -> MosquittoBroker:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
