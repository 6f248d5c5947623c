"""`twin instance check`: does the deployed twin work? One table, a verdict, and a fix for each failing line.

From the caller's side: the stack's status and the first boot's signal (CloudFormation), the instance's state
(EC2), and whether the DCV port completes a TLS handshake from here (the same path a browser takes). On the
host, through SSM Run Command, `userdata/host-check.sh`: the very checks the first boot waited for before it
signalled (X on the GPU, the DCV console session, the agent subscribed, the viewer stable, a capture of the
console that is not one flat colour) plus the telemetry (devices, rates, age of the last message) and the
version the host runs, compared with the stack's. With a file to save it to, the capture comes back too, in
pieces small enough for Run Command's output.
"""

from __future__ import annotations

import base64
import hashlib
import math
import re
import socket
import ssl
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from twin.ops.instance import TERMINATED_STATES, InstanceGoneError

if TYPE_CHECKING:
    from twin.ops.instance import TwinInstance

OK = "OK"
WARN = "WARN"
FAIL = "FAIL"
SKIP = "SKIP"

HOST_CHECK_SCRIPT = "/opt/so101-twin/userdata/host-check.sh"
# SSM Run Command runs as root.
HOST_CHECK_COMMAND = f"bash {HOST_CHECK_SCRIPT}"
DCV_CONNECT_TIMEOUT_S = 5.0
# The console capture host-check.sh keeps on the host. Run Command returns at most 24,000 characters of
# output, so it comes back in pieces of 17,000 bytes (22,668 characters of base64).
SCREENSHOT_FILE = "/var/lib/so101-twin/console.png"
SCREENSHOT_CHUNK_BYTES = 17_000
SCREENSHOT_INFO_COMMAND = (
    f'f={SCREENSHOT_FILE}; if [ -f "$f" ]; then stat -c "%s %Y" "$f"; sha256sum "$f"; else echo missing; fi'
)

# Stack statuses after which the stack is usable as deployed.
_STACK_OK = {"CREATE_COMPLETE", "UPDATE_COMPLETE", "IMPORT_COMPLETE"}
_STACK_WARN = {"UPDATE_ROLLBACK_COMPLETE"}

HOST_FIXES = {
    "x-on-gpu": "X must run on the NVIDIA GPU: docs/deploy.md, Troubleshooting, 'X does not run on the "
    "NVIDIA GPU' (on the host: nvidia-smi; /var/log/Xorg.0.log; restart gdm3, then dcvserver)",
    "dcv-session": "restart DCV once X is up (sudo systemctl restart dcvserver), or create the session: "
    "sudo dcv create-session --type=console --owner ubuntu console; nothing on TCP 8443: docs/deploy.md, "
    "Troubleshooting, 'No DCV console session'",
    "agent": "on the host: journalctl -u so101-twin-agent -n 50; the role may subscribe only to the "
    "configured devices' topics (set devices in twin.settings.toml and cdk deploy); sudo systemctl restart "
    "so101-twin-agent",
    "telemetry": "no arm is publishing to the subscribed topics: start the edge publisher of each device "
    "(or check its topic prefix and device id against the stack's settings)",
    "calibration": "push each arm's LeRobot calibration: twin calibration push ARM FILE (the agent picks it "
    "up within 30 s; docs/agent.md, 'Calibration'); a refused file says why in the console's Events",
    "viewer": "the viewer starts at the desktop login and must keep running: if it keeps restarting, its "
    "supervisor's log says why (on the host: journalctl _UID=$(id -u ubuntu) | grep twin-view); "
    "docs/deploy.md, Troubleshooting, 'The viewer keeps restarting'",
    "screen": "the console shows one flat colour: docs/deploy.md, Troubleshooting, 'The console is black or "
    "blank' (bring the capture back with --screenshot FILE; on the host: sudo systemctl restart gdm3, then "
    "dcvserver)",
}
# The screen line fails for more than a flat console (host-check.sh, check_screen and verify_host): the fix
# for the first of these its detail contains, else HOST_FIXES["screen"].
SCREEN_FIXES = (
    (
        "not captured",
        "the console is captured once a viewer has run 20 s: fix the viewer line first, then check again",
    ),
    (
        "dcv get-screenshot",
        "the capture comes from DCV's console session: see the dcv-session line (on the host: sudo dcv "
        "list-sessions; sudo systemctl restart dcvserver)",
    ),
    (
        # The capture was taken, but judging it failed: nothing about the console is known.
        "could not analyse the capture",
        "the capture was taken but the check could not judge it (its error is quoted): bring the capture "
        "back with --screenshot FILE and look at it; on the host the check runs in /opt/so101-twin/venv, "
        "which re-running the host's setup rebuilds (docs/deploy.md, 'Updates in place')",
    ),
    (
        "window",
        "the viewer's window is missing, hidden or drawn in one colour: docs/deploy.md, Troubleshooting, "
        "'The viewer's window is black' (bring the capture back with --screenshot FILE; its log on the host: "
        "journalctl _UID=$(id -u ubuntu) | grep twin-view)",
    ),
)


