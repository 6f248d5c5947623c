"""The `twin` entry point itself: what every command shares."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from twin.cli.main import EXIT_READER_GONE, main

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.slow
def test_a_reader_that_has_gone_ends_the_command_quietly() -> None:
    # `twin history ls | head`: the reader closes the pipe before the command is done writing. The read end
    # is closed before the command starts, so its first write always meets a broken pipe.
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        done = subprocess.run(
            [sys.executable, "-m", "twin.cli", "config", "reference"],
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            timeout=60,
            check=False,
        )
    finally:
        os.close(write_end)
    assert done.returncode == EXIT_READER_GONE == 141
    assert done.stderr == ""


@pytest.mark.parametrize(
    ("args", "prefix", "says"),
    [
        # An output where no directory can be made: the calibration store (its own error, which also makes
        # a failed restore save the kept calibration), the picture of a render.
        (
            ["calibration", "push", "arm-002", "{example}", "--store", "/proc/nope"],
            "cannot write to /proc/nope/arm-002.json: ",
            "No such file or directory",
        ),
        # A file where the output directory is wanted.
        (
            ["demo", "--seconds", "3", "--out", "{file}"],
            "cannot use ",
            "a file is where a directory is wanted",
        ),
    ],
)
def test_a_path_that_cannot_be_used_is_one_line_naming_it_not_a_traceback(
    args: list[str], prefix: str, says: str, tmp_path: Path
) -> None:
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine\n")
    example = REPO / "robots/so101/calibration/so101_follower_example.json"
    args = [a.format(example=example, file=a_file) for a in args]
    # A process of its own: a command sets up logging and its environment as it starts.
    done = subprocess.run(
        [sys.executable, "-m", "twin.cli", *args], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 1, done.stdout + done.stderr
    err = done.stderr
    assert "Traceback" not in err
    (line,) = [x for x in err.splitlines() if prefix in x]
    assert line.startswith(f"twin {args[0]}: {prefix}") and says in line, err
    assert a_file.read_text() == "mine\n"  # nothing the user had is touched


def test_a_mistyped_option_is_reported_by_its_command_with_the_nearest_one(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["run", "--brokr", "mqtt://127.0.0.1:1883"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: twin run ")  # the command's usage, not twin's list of commands
    assert (
        "twin run: error: unrecognized arguments: --brokr mqtt://127.0.0.1:1883 (did you mean --broker?)"
        in err
    )
    # A command under a command reports it the same way.
    with pytest.raises(SystemExit):
        main(["calibration", "push", "arm-001", "x.json", "--stroe", "out"])
    assert "twin calibration push: error: unrecognized arguments: --stroe out (did you mean --store?)" in (
        capsys.readouterr().err
    )


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert re.fullmatch(r"twin \d+\.\d+\.\d+\S*\n", capsys.readouterr().out)


@pytest.mark.slow
@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_record_dir_the_agent_cannot_make_says_what_to_do(workers: str, tmp_path: Path) -> None:
    """A walk's `--record-dir` on a read-only disk ended in "cannot start: [Errno 30] Read-only file system"
    and no way out; the path the agent cannot write is named with the fix, from its own process or from a
    worker's. (A directory under a file fails as a read-only disk does, also as root, as the tests run.)"""
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine\n")
    sessions = f"{a_file}/sessions"
    line = cannot_start(["--workers", workers, "--record-dir", sessions], tmp_path)
    assert f"the agent must be able to write {sessions}: make that place writable" in line, line
    assert a_file.read_text() == "mine\n"


@pytest.mark.slow
def test_a_rerun_save_the_agent_cannot_create_says_what_to_do(tmp_path: Path) -> None:
    """A walk's `--rerun-save` into a directory it could not write (a read-only disk) ended in a traceback:
    Rerun's FileSink raises RuntimeError, not OSError. /proc stands in: it exists, and no one may create a
    file in it, root included, as the tests run."""
    line = cannot_start(["--rerun-save", "/proc/twin-walk.rrd"], tmp_path)
    assert "the agent must be able to write /proc/twin-walk.rrd: make that place writable" in line, line


def cannot_start(options: list[str], cwd: Path) -> str:
    """`twin run` with `options` on no broker, in a process of its own: it must exit 1 with one "cannot
    start:" line and no traceback; that line."""
    args = ["run", *options, "--broker", "mqtt://127.0.0.1:9", "--http", "127.0.0.1:0"]
    done = subprocess.run(
        [sys.executable, "-m", "twin.cli", *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        cwd=cwd,
    )
    assert done.returncode == 1, done.stdout + done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    (line,) = [x for x in done.stderr.splitlines() if "cannot start:" in x]
    return line
