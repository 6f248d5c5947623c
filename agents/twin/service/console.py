"""What the operator console's pages are sent: the fleet summary, one arm's update, sessions, page shells.

The fleet page of a 2,000-arm fleet must not receive 2,000 full device states (~3 kB each) every tick: it
gets one row per arm with what a card shows (status, last seen, rate, loss, worst alarm, hottest servo), as
arrays under one list of column names, built once per tick from the state every client shares
(`fleet_summary`), with the notices a card cannot show (a subscription the broker refuses) and what the agent
listens on (for the page's word while no arm has been heard from), and the arms held by a refused calibration,
which have no row but whose alarms are raised (`HeldArm`). An arm's page
gets that arm's full state and its alarms (`arm_document`), read from its own mirror where the source can
(`ArmViewSource`), otherwise cut from the whole state (`arm_view_of`).

Sessions come from the telemetry history, which the service layer cannot read itself (the reader lives with
the tools, above it): whoever runs the agent hands the HTTP server a `SessionCatalog` (the CLI's
`twin run` does when `[history]` is on). The pages themselves are static files shipped in the package
(`console_ui/`, no CDN: the console works with no internet), one HTML shell filled per page.
"""

from __future__ import annotations

import html
import math
from collections import Counter
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from string import Template
from typing import NamedTuple, Protocol, runtime_checkable

import msgspec

from twin.core.alarms import WAITING_STATES
from twin.core.units import Units
from twin.robot import so101
from twin.service.calibrations import push_hint
from twin.service.events import Event, EventQuery
from twin.service.state import AgentState, AlarmInfo, DeviceState

__all__ = [
    "ASSETS",
    "FLEET_COLUMNS",
    "SESSION_FILE_KINDS",
    "AlarmHorizon",
    "ArmView",
    "ArmViewSource",
    "EventSource",
    "FleetRow",
    "FleetRowSource",
    "HeldArm",
    "HeldSource",
    "Listening",
    "ListeningSource",
    "NoticeSource",
    "SessionCatalog",
    "SessionInfo",
    "arm_document",
    "arm_view_of",
    "device_rows",
    "fleet_notes",
    "fleet_row",
    "fleet_rows",
    "fleet_summary",
    "held_arms",
    "not_found_page",
    "render_page",
    "rerun_viewer_url",
]

ASSETS = Path(__file__).with_name("console_ui")
PAGES = ("fleet", "arm", "sessions", "events")
FLEET_COLUMNS = (
    "device",
    "status",
    "last_seen",  # epoch seconds of the last message (null: never heard from)
    "rate_hz",
    "loss_pct",  # of the recent window (docs/agent.md, "Loss")
    "alarm_severity",  # the worst alarm that is not NORMAL: critical | warning | null
    "alarm_state",
    "alarm_kind",
    "alarm_joint",
    "hot_joint",  # the hottest servo and its temperature (null: no temperature sent)
    "hot_c",
    "rejected",  # messages rejected so far
    "uncalibrated",  # true: no LeRobot calibration while its units need one (docs/agent.md, "Calibration")
    "mirror",  # running | restarting: its worker process is started again, the row is its last checkpoint
    "unacknowledged",  # how many of its alarms wait for a person: ACTIVE, or LATCHED (cleared, unseen)
    "behind_s",  # how far its worker is behind its messages now (its status and rate: at its last sweep)
    # true: its newest calibration file in the store was refused, and it keeps the one it read before
    "calibration_refused",
)
# From how far behind its messages a worker makes the Fleet page say so (`behind_notice`): a second is ten
# messages of every arm waiting, and each pose on the page that old.
BEHIND_NOTICE_S = 1.0
# What a session offers to download, with the media type of each.
SESSION_FILE_KINDS: dict[str, tuple[str, str]] = {
    "csv": ("text/csv", "csv"),
    "parquet": ("application/vnd.apache.parquet", "parquet"),
    "png": ("image/png", "png"),
    "rrd": ("application/octet-stream", "rrd"),
    "usd": ("application/octet-stream", "usdc"),
}
_SEVERITY_RANK = {"critical": 2, "warning": 1}


