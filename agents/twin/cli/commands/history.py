"""`twin history ls|plot|export`: look back at the telemetry history the agent wrote (docs/history.md).

Every subcommand takes `--history URI` (a directory or s3://bucket/prefix; default out/history, the demo's
and a laptop agent's location). Times are ISO 8601 (no zone = UTC), epoch seconds, or a span before now
(`-2h`, `30m`, `1d`). `plot` and `export` never replace a file that exists unless given `--force`, and
write theirs whole or not at all. Exit codes: 0 done, 1 nothing to show or storage unreadable (the reason on
stderr), 2 bad arguments (an end before its start, an `--out` that exists), 130 interrupted (nothing
written).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from twin.cli.output import Console
from twin.core.locations import location_problem

DEFAULT_URI = "out/history"
# twin.ops.history.DEFAULT_SESSION_GAP_S, the console's [http] session_gap_s, as a plain number: `twin --help`
# must not import polars. A test holds the three equal.
SESSION_GAP_S = 30.0
EXIT_EMPTY = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
EXPORT_SUFFIXES = ["parquet", "csv"]
# What matplotlib (or a viewer) would read as another format: `plot --out x.svg` wrote PNG bytes into it.
NOT_PNG_SUFFIXES = frozenset(
    {".jpg", ".jpeg", ".svg", ".svgz", ".pdf", ".eps", ".ps", ".tif", ".tiff", ".webp", ".gif", ".bmp"}
)


def add_window_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--since", metavar="T", help="from this time on (ISO 8601, epoch s, or 2h = 2 h ago)")
    parser.add_argument("--until", metavar="T", help="before this time (ISO 8601, epoch s, or 30m ago)")


def history_uri(text: str) -> str:
    """`--history` as the agent takes `[history] uri`: another scheme (`gs://`, `http://`) was answered "no
    history table ... nothing was recorded there yet", and a file as a table not there."""
    uri = text.strip()
    problem = location_problem(uri)
    if problem:
        raise argparse.ArgumentTypeError(
            f"{text!r} {problem}; e.g. --history {DEFAULT_URI} or --history s3://<bucket>/history"
        )
    if "://" not in uri and Path(uri).is_file():
        raise argparse.ArgumentTypeError(f"{text!r} is a file; give the directory that holds the history")
    return text


def add_uri_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--history",
        metavar="URI",
        type=history_uri,
        default=DEFAULT_URI,
        help=f"history location: a directory or s3://bucket/prefix (default {DEFAULT_URI})",
    )


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "history",
        help="list, plot and export the recorded telemetry history (Delta Lake)",
        description="Read the telemetry history the agent writes with [history] uri / --history.",
    )
    sub = parser.add_subparsers(dest="history_command", metavar="SUBCOMMAND", required=True)

    ls = sub.add_parser("ls", help="devices, time ranges and sessions (continuous runs)")
    add_uri_argument(ls)
    add_window_arguments(ls)
    ls.add_argument("--device", metavar="D", help="only this device")
    ls.add_argument(
        "--gap",
        type=float,
        default=SESSION_GAP_S,
        help=f"seconds without a message that end a session (default {SESSION_GAP_S:g}, as on the console)",
    )
    ls.add_argument("--json", action="store_true", help="print one JSON object")
    ls.set_defaults(func=run_ls)

    pl_ = sub.add_parser("plot", help="joint angles, temperature, load and current of one device, as a PNG")
    add_uri_argument(pl_)
    add_window_arguments(pl_)
    pl_.add_argument("--device", metavar="D", required=True)
    pl_.add_argument(
        "--out", metavar="PNG", type=Path, default=Path("history.png"), help="default history.png"
    )
    pl_.add_argument("--force", action="store_true", help="replace --out if it exists")
    pl_.set_defaults(func=run_plot)

    ex = sub.add_parser("export", help="the selected rows as one Parquet or CSV file")
    add_uri_argument(ex)
    add_window_arguments(ex)
    ex.add_argument("--device", metavar="D", help="only this device (default: all)")
    ex.add_argument(
        "--format", choices=EXPORT_SUFFIXES, help="default: --out's suffix (.csv or .parquet), else parquet"
    )
    ex.add_argument("--out", metavar="FILE", type=Path, help="default history.parquet / history.csv")
    ex.add_argument(
        "--raw-only", action="store_true", help="stored columns only, without the decoded diagnostics"
    )
    ex.add_argument("--force", action="store_true", help="replace --out if it exists")
    ex.set_defaults(func=run_export)


def window(args: argparse.Namespace) -> tuple[Any, Any]:
    from twin.ops.history import parse_time

    since = parse_time(args.since) if getattr(args, "since", None) else None
    until = parse_time(args.until) if getattr(args, "until", None) else None
    return since, until


