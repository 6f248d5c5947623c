"""`twin instance start|stop|status|url|password|check|console|settings`: run and check the cloud twin host
deployed by the CDK stack, print its DCV password, open its operator console here, and print the settings it
runs with.

The stack defaults to $SO101_TWIN_STACK, else the stackName of the checkout's twin.settings.toml (in the
current directory or above it), else So101TwinStack; the region to --region, else AWS_REGION, else the AWS
config.

Exit codes:
  0  done
  1  any other AWS error (the message carries AWS's code)
  2  bad command line (argparse)
  3  no AWS credentials or region, or credentials AWS rejects, or (`console`) no Session Manager plugin
  4  stack not found in that account and region
  5  stack outputs missing (InstanceId or DcvUrl; for `settings`, the Settings output; for `password`,
     DcvPasswordSecret)
  6  InsufficientInstanceCapacity on start (no G6e capacity in the stack's Availability Zone)
  7  the instance did not reach the wanted state within --timeout, or `start` got no verdict of its checks
  8  `check`: at least one check failed (the table says which and how to fix it); `start`: the host's checks
     after the start failed

`console` forwards the agent's port 8080 on the host to this machine's 127.0.0.1 through Session Manager
(nothing opens in the security group; the Session Manager plugin must be installed) and opens the console in
the browser, until Ctrl-C.

`start` waits for the checks the host runs after every start (X, then DCV's console session, the agent, the
viewer, a capture of the console) and prints their verdict; a host already running is left alone (nothing
starts, so no checks run: `check` checks it). The agent's health does not change the exit code
of `status` (a freshly started host reports "unknown" until its SSM agent registers); scripts that need it
read its `agent ...` line.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from twin.cli.output import Console

if TYPE_CHECKING:
    from twin.ops.instance import AgentHealth, StartVerdict, TwinInstance

console = Console("instance")


EXIT_OK = 0
EXIT_AWS = 1
EXIT_SETUP = 3
EXIT_NO_STACK = 4
EXIT_NO_OUTPUTS = 5
EXIT_CAPACITY = 6
EXIT_WAIT = 7
EXIT_CHECK_FAILED = 8

EPILOG = """exit codes:
  0 done; 1 other AWS error; 2 bad command line; 3 no AWS credentials or region (console: or no plugin);
  4 stack not found; 5 stack outputs missing; 6 InsufficientInstanceCapacity on start;
  7 instance did not reach the state (or start: no verdict of its checks) within --timeout;
  8 a check failed (check, or start: the host's checks after the start)
stack: --stack, else $SO101_TWIN_STACK, else stackName in the checkout's twin.settings.toml (here or
  above), else So101TwinStack"""

DEFAULT_TIMEOUT_S = 900.0
HEALTH_TIMEOUT_S = 60.0
HOST_CHECK_TIMEOUT_S = 90.0
# The Session Manager session usually answers within seconds; the first one after a start can take longer.
CONSOLE_READY_TIMEOUT_S = 60.0


# Each action and its help (its description too).
ACTIONS: tuple[tuple[str, str], ...] = (
    (
        "start",
        "start the instance, wait until it runs and the host's own checks have passed (X, the DCV "
        "console session, the agent, the viewer, the screen), print the DCV URL and their verdict",
    ),
    ("stop", "stop the instance (disk and Elastic IP are kept) and wait until stopped"),
    ("status", "print instance state, type, DCV URL and agent health"),
    ("url", "print only the DCV URL"),
    (
        "password",
        "print only the DCV password of the desktop user 'ubuntu' (the current version of the stack's "
        "DcvPasswordSecret, in Secrets Manager)",
    ),
    (
        "console",
        "open the operator console here: forward the agent's port on the host to 127.0.0.1 through "
        "Session Manager (needs the Session Manager plugin) and open it in the browser, until Ctrl-C",
    ),
    (
        "settings",
        "print the settings the deployed stack runs with, as a twin.settings.toml (save it to keep them: "
        "twin instance settings > twin.settings.toml)",
    ),
    (
        "check",
        "say whether the twin works: stack and boot signal, instance, DCV port over TLS from here, "
        "and on the host X on the GPU, the DCV session, the agent, telemetry, the viewer, a capture of "
        "the console, the version",
    ),
)


def register(subparsers: argparse._SubParsersAction) -> None:
    common = _common_arguments()
    parser = subparsers.add_parser(
        "instance",
        help="start, stop or inspect the cloud twin host (EC2 + DCV)",
        description=__doc__.split("\n\n")[0],
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    for name, help_text in ACTIONS:
        action = actions.add_parser(
            name,
            parents=[common],
            help=help_text,
            description=help_text,
            epilog=EPILOG,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        action.set_defaults(func=run, action=name, screenshot=None, port=None, no_browser=False)
        if name == "console":
            _add_console_arguments(action)
        if name == "check":
            action.add_argument(
                "--screenshot",
                metavar="FILE",
                type=Path,
                help="also bring back the capture of the console the host just checked (PNG) into FILE",
            )


def _common_arguments() -> argparse.ArgumentParser:
    """The flags every action takes: which stack, which region, and how long to wait."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--stack",
        default=None,
        help="CloudFormation stack name (default: $SO101_TWIN_STACK, else stackName in the checkout's "
        "twin.settings.toml, here or above, else So101TwinStack)",
    )
    common.add_argument(
        "--region", default=None, help="AWS region (default: AWS_REGION, else the AWS config)"
    )
    common.add_argument("--no-wait", action="store_true", help="return after the request, without waiting")
    common.add_argument(
        "--timeout",
        type=float,
        default=DEFAULT_TIMEOUT_S,
        metavar="S",
        help=f"seconds to wait for the instance state (default {DEFAULT_TIMEOUT_S:.0f})",
    )
    return common