@runtime_checkable
class EventSource(Protocol):
    """The optional part of the service surface behind the Events page."""

    def events(self, query: EventQuery) -> Sequence[Event]: ...


@runtime_checkable
class AlarmHorizon(Protocol):
    """The optional part of an EventSource that says from when the alarm events it holds are all there were
    (EventStore.alarms_complete_from; None: not known). The Sessions page counts the raises of the sessions
    that began then or later; without it, no count is known."""

    def alarms_complete_from(self) -> float | None: ...


class SessionInfo(msgspec.Struct, frozen=True):
    """One session: a device's continuous telemetry, from its first to its last message (epoch seconds)."""

    device: str
    start: float
    end: float
    messages: int
    status: str = "completed"  # active | completed
    # None: not known, the session began before the agent's alarm events are complete (docs/console.md).
    alarms_raised: int | None = 0

    @property
    def key(self) -> str:
        """How a page names the session: the device and its start in epoch milliseconds."""
        return f"{round(self.start * 1000)}"


@runtime_checkable
class SessionCatalog(Protocol):
    """Sessions from the telemetry history (implemented next to the history reader, in the tools)."""

    def sessions(self, gap_s: float) -> Sequence[SessionInfo]:
        """Every device's sessions: runs of messages no more than `gap_s` apart, newest first."""
        ...

    def session_file(self, session: SessionInfo, kind: str, directory: Path) -> Path:
        """Make the session's file of `kind` (a SESSION_FILE_KINDS key) in `directory`; returns its path.
        Raises ValueError when the history cannot give it (the message says why)."""
        ...


def _worst_alarms(alarms: Sequence[AlarmInfo]) -> dict[str, AlarmInfo]:
    """Each device's first alarm in the list (alarms come worst first)."""
    worst: dict[str, AlarmInfo] = {}
    for alarm in alarms:
        worst.setdefault(alarm.device, alarm)
    return worst


def _round(value: float | None, digits: int) -> float | None:
    if value is None or math.isnan(value):  # NaN is not JSON
        return None
    return round(value, digits)


class FleetRow(NamedTuple):
    """One arm on the Fleet page, in FLEET_COLUMNS order (small and picklable: a sharded agent's workers
    send their arms' rows, not their states)."""

    device: str
    status: str
    last_seen: float | None
    rate_hz: float | None
    loss_pct: float | None
    alarm_severity: str | None
    alarm_state: str | None
    alarm_kind: str | None
    alarm_joint: str | None
    hot_joint: str | None
    hot_c: float | None
    rejected: int
    uncalibrated: bool = False
    mirror: str = "running"
    unacknowledged: int = 0
    behind_s: float = 0.0
    calibration_refused: bool = False


@runtime_checkable
class FleetRowSource(Protocol):
    """The optional part of the service surface that reads the fleet's rows without its whole state."""

    def fleet_rows(self) -> list[FleetRow]: ...


class ForgetOffer(NamedTuple):
    """Whether the agent would forget an arm now, and if not, the words it would refuse it with: the Arm page
    shows this, not a rule of its own (its own, on another clock, offered forgets the agent refused)."""

    allowed: bool
    why: str = ""


class ArmView(NamedTuple):
    """What an arm page shows of one arm: its state (None: no mirror tracks it), its alarms that are not
    NORMAL, worst first, the agent's wall time, its calibration store and when it started (its counters
    count from then)."""

    time: float
    state: DeviceState | None
    alarms: Sequence[AlarmInfo]
    calibration_store: str
    started_at: float | None = None
    # Why the agent holds the arm: its calibration in the store was refused and it has none to keep (with
    # the whole fleet subscribed such an arm is never admitted, and its page read "not known").
    calibration_refused: str = ""
    # A held arm with no state: how many of its messages were refused, and how many seconds ago the last one
    # came (None: none heard, or an arm with a state, whose health says so).
    refused: tuple[int, float] | None = None
    # [health] expected_rate_hz, on which its loss estimate rests (None: not known): an edge at half of it
    # read as a steady 50 % loss, with nothing on the page to say which setting.
    expected_rate_hz: float | None = None
    # Whether the broker limits each connection (IoT Core's, or [broker] per_connection_limit): only then can
    # a connection's quota be why its gaps are all alike (a local broker has none, and the page said IoT
    # Core's did it).
    per_connection_limit: bool = False
    # Whether the agent would forget it now (None: not known), as its mirror decides a forget.
    forget: ForgetOffer | None = None


