"""`twin demo`: the whole pipeline on one machine, a servo that overheats, then the evidence on disk.

The local rig (twin.rig.local): a private mosquitto on a free loopback port, the edge simulator publishing
the edge's mock motion with physical servos (twin.edge.servo_physics), and the agent service (subscriber,
decoder, MuJoCo twin, alarms, health, HTTP and console, USD recording) run in this process for a set time.
The caller gets a status snapshot about four times a second and a note for each step of the story.

The story: the first arm lifts a payload too heavy for it (STORY_PAYLOAD_KG at the gripper tip) through the
mock motion, so its shoulder_lift servo works near and past its overload line (the agent's overload warning
comes and goes from the first seconds) and heats, its thermal model run STORY_SPEEDUP times faster than the
clock so that what takes a real servo minutes happens in the run: the agent raises the over-temperature
warning (60 C) after about 15 s and the critical alarm (65 C) after about 25 s. The other arms carry nothing
and stay cool. When the first of the two heat alarms is raised, the console's Fleet page and the hot arm's
page are photographed in headless Chromium (twin.rig.console_shots); without Chromium or Playwright the demo
says so and goes on without the two pictures.

Afterwards the output directory holds:
  twin.png    the twin's pose: written as soon as the first arm is mirrored, then again with its final pose,
              framed as the GIF is
  twin.gif    a ~30-frame animation of the run (first device) ending on its final pose, rendered offscreen
  console-fleet.png, console-arm.png  the operator console while the hot servo's alarm is up
  session-*.usda  the agent's USD session recording
  twin.rrd    the fleet as a Rerun recording (`.venv/bin/rerun out/demo/twin.rrd` opens it; docs/web.md)
  stats.json  what was sent, received, rejected (by reason), latencies, per-device health, the story
  history/    the agent's telemetry history (Delta Lake tables, docs/history.md)
  history.png the first device's joint angles, temperature, load and current, drawn from that history
Everything started here is stopped in `finally`, also on Ctrl-C / SIGTERM (the caller sets `stop`).
docs/viewer.md explains stats.json.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from twin.core.health import DeviceStatus
from twin.edge.payload import device_ids
from twin.edge.servo_physics import SERVO_MODES, PhysicalServoConfig
from twin.output.rerun_settings import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT
from twin.rig.console_shots import CHROMIUM, ConsoleShotError, console_screenshots, missing_for_shots
from twin.service.events import DEFAULT_CAPACITY as EVENTS_KEPT
from twin.service.events import Event, EventKind, EventQuery
from twin.service.state import AgentState, DeviceState

log = logging.getLogger(__name__)

# Files this module writes into the output directory; earlier runs' copies are removed first so the directory
# always describes one run. Nothing else in the directory is touched: of the USD session recordings there,
# only those earlier runs made are the demo's (_demo_recordings; an agent of the user's may record into the
# same directory: its twin.record_dir).
OUTPUT_PATTERNS = (
    "twin.png",
    "twin.gif",
    "twin.rrd",
    "history.png",
    "console-fleet.png",
    "console-arm.png",
)
HISTORY_DIR = "history"
# Left in the history directory a run makes, and written again once its agent stopped: the next run replaces
# only a history whose commits are all older than it (or than an earlier run's stats.json, from before the
# mark), never one an agent of the user's wrote there (`twin run --history out/history`, then `twin demo`).
HISTORY_MARK = ".twin-demo"
RRD_NAME = "twin.rrd"
STATUS_INTERVAL_S = 0.25
_T = TypeVar("_T")
# The final twin.png: twice the GIF's size, the same shape, so it frames the arm as the GIF does.
PNG_SIZE = (640, 480)
# How long the end of a run waits for the last published messages to be counted by the agent.
SETTLE_TIMEOUT_S = 10.0
# How long past the stale time (health.stale_periods expected periods) the end of a run waits for every arm to
# be reported STALE, stats.json's status_after_stop: on a busy machine the agent may see the silence late.
AFTER_STOP_GRACE_S = 5.0

# The story (module doc). 220 g at the tip keeps the shoulder at three quarters of its stall torque on average
# through the mock motion (at stall a quarter of the time); at 80x its thermal time constant (9.5 minutes,
# twin.robot.sts3215) is 7 s, so the servo passes 60 C after about 15 s and 65 C after about 25 s, and peaks
# just below the servo's 70 C cut-out, which the simulator does not model (docs/servo-health.md, "Physical
# servos", has the figures; tests/test_servo_physics.py checks this timeline).
STORY_JOINT = "shoulder_lift"
STORY_PAYLOAD_KG = 0.22
STORY_SPEEDUP = 80.0
# The story's alarms, each recorded the first time the agent raises it: the overload warning the payload
# raises from the first seconds (it comes and goes), then the two of the heat. The console pictures wait for
# the heat's. They are read from the agent's events, not its list of alarms: a look at the list every
# STATUS_INTERVAL_S (longer while the first picture renders) misses an alarm raised and cleared in between
# when it does not latch or a person acknowledged it, and dates the one it finds latched by the look.
STORY_ALARMS = ("overload", "over_temperature", "over_temperature_critical")
HEAT_ALARMS = frozenset({"over_temperature", "over_temperature_critical"})
# How long the run may go on past its seconds for the console pictures to finish.
PICTURES_GRACE_S = 90.0


class DemoError(RuntimeError):
    """The demo could not run or produced nothing; the message says what failed and what to do."""


@dataclass(frozen=True)
class DemoConfig:
    seconds: float = 30.0
    out_dir: Path = Path("out/demo")
    variant: str = "ticks"  # ticks | degrees (the two edge payload variants)
    devices: int = 6
    rate_hz: float = 10.0
    gif_frames: int = 30
    gif_size: tuple[int, int] = (320, 240)
    # The Rerun sink is on in the demo: it writes twin.rrd, and with rerun_serve also serves the web viewer.
    rerun: bool = True
    rerun_serve: bool = False
    # physical: the story (module doc); mock: the edge mock mode's random servo readings, no story.
    servos: str = "physical"
    # The console pictures, taken with this browser.
    console: bool = True
    chromium: Path = CHROMIUM

    def __post_init__(self) -> None:
        if not 0 < self.seconds <= 3600:
            raise ValueError(f"--seconds {self.seconds} must be in (0, 3600]")
        if self.variant not in ("ticks", "degrees"):
            raise ValueError(f"--variant {self.variant!r} must be ticks or degrees")
        if not 1 <= self.devices <= 100:
            raise ValueError(f"--devices {self.devices} must be between 1 and 100")
        if not 0 < self.rate_hz <= 1000:
            raise ValueError(f"--rate {self.rate_hz} must be in (0, 1000] Hz")
        if self.servos not in SERVO_MODES:
            raise ValueError(f"--servos {self.servos!r} must be one of {', '.join(SERVO_MODES)}")


@dataclass
class DemoStatus:
    """One live snapshot for the status line."""

    elapsed_s: float
    sent: int
    received: int
    rejected: int
    rate_hz: float
    latency_p50_s: float | None
    latency_p99_s: float | None
    statuses: dict[str, str] = field(default_factory=dict)


@dataclass
class _Totals:
    """Message counts summed over the fleet (and the untracked rejections)."""

    received: int = 0
    decoded: int = 0
    applied: int = 0
    ignored_stale: int = 0
    overwritten: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    rate_hz: float = 0.0

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


def _totals(state: AgentState) -> _Totals:
    totals = _Totals()
    for d in state.devices.values():
        c = d.health.counters
        totals.received += c.received
        totals.decoded += c.decoded
        totals.applied += c.applied
        totals.ignored_stale += c.ignored_stale
        totals.overwritten += c.overwritten
        totals.rate_hz += d.health.rate_hz or 0.0
        for reason, n in c.rejected.items():
            totals.rejected[reason] = totals.rejected.get(reason, 0) + n
    for reason, n in state.untracked_rejected.items():
        totals.rejected[reason] = totals.rejected.get(reason, 0) + n
    return totals


def _worst(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return max(known) if known else None


def _edge_latency(state: AgentState, pct: str) -> float | None:
    return _worst([getattr(d.health.edge_clock_latency_s, pct) for d in state.devices.values()])


def _internal_latency(state: AgentState, pct: str) -> float | None:
    return _worst([getattr(d.health.internal_latency_s, pct) for d in state.devices.values()])


def _demo_recordings(out_dir: Path) -> list[Path]:
    """The USD session recordings earlier runs made: those the mark lists (written after every run, also one
    that failed before its stats.json) and the one stats.json names (files.usd: a run of the version before,
    whose mark listed none). Plain session file names in `out_dir` only: nothing else is the demo's."""
    names: list[object] = []
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        names.append(json.loads((out_dir / "stats.json").read_text())["files"]["usd"])
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        names.extend(json.loads((out_dir / HISTORY_DIR / HISTORY_MARK).read_text())["recordings"])
    plain = {n for n in names if isinstance(n, str) and Path(n).name == n and n.startswith("session-")}
    return [out_dir / name for name in sorted(plain)]


