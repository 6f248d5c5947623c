"""Fidelity: how closely the displayed twin follows the true, continuous arm motion.

The edge's mock motion is a known continuous function of time, so the truth is available at every display
instant. The scenario replays an exact timeline: the edge samples it at 10 Hz (integer ticks, as the edge
truncates them), each message reaches the agent after a base delay plus uniform network jitter (so messages
arrive out of order), and the display asks the estimator for a pose at 60 Hz. The error is the joint-angle
difference between the estimate and the truth at the display instant. Both sides go through the real decoder,
so the figures include the edge's tick quantisation and our unit conversion.
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from twin.core.smoothing import make_estimator
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
from twin.edge.payload import encode, make_payload, mock_motion_ticks
from twin.robot import so101

# Edge timestamps must look like a real wall clock (the decoder rejects an unset one).
_EPOCH_MS = 1_706_000_000_000


def _linear_tick_map(decoder: TelemetryDecoder) -> list[tuple[float, float]]:
    """(offset, slope) per joint so that angle = offset + slope * ticks, taken from the real decoder.

    Every conversion the decoder applies to ticks is linear inside the joint ranges, so two probe payloads
    pin it down exactly and the truth uses the same units, calibration and gripper rule as the twin.
    """
    probes = {}
    for ticks in (1700, 2400):
        payload = make_payload("probe", 0.0, "ticks", random.Random(0), timestamp_ms=_EPOCH_MS + ticks)
        for joint in payload["joints"].values():
            joint["position"] = ticks
        probes[ticks] = decoder.decode(encode(payload)).angles_rad
    slope = {name: (probes[2400][name] - probes[1700][name]) / 700.0 for name in so101.JOINT_NAMES}
    return [(probes[1700][name] - slope[name] * 1700, slope[name]) for name in so101.JOINT_NAMES]


@dataclass(frozen=True)
class FidelityResult:
    estimator: str
    jitter_ms: float
    mean_error_rad: float
    max_error_rad: float
    frames: int

    def as_dict(self) -> dict[str, Any]:
        return {
            "estimator": self.estimator,
            "jitter_ms": self.jitter_ms,
            "mean_error_rad": self.mean_error_rad,
            "max_error_rad": self.max_error_rad,
            "mean_error_deg": math.degrees(self.mean_error_rad),
            "max_error_deg": math.degrees(self.max_error_rad),
            "frames": self.frames,
        }


def _truth(tick_map: list[tuple[float, float]], edge_t: float) -> list[float]:
    """Joint angles (JOINT_NAMES order) of the untruncated mock motion at edge time `edge_t`."""
    return [
        offset + slope * ticks
        for (offset, slope), ticks in zip(tick_map, mock_motion_ticks(edge_t), strict=True)
    ]


def _arrivals(
    decoder: TelemetryDecoder,
    rng: random.Random,
    *,
    seconds: float,
    rate_hz: float,
    delay_s: tuple[float, float],
    clock_offset_s: float,
) -> list[tuple[float, int, dict[str, float]]]:
    """(local receive time, edge timestamp ms, decoded angles) of each message, in arrival order.

    The edge samples at `rate_hz`; each message takes `delay_s[0]` plus uniform 0..`delay_s[1]` to arrive.
    """
    arrivals = []
    period = 1.0 / rate_hz
    base, jitter = delay_s
    for k in range(int(seconds * rate_hz) + 1):
        edge_t = k * period
        payload = make_payload("arm-001", edge_t, "ticks", rng, timestamp_ms=_EPOCH_MS + round(edge_t * 1000))
        angles = decoder.decode(encode(payload)).angles_rad
        received = edge_t + clock_offset_s + base + rng.uniform(0.0, jitter)
        arrivals.append((received, payload["timestamp"], angles))
    arrivals.sort(key=lambda a: a[0])  # jitter larger than the period reorders messages, as a network would
    return arrivals


def replay(
    estimator_kind: str,
    *,
    seconds: float = 60.0,
    rate_hz: float = 10.0,
    display_hz: float = 60.0,
    base_delay_ms: float = 5.0,
    jitter_ms: float = 0.0,
    clock_offset_s: float = 1234.5,
    warmup_s: float = 1.0,
    seed: int = 7,
    series: list[tuple[float, float, float, float]] | None = None,
) -> FidelityResult:
    """Replay one timeline through one estimator and measure its error against the truth.

    `clock_offset_s` puts the local clock far from the edge clock, as in the field (the edge is not
    NTP-disciplined); the estimator must not depend on the two agreeing. `series`, when given, receives
    (edge time, mean absolute error over joints, truth and estimate of the first joint) per frame.
    """
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    arrivals = _arrivals(
        decoder,
        random.Random(seed),
        seconds=seconds,
        rate_hz=rate_hz,
        delay_s=(base_delay_ms / 1000.0, jitter_ms / 1000.0),
        clock_offset_s=clock_offset_s,
    )
    total, worst, frames = _display_errors(
        make_estimator(estimator_kind),
        arrivals,
        _linear_tick_map(decoder),
        frame_times=[clock_offset_s + f / display_hz for f in range(int(seconds * display_hz))],
        clock_offset_s=clock_offset_s,
        warmup_s=warmup_s,
        series=series,
    )
    return FidelityResult(
        estimator=estimator_kind,
        jitter_ms=jitter_ms,
        mean_error_rad=total / frames if frames else float("nan"),
        max_error_rad=worst,
        frames=frames,
    )


def _display_errors(
    estimator: Any,
    arrivals: list[Any],
    tick_map: Any,
    *,
    frame_times: list[float],
    clock_offset_s: float,
    warmup_s: float,
    series: list[tuple[float, float, float, float]] | None,
) -> tuple[float, float, int]:
    """At each display instant (local clock): feed the estimator what has arrived, ask it for a pose and
    compare with the truth. Returns the sum of the frames' mean errors, the largest joint error and the
    frames counted (after `warmup_s` of edge time)."""
    names = so101.JOINT_NAMES
    total = worst = 0.0
    frames = next_arrival = 0
    for now in frame_times:
        while next_arrival < len(arrivals) and arrivals[next_arrival][0] <= now:
            received, timestamp_ms, angles = arrivals[next_arrival]
            estimator.add(timestamp_ms, angles, received)
            next_arrival += 1
        pose = estimator.pose_at(now)
        edge_now = now - clock_offset_s
        if pose is None or edge_now < warmup_s:
            continue
        truth = _truth(tick_map, edge_now)
        errors = [abs(pose[name] - truth[i]) for i, name in enumerate(names)]
        frame_mean = sum(errors) / len(errors)
        total += frame_mean
        worst = max(worst, *errors)
        frames += 1
        if series is not None:
            series.append((edge_now, frame_mean, truth[0], pose[names[0]]))
    return total, worst, frames


def run(*, seconds: float = 60.0, jitters_ms: Sequence[float] = (0.0, 50.0), seed: int = 7) -> dict[str, Any]:
    """Hold-last-value against the project's predictor at each jitter; the ratio is hold error / ours."""
    cases = []
    for jitter in jitters_ms:
        hold = replay("hold", seconds=seconds, jitter_ms=jitter, seed=seed)
        ours = replay("predict", seconds=seconds, jitter_ms=jitter, seed=seed)
        cases.append(
            {
                "jitter_ms": jitter,
                "hold_last_value": hold.as_dict(),
                "predict": ours.as_dict(),
                "mean_error_ratio": hold.mean_error_rad / ours.mean_error_rad,
                "max_error_ratio": hold.max_error_rad / ours.max_error_rad,
            }
        )
    return {
        "scenario": "fidelity",
        "telemetry_rate_hz": 10.0,
        "display_rate_hz": 60.0,
        "seconds": seconds,
        "base_delay_ms": 5.0,
        "quantisation": "integer ticks, as the edge publishes",
        "cases": cases,
    }
