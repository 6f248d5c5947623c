"""`twin run`: the agent service (systemd unit on the twin host, or by hand on a laptop).

Exit codes: 0 after SIGTERM/SIGINT and a clean stop (recording flushed); 2 when the configuration is invalid
(the reason on stderr and as a JSON log line); 1 when the service cannot start or dies (e.g. the HTTP address
is taken, or a mirror or the supervisor stopped or is stuck). Logs are JSON lines on stdout. Under systemd it
tells the unit when it is ready, stopping, and alive (twin.service.systemd).
"""

from __future__ import annotations

import argparse
import faulthandler
import logging
import signal
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from twin.cli.output import Console, stop_on_signals
from twin.core.topics import DEFAULT_TOPIC_PREFIX
from twin.output.rerun_settings import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT
from twin.service.config import (
    DEFAULT_HTTP_HOST,
    DEFAULT_HTTP_PORT,
    LOG_LEVELS,
    AgentConfig,
    ConfigError,
    config_notes,
    load_config,
)
from twin.service.logs import setup_logging
from twin.service.systemd import Notifier

if TYPE_CHECKING:
    from twin.output.sinks import TwinSink
    from twin.service.agent import AgentService

log = logging.getLogger("twin.run")
console = Console("run")

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_CONFIG = 2


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run the agent: subscribe to telemetry, mirror each arm in MuJoCo, serve /state and /metrics",
        description=(
            "Run the twin agent. Settings come from --config (TOML, see examples/agent.toml and "
            "docs/configuration.md); the flags below override the file."
        ),
    )
    add_agent_arguments(parser)
    parser.add_argument(
        "--rerun-serve",
        action="store_true",
        default=None,
        help="stream the fleet to Rerun's web viewer on 127.0.0.1 ([rerun] serve; docs/web.md)",
    )
    add_rerun_port_arguments(parser)
    parser.set_defaults(func=run)


def port_number(text: str) -> int:
    """A TCP port from the command line (argparse's `type`, for every command's port flag): `twin web
    FILE.rrd` binds it without the config's checks, and a socket refuses one past 65535 with an
    OverflowError (a traceback)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number (0..65535)") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is outside 0..65535 (0 picks a free port)")
    return port


def add_rerun_port_arguments(parser: argparse.ArgumentParser) -> None:
    """The loopback ports of Rerun's stream and web viewer (`twin run --rerun-serve`, `twin web`)."""
    parser.add_argument(
        "--grpc-port",
        type=port_number,
        metavar="PORT",
        help=f"the stream's loopback port ([rerun] grpc_port, default {DEFAULT_GRPC_PORT}; 0 = any free)",
    )
    parser.add_argument(
        "--web-port",
        type=port_number,
        metavar="PORT",
        help=f"the web viewer's loopback port ([rerun] web_port, default {DEFAULT_WEB_PORT}; 0 = any free)",
    )