def host_fix(name: str, detail: str) -> str:
    """What to do about a failing or warning host-check line: by its name; for the screen, by what it saw."""
    if name == "screen":
        for seen, fix in SCREEN_FIXES:
            if seen in detail:
                return fix
    return HOST_FIXES.get(name, "")


@dataclass(frozen=True)
class CheckLine:
    """One row of the table: what was checked, how it came out, what was seen, and what to do about it."""

    name: str
    status: str  # OK, WARN, FAIL or SKIP
    detail: str
    fix: str = ""


@dataclass(frozen=True)
class CheckReport:
    lines: tuple[CheckLine, ...]

    @property
    def failures(self) -> tuple[CheckLine, ...]:
        return tuple(line for line in self.lines if line.status == FAIL)

    @property
    def warnings(self) -> tuple[CheckLine, ...]:
        return tuple(line for line in self.lines if line.status == WARN)

    @property
    def ok(self) -> bool:
        return not self.failures

    def verdict(self) -> str:
        if self.ok:
            extra = f", {len(self.warnings)} warning(s)" if self.warnings else ""
            return f"the twin works ({sum(line.status == OK for line in self.lines)} checks OK{extra})"
        names = ", ".join(line.name for line in self.failures)
        return f"the twin does not work: {len(self.failures)} failing check(s): {names}"

    def render(self) -> list[str]:
        """The table, then the fixes, then the verdict, as lines of text."""
        width = max(len(line.name) for line in self.lines)
        rows = [f"{'CHECK'.ljust(width)}  RESULT  DETAIL"]
        rows += [f"{line.name.ljust(width)}  {line.status.ljust(6)}  {line.detail}" for line in self.lines]
        fixes = [line for line in self.lines if line.status in (FAIL, WARN) and line.fix]
        if fixes:
            rows.append("")
            rows.append("fixes:")
            rows += [f"  {line.name}: {line.fix}" for line in fixes]
        rows.append("")
        rows.append(f"verdict: {self.verdict()}")
        return rows


def check_stack(status: str, reason: str) -> CheckLine:
    shown = f"{status}" + (f" ({reason})" if reason else "")
    if status in _STACK_OK:
        return CheckLine("stack", OK, status)
    if status in _STACK_WARN:
        return CheckLine(
            "stack",
            WARN,
            shown,
            "the last deploy failed and was rolled back; the host runs the previous deployment: read the "
            "stack's events, fix, deploy again",
        )
    if status.endswith("_IN_PROGRESS"):
        return CheckLine("stack", WARN, shown, "a deploy is running: check again when it has finished")
    return CheckLine(
        "stack",
        FAIL,
        shown,
        "the stack is not deployed in a working state: read its events (aws cloudformation "
        "describe-stack-events), fix, deploy again (cdk deploy --no-rollback keeps a failed instance)",
    )


def _wait_failed(kind: str, reason: str) -> bool:
    return kind == "AWS::CloudFormation::WaitCondition" and "failed message" in reason


def _boot_ended(kind: str, reason: str) -> bool:
    """A boot's end as its instance recorded it: its SUCCESS or FAILURE signal, or the CreationPolicy's
    timeout. The instance's events only: a wait condition's failure quotes the boot's last log lines, which
    often say "timed out" (a review: the step's name was then lost)."""
    return kind == "AWS::EC2::Instance" and (
        "SUCCESS signal" in reason
        or "FAILURE signal" in reason
        or "within the specified duration" in reason
        or "timed out" in reason.lower()
    )


