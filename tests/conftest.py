"""Shared fixtures and helpers: the local rig (real mosquitto on a free loopback port), a plain MQTT
publisher, the agent's HTTP state parsed into its types, polling, /metrics parsed by prometheus_client, and a
headless chromium that reaches loopback addresses only."""

from __future__ import annotations

import os

# MuJoCo binds its GL backend when it is first imported; with none set it takes GLFW, which needs a display.
# `make test` exports MUJOCO_GL=egl; a bare `pytest` (or a shuffled order that imports mujoco in an unexpected
# test first) must get the same, so it is set here, before this file imports anything that imports mujoco.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import json
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
from awscrt import mqtt5
from prometheus_client.parser import text_string_to_metric_families
from twin.core.topics import DEFAULT_TOPIC_PREFIX, telemetry_topic
from twin.edge.payload import encode, make_payload
from twin.rig.local import LocalRig, RigError, wait_until
from twin.rig.mosquitto import MosquittoBroker, MosquittoNotFound
from twin.service.agent import AgentService
from twin.service.config import load_config
from twin.service.state import AgentState, DeviceState
from twin.transport.broker import BrokerConfig, new_client_id
from twin.transport.client import build_mqtt5_client

# The region the moto-backed AWS tests (twin instance, twin instance check) create their resources in.
AWS_TEST_REGION = "us-east-1"
# The broker of an agent fed through feed(): nothing listens on port 1 here and free_port never hands it out
# (it is below the ephemeral range), so no other test's mosquitto, started in parallel, can take the port
# and feed such an agent arms of its own (a port merely free when asked could be).
NO_BROKER = "mqtt://127.0.0.1:1"


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tests marked `long(seconds)` (most of it waiting on real time) go first, the longest first. xdist
    hands tests to its workers in this order, and a long one handed out near the end kept one worker busy
    long after the other had run out of tests. trylast: after pytest-randomly's shuffle, which the rest
    keep (the sort is stable)."""

    def expected_seconds(item: pytest.Item) -> float:
        mark = item.get_closest_marker("long")
        if mark is None:
            return 0.0
        if "seconds" not in mark.kwargs:
            raise pytest.UsageError(
                f"{item.nodeid}: write @pytest.mark.long(seconds=<about how long it takes>)"
            )
        return float(mark.kwargs["seconds"])

    items.sort(key=expected_seconds, reverse=True)


@pytest.fixture
def aws_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Fake credentials and a region for moto; never the developer's real AWS config files."""
    empty = tmp_path / "empty"
    empty.write_text("")
    for name in ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_REGION", "SO101_TWIN_STACK"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(empty))
    monkeypatch.setenv("AWS_CONFIG_FILE", str(empty))
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    monkeypatch.setenv("AWS_DEFAULT_REGION", AWS_TEST_REGION)


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[MosquittoBroker]:
    """A started mosquitto on 127.0.0.1:<free port>; its config and log live in tmp_path/mosquitto."""
    try:
        broker = MosquittoBroker(workdir=tmp_path / "mosquitto")
    except MosquittoNotFound as exc:
        pytest.fail(f"{exc} (the transport tests need a real broker)")
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[LocalRig]:
    """The local rig (twin.rig.local) in tmp_path/rig: its broker runs; agents and edges start on request."""
    try:
        local = LocalRig(workdir=tmp_path / "rig")
    except RigError as exc:
        pytest.fail(str(exc))
    with local:
        yield local