def add_agent_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags every command that runs the agent takes (`twin run`, `twin web`)."""
    parser.add_argument(
        "--config",
        metavar="FILE",
        action="append",
        help="agent config file (TOML); give it again to layer another file on top, key by key (the twin "
        "host runs with its generated config and then /etc/so101-twin/agent.local.toml)",
    )
    _add_broker_arguments(parser)
    parser.add_argument(
        "--http",
        metavar="HOST:PORT",
        help=f"HTTP listen address (default {DEFAULT_HTTP_HOST}:{DEFAULT_HTTP_PORT})",
    )
    parser.add_argument("--units", metavar="U", help="position units: ticks, degrees, range100 or auto")
    parser.add_argument(
        "--devices",
        metavar="IDS",
        help='comma-separated device ids, or "*" (the default) for every device under the prefix',
    )
    parser.add_argument(
        "--per-connection-limit",
        metavar="N",
        type=int,
        help="publishes per second one broker connection may carry (default: 100 on IoT Core, its quota; "
        "unlimited elsewhere); the agent spreads its subscriptions over connections to stay under it",
    )
    parser.add_argument(
        "--topic-prefix", metavar="PREFIX", help=f"topic prefix (default {DEFAULT_TOPIC_PREFIX})"
    )
    parser.add_argument("--mode", metavar="MODE", help="twin mode: kinematic or physics")
    parser.add_argument(
        "--workers",
        metavar="N",
        type=int,
        help="processes that mirror the fleet, each a share of the devices (default 0: one per core for the "
        "whole fleet, fewer for a small listed one; 1: one process)",
    )
    parser.add_argument("--record-dir", metavar="DIR", help="record a USD session into DIR")
    parser.add_argument(
        "--history",
        metavar="URI",
        help='keep telemetry history in Delta Lake at URI (a directory or s3://bucket/prefix; "" = off)',
    )
    parser.add_argument(
        "--rerun-save", metavar="FILE.rrd", help="write the fleet as a Rerun recording ([rerun] save)"
    )
    parser.add_argument("--log-level", metavar="LEVEL", help="DEBUG, INFO, WARNING or ERROR")
    parser.add_argument(
        "--ros2",
        action="store_true",
        default=None,
        help="publish every arm as ROS 2 sensor_msgs/JointState ([ros2] settings; needs the ros2 extra)",
    )


def _add_broker_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--broker", metavar="URL", help='"iot" (AWS IoT Core), mqtt://host:port or mqtts://host:port'
    )
    parser.add_argument(
        "--region",
        metavar="R",
        help="iot only: the AWS region of IoT Core (default: AWS_REGION, else the AWS config)",
    )


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """Flag values as dotted config keys; unset flags are None and leave the file's value."""
    return {
        "broker.url": args.broker,
        "broker.region": args.region,
        "broker.per_connection_limit": args.per_connection_limit,
        "http.listen": args.http,
        "telemetry.units": args.units,
        "telemetry.devices": args.devices,
        "telemetry.topic_prefix": args.topic_prefix,
        "twin.mode": args.mode,
        "twin.workers": args.workers,
        "twin.record_dir": args.record_dir,
        "history.uri": args.history,
        "rerun.save": args.rerun_save,
        "rerun.serve": getattr(args, "rerun_serve", None),
        "rerun.grpc_port": getattr(args, "grpc_port", None),
        "rerun.web_port": getattr(args, "web_port", None),
        "log.level": args.log_level,
        "ros2.enabled": args.ros2,
    }


def _config_error(message: str) -> int:
    console.err(f"configuration error: {message}")
    log.error("configuration error", extra={"error": message, "exit_code": EXIT_CONFIG})
    return EXIT_CONFIG


def run(args: argparse.Namespace) -> int:
    config = configure(args, overrides_from_args(args))
    if isinstance(config, int):
        return config
    if not config.rerun.serve:
        # A port flag alone reads as "serve Rerun there"; ignored, the user waits for a page that never opens.
        for flag, port in (("--grpc-port", args.grpc_port), ("--web-port", args.web_port)):
            if port is not None:
                return _config_error(
                    f"{flag} {port} is a port of the Rerun web viewer, which is off: add --rerun-serve "
                    "(or [rerun] serve = true) to serve it there, or leave the flag out"
                )
    return serve(config)


def configure(args: argparse.Namespace, overrides: dict[str, Any]) -> AgentConfig | int:
    """Logging on, then the config from --config and `overrides`; an exit code when it is invalid. The
    errors printed from here on name the command that was run (`twin web` runs the agent too)."""
    console.command = getattr(args, "command", None) or console.command
    # Log before the config is known: a config error must still come out as a JSON line.
    level = (args.log_level or "INFO").upper()
    setup_logging(level if level in LOG_LEVELS else "INFO")
    try:
        config = load_config(args.config, overrides)
    except ConfigError as exc:
        return _config_error(str(exc))
    setup_logging(config.log.level)
    log.info("configuration", extra={"config": config.to_dict(), "config_file": args.config})
    for note in config_notes(args.config, config):
        log.warning("configuration: %s", note, extra={"event": "config_note"})
    return config


