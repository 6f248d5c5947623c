"""Display-rate pose estimation from 10 Hz telemetry: prediction on the edge timeline, and a hold baseline.

The edge samples its servos at about 10 Hz and stamps each message with its own wall clock; messages reach us
with network jitter, sometimes late, duplicated or out of order, and the edge clock is not NTP-disciplined.
A viewer redraws at about 60 Hz. Showing the newest sample as is ("hold last value") lags the arm by half a
period plus the jitter on average and moves in visible 10 Hz steps.

`PlayoutPredictor` keeps a short history of samples on the *edge* timeline and maps local display time onto
that timeline through a robust estimate of the clock offset, then evaluates the motion at the mapped instant:
interpolating between samples when the instant is covered, and extrapolating a low-order polynomial through
the newest samples (a bounded horizon) when it is not. Everything is a pure function of the samples and the
times passed in (the caller injects its clock), so the benchmark can replay exact timelines.

Design and parameters are described in docs/viewer.md.
"""

from __future__ import annotations

import bisect
import logging
import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

from twin.robot import so101

log = logging.getLogger(__name__)


class PoseEstimator(Protocol):
    """What the viewer and the fidelity benchmark need from an estimator."""

    joint_names: tuple[str, ...]

    def add(self, timestamp_ms: int, angles_rad: Mapping[str, float], received_s: float) -> bool:
        """Feed one sample (edge timestamp, angles by joint name, local receive time in seconds)."""
        ...

    def pose_at(self, now_s: float) -> dict[str, float] | None:
        """The estimated pose at local time `now_s` (same clock as `received_s`); None before any sample."""
        ...

    def reset(self) -> None:
        """Forget every sample (e.g. when the viewer switches device)."""
        ...


def _vector(angles_rad: Mapping[str, float], joint_names: Sequence[str]) -> tuple[float, ...] | None:
    try:
        values = tuple(float(angles_rad[name]) for name in joint_names)
    except (KeyError, TypeError, ValueError):
        return None
    if not all(math.isfinite(v) for v in values):
        return None
    return values


class HoldLastValue:
    """Baseline: show the newest sample (by edge timestamp) until a newer one arrives."""

    def __init__(self, joint_names: Sequence[str] = so101.JOINT_NAMES) -> None:
        self.joint_names = tuple(joint_names)
        self._timestamp_ms: int | None = None
        self._values: tuple[float, ...] | None = None
        self.rejected = 0

    def add(self, timestamp_ms: int, angles_rad: Mapping[str, float], received_s: float) -> bool:
        values = _vector(angles_rad, self.joint_names)
        if values is None:
            self.rejected += 1
            return False
        if self._timestamp_ms is not None and timestamp_ms <= self._timestamp_ms:
            return False
        self._timestamp_ms = int(timestamp_ms)
        self._values = values
        return True

    def pose_at(self, now_s: float) -> dict[str, float] | None:
        if self._values is None:
            return None
        return dict(zip(self.joint_names, self._values, strict=True))

    def reset(self) -> None:
        self._timestamp_ms = None
        self._values = None


