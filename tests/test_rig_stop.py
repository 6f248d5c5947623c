"""How the rig stops an agent: SIGTERM, then SIGKILL only once the agent's shutdown budget and the rig's
margin have passed, as systemd does on the host (so a stop that needs its budget ends as in the field)."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

import pytest
from twin.rig import local
from twin.rig.local import STOP_MARGIN_S, LocalRig
from twin.service.config import AgentConfig

# A child that ignores SIGTERM, and one that takes a while to stop on it; each says "ready" once it is set.
IGNORES_TERM = (
    "import signal, time\n"
    "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
    "print('ready', flush=True)\n"
    "time.sleep(120)\n"
)
STOPS_ON_TERM = (
    "import signal, sys, time\n"
    "def stop(*_):\n"
    "    time.sleep(0.3)\n"
    "    sys.exit(7)\n"
    "signal.signal(signal.SIGTERM, stop)\n"
    "print('ready', flush=True)\n"
    "time.sleep(120)\n"
)


def _child(code: str) -> subprocess.Popen[bytes]:
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline() == b"ready\n"
    return proc


def test_a_child_that_ignores_sigterm_is_killed_only_after_the_timeout() -> None:
    proc = _child(IGNORES_TERM)
    started = time.monotonic()
    local._terminate(proc, 1.0)
    # The wait lasts the whole timeout (it cannot end sooner: the child never exits by itself), then SIGKILL.
    assert time.monotonic() - started >= 1.0
    assert proc.returncode == -signal.SIGKILL


def test_a_child_that_stops_on_sigterm_ends_by_itself() -> None:
    proc = _child(STOPS_ON_TERM)
    local._terminate(proc, 60.0)
    assert proc.returncode == 7


@pytest.mark.parametrize(
    ("config_text", "budget"),
    [
        (None, AgentConfig().twin.shutdown_budget_s),
        ("[twin]\nshutdown_budget_s = 12.0\n", 12.0),
        # A config the agent refuses: it exits by itself; the rig waits by the default budget.
        ("[twin]\nshutdown_budget_s = 1.0\n", AgentConfig().twin.shutdown_budget_s),
    ],
    ids=["default", "configured", "refused"],
)
def test_the_agent_is_given_its_budget_and_the_margin(
    rig: LocalRig, monkeypatch: pytest.MonkeyPatch, config_text: str | None, budget: float
) -> None:
    timeouts: list[float] = []
    terminate = local._terminate

    def recorded(proc: subprocess.Popen[bytes], timeout: float) -> None:
        timeouts.append(timeout)
        terminate(proc, timeout)

    monkeypatch.setattr(local, "_terminate", recorded)
    with rig.agent_process(config_text=config_text) as (proc, _base):
        pass
    assert timeouts == [budget + STOP_MARGIN_S]
    # The agent ended on SIGTERM (or refused its config) by itself, not by the rig's SIGKILL.
    assert proc.returncode is not None and proc.returncode != -signal.SIGKILL


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_an_agent_whose_picked_port_was_taken_starts_again_on_another(
    rig: LocalRig, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The port is picked free and bound later by the agent, so another process can take it between: here it
    # listens there first. The agent exits on it; the rig must not hand out that port, where another server
    # (not the agent) may answer, but the one an agent started again serves.
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        picks = iter([port])
        free_port = local.free_port
        monkeypatch.setattr(local, "free_port", lambda: next(picks, 0) or free_port())
        with rig.agent_process() as (proc, base):
            assert proc.poll() is None, rig.agent_log(port).read_text()
            assert base != f"http://127.0.0.1:{port}"
            assert local._serving_pid(int(base.rsplit(":", 1)[1])) == proc.pid
        assert f"cannot listen on 127.0.0.1:{port}" in rig.agent_log(port).read_text()