def _add_console_arguments(action: argparse.ArgumentParser) -> None:
    from twin.cli.commands.run import port_number
    from twin.service.config import DEFAULT_HTTP_PORT

    action.add_argument(
        "--port",
        type=port_number,
        default=DEFAULT_HTTP_PORT,
        metavar="PORT",
        help="the local port (default %(default)s, the agent's own; 0 = any free port)",
    )
    action.add_argument("--no-browser", action="store_true", help="print the URL, open no browser")


def _console(twin: TwinInstance, args: argparse.Namespace) -> int:
    """The forward until Ctrl-C (or the plugin ends): print the URL, open the browser."""
    import webbrowser

    from twin.cli.output import stop_on_signals
    from twin.service.config import DEFAULT_HTTP_PORT

    with stop_on_signals() as stop:
        forward = twin.forward_port(DEFAULT_HTTP_PORT, args.port)
        try:
            if not forward.wait_ready(CONSOLE_READY_TIMEOUT_S):
                console.err(
                    f"the Session Manager session to {forward.instance_id} did not open port "
                    f"{forward.local_port} here within {CONSOLE_READY_TIMEOUT_S:.0f} s; the plugin said:\n"
                    f"{forward.output or '(nothing)'}\n"
                    "Is the host's SSM agent online? (`twin instance status`)"
                )
                return EXIT_AWS
            console.out(f"console: {forward.url}")
            console.out(
                f"  port {forward.remote_port} of {forward.instance_id}, through Session Manager "
                f"(session {forward.session_id}); Ctrl-C ends it"
            )
            if not args.no_browser and not webbrowser.open(forward.url):
                console.out("  (no browser found here: open the URL yourself)")
            while not stop.wait(0.5):
                if not forward.alive:
                    console.err(f"the Session Manager plugin ended:\n{forward.output or '(no output)'}")
                    return EXIT_AWS
        finally:
            forward.close()
    console.out("console: session ended")
    return EXIT_OK


def _health_line(health: AgentHealth | None) -> str:
    return "agent health: not checked" if health is None else health.describe()


def _version_line(host_version: str | None, expected: str | None) -> str:
    """What the host runs next to what the stack asks for."""
    if host_version is None:
        return f"version: unknown on the host (the stack's: {expected or 'not published'})"
    if host_version == "none":
        return f"version: none verified yet on the host (first boot not finished?); the stack's: {expected}"
    if expected is None or host_version == expected:
        return f"version: {host_version}" + (" (the stack's current deployment)" if expected else "")
    return (
        f"version: the host runs {host_version}, the stack asks for {expected}: the in-place update is "
        "pending or failed (`twin instance check` says more)"
    )


def _print_verdict(verdict: StartVerdict) -> None:
    from twin.ops.instance_check import FAIL, parse_host_check

    console.out(verdict.describe())
    for line in parse_host_check("\n".join(verdict.lines), None, None):
        if line.status == FAIL:
            console.out(f"  {line.name}: {line.detail}")
            if line.fix:
                console.out(f"    fix: {line.fix}")


