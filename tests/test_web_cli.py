"""`twin web` and `twin run --rerun-save` as a user runs them: real processes, the rig's broker and edge.

What matters here: everything `twin web` opens listens on loopback only and answers, SIGTERM stops it with
exit code 0 and leaves no viewer process behind, and `twin run --rerun-save` leaves a recording holding every
applied message.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import unquote, urlsplit

import psutil
import pytest
from conftest import get_state, http_get, read_rrd, wait_for, wait_handled
from twin.rig.local import child_env

TWIN = Path(sys.executable).with_name("twin")
OPEN_LINE = re.compile(r"^open (http://\S+)$", re.MULTILINE)


def read_until_url(proc: subprocess.Popen[str], timeout: float) -> tuple[str, str]:
    """The page `twin web` printed, and everything it printed up to it."""
    seen = ""
    deadline = time.monotonic() + timeout
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            assert proc.poll() is None, f"twin web exited ({proc.returncode}):\n{seen}{proc.stderr.read()}"
            continue
        seen += line
        match = OPEN_LINE.search(seen)
        if match and "stop with Ctrl-C" in line:
            return match.group(1), seen
    raise AssertionError(f"twin web printed no page within {timeout} s:\n{seen}")


def listening(proc: subprocess.Popen[str]) -> list[tuple[str, int]]:
    """(address, port) of every TCP socket the process and its children listen on."""
    out = []
    tree = [psutil.Process(proc.pid), *psutil.Process(proc.pid).children(recursive=True)]
    for p in tree:
        try:
            connections = p.net_connections(kind="tcp")
        except psutil.NoSuchProcess:
            # A short-lived child (a fork about to exec, ctypes' `ldconfig -p`) that ended after the listing
            # listens on nothing: CI once met one gone between the two calls.
            continue
        out.extend((c.laddr.ip, c.laddr.port) for c in connections if c.status == psutil.CONN_LISTEN)
    return out


def stop_and_check(proc: subprocess.Popen[str], ports: list[int]) -> None:
    children = psutil.Process(proc.pid).children(recursive=True)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, f"stdout:\n{out}\nstderr:\n{err}"
    _, alive = psutil.wait_procs(children, timeout=30)
    assert not alive, f"twin web left {alive} running"
    for port in ports:
        with pytest.raises(OSError):
            http_get(f"http://127.0.0.1:{port}/")


def subscribed(base_url: str) -> bool:
    try:
        return get_state(base_url).agent.broker.subscribes > 0
    except OSError:  # its HTTP server is not up yet
        return False


def check_page(url: str) -> list[int]:
    """The page answers with Rerun's viewer and names a loopback stream; returns (page port, stream port)."""
    parts = urlsplit(url)
    assert parts.hostname == "127.0.0.1"
    status, _, body = http_get(url)
    assert status == 200 and b"Rerun" in body
    stream = urlsplit(unquote(parts.query.removeprefix("url=")))
    assert stream.scheme == "rerun+http" and stream.hostname == "127.0.0.1"
    return [parts.port or 0, stream.port or 0]


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_twin_web_runs_the_agent_with_the_viewer_on_loopback_only(rig) -> None:
    edge = rig.start_edge(["arm-001"], seconds=60)
    proc = subprocess.Popen(
        [
            str(TWIN),
            "web",
            "--broker",
            rig.broker.url,
            "--devices",
            "arm-001",
            "--units",
            "ticks",
            "--http",
            "127.0.0.1:0",
            "--grpc-port",
            "0",
            "--web-port",
            "0",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=child_env(),
    )
    try:
        url, printed = read_until_url(proc, 90)
        assert "AWS-StartPortForwardingSession" in printed
        # The native viewer's command names the rerun of this venv: a walk found `rerun` not on PATH.
        rerun = os.path.relpath(Path(sys.executable).with_name("rerun"), Path.cwd())
        assert f"native viewer: {rerun} --connect rerun+http://127.0.0.1:" in printed, printed
        ports = check_page(url)
        sockets = listening(proc)
        assert {port for _, port in sockets} >= set(ports)
        assert all(address == "127.0.0.1" for address, _ in sockets), sockets
        stop_and_check(proc, ports)
    finally:
        if proc.poll() is None:
            proc.kill()
        edge.stop()


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_twin_web_serves_a_recording(tmp_path: Path) -> None:
    from twin.output.rerun_settings import RerunSettings
    from twin.output.rerun_sink import RerunSink
    from twin.robot.model import RobotModel

    path = tmp_path / "fleet.rrd"
    RerunSink(RobotModel.load(), RerunSettings(save=str(path))).close()
    proc = subprocess.Popen(
        [str(TWIN), "web", str(path), "--grpc-port", "0", "--web-port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=child_env(),
    )
    try:
        url, printed = read_until_url(proc, 60)
        assert str(path) in printed
        ports = check_page(url)
        assert all(address == "127.0.0.1" for address, _ in listening(proc))
        stop_and_check(proc, ports)
    finally:
        if proc.poll() is None:
            proc.kill()


def twin_web(*args: str) -> subprocess.CompletedProcess[str]:
    """`twin web ARGS` run to its end (each case here ends at once), its output kept."""
    return subprocess.run(
        [str(TWIN), "web", *args], check=False, capture_output=True, text=True, timeout=60, env=child_env()
    )


def test_twin_web_refuses_what_is_not_a_recording(tmp_path: Path) -> None:
    other = tmp_path / "fleet.json"
    other.write_text("{}")
    proc = twin_web(str(other))
    assert proc.returncode == 2
    assert "is not a .rrd file" in proc.stderr
    missing = twin_web(str(tmp_path / "nosuch.rrd"))
    assert missing.returncode == 2
    assert f"twin web: {tmp_path / 'nosuch.rrd'} does not exist; give a recording" in missing.stderr
    # A walk: a file named .rrd that Rerun did not write was served as an empty page, the rerun binary's
    # error in a log nobody reads.
    cases = [(b"# notes\n", "does not begin as a Rerun recording does (b'# n')"), (b"", "is empty")]
    for content, said in cases:
        named = tmp_path / "named.rrd"
        named.write_bytes(content)
        proc = twin_web(str(named), "--grpc-port", "0", "--web-port", "0")
        assert proc.returncode == 2, proc.stdout
        assert f"twin web: {named} {said}; give a .rrd that Rerun wrote" in proc.stderr


def test_twin_web_refuses_bad_ports_for_a_recording_before_it_binds(tmp_path: Path) -> None:
    """A walk: `twin web FILE.rrd --web-port 70000` ended in an OverflowError traceback, and the same port
    for both in the rerun binary's own coloured error; a file's ports get the agent's checks."""
    path = tmp_path / "fleet.rrd"
    path.write_bytes(b"")  # refused before it is read
    for flags, said in [
        (["--web-port", "70000"], "argument --web-port: 70000 is outside 0..65535"),
        (["--grpc-port", "-1"], "argument --grpc-port: -1 is outside 0..65535"),
        (["--grpc-port", "x"], "argument --grpc-port: 'x' is not a port number"),
        (["--grpc-port", "9999", "--web-port", "9999"], "--grpc-port and --web-port are both 9999"),
    ]:
        proc = twin_web(str(path), *flags)
        assert proc.returncode == 2, (flags, proc.stderr)
        assert said in proc.stderr and "Traceback" not in proc.stderr, (flags, proc.stderr)


def test_twin_web_with_its_stream_port_taken_names_its_own_flag() -> None:
    """The agent `twin web` runs cannot listen on its stream's port: the error names `twin web` (not `twin
    run`) and the flag that chooses another port."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = twin_web("--broker", "mqtt://127.0.0.1:1", "--grpc-port", str(port), "--http", "127.0.0.1:0")
    assert proc.returncode == 1
    assert f"twin web: cannot start: rerun.grpc_port = {port}: 127.0.0.1:{port} is in use" in proc.stderr
    assert "or --grpc-port 0, picks a free one" in proc.stderr


def test_twin_run_serves_rerun_on_the_ports_its_flags_name() -> None:
    """A walk: `twin run --rerun-serve` had no port flags, and its error named `twin web`'s."""
    cases = (("--grpc-port", "grpc_port", "--web-port"), ("--web-port", "web_port", "--grpc-port"))
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        for flag, key, other in cases:
            # The other port any free one: Rerun's defaults may be taken by a test running beside this one.
            serve = ["--rerun-serve", flag, str(port), other, "0"]
            args = [str(TWIN), "run", "--broker", "mqtt://127.0.0.1:1", "--http", "127.0.0.1:0", *serve]
            proc = subprocess.run(
                args, check=False, capture_output=True, text=True, timeout=60, env=child_env()
            )
            assert proc.returncode == 1, proc.stderr
            assert f"twin run: cannot start: rerun.{key} = {port}: 127.0.0.1:{port} is in use" in proc.stderr
            assert f"or {flag} 0, picks a free one" in proc.stderr


def test_twin_run_refuses_a_viewer_port_while_the_viewer_is_off(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk: `twin run --grpc-port 9999` without --rerun-serve started the agent and served no viewer,
    saying nothing."""
    from twin.cli.commands import run as run_command
    from twin.cli.main import main

    # In this process, the agent's JSON log handler would stay on the root logger and write later tests'
    # records into their stdout (a stress run's random order found it).
    monkeypatch.setattr(run_command, "setup_logging", lambda *_args, **_kwargs: None)
    monkeypatch.setattr(run_command, "serve", lambda config: pytest.fail("the agent started"))
    for flag in ("--grpc-port", "--web-port"):
        assert main(["run", "--broker", "mqtt://127.0.0.1:1", flag, "9999"]) == 2
        said = capsys.readouterr().err
        assert f"{flag} 9999 is a port of the Rerun web viewer, which is off: add --rerun-serve" in said
    served: list[int] = []
    monkeypatch.setattr(run_command, "serve", lambda config: served.append(config.rerun.grpc_port) or 0)
    assert main(["run", "--broker", "mqtt://127.0.0.1:1", "--rerun-serve", "--grpc-port", "9999"]) == 0
    assert served == [9999]


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_twin_run_rerun_save_records_every_applied_message(rig, tmp_path: Path) -> None:
    path = tmp_path / "sessions" / "fleet.rrd"
    with rig.agent_process(
        devices="arm-001,arm-002", extra_args=["--units", "ticks", "--rerun-save", str(path)]
    ) as (
        proc,
        base_url,
    ):
        wait_for(lambda: subscribed(base_url), 60, "the agent to subscribe")
        report = rig.start_edge(["arm-001", "arm-002"], seconds=3).join(30)
        # The last messages may still be crossing the broker and the worker.
        state = wait_handled(lambda: get_state(base_url), report.published)
    assert proc.returncode == 0
    rerun = next(s for s in state.agent.sinks if s.name == "rerun")
    assert (rerun.errors, rerun.dropped, rerun.skipped) == (0, 0, 0)
    temporal, static = read_rrd(path)
    for device in ("arm-001", "arm-002"):
        counters = state.devices[device].health.counters
        # Each message reached the twin; a worker behind (a busy machine) coalesces some into newer ones.
        assert counters.applied + counters.coalesced == report.per_device[device]
        applied = counters.applied
        poses = [
            v for v in temporal.column(f"/arms/{device}/gripper:Transform3D:translation").to_pylist() if v
        ]
        assert len(poses) == applied
        assert f"/arms/{device}:Transform3D:translation" in static.schema.names


def test_the_ssm_hint_says_it_is_for_the_twin_host() -> None:
    """A walk on a laptop: `twin web` printed "from a laptop: forward both ports over SSM" under the URL
    that laptop's browser could already open, as if the agent ran elsewhere."""
    from twin.cli.commands.web import _ssm_hint

    hint = _ssm_hint("http://127.0.0.1:9090/?url=x", "rerun+http://127.0.0.1:9876/proxy")
    assert hint.startswith("when this runs on the twin host, a laptop reaches it"), hint
    assert "for p in 9090 9876; do aws ssm start-session" in hint, hint