@runtime_checkable
class ArmViewSource(Protocol):
    """The optional part of the service surface that reads one arm without the whole fleet's state (which an
    arm page would otherwise build twice a second, in every worker, for one arm)."""

    def arm_view(self, device: str) -> ArmView: ...


@runtime_checkable
class NoticeSource(Protocol):
    """The optional part of the service surface that says what the fleet page must show above the arms: a
    problem no arm's card can show (a subscription the broker refuses, whose arms are never heard). `shown`:
    the arms the page has a card for, of which no notice need say they have none."""

    def notices(self, shown: Collection[str] = ()) -> list[str]: ...


class HeldArm(msgspec.Struct, frozen=True):
    """An arm held by its calibration file, refused at the agent's start, with no card: its messages are
    refused, yet its servos' alarms are raised. The Fleet page links it to its page, which lists them."""

    device: str
    why: str  # the refusal, as the arm's page and its notice say it
    unacknowledged: int = 0  # how many of its alarms wait for a person: ACTIVE, or LATCHED
    alarm_severity: str | None = None  # its worst alarm that is not NORMAL: critical | warning | null
    # How many of its messages were refused since the start, 0 for none heard: an arm publishing with no
    # twin, and one that is off, read the same.
    refused: int = 0


@runtime_checkable
class HeldSource(Protocol):
    """The optional part of the service surface that lists the arms held by a refused calibration, every
    one (the notices name five), but those in `shown`, which have a card."""

    def held_arms(self, shown: Collection[str] = ()) -> list[HeldArm]: ...


def held_arms(
    problems: Mapping[str, str], alarms: Sequence[AlarmInfo], refused: Mapping[str, int] | None = None
) -> list[HeldArm]:
    """The arms of `problems` (device: why it is held), by id, each with its `alarms` (worst first) and how
    many of its messages were `refused` (device: count; none heard when absent)."""
    worst = _worst_alarms(alarms)
    waiting = Counter(a.device for a in alarms if a.state in WAITING_STATES)
    counts = refused or {}
    return [
        HeldArm(
            device,
            why,
            waiting[device],
            worst[device].severity if device in worst else None,
            counts.get(device, 0),
        )
        for device, why in sorted(problems.items())
    ]


class Listening(NamedTuple):
    """What the agent subscribes to, and whether every connection to its broker is up: the fleet page says so
    while no arm has been heard from, the moment a new user is most likely to be looking at an empty page."""

    filters: tuple[str, ...]
    connected: bool
    # The agent's stop has begun: its broker connection is closed on purpose, and the page says so rather
    # than "not connected to its broker", which sends a person looking for an outage.
    stopping: bool = False


@runtime_checkable
class ListeningSource(Protocol):
    """The optional part of the service surface that says what it listens on (`Listening`)."""

    def listening(self) -> Listening: ...


@runtime_checkable
class AlarmLister(Protocol):
    """The part of the service surface that lists the alarms (worst first)."""

    def alarms(self, *, include_normal: bool = False) -> tuple[AlarmInfo, ...]: ...


class StateReader(Protocol):
    """The part of the service surface that builds the whole agent state."""

    def state(self) -> AgentState: ...


class FleetParts(NamedTuple):
    """What `fleet_summary` makes the fleet document of."""

    rows: Sequence[FleetRow]
    notices: list[str]
    listening: Listening | None
    held: list[HeldArm]


