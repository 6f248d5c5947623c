"""What streaming to Rerun costs: the same fleet through the agent without and with the `[rerun]` sink.

Two phases against one private broker, with the same offered load (default 100 arms at 10 Hz, the target's
load), each with a fresh `twin run --workers 1` child process (with [rerun] the agent is one process):
1. off: the agent as deployed by default, but in one process;
2. on: the agent with `[rerun]` writing a .rrd and serving the stream and the web viewer (no viewer
   connected; a slow or absent viewer is the gRPC server's to buffer, within its memory limit).
The figures: the mirrored rate of both (messages applied to the twins per second) and what the second lost
against the first, the agent's CPU in both (% of one core) and the difference, and the sink's counters.
Targets (docs/web.md): at most 10 % of the mirrored rate and at most 15 % of a core. The publishers run in
their own processes; everything shares this host's cores, so quote the load average with the figures.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

from twin.bench.harness import (
    ProcessSampler,
    collect,
    drained,
    get_state,
    publishers,
    running_agent,
    sum_devices,
    wait_subscribed,
)
from twin.rig.local import LocalRig


def _rerun_config(rrd: Path) -> str:
    return f'[rerun]\nsave = "{rrd}"\nserve = true\ngrpc_port = 0\nweb_port = 0\n'


def _phase(rig: LocalRig, arms: int, rate: float, seconds: float, config_text: str) -> dict[str, Any]:
    # One worker in both phases: [rerun] runs the agent as one process (one stream), and without it the
    # agent would shard the fleet over one process per core, so the difference would be the shape of the
    # agent, not the stream.
    with running_agent(rig, max_devices=max(4096, arms), config_text=config_text, workers=1) as (
        proc,
        base,
    ):
        wait_subscribed(base, proc)
        before = get_state(base)
        sampler = ProcessSampler(proc.pid).start()
        sent = collect(publishers(rig.broker.url, arms, rate, seconds), timeout=seconds + 60)
        state = drained(base)
        usage = sampler.stop()
        if proc.poll() is not None:
            raise RuntimeError(f"the agent exited during the run (code {proc.returncode})")
    elapsed = sent["elapsed_s"]
    applied = sum_devices(state, "applied")
    received = state.agent.broker.messages - before.agent.broker.messages
    sinks = {s.name: s for s in state.agent.sinks}
    rerun = sinks.get("rerun")
    return {
        **sent,
        "received": received,
        "applied": applied,
        "coalesced": sum_devices(state, "coalesced"),
        "overwritten": sum_devices(state, "overwritten"),
        "mirrored_rate": applied / elapsed if elapsed else 0.0,
        "cpu_percent": usage["cpu_percent"],
        "host_cpu_percent": usage["host_cpu_percent"],
        "rss_max_mb": usage["rss_max_mb"],
        "sink": None
        if rerun is None
        else {
            "delivered": rerun.delivered,
            "dropped": rerun.dropped,
            "skipped": rerun.skipped,
            "errors": rerun.errors,
            "pending": rerun.pending,
        },
    }


def run(*, arms: int = 100, rate: float = 10.0, seconds: float = 20.0) -> dict[str, Any]:
    """Both phases; every figure as one JSON-ready dict (nothing asserted: a benchmark measures)."""
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="so101-bench-rerun-") as tmp:
        rrd = Path(tmp) / "bench.rrd"
        with LocalRig() as rig:
            off = _phase(rig, arms, rate, seconds, "")
            on = _phase(rig, arms, rate, seconds, _rerun_config(rrd))
        rrd_mb = rrd.stat().st_size / 2**20 if rrd.is_file() else None
    rate_cost = 1.0 - on["mirrored_rate"] / off["mirrored_rate"] if off["mirrored_rate"] else None
    return {
        "scenario": "rerun",
        "arms": arms,
        "rate_hz": rate,
        "seconds": seconds,
        "offered_rate": arms * rate,
        "off": off,
        "on": {**on, "rrd_mb": rrd_mb},
        # Targets: mirrored_rate_cost <= 0.10, extra_cpu_percent_of_core <= 15.
        "mirrored_rate_cost": rate_cost,
        "extra_cpu_percent_of_core": on["cpu_percent"] - off["cpu_percent"],
        "load_average_1m": {"before": load_before[0], "after": os.getloadavg()[0]},
        "notes": (
            "agent child process with and without [rerun] (save + serve, no viewer connected); publishers, "
            "broker and agent share this host's cores: figures taken while other work runs are noisy"
        ),
        "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