def _written_by_demo(out_dir: Path, history: Path) -> bool:
    """Whether the history folder is the demo's to replace: nothing in it but the mark, or tables none of
    whose files is newer than the newest of the mark (written again once a run's agent stopped) and the
    run's stats.json (written after it; an earlier version wrote its mark at the start only). A mark or a
    stats.json alone would let a later agent's history there (`twin run --history out/history`) be taken,
    and a folder with no table in it is no history the demo wrote."""
    files = []
    for path in history.rglob("*"):
        with contextlib.suppress(OSError):  # gone meanwhile: not there to lose
            if path.name != HISTORY_MARK and path.is_file():
                files.append(path.stat().st_mtime_ns)
    if not files:
        return True  # nothing to lose (a run that failed before its first commit)
    witnesses = []
    for witness in (history / HISTORY_MARK, out_dir / "stats.json"):
        with contextlib.suppress(OSError):
            witnesses.append(witness.stat().st_mtime_ns)
    if not witnesses or not any(history.rglob("_delta_log")):
        return False
    return max(files) <= max(witnesses)


def _mark_history(history: Path, recordings: Sequence[str] = ()) -> None:
    """Written at a run's start, and again once its agent stopped (every commit of the run older), with the
    recordings the run made, for the next run to remove even if this one never writes its stats.json."""
    mark = {"made_by": "twin demo; the next run replaces this directory", "recordings": list(recordings)}
    (history / HISTORY_MARK).write_text(json.dumps(mark) + "\n")