def run(args: argparse.Namespace, twin: TwinInstance | None = None) -> int:
    from twin.ops import instance as lib

    if args.timeout <= 0:
        console.err(f"--timeout must be positive, got {args.timeout}")
        return 2
    codes: dict[type[lib.TwinInstanceError], int] = {
        lib.AwsSetupError: EXIT_SETUP,
        lib.StackNotFoundError: EXIT_NO_STACK,
        lib.StackOutputsError: EXIT_NO_OUTPUTS,
        lib.InsufficientCapacityError: EXIT_CAPACITY,
        lib.WaitError: EXIT_WAIT,
        lib.AwsCallError: EXIT_AWS,
    }
    twin = twin or lib.TwinInstance(args.stack, region=args.region)
    try:
        if args.action == "url":
            console.out(twin.url())
            return EXIT_OK
        if args.action == "password":
            console.out(twin.dcv_password())
            return EXIT_OK
        if args.action == "console":
            return _console(twin, args)
        if args.action == "settings":
            return _settings(twin)
        if args.action == "check":
            return _check(twin, args)
        if args.action == "stop":
            return _stop(twin, args)
        if args.action == "start":
            return _start(twin, args)
        return _status(twin)
    except lib.TwinInstanceError as exc:
        Console(f"instance {args.action}").err(str(exc))
        # By class, subclasses included: a missing Session Manager plugin is a setup error too.
        return next((code for cls, code in codes.items() if isinstance(exc, cls)), EXIT_AWS)


def _settings(twin: TwinInstance) -> int:
    """The settings the stack was deployed with, as a twin.settings.toml."""
    deployed = twin.settings()
    header = (
        f"The settings of stack {twin.stack_name} in {twin.region}, as deployed (its Settings "
        "output).\nSave as twin.settings.toml in the repository to keep them; commented lines are "
        "defaults."
    )
    console.out(deployed.to_toml(header=header).rstrip("\n"))
    return EXIT_OK


def _check(twin: TwinInstance, args: argparse.Namespace) -> int:
    """Every check of the deployed twin, as a table; fails when one does."""
    from twin.ops.instance_check import check_twin

    report = check_twin(twin, host_timeout_s=HOST_CHECK_TIMEOUT_S, screenshot=args.screenshot)
    for line in report.render():
        console.out(line)
    return EXIT_OK if report.ok else EXIT_CHECK_FAILED


def _stop(twin: TwinInstance, args: argparse.Namespace) -> int:
    outputs = twin.outputs()
    wait = not args.no_wait
    state = twin.stop(wait=wait, timeout_s=args.timeout)
    console.out(f"instance {outputs.instance_id}: {state}")
    if not wait:
        console.out("not waiting; follow it with `twin instance status`")
    return EXIT_OK


def _start(twin: TwinInstance, args: argparse.Namespace) -> int:
    """Start the host and, unless --no-wait, wait for the verdict of the checks it runs after every start."""
    from twin.ops.instance import PASS, UNKNOWN

    outputs = twin.outputs()
    if twin.state() == "running":
        # Nothing starts, so no start checks run: their verdict of this boot may never come (after the
        # first boot, which verifies itself, they have not run at all), and waiting would end in "no verdict".
        console.out(f"instance {outputs.instance_id}: already running (not started now, so no start checks)")
        console.out(f"DCV URL: {outputs.dcv_url}")
        console.out("whether the twin works: `twin instance check`")
        return EXIT_OK
    wait = not args.no_wait
    state = twin.start(wait=wait, timeout_s=args.timeout)
    console.out(f"instance {outputs.instance_id}: {state}")
    console.out(f"DCV URL: {outputs.dcv_url}")
    if not wait:
        console.out("not waiting; follow it with `twin instance status`")
        return EXIT_OK
    console.out(f"waiting up to {args.timeout:.0f} s for the host's checks after the start")
    verdict = twin.start_verdict(args.timeout)
    _print_verdict(verdict)
    if verdict.state == UNKNOWN:
        return EXIT_WAIT
    return EXIT_OK if verdict.state == PASS else EXIT_CHECK_FAILED


def _status(twin: TwinInstance) -> int:
    """The instance's state, its DCV URL, the agent's health and the version it runs (exit 0 whatever the
    health: module doc)."""
    from twin.ops.instance import TERMINATED_STATES

    status = twin.status(check_health=True, health_timeout_s=HEALTH_TIMEOUT_S)
    zone = f" in {status.availability_zone}" if status.availability_zone else ""
    console.out(f"instance {status.instance_id}: {status.state} ({status.instance_type}{zone})")
    console.out(f"DCV URL: {status.dcv_url}")
    console.out(_health_line(status.health))
    console.out(_version_line(status.host_version, status.expected_version))
    if status.state in TERMINATED_STATES:
        console.out(twin.new_host_advice())  # no start brings it back
    return EXIT_OK
