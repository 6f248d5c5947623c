"""The local rig: the whole pipeline on one machine, for `twin demo`, `twin bench` and the end-to-end tests.

    with LocalRig() as rig:                       # a private mosquitto on a free loopback port
        service = rig.start_agent({"telemetry.devices": ["arm-001"]})    # the agent, in this process
        edge = rig.start_edge(["arm-001"], seconds=5)                    # the edge simulator, in a thread
        report = edge.join()
        state = service.state()
    # everything started here is stopped, the temp folder removed

`rig.agent_process(...)` runs the agent as a child process instead (`twin run`), for figures that must be
measured per process (the benchmark's CPU and RSS) or that need a real signal (SIGTERM). Every piece the rig
starts is stopped in `close()`, in reverse order, also when the body raises.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from twin.core.lifetime import die_with_parent
from twin.core.topics import DEFAULT_TOPIC_PREFIX
from twin.rig.mosquitto import MosquittoBroker, MosquittoNotFound, free_port
from twin.service.config import AgentConfig, ConfigError, load_config
from twin.transport.broker import BrokerConfig

if TYPE_CHECKING:
    from twin.service.agent import AgentService

log = logging.getLogger(__name__)

AGENT_CLIENT_PREFIX = "so101-rig-agent-"
EDGE_CLIENT_PREFIX = "so101-rig-edge-"
SUBSCRIBE_TIMEOUT_S = 15.0
# An agent the rig started is killed this long after its shutdown budget (the host's unit gives systemd's
# stop timeout the same margin: userdata/install-agent.sh).
STOP_MARGIN_S = 30.0
# Starts of `agent_process` on a new port when another process took the one picked; and how long one start
# may take before the agent serves HTTP (a cold start on a loaded 2-core machine takes tens of seconds).
AGENT_PORT_ATTEMPTS = 3
AGENT_START_TIMEOUT_S = 240.0


class RigError(RuntimeError):
    """A piece of the rig could not start; the message says which and what to do."""


class EdgeRun:
    """The edge simulator running in a background thread; `join()` returns its report or raises its error."""

    def __init__(self, simulator: Any) -> None:
        self.simulator = simulator
        self._stop = threading.Event()
        self._result: Any = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="rig-edge-sim", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self._result = self.simulator.run(self._stop)
        except Exception as exc:  # handed to whoever joins: the rig's user reports it
            self._error = exc

    @property
    def report(self) -> Any:
        """The simulator's counts so far (live while it runs)."""
        return self.simulator.report

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float | None = None) -> Any:
        """Wait for the run to end; its EdgeSimReport, or the simulator's exception re-raised."""
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise RigError(f"the edge simulator did not finish within {timeout} s")
        if self._error is not None:
            raise self._error
        return self._result