@dataclass(frozen=True)
class SmoothingConfig:
    """Parameters of `PlayoutPredictor` (defaults tuned for 10 Hz telemetry and a 60 Hz display).

    playout_delay_s: how far behind the estimated edge "now" the display runs. 0 predicts the present; a
        positive value trades lag for interpolation only (smoother under heavy jitter); negative leads.
    max_extrapolation_s: the longest prediction past the newest sample; beyond it the pose holds, so a
        stopped stream freezes the twin instead of flinging it along the last velocity.
    order: 2 = quadratic through the newest three samples (constant acceleration), 1 = constant velocity.
    offset_window_s: the clock offset is the minimum of (receive - edge time) over this recent window.
        Jitter only ever adds delay, so the minimum is the least-delayed sample; a window (not all time)
        follows slow drift of the edge clock.
    jump_threshold_s / jump_confirmations: a sample whose offset differs from the estimate by more than the
        threshold is held back; that many consecutive ones agreeing with each other mean the edge clock
        jumped, and the estimator restarts on the new timeline. A single late straggler changes nothing.
    history: samples kept for interpolation and fitting.
    min_spacing_s / max_gap_s: samples closer than min_spacing (in edge time) are not used to fit a
        derivative (noise amplification); samples further apart than max_gap are not bridged by a
        derivative either (the motion between them is unknown), the estimator holds instead.
    """

    playout_delay_s: float = 0.0
    max_extrapolation_s: float = 0.2
    order: int = 2
    offset_window_s: float = 3.0
    jump_threshold_s: float = 1.0
    jump_confirmations: int = 3
    history: int = 8
    min_spacing_s: float = 0.02
    max_gap_s: float = 0.6

    def __post_init__(self) -> None:
        if self.order not in (1, 2):
            raise ValueError(f"SmoothingConfig.order must be 1 or 2, got {self.order}")
        if self.max_extrapolation_s < 0 or self.offset_window_s <= 0 or self.jump_threshold_s <= 0:
            raise ValueError(
                "SmoothingConfig: max_extrapolation_s must be >= 0, offset_window_s and jump_threshold_s > 0"
            )
        if self.history < 3 or self.jump_confirmations < 1:
            raise ValueError("SmoothingConfig: history must be >= 3 and jump_confirmations >= 1")