def _clear_outputs(out_dir: Path) -> None:
    history = out_dir / HISTORY_DIR
    # Checked before anything is removed: a refused run leaves the directory as it was.
    if history.exists() and not history.is_dir():
        raise DemoError(f"{history} is a file, where the demo writes its history; give another --out")
    if history.exists() and not _written_by_demo(out_dir, history):
        raise DemoError(
            f"{history} holds a history the demo did not write, and a run would replace it; "
            "give another --out, or move that directory away first"
        )
    for pattern in OUTPUT_PATTERNS:
        for path in out_dir.glob(pattern):
            path.unlink()
    for recording in _demo_recordings(out_dir):
        recording.unlink(missing_ok=True)
    # A new table per run: appending to the last run's would mix two runs in one history.
    shutil.rmtree(history, ignore_errors=True)
    try:
        history.mkdir()
    except FileExistsError as exc:  # rmtree left some of it (a file it may not remove)
        raise DemoError(f"could not remove the last run's history {history}; remove it by hand") from exc
    _mark_history(history)
    # Last: until the history is gone, it still says whose the history was.
    (out_dir / "stats.json").unlink(missing_ok=True)


@dataclass
class _Story:
    """What the run showed of the hot servo: its alarms as they were raised, and its peak temperature."""

    device: str
    joint: str
    alarms: list[dict[str, Any]] = field(default_factory=list)
    peak_temperature_c: float | None = None
    # The id of the last of the agent's events read: the next read asks for those after it.
    events_read: int = 0

    @property
    def heated(self) -> bool:
        """Whether an alarm of the servo's heat is up: the moment for the console pictures."""
        return any(a["kind"] in HEAT_ALARMS for a in self.alarms)

    def as_dict(self) -> dict[str, Any]:
        return {
            "device": self.device,
            "joint": self.joint,
            "payload_kg": STORY_PAYLOAD_KG,
            "thermal_speedup": STORY_SPEEDUP,
            "alarms": self.alarms,
            "peak_temperature_c": self.peak_temperature_c,
        }


class _ConsolePictures:
    """The two console pictures, taken on a thread of their own while the run goes on (the pages need a live
    agent and live data); `result` is the stats' "console" entry once done."""

    def __init__(
        self, config: DemoConfig, url: str, device: str, out_dir: Path, alarms_now: Callable[[], list[str]]
    ) -> None:
        self._config = config
        self._url = url
        self._device = device
        self._out_dir = out_dir
        self._alarms_now = alarms_now
        self._thread: threading.Thread | None = None
        self.result: dict[str, Any] = {"taken": False, "skipped": None}
        self.shots: Any = None

    @property
    def started(self) -> bool:
        return self._thread is not None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._take, name="demo-console-shots", daemon=True)
        self._thread.start()

    def _take(self) -> None:
        try:
            self.shots = console_screenshots(
                self._url, self._out_dir, device=self._device, chromium=self._config.chromium
            )
        except ConsoleShotError as exc:
            self.result["skipped"] = str(exc)
            return
        # What the arm's page showed: the device's alarms that were up when its picture was taken.
        self.result.update(
            taken=True, console_errors=self.shots.console_errors, alarms_at_pictures=self._alarms_now()
        )

    def join(self, timeout: float) -> None:
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                self.result["skipped"] = f"the pictures were not done {timeout:.0f} s after the run"


