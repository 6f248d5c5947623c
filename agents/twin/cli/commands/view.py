"""`twin view`: the MuJoCo viewer following the agent's live state (what the DCV desktop shows)."""

from __future__ import annotations

import argparse
import logging
import signal
from typing import Any

from twin.cli.output import Console
from twin.service.config import DEFAULT_AGENT_URL

console = Console("view")


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "view",
        help="MuJoCo viewer that mirrors the agent's live twin (needs a display)",
        description=(
            "Opens the MuJoCo viewer and follows the twin agent's live state (SSE /stream, or polling "
            "/state). The pose is predicted at display time from the 10 Hz telemetry (docs/viewer.md). "
            "Overlay: device, status, age, rate, latency. Page Up / Page Down switch device when the agent "
            "mirrors several. "
            "Closing the window or SIGTERM ends it; an unreachable agent is retried forever."
        ),
    )
    parser.add_argument(
        "--agent",
        default=DEFAULT_AGENT_URL,
        metavar="URL",
        help="the agent's HTTP address (default %(default)s)",
    )
    parser.add_argument("--device", metavar="ID", help="device to show first (default: the first reported)")
    parser.add_argument("--model", metavar="MJCF", help="MJCF of the arm (default: the bundled SO-101 scene)")
    parser.add_argument(
        "--smoothing",
        choices=("predict", "hold"),
        default="predict",
        help="predict the pose at display time (default) or hold the last sample",
    )
    parser.add_argument("--fps", type=float, default=60.0, help="display rate (default %(default)s)")
    parser.add_argument(
        "--camera", metavar="NAME", help="use this fixed model camera instead of the free one"
    )
    parser.add_argument("--ui", action="store_true", help="show MuJoCo's side panels")
    parser.add_argument("--log-level", default="WARNING", help="logging level (default %(default)s)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    from twin.robot.model import ModelError
    from twin.viewer.config import ViewerConfig
    from twin.viewer.window import TwinViewer, ViewerError

    try:
        config = ViewerConfig(
            agent_url=args.agent,
            device=args.device,
            model_path=args.model,
            fps=args.fps,
            smoothing=args.smoothing,
            show_ui=args.ui,
            camera=args.camera,
        )
    except ValueError as exc:
        console.err(str(exc))
        return 2
    viewer = TwinViewer(config)

    def _on_signal(signum: int, _frame: object) -> None:
        viewer.stop()

    # systemd / the desktop session stop the viewer with SIGTERM: close the window cleanly.
    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    try:
        return viewer.run()
    except (ViewerError, ModelError) as exc:
        console.err(str(exc))
        return 1