def check_boot_signal(events: list[dict]) -> CheckLine:
    """The verdict of the newest first boot as CloudFormation recorded it: the instance's signal, the wait
    condition. Events come newest first, and the newest verdict decides: a host built again after a failed
    one (hostGeneration, or a deploy after a rollback) leaves the old failure among the recent events."""
    reasons = [(e.get("ResourceType", ""), e.get("ResourceStatusReason") or "") for e in events]
    ends = [i for i, (kind, reason) in enumerate(reasons) if _boot_ended(kind, reason)]
    # A failure newer than any end is a newer boot's (its instance's signal may not be recorded yet); one
    # between the newest end and the end before it is that end's own boot's, on either side of its signal.
    newest = reasons[: ends[0]] if ends else reasons
    last = reasons[ends[0] : ends[1] if len(ends) > 1 else None] if ends else []
    failed = [r for kind, r in newest if _wait_failed(kind, r)]
    if not failed and ends and "FAILURE signal" in reasons[ends[0]][1]:
        failed = [r for kind, r in last if _wait_failed(kind, r)] or [reasons[ends[0]][1]]
    if failed:
        return CheckLine(
            "boot signal",
            FAIL,
            failed[0],
            "the first boot failed at the step named here: docs/deploy.md, Troubleshooting; the full log "
            "is in the HostLogGroup stream <instance-id>/bootstrap",
        )
    if ends and "SUCCESS signal" in reasons[ends[0]][1]:
        return CheckLine("boot signal", OK, "the first boot signalled SUCCESS after verifying the host")
    if ends:
        return CheckLine(
            "boot signal",
            FAIL,
            "no signal before the CreationPolicy's timeout",
            "the host never reported: it could not reach AWS or a step hung; see the bootstrap log stream",
        )
    return CheckLine(
        "boot signal",
        WARN,
        "no signal in the stack's recent events (the boot still runs, or the events are older)",
        "if the deploy has finished, the CloudFormation console's event history shows the signal",
    )


def check_instance(state: str, instance_id: str, new_host_advice: str = "") -> CheckLine:
    """The instance's state; `new_host_advice`: what to do when it is terminated (no start brings it back)."""
    if state == "running":
        return CheckLine("instance", OK, f"{instance_id} running")
    if state in ("stopped", "stopping"):
        return CheckLine("instance", FAIL, f"{instance_id} {state}", "start it: twin instance start")
    if state in TERMINATED_STATES:
        return CheckLine(
            "instance", FAIL, f"{instance_id} {state}: EC2 never starts it again", new_host_advice
        )
    return CheckLine("instance", WARN, f"{instance_id} {state}", "check again in a minute")


def check_dcv_port(dcv_url: str, timeout_s: float = DCV_CONNECT_TIMEOUT_S) -> CheckLine:
    """A TLS handshake with the DCV web port from here (DCV's certificate is self-signed: not verified)."""
    parts = urlsplit(dcv_url)
    host, port = parts.hostname, parts.port or 443
    if not host:
        return CheckLine("dcv port", FAIL, f"DcvUrl {dcv_url!r} names no host", "redeploy the stack")
    context = ssl.create_default_context()
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    try:
        with (
            socket.create_connection((host, port), timeout=timeout_s) as raw,
            context.wrap_socket(raw, server_hostname=host) as tls,
        ):
            version = tls.version()
            der = tls.getpeercert(binary_form=True) or b""
    except (TimeoutError, ConnectionRefusedError, OSError) as exc:
        return CheckLine(
            "dcv port",
            FAIL,
            f"no TLS handshake with {host}:{port} from here ({exc.__class__.__name__}: {exc})",
            "DCV admits only clientCidr: if your public address changed, find it (curl -s "
            'https://checkip.amazonaws.com), write clientCidr = "<it>/32" into twin.settings.toml and cdk '
            "deploy; otherwise dcvserver is down (check dcv-session below)",
        )
    # Anything that speaks TLS completes the handshake, a proxy between here and the host too (a walk's did):
    # the certificate's fingerprint, for the comparison AWS documents (`dcv list-endpoints -j` on the host).
    fingerprint = ":".join(f"{b:02X}" for b in hashlib.sha256(der).digest())
    return CheckLine(
        "dcv port",
        OK,
        f"{host}:{port} completes a TLS handshake from here ({version}); its certificate's SHA-256 is "
        f"{fingerprint}: the same as `sudo dcv list-endpoints -j` shows on the host, unless a proxy between "
        "answered",
    )


def parse_host_check(
    stdout: str, expected_version: str | None, association_id: str | None
) -> list[CheckLine]:
    """The lines `host-check.sh` printed (NAME<TAB>STATUS<TAB>detail), with fixes, the version compared."""
    lines = []
    for raw in stdout.splitlines():
        parts = raw.split("\t", 2)
        if len(parts) != 3 or parts[1] not in (OK, WARN, FAIL):
            continue
        name, status, detail = parts
        if name == "version":
            lines.append(_version_line(detail, expected_version, association_id))
            continue
        lines.append(CheckLine(name, status, detail, host_fix(name, detail) if status != OK else ""))
    return lines


def _version_line(detail: str, expected: str | None, association_id: str | None) -> CheckLine:
    running = detail.split(" ", 1)[0]
    if not expected:
        return CheckLine("version", OK, f"host runs {detail}")
    if running == expected:
        return CheckLine("version", OK, f"host runs {running}, the stack's current deployment")
    rerun = (
        f"aws ssm start-associations-once --association-ids {association_id}"
        if association_id
        else "re-run the stack's <stack>-host-update association"
    )
    last_run = detail.split(" ", 1)[1] if " " in detail else ""
    return CheckLine(
        "version",
        FAIL,
        f"host runs {running}, the stack asks for {expected} {last_run}".rstrip(),
        f"the in-place update has not run or failed: {rerun}; its log is the bootstrap log stream",
    )


