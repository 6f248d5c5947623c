"""`twin replay`: publish a device's recorded telemetry again, so the agent and the viewer mirror the past.

Exit codes: 0 replayed (or stopped by Ctrl-C / SIGTERM), 1 nothing recorded in the window, the broker is
unreachable, or the target device is live on it (the reason on stderr), 2 bad arguments.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from typing import Any

from twin.cli.commands.history import add_uri_argument
from twin.cli.output import Console, stop_on_signals

console = Console("replay")

EXIT_FAILED = 1
EXIT_USAGE = 2
PROGRESS_EVERY_S = 10.0


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "replay",
        help="publish a device's recorded telemetry to a broker again, at its recorded pace",
        description=(
            "Rebuild the edge messages of DEVICE between --from and --to from the history and publish them "
            "at their recorded pace (divided by --speed). Timestamps are shifted to start now unless "
            "--original-timestamps. Refuses a device that is publishing (use --as-device). "
            "docs/history.md explains the rules."
        ),
    )
    add_uri_argument(parser)
    parser.add_argument("--device", metavar="D", required=True, help="the recorded device")
    # "-1h" reads as an option to argparse: the span before now is written without its minus sign (or as
    # --from=-1h), as `twin history` takes it.
    parser.add_argument(
        "--from", dest="start", metavar="T", required=True, help="ISO 8601, epoch s, or 1h = 1 h ago"
    )
    parser.add_argument(
        "--to", dest="end", metavar="T", required=True, help="ISO 8601, epoch s, now, or 10m ago"
    )
    parser.add_argument("--speed", type=float, default=1.0, help="playback speed factor (default 1)")
    parser.add_argument(
        "--broker",
        metavar="URL",
        default="mqtt://127.0.0.1:1883",
        help='"iot" (AWS IoT Core), mqtt://host:port or mqtts://host:port (default mqtt://127.0.0.1:1883)',
    )
    parser.add_argument(
        "--region",
        metavar="R",
        default="",
        help="AWS region of IoT Core (broker iot; default: AWS_REGION, else the AWS config)",
    )
    parser.add_argument("--topic-prefix", metavar="PREFIX", default="dt/lerobot")
    parser.add_argument("--as-device", metavar="ID", help="publish under another device id")
    parser.add_argument(
        "--original-timestamps", action="store_true", help="send the recorded edge timestamps unchanged"
    )
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.set_defaults(func=run)


class _Progress:
    """Lines on stderr while the replay runs (it printed nothing until it ended, minutes for a long window):
    one as it begins, then one at most every PROGRESS_EVERY_S while it publishes, and one before each pause
    in the window."""

    def __init__(self, config: Any) -> None:
        self._config = config
        self._said_at: float | None = None

    def __call__(self, report: Any, pause_s: float) -> None:
        now = time.monotonic()
        config = self._config
        if self._said_at is None:
            console.err(
                f"replaying {config.device} as {config.target_device} to {config.broker.where()} at "
                f"{config.speed:g}x, from {report.first_recorded} (Ctrl-C stops)"
            )
        elif pause_s:
            console.err(
                f"replayed {report.published} messages; the recording pauses after "
                f"{report.last_recorded}: the next message is in {pause_s:.0f} s at {config.speed:g}x"
            )
        elif now - self._said_at >= PROGRESS_EVERY_S:
            console.err(f"replayed {report.published} messages, recorded up to {report.last_recorded}")
        else:
            return
        self._said_at = now


def run(args: argparse.Namespace) -> int:
    from twin.ops.history import HistoryReadError, parse_time
    from twin.ops.replay import ReplayConfig, ReplayRefusedError, replay
    from twin.transport.broker import BrokerConfig, BrokerConfigError

    try:
        config = ReplayConfig(
            uri=args.history,
            device=args.device,
            start=parse_time(args.start),
            end=parse_time(args.end),
            broker=BrokerConfig(url=args.broker, region=args.region, client_id_prefix="so101-replay-"),
            topic_prefix=args.topic_prefix,
            speed=args.speed,
            as_device=args.as_device,
            original_timestamps=args.original_timestamps,
        )
    except (ValueError, BrokerConfigError) as exc:
        console.err(str(exc))
        return EXIT_USAGE
    # The replay's warnings (a failed connect, said at once; a speed over IoT Core's quota) as its other
    # lines: they came through Python's last-resort handler, bare.
    logging.basicConfig(level=logging.WARNING, format=f"twin {console.command}: %(message)s")
    with stop_on_signals() as stop:
        try:
            report = replay(config, stop=stop, on_progress=_Progress(config))
        # BrokerConfigError here: what only building the client finds out (no region, no such AWS profile),
        # said as the fix it names, as `twin edge-sim` says it, rather than as a traceback.
        except (HistoryReadError, ReplayRefusedError, BrokerConfigError) as exc:
            console.err(str(exc))
            return EXIT_FAILED
    if args.json:
        console.out(json.dumps(report.as_dict(), indent=2))
    else:
        console.out(
            f"replayed {report.published} messages of {args.device} as {config.target_device} in "
            f"{report.elapsed_s:.1f} s (recorded {report.first_recorded} .. {report.last_recorded}); "
            f"publish failures {report.publish_failures}, late {report.late}"
            + (", stopped early" if report.stopped else "")
        )
    return 0
