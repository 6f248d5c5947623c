"""twin.core.heap: the rate limit of malloc_trim, and the no-op where glibc is absent."""

from __future__ import annotations

import ctypes.util
import platform

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
