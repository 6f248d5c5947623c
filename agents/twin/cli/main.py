"""The `twin` command line. Each subcommand lives in its own module under `twin.cli.commands`.

A command module defines `register(subparsers)`, which adds its parser and sets `func` to a callable taking
the parsed namespace and returning the process exit code. Modules are discovered, so adding a command never
edits this file; imports stay lazy inside each command so `twin decode` does not pay for MuJoCo or awscrt.
"""

from __future__ import annotations

import argparse
import difflib
import errno
import importlib
import importlib.metadata
import os
import pkgutil
import sys
from collections.abc import Sequence

from twin.cli import commands
from twin.cli.output import Console, missing_extra_message

# 128 + SIGPIPE: what a shell reports for a command whose reader closed the pipe.
EXIT_READER_GONE = 141


class CommandParser(argparse.ArgumentParser):
    """Every `twin` parser. An option no command knows (`twin run --brokr URL`) was reported by the top-level
    parser, with `twin`'s own usage and nothing more; each command now reports it with its usage and the
    nearest option it has."""

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        parsed, extra = super().parse_known_args(args, namespace)
        if extra:
            self.error(self._unrecognized(extra))
        return parsed, extra

    def _unrecognized(self, extra: list[str]) -> str:
        known = [o for action in self._actions for o in action.option_strings if o.startswith("--")]
        message = f"unrecognized arguments: {' '.join(extra)}"
        for arg in extra:
            if arg.startswith("--"):
                near = difflib.get_close_matches(arg.split("=", 1)[0], known, n=1)
                if near:
                    return f"{message} (did you mean {near[0]}?)"
        return message


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(
        prog="twin", description="so101-twin: a real-time digital twin of the LeRobot SO-101 arm."
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
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
        code = int(args.func(args) or 0)
        # Flushed here rather than at exit, so a reader that has gone is met below, not in a traceback.
        sys.stdout.flush()
        return code
    except BrokenPipeError:
        return _reader_gone()
    except KeyboardInterrupt:
        return 130
    except ModuleNotFoundError as exc:
        message = missing_extra_message(exc)
        if message is None:
            raise
        Console(args.command).err(message)
        return 1
    except OSError as exc:
        # A path the user gave that cannot be used (an output in a missing or read-only directory, a file
        # where a directory is wanted): a line naming it and what to do, not a traceback. Errors of no
        # path are not the user's to fix here.
        if exc.filename is None:
            raise
        Console(args.command).err(path_error_message(exc))
        return 1


def _version() -> str:
    """The installed distribution's version (pyproject.toml)."""
    try:
        return importlib.metadata.version("so101-twin")
    except importlib.metadata.PackageNotFoundError:
        return "(not installed)"


def path_error_message(exc: OSError) -> str:
    """What went wrong with the path of `exc`, and the fix."""
    path = exc.filename if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
    reason = exc.strerror or str(exc)
    if exc.errno == errno.ENOENT:
        fix = "check the path: its directory must exist"
    elif exc.errno in (errno.EEXIST, errno.ENOTDIR, errno.EISDIR):
        fix = "a file is where a directory is wanted, or the other way round; give another path"
    elif exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        fix = "give a path you may write, or change its permissions"
    elif exc.errno == errno.ENOSPC:
        fix = "free some space on that disk, or give a path on another"
    else:
        fix = "check the path"
    return f"cannot use {path}: {reason}; {fix}"


def _reader_gone() -> int:
    """The process reading our output went away (`twin history ls | head`): stop quietly with the exit code
    of a process SIGPIPE ended, as Unix tools do. What is still buffered goes to /dev/null, so the flush at
    exit does not print a second error."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return EXIT_READER_GONE


if __name__ == "__main__":
    sys.exit(main())
