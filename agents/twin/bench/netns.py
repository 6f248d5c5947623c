"""Loopback-only network namespaces: where anything doing network discovery (DDS) runs on a shared machine.

`run_in_loopback_namespace(argv)` runs a command under `unshare -n` with only `lo`, brought up with multicast
routed over it, so DDS discovery (multicast SPDP) works inside and never reaches a real interface. Needs root
with CAP_SYS_ADMIN (to make the namespace) and CAP_NET_ADMIN (to bring lo up), as the development machine and
CI have.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path

from twin.bench.unavailable import Unavailable

# Set inside the namespace, so a command that re-executes itself there knows it has arrived.
INSIDE_ENV = "TWIN_LOOPBACK_NETNS"
# lo is down in a new namespace and has no multicast route: DDS discovery multicasts to 239.255.0.1.
_SETUP = 'ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo && exec "$@"'


class NamespaceError(Unavailable):
    """A loopback namespace cannot be made here; the message says what is missing."""


def inside() -> bool:
    return os.environ.get(INSIDE_ENV) == "1"


def missing_prerequisites() -> str | None:
    """Why a loopback namespace cannot be made here, with the fix; None when it can."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare and ip are needed (util-linux, iproute2: make setup installs them)"
    probe = subprocess.run(
        ["unshare", "-n", "sh", "-c", "ip link set lo up"], capture_output=True, text=True, check=False
    )
    if probe.returncode != 0:
        return _probe_failed(probe.stderr.strip(), root=os.geteuid() == 0)
    return None


def _probe_failed(stderr: str, *, root: bool) -> str:
    """The probe's failure with its fix: which capability is missing depends on which command failed."""
    if not root:
        return f"unshare -n failed ({stderr}): a loopback namespace needs root; run it as root"
    # Root already, so a capability is missing (a container without it). unshare names itself when it cannot
    # make the namespace (CAP_SYS_ADMIN); otherwise the namespace was made and `ip` could not bring lo up
    # (CAP_NET_ADMIN, which Docker drops by default).
    if stderr.startswith("unshare"):
        return (
            f"unshare -n failed ({stderr}): this root lacks CAP_SYS_ADMIN, which a network namespace needs: "
            "give it (docker run --cap-add SYS_ADMIN --cap-add NET_ADMIN: the namespace needs both)"
        )
    return (
        f"`ip link set lo up` in a new namespace failed ({stderr}): this root lacks CAP_NET_ADMIN, which "
        "bringing lo up needs: give it (docker run --cap-add NET_ADMIN --cap-add SYS_ADMIN: it needs both)"
    )


def run_in_loopback_namespace(
    argv: Sequence[str],
    *,
    env: Mapping[str, str] | None = None,
    timeout: float = 120.0,
    cwd: Path | None = None,
) -> subprocess.CompletedProcess[str]:
    """Run argv in a fresh loopback-only namespace; returns the finished process (stdout, stderr as text)."""
    reason = missing_prerequisites()
    if reason is not None:
        raise NamespaceError(reason)
    child_env = {**(os.environ if env is None else env), INSIDE_ENV: "1"}
    return subprocess.run(
        ["unshare", "-n", "sh", "-c", _SETUP, "netns", *argv],
        env=child_env,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        cwd=cwd,
    )