def serve(config: AgentConfig, on_started: Callable[[AgentService], None] | None = None) -> int:
    """Run the agent until SIGTERM/SIGINT; `on_started(service)` runs once it is up. Returns the exit code."""
    service = _build_service(config)
    if isinstance(service, int):
        return service

    # systemd's watchdog kills a process whose main thread stopped (WatchdogSec, twin.service.systemd) with
    # SIGABRT: every thread's stack then goes to stderr, the unit's journal, saying where it was stuck.
    faulthandler.enable(all_threads=True)
    notifier = Notifier.from_env()
    received: list[str] = []
    with stop_on_signals(lambda signum: received.append(signal.Signals(signum).name)) as stop:
        try:
            service.start()
        except ConfigError as exc:  # found by a worker process as it started (a sink's extra missing)
            service.stop()
            return _config_error(str(exc))
        except (OSError, ValueError, RuntimeError) as exc:  # RuntimeError: a worker could not start
            service.stop()  # closes the sinks too
            return _cannot_start(exc)
        notifier.ready(f"mirroring {', '.join(service.topic_filters)}; console {service.http_url}")
        if on_started is not None:
            on_started(service)
        try:
            return _run_until_stopped(service, stop, notifier, received)
        finally:
            notifier.close()


def _run_until_stopped(
    service: AgentService, stop: threading.Event, notifier: Notifier, received: list[str]
) -> int:
    """Until a signal (EXIT_OK) or a mirror gone for good (EXIT_FAILURE: systemd starts the agent again),
    telling systemd's watchdog every turn that the main thread runs; then the agent's stop."""
    while not stop.wait(1.0):
        notifier.watchdog()
        if not service.running:
            said = "a twin worker or the agent's supervisor stopped or is stuck (the log above says which)"
            log.error(f"{said}; exiting to be started again", extra={"exit_code": EXIT_FAILURE})
            notifier.stopping("a mirror or the supervisor stopped or is stuck: exiting to be started again")
            service.stop()
            return EXIT_FAILURE
    signal_name = received[0] if received else None
    log.info("signal received; stopping", extra={"signal": signal_name})
    notifier.stopping(f"stopping ({signal_name or 'asked'})")
    service.stop()
    return EXIT_OK


def _build_service(config: AgentConfig) -> AgentService | int:
    """The agent with as many worker processes as the config asks for (in-process for one); an exit code
    when the configuration is invalid or a sink cannot open."""
    from twin.service.workerstart import start_fork_server, worker_count

    workers = worker_count(config)
    if workers > 1 and config.ros2.enabled:
        # The workers open the bridge after the agent has connected: a missing extra or a bad setting is
        # told before, as for an in-process mirror, not as messages that were never mirrored.
        from twin.output.ros2 import Ros2Error, preflight

        try:
            preflight(config.ros2)
        except Ros2Error as exc:
            return _config_error(str(exc))
    if workers > 1:
        # First: the workers' fork server imports the mirror on another core while this process goes on.
        start_fork_server(config.twin.model)
    # awscrt (and for an in-process mirror MuJoCo and USD) load here, not at import: `twin --help` stays fast.
    from twin.ops.sessions import history_sessions
    from twin.service.agent import AgentService

    sinks: list[TwinSink] = []
    if workers == 1:
        # Worker processes build their own sinks from the config; an in-process mirror takes these. (The
        # outputs load MuJoCo: not in an agent whose mirrors are worker processes.)
        from twin.service.outputs import configured_sinks

        try:
            sinks = configured_sinks(config)
        except ConfigError as exc:
            return _config_error(str(exc))
        except OSError as exc:
            return _cannot_start(exc)
    try:
        # The console's Sessions page reads the agent's own history (docs/console.md).
        return AgentService(config, workers=workers, sinks=sinks, sessions=history_sessions(config))
    except (ConfigError, ValueError) as exc:
        if sinks:
            from twin.service.outputs import close_sinks

            close_sinks(sinks)
        return _config_error(str(exc))


def _cannot_start(exc: BaseException) -> int:
    from twin.service.outputs import unwritable_fix

    console.err(f"cannot start: {exc}{unwritable_fix(exc)}")
    log.error("cannot start", extra={"error": str(exc), "exit_code": EXIT_FAILURE})
    return EXIT_FAILURE
