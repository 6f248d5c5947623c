"""Hand freed heap memory back to the operating system (glibc's `malloc_trim`).

glibc keeps memory a process freed in its arenas for reuse, and returns it to the system only from the top
of the main heap. A burst of allocations (a sink's backlog, a recording's last session, a Delta commit's
table state) that is freed afterwards can therefore stay in the process's RSS for as long as it runs: the
soak saw RSS step up at such bursts and never come back down (docs/performance.md, "Soak").
`malloc_trim(0)` walks every arena and releases its free pages.

A trim walks the whole heap (a few milliseconds for a few hundred MB), so `Trimmer` does it at most once
per `min_interval_s`; callers call `trim()` after each burst and the rate limit decides. Where glibc is
absent (musl, macOS) `trim()` is a no-op that returns False.

deltalake's native library does not allocate from glibc: it carries a jemalloc of its own, which
malloc_trim does not reach and which reads its settings from one environment variable when it first
allocates. `tune_deltalake_allocator()` sets them for a process that commits history.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading
import time
from collections.abc import Callable, MutableMapping

# Bursts that end less than this far apart share one trim.
DEFAULT_MIN_INTERVAL_S = 30.0

# The variable deltalake's jemalloc reads its settings from (its symbols carry the `_rjem_` prefix).
DELTALAKE_ALLOCATOR_ENV = "_RJEM_MALLOC_CONF"
# jemalloc's defaults keep freed pages for 10 s in each of 4 arenas per CPU, so commits back to back (a
# backlog) never gave their peak back: the writer's RSS swung between 230 and 300 MB with which arenas the
# library's threads happened to touch. One arena, freed pages handed back after 1 s by jemalloc's background
# thread, held the same commits at 220-227 MB with no change in commit time. At one commit every 10 s it
# changes nothing measurable (docs/performance.md, "Soak", has the runs).
DELTALAKE_ALLOCATOR_SETTINGS = "narenas:1,background_thread:true,dirty_decay_ms:1000,muzzy_decay_ms:0"


def load_malloc_trim(library: str | None = "c") -> Callable[[int], int] | None:
    """glibc's malloc_trim from the C library `library` (a name for ctypes.util.find_library, or a path), or
    None where that library or the function is absent."""
    if library is None:
        return None
    path = ctypes.util.find_library(library) if "/" not in library else library
    if path is None:
        return None
    try:
        libc = ctypes.CDLL(path)
        function = libc.malloc_trim
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_size_t]
    function.restype = ctypes.c_int
    release: Callable[[int], int] = function
    return release


class Trimmer:
    """Calls `release(0)` (malloc_trim) at most once per `min_interval_s`; thread-safe."""

    def __init__(
        self,
        release: Callable[[int], int] | None,
        *,
        min_interval_s: float = DEFAULT_MIN_INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if min_interval_s < 0:
            raise ValueError(f"min_interval_s must not be negative, got {min_interval_s}")
        self._release = release
        self._min_interval_s = min_interval_s
        self._clock = clock
        self._lock = threading.Lock()
        self._last: float | None = None
        self.trims = 0

    @property
    def available(self) -> bool:
        return self._release is not None

    def trim(self, *, force: bool = False) -> bool:
        """Release free heap pages unless one was released within `min_interval_s` (`force`: regardless);
        True when it called malloc_trim."""
        if self._release is None:
            return False
        with self._lock:
            now = self._clock()
            if not force and self._last is not None and now - self._last < self._min_interval_s:
                return False
            self._last = now
            self.trims += 1
        # Outside the lock: a concurrent caller is refused by the timestamp already, and must not wait here.
        self._release(0)
        return True


_process_trimmer: Trimmer | None = None
_process_lock = threading.Lock()


def process_trimmer() -> Trimmer:
    """The process's one Trimmer (every caller shares its rate limit), made at first use."""
    global _process_trimmer  # noqa: PLW0603 - one per process, by design
    with _process_lock:
        if _process_trimmer is None:
            _process_trimmer = Trimmer(load_malloc_trim())
        return _process_trimmer


def tune_deltalake_allocator(environ: MutableMapping[str, str] | None = None) -> str:
    """Give deltalake's allocator DELTALAKE_ALLOCATOR_SETTINGS in `environ` (the process's own by default)
    unless the operator set DELTALAKE_ALLOCATOR_ENV already; returns the settings in effect. Call it before
    deltalake is imported: the library reads them once. Child processes inherit them."""
    target = os.environ if environ is None else environ
    return target.setdefault(DELTALAKE_ALLOCATOR_ENV, DELTALAKE_ALLOCATOR_SETTINGS)


def trim(*, force: bool = False) -> bool:
    """Release the process's free heap pages, at most once per DEFAULT_MIN_INTERVAL_S (module doc)."""
    return process_trimmer().trim(force=force)