class PlayoutPredictor:
    """Predict the pose at display time from jittered samples on the edge timeline (see module docstring)."""

    def __init__(
        self, config: SmoothingConfig | None = None, joint_names: Sequence[str] = so101.JOINT_NAMES
    ) -> None:
        self.config = config or SmoothingConfig()
        self.joint_names = tuple(joint_names)
        self.rejected = 0
        self.duplicates = 0
        self.clock_resets = 0
        self.reset()

    def reset(self) -> None:
        self._times: list[float] = []  # edge seconds, ascending
        self._values: list[tuple[float, ...]] = []
        self._offsets: deque[tuple[float, float]] = deque()  # (received_s, received_s - edge_s)
        self._offset: float | None = None
        self._pending: list[tuple[float, float, tuple[float, ...]]] = []
        self._last_target: float | None = None

    @property
    def offset_s(self) -> float | None:
        """Estimated (local clock - edge clock), including the minimum one-way network delay."""
        return self._offset

    @property
    def newest_timestamp_ms(self) -> int | None:
        return round(self._times[-1] * 1000.0) if self._times else None

    def add(self, timestamp_ms: int, angles_rad: Mapping[str, float], received_s: float) -> bool:
        values = _vector(angles_rad, self.joint_names)
        if values is None or not math.isfinite(received_s):
            self.rejected += 1
            return False
        edge_s = timestamp_ms / 1000.0
        if self._times and edge_s == self._times[-1]:
            # The newest sample again (a viewer that polls a silent arm's state): ignored before the jump
            # check, which took its growing age for an edge clock jumping back, once a second.
            self.duplicates += 1
            return False
        sample_offset = received_s - edge_s
        if self._offset is not None and abs(sample_offset - self._offset) > self.config.jump_threshold_s:
            return self._hold_back(edge_s, received_s, values, self._offset)
        self._pending.clear()
        self._track_offset(received_s, sample_offset)
        return self._insert(edge_s, values)

    def _hold_back(self, edge_s: float, received_s: float, values: tuple[float, ...], offset: float) -> bool:
        # Either a straggler from a network stall or the first samples after an edge clock jump; only a run
        # of samples that agree with each other proves the latter.
        sample_offset = received_s - edge_s
        if self._pending and abs(sample_offset - (self._pending[-1][1] - self._pending[-1][0])) > (
            self.config.jump_threshold_s
        ):
            self._pending.clear()
        self._pending.append((edge_s, received_s, values))
        if len(self._pending) < self.config.jump_confirmations:
            return False
        pending = self._pending
        log.info("edge clock jumped by %.3f s: restarting the playout timeline", -sample_offset + offset)
        self.reset()
        self.clock_resets += 1
        for p_edge, p_received, p_values in pending:
            self._track_offset(p_received, p_received - p_edge)
            self._insert(p_edge, p_values)
        return True

    def _track_offset(self, received_s: float, sample_offset: float) -> None:
        self._offsets.append((received_s, sample_offset))
        horizon = received_s - self.config.offset_window_s
        while len(self._offsets) > 1 and self._offsets[0][0] < horizon:
            self._offsets.popleft()
        self._offset = min(o for _, o in self._offsets)

    def _insert(self, edge_s: float, values: tuple[float, ...]) -> bool:
        i = bisect.bisect_left(self._times, edge_s)
        if i < len(self._times) and abs(self._times[i] - edge_s) < 1e-6:
            self.duplicates += 1
            return False
        if i == 0 and len(self._times) >= self.config.history:
            return False  # older than everything kept: no use for the present
        self._times.insert(i, edge_s)
        self._values.insert(i, values)
        if len(self._times) > self.config.history:
            del self._times[0]
            del self._values[0]
        return True

    def pose_at(self, now_s: float) -> dict[str, float] | None:
        if not self._times or self._offset is None:
            return None
        target = now_s - self._offset - self.config.playout_delay_s
        # The offset estimate can rise when its minimum leaves the window; the display must not rewind.
        if self._last_target is not None and target < self._last_target:
            target = self._last_target
        self._last_target = target
        return dict(zip(self.joint_names, self._evaluate(target), strict=True))

    def _evaluate(self, t: float) -> tuple[float, ...]:
        times, values = self._times, self._values
        if t <= times[0]:
            return values[0]
        if t < times[-1]:
            i = bisect.bisect_right(times, t)
            t0, t1 = times[i - 1], times[i]
            w = (t - t0) / (t1 - t0)
            return tuple(a + (b - a) * w for a, b in zip(values[i - 1], values[i], strict=True))
        t = min(t, times[-1] + self.config.max_extrapolation_s)
        return self._extrapolate(t)

    def _extrapolate(self, t: float) -> tuple[float, ...]:
        times, values, cfg = self._times, self._values, self.config
        n = len(times)
        usable = 1
        while usable < min(n, cfg.order + 1):
            gap = times[n - usable] - times[n - usable - 1]
            if gap < cfg.min_spacing_s or gap > cfg.max_gap_s:
                break
            usable += 1
        if usable == 1:
            return values[-1]
        if usable == 2:
            t1, t2 = times[-2], times[-1]
            k = (t - t2) / (t2 - t1)
            return tuple(b + (b - a) * k for a, b in zip(values[-2], values[-1], strict=True))
        # Lagrange form of the parabola through the newest three samples (spacing need not be uniform).
        t0, t1, t2 = times[-3], times[-2], times[-1]
        l0 = (t - t1) * (t - t2) / ((t0 - t1) * (t0 - t2))
        l1 = (t - t0) * (t - t2) / ((t1 - t0) * (t1 - t2))
        l2 = (t - t0) * (t - t1) / ((t2 - t0) * (t2 - t1))
        return tuple(
            l0 * a + l1 * b + l2 * c for a, b, c in zip(values[-3], values[-2], values[-1], strict=True)
        )


def make_estimator(kind: str = "predict", config: SmoothingConfig | None = None) -> PoseEstimator:
    """`predict` (PlayoutPredictor) or `hold` (HoldLastValue); the viewer's --smoothing flag."""
    if kind == "predict":
        return PlayoutPredictor(config)
    if kind == "hold":
        return HoldLastValue()
    raise ValueError(f"unknown smoothing {kind!r}: use 'predict' or 'hold'")