def screenshot_chunk_command(index: int) -> str:
    """The shell command that prints piece `index` of the capture as base64."""
    return (
        f"dd if={SCREENSHOT_FILE} bs={SCREENSHOT_CHUNK_BYTES} skip={index} count=1 status=none | base64 -w0"
    )


def fetch_screenshot(twin: TwinInstance, target: Path, *, timeout_s: float = 90.0) -> CheckLine:
    """Bring the console capture kept on the host back into `target`, checked against its SHA-256."""
    info = twin.run_on_host([SCREENSHOT_INFO_COMMAND], "twin instance check: screenshot size", timeout_s)
    match = re.match(r"(\d+) (\d+)\s+([0-9a-f]{64})\s", info.stdout)
    if info.problem or match is None:
        shown = info.problem or (info.stdout.strip()[:200] or "nothing")
        return CheckLine(
            "screenshot",
            FAIL,
            f"no capture to fetch from {SCREENSHOT_FILE} ({shown})",
            "the host captures the console in its checks: run `twin instance check` again once it is up",
        )
    size, captured, digest = int(match.group(1)), int(match.group(2)), match.group(3)
    pieces = []
    for index in range(math.ceil(size / SCREENSHOT_CHUNK_BYTES)):
        piece = twin.run_on_host(
            [screenshot_chunk_command(index)], f"twin instance check: screenshot {index}", timeout_s
        )
        if piece.problem:
            return CheckLine(
                "screenshot", FAIL, f"piece {index} of the capture did not arrive: {piece.problem}"
            )
        pieces.append(base64.b64decode(piece.stdout.strip()))
    data = b"".join(pieces)
    if len(data) != size or hashlib.sha256(data).hexdigest() != digest:
        return CheckLine(
            "screenshot",
            FAIL,
            f"the capture arrived damaged ({len(data)} of {size} bytes, or another SHA-256); it may have "
            "been replaced while it was read",
            "fetch it again: twin instance check --screenshot FILE",
        )
    target.write_bytes(data)
    return CheckLine("screenshot", OK, f"saved {target} ({size} bytes, captured at epoch {captured})")


def check_twin(
    twin: TwinInstance, *, host_timeout_s: float = 90.0, screenshot: Path | None = None
) -> CheckReport:
    """Run every check, in the order a person would look; later checks are skipped when they cannot run."""
    lines: list[CheckLine] = []
    stack = twin.stack_description()
    lines.append(check_stack(stack.get("StackStatus", "?"), stack.get("StackStatusReason", "")))
    outputs = twin.outputs()
    lines.append(check_boot_signal(twin.stack_events()))
    try:
        state = twin.describe_instance()["State"]["Name"]
    except InstanceGoneError:
        # Terminated over an hour ago: the same verdict and way back as while EC2 still lists it, in the
        # table, not an AWS error in its place.
        state = "terminated"
    advice = twin.new_host_advice() if state in TERMINATED_STATES else ""
    lines.append(check_instance(state, outputs.instance_id, advice))
    if state != "running":
        lines.append(CheckLine("dcv port", SKIP, f"the instance is {state}"))
        lines.append(CheckLine("host", SKIP, f"the instance is {state}"))
        return CheckReport(tuple(lines))
    lines.append(check_dcv_port(outputs.dcv_url))
    result = twin.run_on_host([HOST_CHECK_COMMAND], "twin instance check: host checks", host_timeout_s)
    host_lines = parse_host_check(result.stdout, outputs.deployment_version, outputs.update_association_id)
    if host_lines:
        lines += host_lines
        if screenshot is not None:
            lines.append(fetch_screenshot(twin, screenshot, timeout_s=host_timeout_s))
    elif result.problem:
        lines.append(
            CheckLine(
                "host",
                FAIL,
                result.problem,
                "SSM Run Command could not ask the host: wait until its SSM agent has registered (a few "
                "minutes after a start) and check again",
            )
        )
    else:
        shown = (result.stdout + result.stderr).strip()[:300] or "nothing"
        lines.append(
            CheckLine(
                "host",
                FAIL,
                f"{HOST_CHECK_SCRIPT} printed no check lines ({result.status}: {shown!r})",
                "the first boot has not fetched the scripts yet (still booting) or failed at 'fetch': see "
                "the bootstrap log stream",
            )
        )
    return CheckReport(tuple(lines))
