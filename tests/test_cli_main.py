"""The `twin` entry point itself: what every command shares."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from twin.cli.main import EXIT_READER_GONE


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