@dataclass
class _Run:
    """What watching the run collected: GIF frames, each arm's status while the edge still published, the
    story and the console pictures."""

    frames: list[dict[str, float]] = field(default_factory=list)
    running_statuses: dict[str, str] = field(default_factory=dict)
    after_stop_statuses: dict[str, str] = field(default_factory=dict)
    started: float = 0.0
    # The start on the wall clock, which the agent's events are stamped with (raised_after_s).
    started_wall: float = 0.0
    final_state: AgentState | None = None
    report: Any = None
    first_png: Path | None = None
    story: _Story | None = None
    pictures: _ConsolePictures | None = None
    console: dict[str, Any] = field(default_factory=lambda: {"taken": False, "skipped": None})


def run_demo(
    config: DemoConfig,
    *,
    on_status: Callable[[DemoStatus], None] | None = None,
    stop: threading.Event | None = None,
    on_viewer: Callable[[str], None] | None = None,
    on_note: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the demo; returns the stats written to stats.json. Raises DemoError on any failure.

    `on_viewer(url)` is called with the web viewer's page when `config.rerun_serve` serves one, `on_note`
    with a line for each step of the story (an alarm raised, a picture written or skipped).

    The steps: start the local rig (broker + agent recording into the output folder), publish with the edge
    simulator while watching the agent's state and taking the pictures, then write stats.json, the PNG, the
    GIF (the recording is closed, with its final save, when the rig stops the agent).
    """
    stop = stop or threading.Event()
    note = on_note or (lambda line: log.info("%s", line))
    out_dir = Path(config.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    _clear_outputs(out_dir)
    before = {path.name for path in out_dir.glob("session-*.usda")}
    devices = device_ids(config.devices)
    run = _prepared_run(config, devices, note)
    try:
        broker, service = _run_on_rig(
            config, devices, out_dir, run, on_status=on_status, on_viewer=on_viewer, note=note, stop=stop
        )
    finally:
        # The agent has stopped, its history's last commit made: the next run finds the mark newer. (A folder
        # removed meanwhile is no longer the demo's to mark.)
        made = sorted(path.name for path in out_dir.glob("session-*.usda") if path.name not in before)
        with contextlib.suppress(OSError):
            _mark_history(out_dir / HISTORY_DIR, made)
    stats, final = _checked_stats(config, run, broker, service, interrupted=stop.is_set())
    # History first: stats.json, written with the other outputs, says what the table holds.
    _write_history_outputs(devices, stats, out_dir)
    _write_outputs(
        config=config, state=final, service=service, run=run, devices=devices, stats=stats, out_dir=out_dir
    )
    return stats


def _prepared_run(config: DemoConfig, devices: list[str], note: Callable[[str], None]) -> _Run:
    """The run's record before it starts: the story's arm and joint, and whether the console pictures can
    be taken here (the note says why not)."""
    run = _Run(started=time.monotonic())
    if config.servos == "physical":
        run.story = _Story(devices[0], STORY_JOINT)
    if config.console:
        missing = missing_for_shots(config.chromium)
        if missing:
            run.console["skipped"] = missing
            note(f"console pictures skipped: {missing}")
    return run


def _run_on_rig(
    config: DemoConfig,
    devices: list[str],
    out_dir: Path,
    run: _Run,
    *,
    on_status: Callable[[DemoStatus], None] | None,
    on_viewer: Callable[[str], None] | None,
    note: Callable[[str], None],
    stop: threading.Event,
) -> tuple[dict[str, Any], Any]:
    """The local rig (broker and agent) while the edge simulator publishes and `_watch` follows the run into
    `run`; returns (the broker's URL and pid, the stopped agent's service). DemoError when a part fails."""
    from twin.rig.local import LocalRig, RigError  # noqa: PLC0415 - MuJoCo, USD and awscrt load here

    try:
        with LocalRig() as rig:
            broker = {"url": rig.broker.url, "pid": rig.broker.pid}
            service = _start_agent(rig, config, devices, out_dir, on_viewer)
            # The agent listens on a free port: the operator needs to be told where its console is.
            note(f"console at {service.http_url}/ while the demo runs")
            if config.console and run.console["skipped"] is None:
                run.pictures = _ConsolePictures(
                    config,
                    service.http_url,
                    devices[0],
                    out_dir,
                    lambda: [a.alarm_id for a in service.alarms() if a.device == devices[0]],
                )
            # Until stopped: the run lasts its seconds, and longer while the console pictures are taken.
            edge = rig.start_edge(
                devices, variant=config.variant, rate_hz=config.rate_hz, **_edge_options(config, devices)
            )
            run.started, run.started_wall = time.monotonic(), time.time()
            _watch(
                config=config,
                service=service,
                edge=edge,
                devices=devices,
                run=run,
                on_status=on_status,
                note=note,
                stop=stop,
                out_dir=out_dir,
            )
            run.after_stop_statuses = _statuses_after_stop(service)
    except RigError as exc:
        raise DemoError(str(exc)) from exc
    except (ConnectionError, ValueError) as exc:  # the edge simulator's failure, re-raised by join()
        raise DemoError(f"the edge simulator failed: {exc}") from exc
    if run.story is not None:
        # The alarms raised in the run's last half second: the agent's stop collected their events.
        _story_alarms(run.story, service, run.started_wall, note)
    return broker, service


def _edge_options(config: DemoConfig, devices: list[str]) -> dict[str, Any]:
    """The edge simulator's servo settings: physical servos for every arm, the story's payload and thermal
    speed-up on the first."""
    if config.servos != "physical":
        return {}
    hot = PhysicalServoConfig(payload_kg=STORY_PAYLOAD_KG, speedup={STORY_JOINT: STORY_SPEEDUP})
    return {"servos": "physical", "physical_by_device": {devices[0]: hot}}


def _checked_stats(
    config: DemoConfig, run: _Run, broker: dict[str, Any], service: Any, *, interrupted: bool
) -> tuple[dict[str, Any], AgentState]:
    """(stats.json's content, the final state); DemoError when there is no state or no telemetry arrived."""
    duration = time.monotonic() - run.started
    final = run.final_state
    if final is None:
        raise DemoError("the demo ended before the agent reported any state")
    totals = _totals(final)
    if totals.received == 0:
        raise DemoError(
            f"the agent received no telemetry in {duration:.1f} s although the edge simulator published "
            f"{run.report.published} messages to {broker['url']}: check the broker log and the agent log "
            "above"
        )
    stats = _stats(
        config=config,
        state=final,
        run=run,
        totals=totals,
        duration=duration,
        interrupted=interrupted,
        broker=broker,
        service=service,
    )
    return stats, final


def _agent_overrides(config: DemoConfig, devices: list[str], out_dir: Path) -> dict[str, Any]:
    return {
        "telemetry.devices": devices,
        "telemetry.units": config.variant,
        "twin.record_dir": str(out_dir),
        "twin.record_format": "usda",
        "health.expected_rate_hz": config.rate_hz,
        # A commit every 2 s, so even a short demo leaves a table of several versions.
        "history.uri": str(out_dir / HISTORY_DIR),
        "history.commit_every_s": 2.0,
        "rerun.save": str(out_dir / RRD_NAME) if config.rerun else "",
        "rerun.serve": config.rerun_serve,
        # Rerun's own ports when they are free, else any: a demo has no flag to choose them, and one that
        # stopped on a viewer already open left a cut twin.rrd (a walk). The URL printed is the one it serves.
        **(
            {
                "rerun.grpc_port": _free_or_any(DEFAULT_GRPC_PORT),
                "rerun.web_port": _free_or_any(DEFAULT_WEB_PORT),
            }
            if config.rerun_serve
            else {}
        ),
    }


def _free_or_any(port: int) -> int:
    """`port` when nothing listens on it on the loopback, else 0 (the sink then takes any free one)."""
    from twin.output.rerun_sink import RerunSinkError, bindable_port  # noqa: PLC0415 - rerun loads here

    try:
        return bindable_port(port, "rerun.grpc_port")
    except RerunSinkError:
        return 0


def _start_agent(
    rig: Any, config: DemoConfig, devices: list[str], out_dir: Path, on_viewer: Callable[[str], None] | None
) -> Any:
    """The agent with the config's extra sinks (the Rerun stream); they close when the rig stops it."""
    from twin.service.outputs import close_sinks, configured_sinks  # noqa: PLC0415 - rerun loads here

    agent_config = rig.agent_config(_agent_overrides(config, devices, out_dir))
    try:
        sinks = configured_sinks(agent_config)
    except OSError as exc:
        raise DemoError(f"the Rerun sink cannot start: {exc}") from exc
    owners = len(rig.services)
    try:
        service = rig.start_agent(agent_config, sinks=sinks)
    except Exception:
        if len(rig.services) == owners:  # no service took the sinks over (its stop() would close them)
            close_sinks(sinks)
        raise
    for sink in sinks:
        url = getattr(sink, "viewer_url", None)
        if url and on_viewer is not None:
            on_viewer(url)
    return service


def _watch(
    *,
    config: DemoConfig,
    service: Any,
    edge: Any,
    devices: list[str],
    run: _Run,
    on_status: Callable[[DemoStatus], None] | None,
    note: Callable[[str], None],
    stop: threading.Event,
    out_dir: Path,
) -> None:
    """Poll the agent while the edge publishes: status line, the first picture, GIF frames, the story and
    the console pictures, then the final state. The edge publishes for `config.seconds`, and on while the
    console pictures are taken (at most PICTURES_GRACE_S more)."""
    frame_period = config.seconds / max(1, config.gif_frames)
    next_frame = run.started
    end = run.started + config.seconds
    pictures = run.pictures
    while edge.alive and not stop.is_set():
        stop.wait(STATUS_INTERVAL_S)
        now = time.monotonic()
        state = service.state()
        run.running_statuses = {device: str(d.health.status) for device, d in state.devices.items()}
        if on_status is not None:
            on_status(_status(state, edge.report.published, now - run.started))
        first = state.devices.get(devices[0])
        if first is not None and first.joints_rad:
            if now >= next_frame:
                run.frames.append(dict(first.joints_rad))
                next_frame += frame_period
            if run.first_png is None:
                # The first picture as early as it can be: the twin's, while the run goes on.
                run.first_png = _render_twin(service, first.joints_rad, out_dir, f"{devices[0]}  first pose")
                note(f"picture: {run.first_png}")
        if run.story is not None:
            _follow_story(run.story, service, state, run.started_wall, note)
        # The pictures when the hot servo's alarm is up; a run without the story, or too short for it, at its
        # end.
        story_told = run.story is not None and run.story.heated
        if pictures is not None and not pictures.started and (story_told or now >= end):
            note(f"taking the console pictures of {devices[0]} (headless Chromium)")
            pictures.start()
        if now >= end and (pictures is None or not pictures.running or now >= end + PICTURES_GRACE_S):
            break
    edge.stop()
    run.report = edge.join(10.0)
    if pictures is not None:
        pictures.join(0.0 if stop.is_set() else 30.0)
        run.console = pictures.result if pictures.started else {"taken": False, "skipped": "interrupted"}
        if stop.is_set() and pictures.running:
            run.console = {"taken": False, "skipped": "interrupted while the pictures were taken"}
        if run.console["taken"]:
            note(f"pictures: {pictures.shots.fleet}, {pictures.shots.arm}")
        elif pictures.started:
            note(f"console pictures skipped: {run.console['skipped']}")
    run.final_state = _settled_state(service, run.report.published)
    if on_status is not None:
        on_status(_status(run.final_state, run.report.published, time.monotonic() - run.started))


def _poll(read: Callable[[], _T], done: Callable[[_T], bool], timeout_s: float) -> _T:
    """`read()` again every 50 ms until `done` holds for what it returned, or `timeout_s` has passed: then
    what it returned last (the end of a run reports what it saw rather than fail)."""
    deadline = time.monotonic() + timeout_s
    value = read()
    while not done(value) and time.monotonic() < deadline:
        time.sleep(0.05)
        value = read()
    return value


def _settled_state(service: Any, published: int) -> AgentState:
    """The agent's state once it has counted every published message (the last ones are still crossing the
    broker and the mirror when the edge stops), or after SETTLE_TIMEOUT_S if some never arrive."""
    state: AgentState = _poll(service.state, lambda s: s.messages_handled() >= published, SETTLE_TIMEOUT_S)
    return state


def _statuses_after_stop(service: Any) -> dict[str, str]:
    """Each arm's health once the agent has noticed that the edge went silent: polled until no arm is ONLINE
    (STALE after the stale time), or for at most AFTER_STOP_GRACE_S past that time, then as it is. The
    settled state comes too early for it: it is read as soon as the last message is counted, well inside the
    stale time, so every arm is still ONLINE there."""

    def statuses() -> dict[str, str]:
        return {device: str(d.health.status) for device, d in service.state().devices.items()}

    timeout_s = service.config.health.stale_after_s + AFTER_STOP_GRACE_S
    return _poll(statuses, lambda now: DeviceStatus.ONLINE not in now.values(), timeout_s)


def _follow_story(
    story: _Story, service: Any, state: AgentState, started_wall: float, note: Callable[[str], None]
) -> None:
    """Record the hot servo's temperature (as this look at the agent's state finds it), and each of its
    STORY_ALARMS the first time it was raised (_story_alarms)."""
    device = state.devices.get(story.device)
    servo = None if device is None or device.servos is None else device.servos.get(story.joint)
    if servo is not None and servo.temperature_c is not None:
        story.peak_temperature_c = max(story.peak_temperature_c or servo.temperature_c, servo.temperature_c)
    _story_alarms(story, service, started_wall, note)


def _story_alarms(story: _Story, service: Any, started_wall: float, note: Callable[[str], None]) -> None:
    """Each of the story's STORY_ALARMS the first time its raise is among the agent's events since the last
    read, dated by the event (seconds after `started_wall`). The agent collects its mirrors' events every
    half second and at its stop, and keeps the newest EVENTS_KEPT: a read after each look loses none."""
    query = EventQuery(
        device=story.device,
        kinds=frozenset({EventKind.ALARM.value}),
        after_id=story.events_read,
        limit=EVENTS_KEPT,
    )
    events: list[Event] = service.events(query)
    if events:
        story.events_read = events[-1].id
    seen = {a["kind"] for a in story.alarms}
    for event in events:
        data = event.data
        if data.get("action") != "raised" or data.get("joint") != story.joint:
            continue
        kind = data.get("kind", "")
        if kind not in STORY_ALARMS or kind in seen:
            continue
        seen.add(kind)
        after_s = round(event.time - started_wall, 1)
        alarm_id, state, severity = data["alarm_id"], data["state"], data["severity"]
        story.alarms.append(
            {
                "alarm_id": alarm_id,
                "kind": kind,
                "severity": severity,
                "state": state,
                "raised_after_s": after_s,
                "message": data["text"],
            }
        )
        note(f"{after_s:5.1f}s  alarm {alarm_id} {state} ({severity}): {data['text']}")


def _render_twin(service: Any, joints: dict[str, float], out_dir: Path, text: str) -> Path:
    from twin.output.render import RenderError, render_png  # noqa: PLC0415

    try:
        return render_png(service.robot, joints, out_dir / "twin.png", text=text)
    except RenderError as exc:
        raise DemoError(f"rendering failed: {exc}") from exc


def _status(state: AgentState, sent: int, elapsed: float) -> DemoStatus:
    totals = _totals(state)
    return DemoStatus(
        elapsed_s=elapsed,
        sent=sent,
        received=totals.received,
        rejected=totals.rejected_total,
        rate_hz=totals.rate_hz,
        latency_p50_s=_edge_latency(state, "p50"),
        latency_p99_s=_edge_latency(state, "p99"),
        statuses={device: str(d.health.status) for device, d in state.devices.items()},
    )


def _device_stats(run: _Run, device: str, d: DeviceState) -> dict[str, Any]:
    return {
        # Health at the end of the publishing run, and once the agent noticed the edge stop (STALE).
        "status": run.running_statuses.get(device, str(d.health.status)),
        "status_after_stop": run.after_stop_statuses.get(device, str(d.health.status)),
        "received": d.health.counters.received,
        "applied": d.health.counters.applied,
        "rejected": dict(d.health.counters.rejected),
        "rate_hz": d.health.rate_hz,
        "end_to_end_latency_s": {
            "p50": d.health.edge_clock_latency_s.p50,
            "p99": d.health.edge_clock_latency_s.p99,
        },
        "internal_latency_s": {
            "p50": d.health.internal_latency_s.p50,
            "p99": d.health.internal_latency_s.p99,
        },
        # Estimated from the gaps in the edge timestamps (docs/agent.md, Loss).
        "loss": {"lost": d.loss.lost, "loss_ratio": d.loss.loss_ratio, "losing": d.loss.losing},
        "joints_rad": d.joints_rad,
    }


def _message_stats(report: Any, totals: _Totals, state: AgentState, devices: int) -> dict[str, Any]:
    return {
        "sent": report.published,
        "generated": report.generated,
        # Samples the edge never made: it skips ahead when it falls over a second behind its schedule (an
        # overloaded machine), which leaves gaps in the timestamps that the agent's estimate counts as lost.
        "edge_skipped": report.skipped_ticks * devices,
        "publish_failures": report.publish_failures,
        "received": totals.received,
        "decoded": totals.decoded,
        "applied": totals.applied,
        "ignored_stale": totals.ignored_stale,
        "overwritten": totals.overwritten,
        "rejected": totals.rejected_total,
        "rejected_by_reason": totals.rejected,
        "lost": max(0, report.published - totals.received),
        # The agent's own estimate of what never arrived, from the edge timestamps alone (it does not know
        # `sent`): on this loopback broker at most `edge_skipped`, on IoT Core it shows quota discards too.
        "estimated_lost": state.agent.loss.lost,
        "estimated_loss_ratio": state.agent.loss.loss_ratio,
    }


def _stats(
    *,
    config: DemoConfig,
    state: AgentState,
    run: _Run,
    totals: _Totals,
    duration: float,
    interrupted: bool,
    broker: dict[str, Any],
    service: Any,
) -> dict[str, Any]:
    per_device = {device: _device_stats(run, device, d) for device, d in state.devices.items()}
    return {
        "duration_s": round(duration, 3),
        "interrupted": interrupted,
        "variant": config.variant,
        "rate_hz": config.rate_hz,
        "devices": sorted(state.devices),
        "messages": _message_stats(run.report, totals, state, config.devices),
        # Percentiles over the agent's health window (the last seconds of the run), worst device. The edge
        # simulator stamps messages with this host's clock, so end-to-end latency here has no skew in it.
        "latency_s": {
            "end_to_end": {"p50": _edge_latency(state, "p50"), "p99": _edge_latency(state, "p99")},
            "internal": {"p50": _internal_latency(state, "p50"), "p99": _internal_latency(state, "p99")},
            "window_s": service.config.health.window_s,
        },
        "per_device": per_device,
        "broker": broker,
        "servos": config.servos,
        # The hot servo's alarms as they were raised (null without the story: --servos mock).
        "story": None if run.story is None else run.story.as_dict(),
        # The console pictures: taken, or why not (skipped).
        "console": run.console,
        "files": {},
    }


def _write_outputs(
    *,
    config: DemoConfig,
    state: AgentState,
    service: Any,
    run: _Run,
    devices: list[str],
    stats: dict[str, Any],
    out_dir: Path,
) -> None:
    from twin.output.render import RenderError, framing_camera, render_png  # noqa: PLC0415

    first = state.devices.get(devices[0])
    joints = first.joints_rad if first is not None else None
    if not joints:
        raise DemoError(f"device {devices[0]} was never mirrored: nothing to render (see stats above)")
    files: dict[str, str] = {}
    status = stats["per_device"][devices[0]]["status"]
    # The GIF ends on the final pose, and the final picture is framed as the GIF is, over every pose of the
    # run. Framed on its own pose alone (render_png's default, which the first picture keeps: it has no other
    # pose) the arm fills the picture to the framing's 8 % margin from a camera about a third of a metre
    # away: a close-up whose near parts loom, with less room at its top than the label takes.
    frames = [*run.frames, dict(joints)]
    width, height = PNG_SIZE
    try:
        png = render_png(
            service.robot,
            joints,
            out_dir / "twin.png",
            width=width,
            height=height,
            camera=framing_camera(service.robot, frames, aspect=width / height),
            text=f"{devices[0]}  {status}  after {stats['duration_s']:.0f} s",
        )
        files["png"] = png.name
        if len(run.frames) >= 2:
            files["gif"] = _write_gif(service.robot, frames, out_dir / "twin.gif", config.gif_size).name
    except RenderError as exc:
        raise DemoError(f"rendering failed: {exc}") from exc
    recording = service.recording_path
    if recording is None or not Path(recording).is_file():
        raise DemoError(f"the agent did not leave its USD session recording in {out_dir}")
    files["usd"] = Path(recording).name
    if config.rerun:
        rrd = out_dir / RRD_NAME
        if not rrd.is_file() or rrd.stat().st_size == 0:
            raise DemoError(f"the Rerun sink did not leave {rrd} (see the log above)")
        files["rrd"] = rrd.name
    if run.console.get("taken"):
        files["console_fleet"] = "console-fleet.png"
        files["console_arm"] = "console-arm.png"
    stats["files"] = files
    (out_dir / "stats.json").write_text(json.dumps(stats, indent=2, sort_keys=False) + "\n")


def _write_history_outputs(devices: list[str], stats: dict[str, Any], out_dir: Path) -> None:
    """What the history holds after the agent stopped (its last commit included), and its plot."""
    from twin.ops.history import HistoryReader, HistoryReadError, plot  # noqa: PLC0415

    reader = HistoryReader(str(out_dir / HISTORY_DIR))
    try:
        summary = reader.summary()
        result = plot(reader, devices[0], out_dir / "history.png")
    except HistoryReadError as exc:
        raise DemoError(f"the agent left no usable history in {out_dir / HISTORY_DIR}: {exc}") from exc
    stats["history"] = {
        "uri": HISTORY_DIR,
        "rows": {d.device_id: d.rows for d in summary},
        "rejected": reader.rejected_counts(),
        "plot": Path(result["path"]).name,
    }


def _write_gif(robot: Any, frames: list[dict[str, float]], path: Path, size: tuple[int, int]) -> Path:
    """An animated GIF of the mirrored poses, framed once over all of them so the view holds still."""
    from twin.output.render import render_gif  # noqa: PLC0415

    width, height = size
    return render_gif(robot, frames, path, width=width, height=height)