def fleet_parts(
    source: StateReader, state: AgentState | None = None, alarms: Sequence[AlarmInfo] | None = None
) -> FleetParts:
    """The fleet document's parts: its rows, its notices, what the agent listens on and the arms held with
    no card (a source that is no HeldSource holds none). The rows are the
    source's own when it can give them without its whole state (`FleetRowSource`), else made from `state`
    and `alarms`, each read from the source when not given. Blocking (it reads the agent under its locks):
    the console's HTTP handler and its stream both call it in one hop to a thread."""
    if isinstance(source, FleetRowSource):
        rows: Sequence[FleetRow] = source.fleet_rows()
    else:
        if state is None:
            state = source.state()
        if alarms is None:
            alarms = source.alarms() if isinstance(source, AlarmLister) else ()
        rows = fleet_rows(state, alarms)
    shown = {row.device for row in rows}
    notices, listening = fleet_notes(source, shown)
    held = source.held_arms(shown) if isinstance(source, HeldSource) else []
    return FleetParts(rows, [*behind_notice(rows), *notices], listening, held)


def behind_notice(rows: Sequence[FleetRow]) -> list[str]:
    """What the Fleet page says of workers behind their messages by BEHIND_NOTICE_S or more: no card can,
    since each arm's status is read where its worker stands (so the page does not turn STALE for a host
    short of CPU), and every pose is older than its arm's status suggests."""
    behind = max((row.behind_s for row in rows), default=0.0)
    if behind < BEHIND_NOTICE_S:
        return []
    return [
        f"the agent is {behind:.1f} s behind the arms' messages: its host is short of CPU, so every pose "
        "shown is about that old (the arms' status is read where the agent stands). Give the host fewer "
        "arms or more cores (docs/scaling.md)"
    ]


def fleet_notes(source: object, shown: Collection[str] = ()) -> tuple[list[str], Listening | None]:
    """The fleet page's notices and what the agent listens on, from a source that says (else none of
    either); `shown` the arms with a card (NoticeSource). Blocking: both read the agent under its locks."""
    notices = source.notices(shown) if isinstance(source, NoticeSource) else []
    listening = source.listening() if isinstance(source, ListeningSource) else None
    return notices, listening


def fleet_row(
    device: str,
    *,
    status: str,
    last_seen: float | None,
    rate_hz: float | None,
    loss_ratio: float,
    temperatures: Mapping[str, float | None],
    rejected: int,
    alarm: tuple[str, str, str, str] | None,
    uncalibrated: bool = False,
    mirror: str = "running",
    unacknowledged: int = 0,
    behind_s: float = 0.0,
    calibration_refused: bool = False,
) -> FleetRow:
    """A row from its parts; `alarm` is the worst one that is not NORMAL: (severity, state, kind, joint);
    `unacknowledged` how many of its alarms are in WAITING_STATES; `behind_s` how far its worker stands
    behind its input (service.mirror)."""
    hot_joint, hot_c = None, None
    for joint, temp in temperatures.items():
        if temp is not None and (hot_c is None or temp > hot_c):
            hot_joint, hot_c = joint, temp
    severity, state, kind, alarm_joint = alarm if alarm is not None else (None, None, None, None)
    return FleetRow(
        device,
        status,
        _round(last_seen, 3),
        _round(rate_hz, 1),
        _round(loss_ratio * 100.0, 1),
        severity,
        state,
        kind,
        alarm_joint,
        hot_joint,
        _round(hot_c, 1),
        rejected,
        uncalibrated,
        mirror,
        unacknowledged,
        round(behind_s, 2),
        calibration_refused,
    )


def fleet_rows(state: AgentState, alarms: Sequence[AlarmInfo]) -> list[FleetRow]:
    """One row per device of a full state, sorted by device id (for a source without `fleet_rows`)."""
    return device_rows(state.devices, alarms, state.agent.time)


def card_uncalibrated(uncalibrated: bool, held: bool, units: Units | None) -> bool:
    """A Fleet row's `uncalibrated`, which with `calibration_refused` makes its card say "held": the arm's
    own flag (/state's, the calibration's alone), or the arm is `held` (its file in the store refused at the
    start, none kept), which no calibration decodes, neither one units = auto has yet to decide nor the
    config's for every arm (its card read "file refused, it keeps the one it had"). Not with degrees, which
    use no calibration. The one rule for the mirror's rows and those read from a worker's checkpoint."""
    return uncalibrated or (held and units is not Units.DEGREES)


