"""What `twin run` tells systemd, by its notify protocol (sd_notify(3)), when the unit runs it with
`Type=notify` and `WatchdogSec=` (userdata/install-agent.sh):

- `READY=1` once the agent is up (its mirrors run, HTTP answers): `systemctl start` returns then, and the
  host checks ordered after the agent's unit see it serving;
- `WATCHDOG=1` from the main thread while the agent runs: a process whose main thread cannot run any more
  (a native call stuck holding the GIL, a deadlock) sends none, and systemd kills it after `WatchdogSec`
  and starts it again (`Restart=always`);
- `STOPPING=1` as it stops, and a `STATUS=` line `systemctl status` shows.

Outside systemd (`NOTIFY_SOCKET` unset: a laptop, the tests' own agents) every call does nothing. A message
that cannot be sent is logged once and never stops the agent: systemd's watchdog then says what went wrong.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


class Notifier:
    """The notify socket of the service manager that started this process (none: every call is a no-op)."""

    def __init__(self, address: str | None, watchdog_s: float | None) -> None:
        # A name starting with "@" is in Linux's abstract namespace (a leading NUL byte), as sd_notify reads.
        if address is not None and address.startswith("@"):
            address = "\0" + address[1:]
        self._address = address
        self.watchdog_s = watchdog_s
        self._socket: socket.socket | None = None
        self._failed = False

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> Notifier:
        """From `NOTIFY_SOCKET`, `WATCHDOG_USEC` and `WATCHDOG_PID` as systemd sets them; the watchdog only
        when it is this process's (`WATCHDOG_PID` unset or ours). Unsupported addresses (vsock) notify
        nothing, said once in the log."""
        env = os.environ if env is None else env
        address = env.get("NOTIFY_SOCKET") or None
        if address is not None and not address.startswith(("/", "@")):
            log.warning("NOTIFY_SOCKET %r is not a unix socket: systemd is not notified", address)
            address = None
        watchdog_s = None
        usec, pid = env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            watchdog_s = int(usec) / 1e6
        return cls(address, watchdog_s)

    @property
    def enabled(self) -> bool:
        return self._address is not None

    def ready(self, status: str) -> None:
        self._send(f"READY=1\nSTATUS={status}")

    def stopping(self, status: str) -> None:
        self._send(f"STOPPING=1\nSTATUS={status}")

    def watchdog(self) -> None:
        """Tell the watchdog the main thread runs (systemd asks for it at least every half interval; `twin
        run` sends it every second, one datagram)."""
        if self.watchdog_s is not None:
            self._send("WATCHDOG=1")

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    def _send(self, message: str) -> None:
        if self._address is None:
            return
        try:
            if self._socket is None:
                # Never blocking: a manager that stopped reading must not stop the main thread with it.
                self._socket = socket.socket(
                    socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK
                )
            self._socket.sendto(message.encode(), self._address)
        except OSError as exc:
            if not self._failed:
                # Once: a manager that went away fails every send the same way.
                self._failed = True
                log.error("cannot notify systemd at %s: %s", self._address.replace("\0", "@"), exc)
