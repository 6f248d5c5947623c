"""How many worker processes an agent runs, and how they start: forked from a server that imported the
mirror once.

Standard library only, so `twin run` can decide and start the server right after reading its config, before
its own imports (the agent's runtime, awscrt, the HTTP framework): the server imports NumPy, MuJoCo and the
mirror on another core meanwhile, and compiles the agent's model (twin.service.worker_preload); each worker
forked from it, at start or again after a crash, skips both. Measured in docs/performance.md ("Footprint").
"""

from __future__ import annotations

import math
import multiprocessing
import multiprocessing.forkserver
import os
from multiprocessing.context import ForkServerContext
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from twin.service.config import AgentConfig

# Messages a second one worker is planned for when `[twin] workers = 0` chooses the count for a listed fleet:
# about a third of what one worker mirrors on this project's 2-core development machine, so a fleet of up to
# 100 arms at 10 Hz stays in one process (docs/scaling.md, "Workers").
WORKER_PLAN_RATE = 1000.0
# What the fork server imports once, before it forks any worker: the worker's entry point and the mirror
# with NumPy and MuJoCo, and the agent's model compiled meanwhile (that module's doc).
WORKER_PRELOAD = ("twin.service.worker_preload",)
# The MJCF file the fork server compiles ahead, `[twin] model`: besides sys.path, the environment at its start
# is all the server takes from the agent, so it is passed there (empty: the bundled scene). A server started
# again by a worker's start (after it died) goes without, and compiles the bundled scene.
WORKER_MODEL_ENV = "TWIN_WORKER_MODEL"


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity, which containers and taskset narrow)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


def worker_count(config: AgentConfig, cores: int | None = None) -> int:
    """How many worker processes `config` asks for: `[twin] workers`, or when it is 0 one per usable core,
    but one per WORKER_PLAN_RATE of a listed fleet's expected messages, and one when the Rerun stream is on
    (one stream, one process). 1 means the mirror runs in the agent's own process."""
    requested = config.twin.workers
    if requested:
        return requested
    if config.rerun.enabled:
        return 1
    cores = usable_cores() if cores is None else cores
    if config.telemetry.all_devices:
        return cores
    expected = len(config.telemetry.devices) * config.health.expected_rate_hz
    return max(1, min(cores, len(config.telemetry.devices), math.ceil(expected / WORKER_PLAN_RATE)))


def worker_context() -> ForkServerContext:
    """The context worker processes are started in: forked from the server, which preloads the mirror."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(list(WORKER_PRELOAD))
    return context


def start_fork_server(model: str = "") -> None:
    """Start the fork server now, if it does not run yet; it imports WORKER_PRELOAD and compiles `model`
    (`[twin] model`, empty for the bundled scene) in the background (a worker's start waits for that, this
    call does not). The variable is set for the server's start only: this process's other children do not
    see it."""
    worker_context()
    before = os.environ.get(WORKER_MODEL_ENV)
    os.environ[WORKER_MODEL_ENV] = os.path.abspath(model) if model else ""
    try:
        multiprocessing.forkserver.ensure_running()
    finally:
        if before is None:
            del os.environ[WORKER_MODEL_ENV]
        else:
            os.environ[WORKER_MODEL_ENV] = before