class Publisher:
    """A plain awscrt MQTT5 publisher (QoS 0, like the edge); reconnects by itself after broker restarts."""

    def __init__(self, url: str, prefix: str = DEFAULT_TOPIC_PREFIX) -> None:
        self.prefix = prefix
        self.connected = threading.Event()
        self.stopped = threading.Event()
        self.client = build_mqtt5_client(
            BrokerConfig(url=url, min_reconnect_delay_ms=100, max_reconnect_delay_ms=500),
            new_client_id("test-pub-"),
            on_connection_success=lambda _d: self.connected.set(),
            on_disconnection=lambda _d: self.connected.clear(),
            on_stopped=lambda _d: self.stopped.set(),
        )
        self.client.start()
        if not self.connected.wait(30):
            pytest.fail(f"test publisher could not connect to {url}")

    def publish(self, device: str, payload: bytes) -> None:
        packet = mqtt5.PublishPacket(
            topic=telemetry_topic(self.prefix, device), payload=payload, qos=mqtt5.QoS.AT_MOST_ONCE
        )
        self.client.publish(packet).result(30)

    def close(self) -> None:
        self.client.stop()
        self.stopped.wait(30)


def start_agent_on_clock(
    rig: LocalRig, overrides: dict[str, Any], clock: Callable[[], float]
) -> AgentService:
    """rig.start_agent(overrides), with the agent on `clock` (a ManualClock); the rig stops it."""
    service = AgentService(rig.agent_config(overrides), clock=clock)
    rig.services.append(service)
    service.start()
    assert service.wait_subscribed(30), f"the agent did not subscribe (broker log: {rig.broker.log_path})"
    return service


@pytest.fixture
def publisher(rig: LocalRig) -> Iterator[Publisher]:
    pub = Publisher(rig.broker.url)
    yield pub
    pub.close()


@contextmanager
def full_disk(directory: Path) -> Iterator[Path]:
    """A real full filesystem at `directory`: a 1 MiB tmpfs mounted there and filled (the tests run as root,
    as `make setup` does); unmounted afterwards whatever happens."""
    directory.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(directory)], check=True)
    try:
        fill(directory)
        yield directory
    finally:
        subprocess.run(["umount", "-l", str(directory)], check=False)


def fill(directory: Path) -> None:
    """Write a file in `directory` until its filesystem is full."""
    try:
        with (directory / "filler").open("wb") as fh:
            while True:
                fh.write(b"\0" * 4096)
                fh.flush()
    except OSError:
        pass  # full


def wait_for(predicate: Callable[[], Any], timeout: float, what: str, interval: float = 0.02) -> Any:
    """Poll until `predicate()` is truthy and return that value; AssertionError naming `what` on timeout
    (the rig's own wait, failing the test rather than the rig)."""
    return wait_until(predicate, timeout, what, interval, error=AssertionError)


def run_twin(
    args: Sequence[str], env: Mapping[str, str], cwd: Path | None = None, timeout: float = 180.0
) -> subprocess.CompletedProcess[str]:
    """`twin <args>` as a user runs it, in a process of its own, to its exit (its output captured)."""
    return subprocess.run(
        [sys.executable, "-m", "twin.cli", *args],
        check=False,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=dict(env),
        cwd=cwd,
    )


def copy_bundled_scene(directory: Path) -> Path:
    """The bundled SO-101 scene and arm copied into `directory`, their meshes linked (the MJCF's meshdir is
    relative to it), for a test that edits or moves the model; returns the scene's path."""
    from twin.robot.model import default_model_path

    bundled = default_model_path().parent
    for name in ("so101.xml", "scene.xml"):
        shutil.copy(bundled / name, directory / name)
    (directory / "meshes").symlink_to(bundled / "meshes")
    return directory / "scene.xml"


class ManualClock:
    """A monotonic clock that stands still until the test moves it, for the `clock=` an agent, its health and
    its pool take: ages, staleness and "behind" are then decided by the test, not by how long this shared
    machine took to run it. The agent stamps what it receives (`feed`, its broker connections) with it too.
    Starts at the real monotonic time, so stamps taken with time.monotonic() around it stay comparable. That
    start is the machine's uptime, so decimal steps meant to sum to a threshold exactly (5 x 0.4 s to a 2 s
    limit) land a hair under or over it by machine: step past thresholds with a margin (0.41 s)."""

    def __init__(self) -> None:
        self.now = time.monotonic()

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds


def messages_handled(state: AgentState) -> int:
    """AgentState.messages_handled: what a test waiting for N messages waits on."""
    return state.messages_handled()


def wait_handled(read_state: Callable[[], AgentState], count: int, timeout: float = 60.0) -> AgentState:
    """The agent's state once it has handled `count` messages (messages_handled); AssertionError on timeout.
    Twin poses (joints_rad, timestamp_ms) are published after a whole batch: wait on those themselves."""

    def handled() -> AgentState | None:
        state = read_state()
        return state if messages_handled(state) >= count else None

    return wait_for(handled, timeout, f"the agent to handle {count} messages")


def http_get(url: str, timeout: float = 30.0) -> tuple[int, str, bytes]:
    """(status, content type, body) of a GET, 4xx/5xx included. The timeout is for a wedged server, not a
    slow one: an agent answers in milliseconds, but this machine may be busy with other test runs."""
    try:
        with urllib.request.urlopen(url, timeout=timeout) as resp:
            return resp.status, resp.headers.get("Content-Type", ""), resp.read()
    except urllib.error.HTTPError as err:
        return err.code, err.headers.get("Content-Type", ""), err.read()


def get_state(base_url: str) -> AgentState:
    """GET /state, parsed into the agent's types (so every test also checks the JSON round trip)."""
    status, _, body = http_get(base_url + "/state")
    assert status == 200, body
    return AgentState.from_json(body)


def get_health(base_url: str) -> tuple[int, dict[str, Any]]:
    status, _, body = http_get(base_url + "/healthz")
    return status, json.loads(body)


def device_state(base_url: str, device: str) -> DeviceState:
    return get_state(base_url).devices[device]


