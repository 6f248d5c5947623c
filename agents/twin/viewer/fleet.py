"""What the viewer knows about the fleet: per device, the latest health figures and a pose estimator.

`FleetView` is shared by the feed thread (which writes each agent state into it) and the display loop (which
asks it for the pose at the current instant); `DevicePicker` chooses which device the window follows.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from twin.core.smoothing import PoseEstimator, make_estimator
from twin.core.throttle import Throttle
from twin.service.state import AgentState, DeviceState, DeviceView, ServoState, device_attention

log = logging.getLogger(__name__)

T = TypeVar("T")

# GLFW key codes (stable across GLFW 3.x). The simulate UI already binds letters (visual flags), digits (geom
# groups: group 2 is the arm itself), arrows (stepping) and [ ] (cameras); Page Up/Down only select a parent
# body when a body is picked, so they are free for the device picker.
KEY_PAGE_UP = 266
KEY_PAGE_DOWN = 267

LINK_CONNECTING = "connecting"
LINK_STREAM = "stream"
LINK_POLLING = "polling"
LINK_UNREACHABLE = "unreachable"
# A document not understood (another service on the port) is logged at most once per this many seconds.
BAD_LOG_INTERVAL_S = 60.0


@dataclass
class DeviceInfo:
    """What the overlay shows for one device (figures as the agent published them)."""

    status: str = "UNKNOWN"
    age_s: float | None = None
    rate_hz: float | None = None
    latency_p50_s: float | None = None
    latency_p99_s: float | None = None
    internal_p99_s: float | None = None
    last_timestamp_ms: int | None = None
    received_s: float = 0.0  # local monotonic time the snapshot arrived
    # Per joint: the servo readings and its worst alarm (None until the agent reports diagnostics).
    servos: dict[str, ServoState] | None = None
    # The agent's loss estimate (docs/agent.md, Loss): losing data now, and the share lost recently.
    losing: bool = False
    recent_loss_ratio: float = 0.0
    lost: int = 0


class FleetView:
    """Latest figures and a pose estimator per device; shared by the feed thread and the display loop."""

    def __init__(
        self, estimator_factory: Callable[[], PoseEstimator] = lambda: make_estimator("predict")
    ) -> None:
        self._lock = threading.Lock()
        self._factory = estimator_factory
        self._info: dict[str, DeviceInfo] = {}
        self._estimators: dict[str, PoseEstimator] = {}
        self.link = LINK_CONNECTING
        self.link_error: str | None = None
        self.link_since: float = time.monotonic()
        self.snapshots = 0
        self.bad_snapshots = 0
        # When a document not understood was last logged, and how many came since (_parsed).
        self._bad_lines = Throttle(BAD_LOG_INTERVAL_S)
        # The agent's device ids as it last listed them (None until it has: then the devices seen so far).
        self._listed: list[str] | None = None
        # The arms that want a look, with why (DeviceView.attention), as the agent last said.
        self._attention: dict[str, str] = {}

    def set_link(self, link: str, error: str | None = None, now: float | None = None) -> None:
        with self._lock:
            if link != self.link:
                self.link_since = time.monotonic() if now is None else now
                log.info("agent link: %s%s", link, f" ({error})" if error else "")
            self.link = link
            self.link_error = error

    def update_json(self, document: bytes | str, received_s: float) -> int:
        """Take one agent state document (GET /state, one /stream event); returns the devices in it.

        A document that is not an agent state (another service on that port, a truncated body) is counted
        in `bad_snapshots` and logged, never raised: the feed keeps reading.
        """
        state = self._parsed(AgentState.from_json, document, "state")
        return 0 if state is None else self.update(state, received_s)

    def update(self, state: AgentState, received_s: float) -> int:
        """Take one agent state; returns the number of devices in it."""
        with self._lock:
            self.snapshots += 1
            self._list(sorted(state.devices))
            marks = ((device_id, device_attention(d)) for device_id, d in state.devices.items())
            self._attention = {device_id: mark for device_id, mark in marks if mark}
            for device_id, d in state.devices.items():
                self._take(device_id, d, received_s)
            return len(state.devices)

    def update_view_json(self, document: bytes | str, received_s: float) -> int:
        """Take one arm's view (a `/stream?device=` event: DeviceView); returns the devices it carries (0 or
        1). A document that is not one is counted and logged, as in `update_json`."""
        view = self._parsed(DeviceView.from_json, document, "view")
        return 0 if view is None else self.update_view(view, received_s)

    def _parsed(self, parse: Callable[[bytes | str], T], document: bytes | str, what: str) -> T | None:
        """`parse(document)`, or None for a document that is not what the agent sends (counted, logged)."""
        try:
            return parse(document)
        except ValueError as exc:
            with self._lock:
                self.bad_snapshots += 1
                # Another service on the port answers every poll: one line a minute, not eleven a second.
                count = self._bad_lines.due()
            if count is None:
                return None
            log.warning(
                "agent %s not understood (%s; %d such document(s) since the last line); is --agent pointing "
                "at a twin agent?",
                what,
                exc,
                count,
            )
            return None

    def update_view(self, view: DeviceView, received_s: float) -> int:
        """Take one arm's view: the arm's figures and pose, and the agent's device ids."""
        with self._lock:
            self.snapshots += 1
            self._list(list(view.devices))
            self._attention = dict(view.attention)
            if view.device is None:
                return 0
            self._take(view.device.device_id, view.device, received_s)
            return 1

    def _list(self, listed: list[str]) -> None:
        """The agent's device ids now (under the lock): an arm it no longer lists (forgotten) is dropped,
        figures and pose, rather than shown as it was last."""
        self._listed = listed
        for gone in set(self._info).difference(listed):
            del self._info[gone]
            self._estimators.pop(gone, None)

    def _take(self, device_id: str, d: DeviceState, received_s: float) -> None:
        # (Under the lock.)
        info = self._info.setdefault(device_id, DeviceInfo())
        info.status = str(d.health.status)
        info.age_s = d.health.age_s
        info.rate_hz = d.health.rate_hz
        info.latency_p50_s = d.health.edge_clock_latency_s.p50
        info.latency_p99_s = d.health.edge_clock_latency_s.p99
        info.internal_p99_s = d.health.internal_latency_s.p99
        info.received_s = received_s
        info.servos = d.servos
        info.losing = d.loss.losing
        info.recent_loss_ratio = d.loss.recent_loss_ratio
        info.lost = d.loss.lost
        # timestamp_ms belongs to the same twin snapshot as joints_rad (last_timestamp_ms: health's).
        if d.timestamp_ms is not None and d.joints_rad is not None:
            info.last_timestamp_ms = d.timestamp_ms
            estimator = self._estimators.get(device_id)
            if estimator is None:
                estimator = self._estimators[device_id] = self._factory()
            # The stream repeats the same sample until the agent applies a newer one; the estimator drops
            # duplicates by timestamp, so only genuine new samples move it.
            estimator.add(d.timestamp_ms, d.joints_rad, received_s)

    def devices(self) -> list[str]:
        """The agent's device ids as it last listed them (an arm it forgot drops out), sorted."""
        with self._lock:
            return sorted(self._info) if self._listed is None else list(self._listed)

    def attention(self) -> dict[str, str]:
        """The arms that want a look and why (`OFFLINE`, `CRITICAL`, `warning ack`), as last listed."""
        with self._lock:
            return dict(self._attention)

    def info(self, device_id: str) -> DeviceInfo | None:
        with self._lock:
            info = self._info.get(device_id)
            return None if info is None else DeviceInfo(**vars(info))

    def pose(self, device_id: str, now_s: float) -> dict[str, float] | None:
        with self._lock:
            estimator = self._estimators.get(device_id)
            return None if estimator is None else estimator.pose_at(now_s)


class DevicePicker:
    """Which device the viewer follows: the configured one, else the first; Page Up/Down cycle."""

    def __init__(self, preferred: str | None = None) -> None:
        self._lock = threading.Lock()
        self._selected = preferred
        self._step = 0

    def on_key(self, key: int) -> None:
        # Called on the viewer's render thread: record the request only, the display loop applies it.
        with self._lock:
            if key == KEY_PAGE_DOWN:
                self._step += 1
            elif key == KEY_PAGE_UP:
                self._step -= 1

    @property
    def selected(self) -> str | None:
        """The device chosen last (what the feed asks the agent for); None before any."""
        with self._lock:
            return self._selected

    def current(self, devices: list[str]) -> str | None:
        with self._lock:
            if devices and self._selected is None:
                self._selected = devices[0]
            if self._step and devices:
                # From an arm the agent no longer lists: Page Down shows the first, Page Up the last.
                i = (
                    devices.index(self._selected)
                    if self._selected in devices
                    else (-1 if self._step > 0 else 0)
                )
                self._selected = devices[(i + self._step) % len(devices)]
            self._step = 0
            return self._selected
