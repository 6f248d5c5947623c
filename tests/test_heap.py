"""twin.core.heap: the rate limit of malloc_trim, the no-op where glibc is absent, and deltalake's allocator
settings (read for real by the installed deltalake, in a child process)."""

from __future__ import annotations

import ctypes.util
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

import pytest
from twin.core import heap
from twin.core.heap import Trimmer, load_malloc_trim


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_trims_at_most_once_per_interval_unless_forced() -> None:
    calls: list[int] = []
    clock = Clock()

    def release(pad: int) -> int:
        calls.append(pad)
        return 1

    trimmer = Trimmer(release, min_interval_s=30.0, clock=clock)
    assert trimmer.trim()
    clock.now += 29.9
    assert not trimmer.trim()  # within the interval: refused
    assert calls == [0]
    clock.now += 0.1
    assert trimmer.trim()
    assert trimmer.trim(force=True)
    assert calls == [0, 0, 0] and trimmer.trims == 3
    clock.now += 10.0
    assert not trimmer.trim()  # the forced one counts for the interval too


def test_without_glibc_trim_is_a_no_op() -> None:
    trimmer = Trimmer(None)
    assert not trimmer.available
    assert not trimmer.trim() and not trimmer.trim(force=True)
    assert trimmer.trims == 0
    assert load_malloc_trim(None) is None
    assert load_malloc_trim("/nonexistent/libc.so.6") is None
    # A C library without the function (libm has no malloc_trim): None, not an AttributeError.
    libm = ctypes.util.find_library("m")
    if libm is not None:
        assert load_malloc_trim(libm) is None


def test_a_negative_interval_is_refused() -> None:
    with pytest.raises(ValueError, match="min_interval_s"):
        Trimmer(None, min_interval_s=-1.0)


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_on_glibc_the_process_trimmer_calls_malloc_trim() -> None:
    release = load_malloc_trim()
    assert release is not None
    assert release(0) in (0, 1)  # malloc_trim's answer: whether it released memory
    assert heap.process_trimmer().available
    assert heap.process_trimmer() is heap.process_trimmer()
    assert heap.trim(force=True)


def test_the_deltalake_allocator_settings_are_set_unless_the_operator_set_their_own() -> None:
    environ: dict[str, str] = {}
    assert heap.tune_deltalake_allocator(environ) == heap.DELTALAKE_ALLOCATOR_SETTINGS
    assert environ == {heap.DELTALAKE_ALLOCATOR_ENV: heap.DELTALAKE_ALLOCATOR_SETTINGS}
    own = {heap.DELTALAKE_ALLOCATOR_ENV: "dirty_decay_ms:5000"}
    assert heap.tune_deltalake_allocator(own) == "dirty_decay_ms:5000"
    assert own == {heap.DELTALAKE_ALLOCATOR_ENV: "dirty_decay_ms:5000"}


def test_the_installed_deltalake_reads_the_allocator_settings(tmp_path: Path) -> None:
    """A deltalake release that dropped its jemalloc, or renamed the variable, would silently ignore the
    settings: jemalloc's own report of its options (stats_print, at exit) must show ours."""
    script = (
        "import deltalake, pyarrow as pa, sys\n"
        "deltalake.write_deltalake(sys.argv[1], pa.table({'a': [1, 2, 3]}))\n"
    )
    env = dict(os.environ)
    env[heap.DELTALAKE_ALLOCATOR_ENV] = heap.DELTALAKE_ALLOCATOR_SETTINGS + ",stats_print:true"
    done = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path / "t")],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    options = dict(re.findall(r"^\s*opt\.(\w+): (\S+)", done.stderr, re.MULTILINE))
    for setting in heap.DELTALAKE_ALLOCATOR_SETTINGS.split(","):
        name, value = setting.split(":")
        assert options.get(name) == value, (name, options)


def test_the_history_writer_module_loads_no_deltalake_before_it_sets_the_allocator() -> None:
    """writer_main sets the settings first thing; they are read only if deltalake is not loaded by then,
    i.e. by importing the module that holds writer_main (what a spawned process does before calling it)."""
    probe = (
        "import sys, twin.output.history_feed, twin.cli.main\n"
        "print(sorted(m for m in sys.modules if m.startswith('deltalake')))"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True
    )
    assert done.stdout.strip() == "[]"
