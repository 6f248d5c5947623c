"""A stop while the history writer is down (docs/history.md): the agent does not wait for a writer it will
not start again.

A writer that dies within QUICK_DEATH_S of its start is started again after a growing pause. A stop that came
during that pause used to wait the whole shutdown budget: every mirror's feed held rows and kept trying to
reach a writer that nothing would start any more. Now the stop tells the feeds, and they give up at once;
their rows are counted as not written, as they were at the end of that budget.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest
from conftest import wait_for
from test_alerts import hot, hot_arm_settings
from twin.output.history_feed import MAX_RESTART_PAUSE_S
from twin.service.agent import AgentService
from twin.service.config import load_config

pytest.importorskip("deltalake")

ARM = "arm-003"
TOPIC = f"dt/lerobot/{ARM}/telemetry"


def _received(agent: AgentService) -> int:
    device = agent.state().devices.get(ARM)
    return device.health.counters.received if device is not None else 0


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2], ids=["in-process", "two-worker-processes"])
def test_a_stop_while_the_writer_waits_to_be_started_again_does_not_wait_for_it(
    tmp_path: Path, workers: int
) -> None:
    settings = hot_arm_settings(
        **{"history.uri": str(tmp_path / "history"), "history.commit_every_s": 3600.0}
    )
    agent = AgentService(load_config(None, settings), workers=workers)
    agent.start()
    try:
        history = agent._history
        assert history is not None and history.pid is not None
        # The next pause is the longest there is, as after a writer that died again and again within
        # QUICK_DEATH_S of its start (however long this agent took to start on a loaded machine).
        history.restarts, history.started_at = 6, time.monotonic()
        os.kill(history.pid, signal.SIGKILL)
        wait_for(lambda: history._restart_at is not None, 30, "the supervisor to see the writer dead")
        pending = 10
        for _ in range(pending):
            agent.feed(TOPIC, hot(ARM, int(time.time() * 1000), 35))
        wait_for(lambda: _received(agent) >= pending, 30, "the messages mirrored, their rows in the feed")
        assert history._restart_at is not None  # still in its pause

        began = time.monotonic()
        agent.stop()
        took = time.monotonic() - began
    finally:
        agent.stop()
    # Before, the stop took the whole budget (the workers' share of it with worker processes): 50-60 s.
    assert took < MAX_RESTART_PAUSE_S / 2, f"the stop took {took:.1f} s"
    unwritten = sum(r.unwritten.get("history_rows", 0) for r in agent.stop_reports.values() if r is not None)
    assert unwritten >= pending, agent.stop_reports
    assert not history.alive and history.restarts == 6  # not started again for the stop
