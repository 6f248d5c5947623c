"""`twin demo`: broker + edge simulator + agent for a set time, live status line, files left in --out."""

from __future__ import annotations

import argparse
import logging
import os
import shlex
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

from twin.cli.output import Console, DevToolMissing, import_dev_tool, program, runnable, stop_on_signals

console = Console("demo")


EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
# Without a terminal (CI logs, make output captured) a status line every few seconds is enough.
PLAIN_STATUS_EVERY_S = 2.0


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="broker, edge simulator and agent locally: a servo overheats; leave pictures, USD, rrd, stats",
        description=(
            "Starts a private mosquitto on a free loopback port, the edge simulator and the twin agent. The "
            "first arm lifts a payload too heavy for it and its shoulder servo overheats until the agent "
            "raises the alarm; the operator console is then photographed in headless Chromium. Shows a "
            "live status line, then writes twin.png, twin.gif, console-fleet.png, console-arm.png, the USD "
            "session, the Rerun recording twin.rrd, the history and stats.json to --out (docs/viewer.md, "
            "docs/web.md). Stops everything it started, also on Ctrl-C."
        ),
    )
    parser.add_argument("--seconds", type=float, default=30.0, help="run time (default %(default)s)")
    parser.add_argument(
        "--out", default="out/demo", metavar="DIR", help="output directory (default %(default)s)"
    )
    parser.add_argument(
        "--variant",
        choices=("ticks", "degrees"),
        default="ticks",
        help="edge payload variant (default ticks)",
    )
    parser.add_argument("--devices", type=int, default=6, metavar="N", help="simulated arms (default 6)")
    parser.add_argument(
        "--rate", type=float, default=10.0, metavar="HZ", help="messages/s per arm (default 10)"
    )
    parser.add_argument(
        "--rerun-serve",
        action="store_true",
        help="also serve the Rerun web viewer on 127.0.0.1 while the demo runs (docs/web.md)",
    )
    parser.add_argument("--no-rerun", action="store_true", help="write no twin.rrd (and serve nothing)")
    parser.add_argument(
        "--servos",
        choices=("physical", "mock"),
        default="physical",
        help=(
            "physical (default): servo readings from the motion, and the overheating servo; mock: the edge "
            "mock mode's random readings, no story"
        ),
    )
    parser.add_argument("--no-console", action="store_true", help="take no pictures of the operator console")
    parser.add_argument(
        "--chromium",
        default="/usr/bin/chromium",
        metavar="PATH",
        help="the browser the console pictures are taken with (default %(default)s, Debian's chromium)",
    )
    parser.add_argument("--log-level", default="WARNING", help="logging level (default %(default)s)")
    parser.set_defaults(func=run)


def _format(status: Any) -> str:
    def ms(value: float | None) -> str:
        return "-" if value is None else f"{value * 1000:.1f}"

    devices = " ".join(f"{d}:{s}" for d, s in sorted(status.statuses.items()))
    return (
        f"{status.elapsed_s:5.1f}s  sent {status.sent}  received {status.received}  "
        f"rate {status.rate_hz:.1f}/s  rejected {status.rejected}  "
        f"latency p50 {ms(status.latency_p50_s)} ms p99 {ms(status.latency_p99_s)} ms  {devices}"
    )


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    # Rendering the PNG/GIF needs no window: EGL works headless (the Makefile exports the same default).
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    try:
        demo = import_dev_tool("twin.rig.demo", "demo")
    except DevToolMissing as exc:
        console.err(str(exc))
        return EXIT_FAILED
    try:
        config = _demo_config(demo, args)
    except ValueError as exc:
        console.err(str(exc))
        return EXIT_USAGE
    tty = sys.stdout.isatty()
    console.out(
        f"twin demo: {config.devices} simulated arm(s), {config.variant} payloads at {config.rate_hz:g} Hz "
        f"for {config.seconds:g} s -> {config.out_dir}"
    )
    try:
        # A signal sets `stop`, not KeyboardInterrupt: the demo must get to its cleanup and still write what
        # it has.
        with stop_on_signals() as stop:
            stats = demo.run_demo(
                config,
                on_status=_status_printer(tty),
                stop=stop,
                on_viewer=lambda url: console.out(f"twin demo: Rerun web viewer at {url}"),
                on_note=_note_printer(tty),
            )
    except demo.DemoError as exc:
        if tty:
            sys.stdout.write("\n")
        console.err(f"failed: {exc}")
        return EXIT_FAILED
    if tty:
        sys.stdout.write("\n")
    _summary(stats, config.out_dir)
    if stats["interrupted"]:
        console.err("interrupted: the files above cover the run up to the interruption")
        return EXIT_INTERRUPTED
    return EXIT_OK