def get_metrics(base_url: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """GET /metrics parsed by prometheus_client's own parser: {(sample name, sorted labels): value}."""
    status, _, body = http_get(base_url + "/metrics")
    assert status == 200
    return parse_metrics(body.decode())


def parse_metrics(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    samples = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            samples[(sample.name, tuple(sorted(sample.labels.items())))] = sample.value
    return samples


def metric(samples: dict[tuple[str, tuple[tuple[str, str], ...]], float], name: str, **labels: str) -> float:
    """One sample's value; KeyError naming it when absent."""
    key = (name, tuple(sorted(labels.items())))
    if key not in samples:
        raise KeyError(f"no sample {name}{labels} in /metrics")
    return samples[key]


def unbrokered_agent(tmp_path: Path, workers: int = 2, **overrides: Any) -> AgentService:
    """A started AgentService fed only through `feed` (its broker, NO_BROKER, never answers), ticks telemetry,
    its alarms kept in tmp_path/state.json, `workers` worker processes (1: the mirror in-process). `overrides`
    are config keys ({"twin.events_file": ...}). The caller stops it."""
    config = load_config(
        None,
        {
            "broker.url": NO_BROKER,
            "http.listen": "127.0.0.1:0",
            "telemetry.units": "ticks",
            "twin.state_file": str(tmp_path / "state.json"),
            **overrides,
        },
    )
    agent = AgentService(config, workers=workers)
    agent.start()
    return agent


def one_arm_agent(sinks: Sequence[Any] = (), clock: Any = None) -> AgentService:
    """A started in-process AgentService of arm-001 in ticks, on no broker (fed with `service.feed`), with
    `sinks` and, when given, on `clock` (a ManualClock); the caller stops it."""
    config = load_config(
        None,
        {
            "broker.url": NO_BROKER,
            "http.listen": "127.0.0.1:0",
            "telemetry.devices": ["arm-001"],
            "telemetry.units": "ticks",
        },
    )
    service = (
        AgentService(config, sinks=sinks) if clock is None else AgentService(config, sinks=sinks, clock=clock)
    )
    service.start()
    return service


@contextmanager
def fed_agent(
    messages: int = 12, *, sinks: Sequence[Any] = (), workers: int = 1, **overrides: Any
) -> Iterator[AgentService]:
    """A started AgentService fed through `feed` (no broker needed: the configured one never
    answers, so the state also shows a disconnected broker): arm-001 mirrored from ticks telemetry with one
    rejected message, arm-002 configured but never heard from, and garbage on an unknown device.
    `overrides` are config keys ({"twin.record_dir": ...}); `workers` > 1 mirrors in worker processes."""
    config = load_config(
        None,
        {
            "broker.url": NO_BROKER,
            "http.listen": "127.0.0.1:0",
            "telemetry.devices": ["arm-001", "arm-002"],
            "telemetry.units": "ticks",
            **overrides,
        },
    )
    service = AgentService(config, sinks=sinks, workers=workers)
    service.start()
    try:
        rng = random.Random(5)
        t0 = int(time.time() * 1000)
        for i in range(messages):
            payload = encode(make_payload("arm-001", 0.1 * i, "ticks", rng, timestamp_ms=t0 + 100 * i))
            service.feed("dt/lerobot/arm-001/telemetry", payload)
            wait_for(
                lambda n=i + 1: service.state().devices["arm-001"].health.counters.received >= n,
                30,
                "the worker",
            )
        service.feed("dt/lerobot/arm-001/telemetry", b"{not json")
        service.feed("dt/lerobot/ghost/telemetry", b"\xff")
        # Not worker.processed, which counts a message when the worker takes it, before its rejection is.
        wait_handled(service.state, messages + 2)
        yield service
    finally:
        service.stop()


# --- a real headless browser (Debian's chromium, driven by Playwright; no browser is ever downloaded) -------

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")


def _loopback_only(route: Any) -> None:
    # Tests talk to loopback only; the page may not reach out (the Rerun viewer tries to, and gets refused).
    url = route.request.url
    if url.startswith(("data:", "blob:")) or (urlsplit(url).hostname or "") in LOOPBACK_HOSTS:
        route.continue_()
    else:
        route.abort()


@pytest.fixture
def chromium_page(tmp_path: Path) -> Iterator[Any]:
    """A Playwright page in a fresh headless chromium profile that can reach loopback addresses only."""
    from playwright.sync_api import sync_playwright

    if not CHROMIUM.is_file():
        pytest.fail(f"{CHROMIUM} is missing; `make setup` installs Debian's chromium for the browser tests")

    with sync_playwright() as pw:
        context = pw.chromium.launch_persistent_context(
            str(tmp_path / "chromium-profile"),
            executable_path=str(CHROMIUM),
            headless=True,
            args=CHROMIUM_FLAGS,
            viewport={"width": 1024, "height": 640},
        )
        try:
            context.route("**/*", _loopback_only)
            yield context.pages[0] if context.pages else context.new_page()
        finally:
            context.close()


# --- Rerun recordings, read back with Rerun's own dataframe API -----------------------------------------


def read_rrd(path: Path) -> tuple[Any, Any]:
    """A .rrd's temporal (`edge_time`) and static data as Arrow tables, through a loopback Rerun server."""
    import rerun as rr

    with rr.server.Server(host="127.0.0.1", datasets={"twin": [str(path)]}) as server:
        client = server.client()  # keep it referenced while the DataFusion frames execute
        dataset = client.get_dataset("twin")
        temporal = dataset.reader(index="edge_time").to_arrow_table()
        static = dataset.reader(index=None).to_arrow_table()
    return temporal, static


def signal_and_await_restart(shard: Any, signum: int = signal.SIGKILL, timeout: float = 60.0) -> int:
    """Send `signum` to a WorkerShard's worker process and wait until the one started again runs (its first
    restart); the pid signalled."""
    victim = int(shard.pid)
    os.kill(victim, signum)
    wait_for(
        lambda: shard.restarts == 1 and shard.answering and shard.pid != victim,
        timeout,
        "the worker to run again",
        interval=0.1,
    )
    return victim
