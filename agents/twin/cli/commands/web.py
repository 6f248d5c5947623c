"""`twin web`: the fleet in a browser, through Rerun's web viewer on loopback ports (docs/web.md).

Without a file it runs the agent (the settings and flags of `twin run`) with the Rerun stream and the web
viewer served on 127.0.0.1, and prints the page to open. With a `.rrd` file it serves that recording instead.
Either way nothing listens beyond loopback: on the twin host, reach the ports through SSM port forwarding or
open the page in the DCV desktop's browser.

Exit codes as `twin run`: 0 after SIGTERM/SIGINT, 1 when it cannot start, 2 for a bad configuration.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from twin.cli.commands import run as run_command
from twin.cli.output import Console, program, stop_on_signals
from twin.output.rerun_settings import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT

console = Console("web")
# How every Rerun recording begins (its FourCC; the version digit after it is the rerun binary's to judge).
RRD_MAGIC = b"RRF"

# Said wherever `twin web` runs, which it cannot tell: on a laptop the URL above is already the one to open.
SSM_HINT = (
    "when this runs on the twin host, a laptop reaches it by forwarding both ports over SSM "
    "(docs/web.md), e.g. "
    "for p in {web} {grpc}; do aws ssm start-session --target <InstanceId> --document-name "
    'AWS-StartPortForwardingSession --parameters "{{\\"portNumber\\":[\\"$p\\"],\\"localPortNumber\\":'
    '[\\"$p\\"]}}" & done; wait'
)


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "web",
        help="the fleet in a browser: run the agent with Rerun's web viewer on 127.0.0.1, or serve a .rrd",
        description=(
            "Runs the agent (settings and flags as `twin run`) streaming to Rerun, and serves Rerun's web "
            "viewer and the stream on loopback ports; or, given a .rrd file, serves that recording. "
            "Open the printed URL here, in the DCV desktop's browser, or on a laptop through SSM port "
            "forwarding (docs/web.md)."
        ),
    )
    parser.add_argument(
        "rrd", nargs="?", metavar="FILE.rrd", help="serve this recording instead of the agent"
    )
    run_command.add_agent_arguments(parser)
    run_command.add_rerun_port_arguments(parser)
    parser.set_defaults(func=web)


def web(args: argparse.Namespace) -> int:
    if args.rrd:
        return serve_file(Path(args.rrd), args)
    overrides = run_command.overrides_from_args(args)
    overrides["rerun.serve"] = True
    config = run_command.configure(args, overrides)
    if isinstance(config, int):
        return config
    return run_command.serve(config, on_started=_announce)


def _announce(service: Any) -> None:
    sink = next((s for s in service.sinks if getattr(s, "viewer_url", None)), None)
    if sink is None:  # cannot happen: rerun.serve is forced on; say so rather than print nothing
        console.err("the Rerun sink is not serving; see the log above")
        return
    console.out(f"open {sink.viewer_url}")
    # The rerun beside this interpreter: the venv's bin/ is not on PATH unless it is activated.
    console.out(f"  native viewer: {program('rerun') or 'rerun'} --connect {sink.grpc_url}")
    console.out("  " + _ssm_hint(sink.viewer_url, sink.grpc_url))
    console.out("  stop with Ctrl-C")


def _ssm_hint(page_url: str, grpc_url: str) -> str:
    return SSM_HINT.format(web=urlsplit(page_url).port, grpc=urlsplit(grpc_url).port)


def serve_file(path: Path, args: argparse.Namespace) -> int:
    """Serve a recording with the `rerun` binary from the wheel (it binds to loopback) until interrupted."""
    from twin.output.rerun_sink import (
        LOOPBACK,
        RerunSinkError,
        bindable_port,
        start_web_viewer,
        stop_process,
        viewer_url,
    )

    if not path.exists():
        console.err(
            f"{path} does not exist; give a recording (e.g. out/demo/twin.rrd, which `make demo` writes)"
        )
        return run_command.EXIT_CONFIG
    if path.suffix != ".rrd" or not path.is_file():
        console.err(f"{path} is not a .rrd file; give a recording (e.g. out/demo/twin.rrd)")
        return run_command.EXIT_CONFIG
    grpc_port = DEFAULT_GRPC_PORT if args.grpc_port is None else args.grpc_port
    web_port = DEFAULT_WEB_PORT if args.web_port is None else args.web_port
    if grpc_port != 0 and grpc_port == web_port:
        # The agent's settings refuse this too; here the rerun binary would, in its own coloured log lines.
        console.err(f"--grpc-port and --web-port are both {grpc_port}; give them different ports")
        return run_command.EXIT_CONFIG
    try:
        with path.open("rb") as file:
            head = file.read(len(RRD_MAGIC))
    except OSError as exc:
        console.err(f"{path} cannot be read ({exc.strerror}); give a recording this user may read")
        return run_command.EXIT_CONFIG
    if head != RRD_MAGIC:
        # The rerun binary says so only in its own log, which nobody reads: the page would open empty.
        said = "is empty" if not head else f"does not begin as a Rerun recording does ({head!r})"
        console.err(f"{path} {said}; give a .rrd that Rerun wrote (e.g. out/demo/twin.rrd)")
        return run_command.EXIT_CONFIG
    with stop_on_signals() as stop:
        try:
            grpc = bindable_port(grpc_port, "--grpc-port")
            page = bindable_port(web_port, "--web-port")
            proc = start_web_viewer(str(path.resolve()), page, grpc_port=grpc)
        except RerunSinkError as exc:
            console.err(str(exc))
            return run_command.EXIT_FAILURE
        try:
            grpc_url = f"rerun+http://{LOOPBACK}:{grpc}/proxy"
            url = viewer_url(page, grpc_url)
            console.out(f"open {url}")
            console.out(f"  serving {path}")
            console.out("  " + _ssm_hint(url, grpc_url))
            console.out("  stop with Ctrl-C")
            while not stop.wait(0.5):
                if proc.poll() is not None:
                    console.err(f"the Rerun viewer exited (code {proc.returncode})")
                    return run_command.EXIT_FAILURE
            return run_command.EXIT_OK
        finally:
            stop_process(proc)
