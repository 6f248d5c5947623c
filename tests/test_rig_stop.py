"""How the rig stops an agent: SIGTERM, then SIGKILL only once the agent's shutdown budget and the rig's
margin have passed, as systemd does on the host (so a stop that needs its budget ends as in the field)."""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest
from conftest import wait_for
from twin.core.lifetime import die_with_parent
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


# A rig in a process of its own: its broker and an agent started, their pids printed, then it waits to be
# killed (as a test run's timeout or `kill -9` ends it, with no chance to stop its children).
RIG_PARENT = (
    "import sys, time\n"
    "from pathlib import Path\n"
    "from twin.rig.local import LocalRig\n"
    "rig = LocalRig(workdir=Path(sys.argv[1]))\n"
    "rig.__enter__()\n"
    "with rig.agent_process() as (proc, base):\n"
    "    print(rig.broker.pid, proc.pid, flush=True)\n"
    "    time.sleep(600)\n"
)


@pytest.mark.slow
def test_a_rig_killed_outright_leaves_no_broker_or_agent_behind(tmp_path: Path) -> None:
    parent = subprocess.Popen(
        [sys.executable, "-c", RIG_PARENT, str(tmp_path / "rig")],
        stdout=subprocess.PIPE,
        env=local.child_env(),
    )
    children: list[psutil.Process] = []
    try:
        assert parent.stdout is not None
        line = parent.stdout.readline().decode()
        assert line, f"the rig process exited with {parent.wait()} before its agent served"
        children = [psutil.Process(int(pid)) for pid in line.split()]
        parent.kill()
        parent.wait()

        def gone() -> bool:
            return all(not c.is_running() or c.status() == psutil.STATUS_ZOMBIE for c in children)

        # They were the killed rig's; the kernel ends them with it (die_with_parent), or they would keep the
        # broker's port and an agent on a core until someone found them.
        wait_for(gone, 60, "the broker and the agent of a killed rig to end")
    finally:
        # A failure before the kill (its output never came, a timeout) must not leave the rig's process
        # sleeping out its 600 s with a broker and an agent.
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        for child in children:
            with contextlib.suppress(psutil.Error):
                child.kill()


def test_only_the_main_thread_ties_a_child_to_the_process() -> None:
    # The kernel's signal follows the thread that forked: a child started from a thread that then returns
    # would be stopped with that thread.
    assert callable(die_with_parent())
    off_main: list[object] = []
    thread = threading.Thread(target=lambda: off_main.append(die_with_parent()))
    thread.start()
    thread.join()
    assert off_main == [None]
