"""The `twin` command line. Each subcommand lives in its own module under `twin.cli.commands`.

A command module defines `register(subparsers)`, which adds its parser and sets `func` to a callable taking
the parsed namespace and returning the process exit code. Modules are discovered, so adding a command never
edits this file; imports stay lazy inside each command so `twin decode` does not pay for MuJoCo or awscrt.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from collections.abc import Sequence

from twin.cli import commands
from twin.cli.output import Console, missing_extra_message


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="twin", description="so101-twin: a real-time digital twin of the LeRobot SO-101 arm."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except ModuleNotFoundError as exc:
        message = missing_extra_message(exc)
        if message is None:
            raise
        Console(args.command).err(message)
        return 1


if __name__ == "__main__":
    sys.exit(main())