def _console(command: str) -> Console:
    return Console(f"history {command}")


def _fail(command: str, exc: Exception) -> int:
    from twin.ops.history import HistoryArgumentError

    _console(command).err(str(exc))
    return EXIT_USAGE if isinstance(exc, HistoryArgumentError) else EXIT_EMPTY


def _taken(command: str, out: Path, force: bool) -> int | None:
    """EXIT_USAGE, said, when `out` exists and `--force` was not given: what a person had is not replaced."""
    if force or not out.exists() or out.is_dir():
        return None
    _console(command).err(f"{out} exists; pass --force to replace it, or another --out")
    return EXIT_USAGE


def _export_format(fmt: str | None, out: Path | None) -> str | None:
    """The format `--out`'s suffix names when `--format` is not given (`--out a.csv` wrote Parquet into
    a.csv); None, said, when the two disagree, so no file holds what its name does not say."""
    named = out.suffix.lower().lstrip(".") if out is not None else ""
    if named not in EXPORT_SUFFIXES:
        return fmt or "parquet"
    if fmt is None or fmt == named:
        return named
    _console("export").err(
        f"--out {out} names a .{named} file but --format is {fmt}; drop --format, or give --out a .{fmt} name"
    )
    return None


def run_ls(args: argparse.Namespace) -> int:
    from twin.ops.history import HistoryReader, HistoryReadError, empty_hint

    console = _console("ls")
    try:
        since, until = window(args)
        reader = HistoryReader(args.history)
        devices = reader.summary(device=args.device, since=since, until=until, gap_s=args.gap)
        rejected = reader.rejected_counts(device=args.device, since=since, until=until)
        hint = empty_hint(reader, args.device) if not devices else ""
    except HistoryReadError as exc:
        return _fail("ls", exc)
    if args.json:
        out = {"uri": args.history, "devices": [d.as_dict() for d in devices], "rejected": rejected}
        console.out(json.dumps(out, indent=2))
    if not devices:
        # With --json too, on stderr: a script's exit 1 otherwise came with no reason at all.
        console.err(f"no rows in {args.history} for this selection{hint}")
        return EXIT_EMPTY
    if args.json:
        return 0
    rows = sum(d.rows for d in devices)
    total_rejected = sum(rejected.values())
    console.out(f"{args.history}: {len(devices)} device(s), {rows} messages, {total_rejected} rejected")
    for d in devices:
        first, last = d.as_dict()["first"], d.as_dict()["last"]
        console.out(f"{d.device_id}  {d.rows} messages  {first} .. {last}  units {','.join(d.units)}")
        for i, s in enumerate(d.sessions, start=1):
            info = s.as_dict()
            rate = f"{info['rate_hz']:.1f} Hz" if info["rate_hz"] else "-"
            console.out(
                f"  session {i}: {info['start']} .. {info['end']}  {info['seconds']:.0f} s  "
                f"{info['rows']} messages  {rate}"
            )
    if rejected:
        console.out("rejected: " + ", ".join(f"{k} {v}" for k, v in sorted(rejected.items())))
    return 0


def run_plot(args: argparse.Namespace) -> int:
    from twin.ops.history import HistoryReader, HistoryReadError, plot

    if args.out.suffix.lower() in NOT_PNG_SUFFIXES:
        _console("plot").err(f"--out {args.out}: plot writes PNG only; give a name ending .png")
        return EXIT_USAGE
    taken = _taken("plot", args.out, args.force)
    if taken is not None:
        return taken
    try:
        since, until = window(args)
        result = plot(HistoryReader(args.history), args.device, args.out, since=since, until=until)
    except HistoryReadError as exc:
        return _fail("plot", exc)
    _console("plot").out(
        f"wrote {result['path']}: {result['rows']} messages of {args.device}, "
        f"{result['first']} .. {result['last']}"
    )
    return 0


def run_export(args: argparse.Namespace) -> int:
    from twin.ops.history import HistoryReader, HistoryReadError, export

    fmt = _export_format(args.format, args.out)
    if fmt is None:
        return EXIT_USAGE
    out = args.out or Path(f"history.{fmt}")
    taken = _taken("export", out, args.force)
    if taken is not None:
        return taken
    try:
        since, until = window(args)
        rows = export(
            HistoryReader(args.history),
            out,
            fmt,
            device=args.device,
            since=since,
            until=until,
            decoded=not args.raw_only,
        )
    except HistoryReadError as exc:
        return _fail("export", exc)
    except KeyboardInterrupt:
        # The export writes beside `out` and renames once whole: stopped, it leaves `out` as it was.
        _console("export").err(f"interrupted: nothing written ({out} is as it was)")
        return EXIT_INTERRUPTED
    _console("export").out(f"wrote {out}: {rows} rows ({fmt})")
    return 0
