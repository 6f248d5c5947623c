"""What every `twin` command shares: how it writes results and errors, how it loads development tooling, and
how a long-running command stops on SIGTERM or Ctrl-C.

Results go to stdout (one line at a time, flushed, so a pipe or a CI log sees them as they happen); errors go
to stderr prefixed with the command (`twin demo: ...`), so a user who ran several commands knows which one
complained.
"""

from __future__ import annotations

import importlib
import os
import shlex
import shutil
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType


class Console:
    """stdout/stderr of one command."""

    def __init__(self, command: str) -> None:
        self.command = command

    def out(self, text: str = "") -> None:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()

    def err(self, text: str) -> None:
        sys.stderr.write(f"twin {self.command}: {text}\n")


# The optional parts of the distribution and the libraries each brings (pyproject.toml's extras): a command
# that needs one of them and finds it absent names the extra to install instead of a bare import error.
EXTRA_OF_LIBRARY = {
    "deltalake": "history",
    "polars": "history",
    "matplotlib": "history",
    "cyclonedds": "ros2",
    "psutil": "bench",
}


def missing_extra_message(exc: ModuleNotFoundError) -> str | None:
    """What to tell a user whose command needs an extra that is not installed, or None for any other import
    error."""
    library = (exc.name or "").split(".", 1)[0]
    extra = EXTRA_OF_LIBRARY.get(library)
    if extra is None:
        return None
    return (
        f"{library} is not installed: this needs the {extra} extra. Install it with "
        f"pip install 'so101-twin[{extra}]' (a clone: make setup installs every extra)."
    )


class DevToolMissing(RuntimeError):  # noqa: N818 - reads as what happened: a tool is missing
    """A development-only module (benchmark, local rig, demo) is not part of this install."""


def import_dev_tool(module: str, command: str) -> ModuleType:
    """Import `module`, or raise DevToolMissing saying why it is absent and where the command runs.

    The agent asset deployed to the instance holds only what the instance runs (stacks/twin_host.py,
    AGENT_ASSET_PATTERNS), so the benchmark, the local rig and the demo are not there. A missing dependency
    *inside* the tool is a different error and is re-raised as it is.
    """
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        missing = exc.name or ""
        if not (module == missing or module.startswith(missing + ".")) or not missing.startswith("twin."):
            raise
        raise DevToolMissing(
            f"`twin {command}` is development tooling and is not part of this install ({missing} is absent: "
            "the agent package deployed to the instance carries only what the instance runs). Run it from a "
            "clone of the repository after `make setup`."
        ) from None


@contextmanager
def stop_on_signals(on_signal: Callable[[int], None] | None = None) -> Iterator[threading.Event]:
    """An Event that SIGTERM or SIGINT sets while the block runs; the previous handlers are back after it.

    `on_signal(signum)` runs first, inside the handler, which interrupts the main thread between bytecodes
    (it may hold locks): keep it to recording the signal."""
    stop = threading.Event()

    def handler(signum: int, _frame: object) -> None:
        if on_signal is not None:
            on_signal(signum)
        stop.set()

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


def program(name: str) -> str | None:
    """The executable `name` this environment installed (beside its interpreter, else on PATH), as a
    path that runs as printed from the current directory; None when there is none.

    Console scripts land in the venv's bin/, which is not on PATH unless the venv is activated, and `make
    demo` does not activate it: a bare `twin` or `rerun` in what a command prints would not be found."""
    beside = Path(sys.executable).with_name(name)
    found = str(beside) if beside.is_file() and os.access(beside, os.X_OK) else shutil.which(name)
    return None if found is None else runnable(Path(found))


def runnable(path: Path) -> str:
    """`path` relative to the current directory when it is under it, else absolute, quoted for a shell."""
    absolute = Path(os.path.abspath(path))  # not resolved: the venv's python is a link out of the venv
    try:
        shown = str(absolute.relative_to(Path.cwd()))
    except ValueError:
        return shlex.quote(str(absolute))
    # A name without a directory would be looked up on PATH instead of here.
    return shlex.quote(shown if os.sep in shown else f".{os.sep}{shown}")