def device_rows(
    devices: Mapping[str, DeviceState],
    alarms: Sequence[AlarmInfo],
    now: float,
    held: Collection[str] = (),
) -> list[FleetRow]:
    """One row per device state, in the order given; `alarms` worst first, `now` the wall time. `held`: the
    arms held by a refused calibration, whose card says so (`card_uncalibrated`, as the mirror's rows): from
    a restarting worker's checkpoint such a card read "file refused, it keeps the one it had"."""
    worst = _worst_alarms(alarms)
    waiting = Counter(a.device for a in alarms if a.state in WAITING_STATES)
    rows: list[FleetRow] = []
    for device_id, d in devices.items():
        a = worst.get(device_id)
        rows.append(
            fleet_row(
                device_id,
                status=str(d.health.status),
                last_seen=now - d.health.age_s if d.health.age_s is not None and now else None,
                rate_hz=d.health.rate_hz,
                loss_ratio=d.loss.recent_loss_ratio,
                temperatures={joint: servo.temperature_c for joint, servo in (d.servos or {}).items()},
                rejected=sum(d.health.counters.rejected.values()),
                alarm=(a.severity, a.state, a.kind, a.joint) if a else None,
                uncalibrated=card_uncalibrated(d.uncalibrated, device_id in held, d.units),
                mirror=str(d.mirror),
                unacknowledged=waiting[device_id],
                calibration_refused=bool(d.calibration_problem),
            )
        )
    return rows


def fleet_summary(
    rows: Sequence[FleetRow],
    time_s: float,
    notices: Sequence[str] = (),
    listening: Listening | None = None,
    *,
    held: Sequence[HeldArm] = (),
) -> bytes:
    """The fleet page's document: {"time", "columns", "rows", "counts", "notices", "listening", "held"}
    (module doc); "listening" is {"filters", "connected", "stopping"}, or null from a source that does not
    say; "held" the arms held by a refused calibration, with no row (HeldArm)."""
    statuses: dict[str, int] = {"ONLINE": 0, "STALE": 0, "OFFLINE": 0}
    severities: dict[str, int] = {"critical": 0, "warning": 0}
    for row in rows:
        statuses[row.status] = statuses.get(row.status, 0) + 1
    # A held arm's alarms are raised as a row's: the page counted fewer arms alarmed than /alarms listed.
    for severity in [*(row.alarm_severity for row in rows), *(arm.alarm_severity for arm in held)]:
        if severity:
            severities[severity] = severities.get(severity, 0) + 1
    return msgspec.json.encode(
        {
            "time": time_s,
            "columns": FLEET_COLUMNS,
            "rows": rows,
            "counts": {"status": statuses, "alarmed_devices": severities, "devices": len(rows)},
            "notices": list(notices),
            "listening": (
                None
                if listening is None
                else {
                    "filters": list(listening.filters),
                    "connected": listening.connected,
                    "stopping": listening.stopping,
                }
            ),
            "held": list(held),
        }
    )


def arm_view_of(
    source: StateReader,
    device: str,
    state: AgentState | None = None,
    alarms: Sequence[AlarmInfo] | None = None,
) -> ArmView:
    """One arm's view (blocking): asked of its own mirror when the source can (ArmViewSource), otherwise
    cut from the whole state and every alarm (those given, else read here), as `fleet_parts` does for rows."""
    if isinstance(source, ArmViewSource):
        return source.arm_view(device)
    if state is None:
        state = source.state()
    if alarms is None:
        alarms = source.alarms() if isinstance(source, AlarmLister) else ()
    mine = [a for a in alarms if a.device == device]
    return ArmView(
        state.agent.time,
        state.devices.get(device),
        mine,
        state.agent.calibration_store,
        state.agent.started_at,
        per_connection_limit=state.agent.broker.per_connection_limit is not None,
    )