class LocalRig:
    """A private broker plus, on request, the agent (in-process or as a child) and edge simulators."""

    def __init__(self, workdir: Path | None = None) -> None:
        self._own_workdir = workdir is None
        self.workdir = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="so101-rig-"))
        try:
            self.broker = MosquittoBroker(workdir=self.workdir / "mosquitto")
        except MosquittoNotFound as exc:
            self._remove_workdir()
            raise RigError(f"{exc}. The local rig needs mosquitto: run `make setup`.") from exc
        self.services: list[Any] = []
        self._edges: list[EdgeRun] = []
        self._closed = False

    # -- lifecycle ----------------------------------------------------------------------------------------

    def __enter__(self) -> LocalRig:
        self.broker.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the edge simulators, the agents and the broker (in that order); remove the temp folder."""
        if self._closed:
            return
        self._closed = True
        for edge in self._edges:
            edge.stop()
        for edge in self._edges:
            with contextlib.suppress(Exception):  # its error was the caller's to collect via join()
                edge.join(10.0)
        for service in reversed(self.services):
            try:
                service.stop()
            except Exception:
                log.exception("stopping a rig agent failed")
        self.broker.stop()
        self._remove_workdir()

    def _remove_workdir(self) -> None:
        if self._own_workdir:
            shutil.rmtree(self.workdir, ignore_errors=True)

    # -- the agent ----------------------------------------------------------------------------------------

    def agent_config(self, overrides: Mapping[str, Any] | None = None) -> AgentConfig:
        """An agent config for this rig: its broker, HTTP on a free loopback port, then `overrides`
        (dotted keys, as `twin run` flags: {"telemetry.devices": ["arm-001"], ...})."""
        values: dict[str, Any] = {
            "broker.url": self.broker.url,
            "broker.client_id_prefix": AGENT_CLIENT_PREFIX,
            "http.listen": "127.0.0.1:0",
        }
        values.update(overrides or {})
        return load_config(None, values)

    def start_agent(
        self,
        overrides: Mapping[str, Any] | AgentConfig | None = None,
        *,
        sinks: Sequence[Any] = (),
        wait_subscribed: bool = True,
        workers: int = 1,
    ) -> AgentService:
        """Start an AgentService in this process (stopped by close()), its mirror in-process or, with
        `workers` > 1, in as many worker processes (`twin run --workers N`); waits until it has subscribed."""
        from twin.ops.sessions import history_sessions  # noqa: PLC0415
        from twin.service.agent import AgentService  # noqa: PLC0415 - awscrt (and MuJoCo, USD) load here

        config = overrides if isinstance(overrides, AgentConfig) else self.agent_config(overrides)
        service = AgentService(config, workers=workers, sinks=sinks, sessions=history_sessions(config))
        self.services.append(service)
        service.start()
        if wait_subscribed and not service.wait_subscribed(SUBSCRIBE_TIMEOUT_S):
            raise RigError(
                f"the agent did not subscribe on {self.broker.url} within {SUBSCRIBE_TIMEOUT_S:.0f} s "
                f"(the broker log: {self.broker.log_path})"
            )
        return service

    @contextlib.contextmanager
    def agent_process(
        self,
        *,
        devices: str = "*",
        config_text: str | None = "",
        extra_args: Sequence[str] = (),
        log_name: str = "agent",
    ) -> Iterator[tuple[subprocess.Popen[bytes], str]]:
        """`twin run` as a child process on this rig's broker; yields (process, HTTP base URL) once the agent
        serves that URL itself (or has exited by itself: a config it refuses).

        `config_text` is written as its TOML config (None: no --config, the defaults and the flags only);
        stdout and stderr go to `<workdir>/<log_name>-<port>.log`. Stopped with SIGTERM on exit, and killed
        only once its `[twin] shutdown_budget_s` and STOP_MARGIN_S have passed, as systemd does on the host:
        a stop that needs its budget (history's last commit, say) ends as it would in the field.
        """
        budget = AgentConfig().twin.shutdown_budget_s
        config_args: list[str] = []
        if config_text is not None:
            config = self._agent_config_file(config_text, log_name)
            config_args = ["--config", str(config)]
            with contextlib.suppress(ConfigError):  # the agent itself says what is wrong, and exits
                budget = load_config(config).twin.shutdown_budget_s
        # The port is picked free, then bound by the agent: another process can take it between. Then the
        # agent exits saying so and runs again on another port (the log's name carries the port, and the
        # agent reports a port 0 bound only in a log line `--log-level WARNING` hides).
        for attempt in range(AGENT_PORT_ATTEMPTS):
            port = free_port()
            proc = self._spawn_agent(port, devices, [*config_args, *extra_args], log_name)
            try:
                taken = not self._await_own_http(proc, port, log_name)
            except BaseException:
                _terminate(proc, budget + STOP_MARGIN_S)
                raise
            if not taken or attempt == AGENT_PORT_ATTEMPTS - 1:
                break
            log.warning("the agent's HTTP port %d was taken by another process; starting it again", port)
        try:
            yield proc, f"http://127.0.0.1:{port}"
        finally:
            _terminate(proc, budget + STOP_MARGIN_S)

    def _agent_config_file(self, config_text: str, log_name: str) -> Path:
        # One file per agent_process: two running at once under one log name keep their own configs.
        fd, name = tempfile.mkstemp(prefix=f"{log_name}-", suffix=".toml", dir=self.workdir)
        os.close(fd)
        config = Path(name)
        config.write_text(config_text)
        return config

    def _spawn_agent(
        self, port: int, devices: str, args: Sequence[str], log_name: str
    ) -> subprocess.Popen[bytes]:
        cmd = [
            sys.executable,
            "-m",
            "twin.cli",
            "run",
            "--broker",
            self.broker.url,
            "--devices",
            devices,
            "--http",
            f"127.0.0.1:{port}",
            *args,
        ]
        with self.agent_log(port, log_name).open("wb") as log_file:
            return subprocess.Popen(
                cmd,
                stdout=log_file,
                stderr=subprocess.STDOUT,
                env=child_env(),
                # A rig killed outright must not leave an agent serving its port and using a core.
                preexec_fn=die_with_parent(),  # noqa: PLW1509 - only prctl
            )

    def _await_own_http(self, proc: subprocess.Popen[bytes], port: int, log_name: str) -> bool:
        """Whether the agent `proc` serves `port` itself or exited for a reason of its own; False when it
        exited because the port was taken."""
        log_path = self.agent_log(port, log_name)
        said = await_own_http(
            proc, port, functools.partial(log_path.read_text, errors="replace"), where=f"its log: {log_path}"
        )
        return said is None or not port_taken(said, port)

    def agent_log(self, port: int | str, log_name: str = "agent") -> Path:
        """Where `agent_process` writes the output of the agent serving HTTP on `port` (kept until the rig
        closes)."""
        return self.workdir / f"{log_name}-{port}.log"

    # -- the edge -----------------------------------------------------------------------------------------

    def broker_config(self, client_id_prefix: str = EDGE_CLIENT_PREFIX, **settings: Any) -> BrokerConfig:
        """Settings for a client of this rig's broker (a publisher in a test, say)."""
        return BrokerConfig(url=self.broker.url, client_id_prefix=client_id_prefix, **settings)

    def start_edge(
        self,
        devices: Sequence[str],
        *,
        variant: str = "ticks",
        rate_hz: float = 10.0,
        seconds: float | None = None,
        seed: int = 101,
        topic_prefix: str = DEFAULT_TOPIC_PREFIX,
        **options: Any,
    ) -> EdgeRun:
        """The edge simulator publishing `devices` to this rig's broker, in a background thread.

        `options` go to EdgeSimConfig (faults=FaultConfig(...), load_sign=True, ...)."""
        from twin.edge.simulator import EdgeSimConfig, EdgeSimulator  # noqa: PLC0415 - awscrt loads here

        simulator = EdgeSimulator(
            EdgeSimConfig(
                broker=self.broker_config(),
                devices=list(devices),
                variant=variant,
                rate_hz=rate_hz,
                seconds=seconds,
                seed=seed,
                topic_prefix=topic_prefix,
                **options,
            )
        )
        edge = EdgeRun(simulator)
        self._edges.append(edge)
        return edge


def child_env() -> dict[str, str]:
    """The environment of a child agent: headless MuJoCo (EGL) unless set, unbuffered output."""
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def await_own_http(
    proc: subprocess.Popen[Any], port: int, output: Callable[[], str], *, where: str
) -> str | None:
    """None once the agent `proc` serves GET /state on `port` itself (a server answering there with another
    pid is not it); what it printed (`output()`) once it exited instead. RigError, naming `where` its output
    is, when it does neither within AGENT_START_TIMEOUT_S."""
    deadline = time.monotonic() + AGENT_START_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return output()
        if _serving_pid(port) == proc.pid:
            return None
        time.sleep(0.1)
    raise RigError(
        f"the agent (pid {proc.pid}) did not serve http://127.0.0.1:{port} within "
        f"{AGENT_START_TIMEOUT_S:.0f} s; {where}"
    )


def port_taken(said: str, port: int) -> bool:
    """Whether an agent's output says it exited because another process had taken its HTTP port."""
    return f"cannot listen on 127.0.0.1:{port}" in said


def _serving_pid(port: int) -> int | None:
    """The pid the agent answering GET /state on `port` reports; None when nothing (or not an agent)
    answers yet."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/state", timeout=5.0) as response:
            return int(json.loads(response.read())["agent"]["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _terminate(proc: subprocess.Popen[bytes], timeout: float) -> None:
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)


def wait_until(
    predicate: Any,
    timeout: float,
    what: str,
    interval: float = 0.02,
    *,
    error: type[Exception] = RigError,
) -> Any:
    """Poll `predicate` until it returns something truthy (returned) or `timeout` s pass (`error`, naming
    `what`: a RigError for the rig; the tests fail with an AssertionError instead)."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise error(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)