def _demo_config(demo: ModuleType, args: argparse.Namespace) -> Any:
    """The demo's DemoConfig from the flags (it raises ValueError naming a bad value)."""
    return demo.DemoConfig(
        seconds=args.seconds,
        out_dir=Path(args.out),
        variant=args.variant,
        devices=args.devices,
        rate_hz=args.rate,
        rerun=not args.no_rerun,
        rerun_serve=args.rerun_serve and not args.no_rerun,
        servos=args.servos,
        console=not args.no_console,
        chromium=Path(args.chromium),
    )


def _status_printer(tty: bool) -> Any:
    """The status callback: one line rewritten in place on a terminal, a line every few seconds otherwise."""
    last_plain = [0.0]

    def on_status(status: Any) -> None:
        line = _format(status)
        if tty:
            sys.stdout.write("\r\x1b[2K" + line)
            sys.stdout.flush()
        elif time.monotonic() - last_plain[0] >= PLAIN_STATUS_EVERY_S:
            last_plain[0] = time.monotonic()
            console.out(line)

    return on_status


def _note_printer(tty: bool) -> Any:
    """A story line on a line of its own, above the status line on a terminal."""

    def on_note(line: str) -> None:
        if tty:
            sys.stdout.write("\r\x1b[2K")
        console.out(f"twin demo: {line}")

    return on_note


def _summary(stats: dict[str, Any], out_dir: Path) -> None:
    msgs = stats["messages"]
    e2e = stats["latency_s"]["end_to_end"]
    console.out(
        f"done in {stats['duration_s']:.1f} s: sent {msgs['sent']}, received {msgs['received']}, "
        f"rejected {msgs['rejected']}, end-to-end p50 {_ms(e2e['p50'])} / p99 {_ms(e2e['p99'])}"
    )
    for kind, name in stats["files"].items():
        console.out(f"  {kind:13s} {out_dir / name}")
    console.out(f"  json {out_dir / 'stats.json'}")
    history = stats.get("history")
    if history:
        table = out_dir / history["uri"]
        console.out(f"  hist {table}  (`{_twin_program()} history ls --history {shlex.quote(str(table))}`)")
        if history.get("plot"):
            console.out(f"  plot {out_dir / history['plot']}")
    story = stats.get("story")
    if story:
        raised = ", ".join(f"{a['kind']} after {a['raised_after_s']:.0f} s" for a in story["alarms"])
        peak = story["peak_temperature_c"]
        console.out(
            f"  story: {story['device']} {story['joint']} peaked at "
            f"{'-' if peak is None else f'{peak:.0f} C'}; its alarms raised: {raised or 'none'}"
        )
    if stats["console"].get("skipped"):
        console.out(f"  console pictures skipped: {stats['console']['skipped']}")
    if "rrd" in stats["files"]:
        rrd = shlex.quote(str(out_dir / stats["files"]["rrd"]))
        # Rerun's native viewer exits at once without a display, which is how make demo often runs; twin web
        # serves the recording to a browser instead.
        native = program("rerun") if _has_display() else None
        viewer = native or f"{_twin_program()} web"
        console.out(f"  open the Rerun recording: `{viewer} {rrd}`  (docs/web.md)")


def _has_display() -> bool:
    env = os.environ
    return sys.platform != "linux" or bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))


def _twin_program() -> str:
    """How to run `twin` as printed: this environment's console script, or its interpreter with -m."""
    return program("twin") or f"{runnable(Path(sys.executable))} -m twin.cli"


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value * 1000:.1f} ms"