def arm_document(device: str, view: ArmView) -> bytes:
    """An arm page's document: {"time", "device": DeviceState or null, "alarms": [...],
    "calibration_push": {"store", "command", "text"}, "agent_started_at", "motor_ids",
    "calibration_refused"}; its alarms are every one that is not NORMAL, worst first, "calibration_push"
    says how to give the arm a calibration this agent reads (calibrations.push_hint), "agent_started_at"
    (epoch seconds) is where the arm's counters begin, and "motor_ids" each joint's servo id, by which the
    page names a servo as the alarms do; "calibration_refused" why the agent holds the arm, with a state or
    none ("" when it does not), and "refused" {"count", "age_s"} of such an arm with no state: its messages
    refused so far and how long ago the last came (null: none heard, or an arm with a state);
    "expected_rate_hz" the setting its loss is estimated with (null: not known); "per_connection_limit"
    whether the broker limits each connection's messages (a quota that can lose them); "forget" {"allowed",
    "why"} whether the agent would forget the arm now and, if not, the words it would refuse it with."""
    # Made here, not in the page: only the agent knows its store, and a command for another store (the
    # stack's, from a laptop's agent) would push a file this agent never reads.
    hint = push_hint(device, view.calibration_store)
    return msgspec.json.encode(
        {
            "time": view.time,
            "device": view.state,
            "alarms": view.alarms,
            "calibration_push": {"store": hint.store, "command": hint.command, "text": hint.text},
            "agent_started_at": view.started_at,
            "motor_ids": so101.MOTOR_IDS,
            "calibration_refused": view.calibration_refused,
            "refused": None if view.refused is None else {"count": view.refused[0], "age_s": view.refused[1]},
            "expected_rate_hz": view.expected_rate_hz,
            "per_connection_limit": view.per_connection_limit,
            "forget": None if view.forget is None else view.forget._asdict(),
        }
    )


def render_page(page: str, *, csrf_token: str, device: str = "", rerun_url: str = "") -> bytes:
    """The HTML shell of one console page; its script builds the page from the JSON API."""
    if page not in PAGES:
        raise ValueError(f"no console page {page!r}; the pages are {', '.join(PAGES)}")
    shell = Template((ASSETS / "page.html").read_text(encoding="utf-8"))
    title = {"fleet": "Fleet", "arm": device or "Arm", "sessions": "Sessions", "events": "Events"}[page]
    return shell.substitute(
        page=page,
        title=html.escape(title),
        csrf=html.escape(csrf_token),
        device=html.escape(device),
        rerun=html.escape(rerun_url),
    ).encode("utf-8")


def not_found_page(path: str) -> bytes:
    """What a browser gets for a path the agent does not serve: a page in the console's look that names the
    path and links to the pages there are (a script or curl still gets the JSON error with the endpoints)."""
    links = "".join(
        f'<li><a href="{href}">{name}</a></li>'
        for name, href in (("Fleet", "/"), ("Sessions", "/sessions"), ("Events", "/events"))
    )
    return (
        '<!doctype html>\n<html lang="en"><head><meta charset="utf-8"><title>Not found · so101-twin console'
        '</title><link rel="icon" href="data:,"><link rel="stylesheet" href="/static/console.css"></head>'
        '<body><main id="main"><h1>Nothing here</h1><p id="not-found">This agent serves no page at '
        f"<code>{html.escape(path)}</code>. An arm's page is <code>/arm/&lt;device&gt;</code>; the Fleet "
        f"page lists the arms this agent knows.</p><ul>{links}</ul></main></body></html>\n"
    ).encode()


def severity_rank(severity: str | None) -> int:
    return _SEVERITY_RANK.get(severity or "", 0)


@runtime_checkable
class _ViewerLinked(Protocol):
    @property
    def viewer_url(self) -> str | None: ...


def rerun_viewer_url(sinks: Sequence[object]) -> str:
    """The Rerun web viewer a sink serves (twin.output.rerun_sink), for the arm page's link; "" if none."""
    for sink in sinks:
        if isinstance(sink, _ViewerLinked) and sink.viewer_url:
            return sink.viewer_url
    return ""
