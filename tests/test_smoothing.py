"""The display-rate estimator against the true continuous edge motion (the mock formula); edge cases."""

from __future__ import annotations

import itertools
import math
import random

import pytest
from twin.core.smoothing import HoldLastValue, PlayoutPredictor, SmoothingConfig, make_estimator
from twin.edge.payload import mock_motion_ticks, mock_ticks
from twin.robot import so101

EPOCH_MS = 1_706_000_000_000  # edge wall clock: epoch ms, nothing like the viewer's monotonic clock
LOCAL_START = 1234.5  # time.monotonic() of the viewer when the edge clock reads EPOCH_MS
RATE_HZ = 10.0
DISPLAY_HZ = 60.0


def true_rad(t: float, i: int) -> float:
    """The edge mock motion (twin.edge.payload, its one definition; hand-derived values in
    test_edge_sim.py) before its int() truncation, as radians about the 2048-tick centre."""
    return (mock_motion_ticks(t)[i] - 2048) * 2 * math.pi / 4096


def published_rad(t: float, i: int) -> float:
    """What the edge publishes: the same motion truncated to whole ticks."""
    return (mock_ticks(t)[i] - 2048) * 2 * math.pi / 4096


def samples(seconds: float, jitter_s: float, seed: int = 7, drop=lambda t: False, edge_ms=None):
    """(arrival local s, edge timestamp ms, angles) sorted by arrival; arrival = send + U(0, jitter)."""
    rng = random.Random(seed)
    out = []
    for k in range(int(seconds * RATE_HZ)):
        t = k / RATE_HZ
        if drop(t):
            continue
        angles = {name: published_rad(t, i) for i, name in enumerate(so101.JOINT_NAMES)}
        stamp = edge_ms(t) if edge_ms else EPOCH_MS + round(t * 1000)
        out.append((LOCAL_START + t + rng.uniform(0.0, jitter_s), stamp, angles))
    out.sort(key=lambda s: s[0])
    return out


def replay(estimator, stream, seconds: float, warmup_s: float = 1.0, skip=lambda t: False):
    """Errors (rad, per joint per frame) of the estimator at 60 Hz against the true motion at that instant."""
    errors: list[float] = []
    poses = []
    j = 0
    for f in range(int(seconds * DISPLAY_HZ)):
        t = f / DISPLAY_HZ
        now = LOCAL_START + t
        while j < len(stream) and stream[j][0] <= now:
            estimator.add(stream[j][1], stream[j][2], stream[j][0])
            j += 1
        pose = estimator.pose_at(now)
        if pose is None or t < warmup_s or skip(t):
            continue
        poses.append(pose)
        errors.extend(abs(pose[name] - true_rad(t, i)) for i, name in enumerate(so101.JOINT_NAMES))
    return errors, poses


def mean(values) -> float:
    return sum(values) / len(values)


@pytest.mark.parametrize("jitter_s", [0.0, 0.05])
def test_prediction_beats_hold_last_value_by_a_wide_margin(jitter_s):
    stream = samples(40.0, jitter_s)
    hold, _ = replay(HoldLastValue(), stream, 40.0)
    pred, poses = replay(PlayoutPredictor(), stream, 40.0)
    assert all(math.isfinite(v) for pose in poses for v in pose.values())
    ratio = mean(hold) / mean(pred)
    # Issue 5's target is 3x; the design reaches far more, so 3x here still fails on a real regression.
    assert ratio >= 3.0, (
        f"mean error hold {mean(hold):.5f} vs predict {mean(pred):.5f} rad (ratio {ratio:.1f})"
    )
    # Absolute sanity: within a few encoder ticks on average (1 tick = 1.5 mrad, truncation alone 0.5).
    assert mean(pred) < 0.004
    assert max(pred) < 0.03


def test_constant_velocity_variant_also_beats_hold():
    stream = samples(20.0, 0.05)
    hold, _ = replay(HoldLastValue(), stream, 20.0)
    cv, _ = replay(PlayoutPredictor(SmoothingConfig(order=1)), stream, 20.0)
    assert mean(hold) / mean(cv) >= 3.0


def test_gap_holds_then_recovers():
    gap = (10.0, 12.0)
    stream = samples(20.0, 0.05, drop=lambda t: gap[0] <= t < gap[1])
    est = PlayoutPredictor()
    _, poses = replay(est, stream, 20.0)
    assert all(math.isfinite(v) for pose in poses for v in pose.values())
    # During the gap the prediction is clamped: past max_extrapolation_s the twin holds still instead of
    # flying off along the last velocity and acceleration.
    _, inside = replay(PlayoutPredictor(), stream, 20.0, skip=lambda t: not (gap[0] + 0.5 <= t < gap[1]))
    assert len(inside) > 60
    assert all(pose == inside[0] for pose in inside)
    # The first samples after the gap are too far from the last ones to fit a derivative across; after
    # three fresh samples the estimate is back to normal accuracy.
    after, _ = replay(PlayoutPredictor(), stream, 20.0, skip=lambda t: not (gap[1] + 0.4 <= t))
    assert mean(after) < 0.004


def test_reordered_and_duplicated_samples_never_rewind_the_display():
    # A ramp makes the pose equal the edge time it shows, so "never backwards" is directly observable.
    rng = random.Random(3)
    est = PlayoutPredictor(joint_names=("j",))
    stream = []
    for k in range(100):
        t = k / RATE_HZ
        arrival = LOCAL_START + t + rng.uniform(0.0, 0.25)  # jitter > period: heavy reordering
        stream.append((arrival, EPOCH_MS + k * 100, {"j": t}))
        if k % 7 == 0:
            stream.append((arrival + 0.03, EPOCH_MS + k * 100, {"j": t}))  # duplicate
    stream.sort(key=lambda s: s[0])
    assert any(a[1] > b[1] for a, b in itertools.pairwise(stream)), "stream must be reordered"
    shown = []
    j = 0
    for f in range(int(10.5 * DISPLAY_HZ)):
        now = LOCAL_START + f / DISPLAY_HZ
        while j < len(stream) and stream[j][0] <= now:
            est.add(stream[j][1], stream[j][2], stream[j][0])
            j += 1
        pose = est.pose_at(now)
        if pose is not None:
            shown.append(pose["j"])
    assert est.duplicates >= 10
    assert all(b >= a - 1e-9 for a, b in itertools.pairwise(shown))
    assert shown[-1] == pytest.approx(9.9 + SmoothingConfig().max_extrapolation_s, abs=1e-6)


def test_hold_last_value_ignores_older_samples():
    est = HoldLastValue(("j",))
    assert est.pose_at(0.0) is None
    assert est.add(2000, {"j": 2.0}, 1.0)
    assert not est.add(1000, {"j": 1.0}, 1.1)
    assert not est.add(2000, {"j": 5.0}, 1.2)
    assert est.pose_at(5.0) == {"j": 2.0}


def test_edge_clock_jump_restarts_the_timeline_but_a_straggler_does_not():
    def edge_ms(t: float) -> int:
        return EPOCH_MS + round(t * 1000) + (5000 if t >= 10.0 else 0)  # the edge clock jumps +5 s

    stream = samples(20.0, 0.05, edge_ms=edge_ms)
    est = PlayoutPredictor()
    after, poses = replay(est, stream, 20.0, skip=lambda t: t < 10.6)
    assert est.clock_resets == 1
    assert mean(after) < 0.004
    assert all(math.isfinite(v) for pose in poses for v in pose.values())

    straggler = samples(20.0, 0.0)
    late = straggler.pop(50)  # t = 5.0 s delivered 3 s late
    straggler.append((late[0] + 3.0, late[1], late[2]))
    straggler.sort(key=lambda s: s[0])
    est = PlayoutPredictor()
    errors, _ = replay(est, straggler, 20.0)
    assert est.clock_resets == 0
    assert mean(errors) < 0.004


def test_a_silent_arms_newest_sample_seen_again_is_no_clock_jump():
    """A viewer polls the agent: a silent arm's state repeats its last sample, later and later. The jump check
    took its growing age for the edge clock going back, and restarted the timeline once a second (a walk)."""
    est = PlayoutPredictor()
    stream = samples(5.0, 0.0)
    for received, stamp, angles in stream:
        est.add(stamp, angles, received)
    last_received, last_stamp, last_angles = stream[-1]
    for k in range(1, 40):  # the same sample, polled every second for 39 s of silence
        assert not est.add(last_stamp, last_angles, last_received + k)
    assert est.clock_resets == 0


def test_slow_edge_clock_drift_is_followed():
    # 500 ppm (far worse than an unsynchronised crystal); the windowed offset keeps up.
    stream = samples(30.0, 0.05, edge_ms=lambda t: EPOCH_MS + round(t * 1000 * 1.0005))
    hold, _ = replay(HoldLastValue(), stream, 30.0)
    pred, _ = replay(PlayoutPredictor(), stream, 30.0)
    assert mean(hold) / mean(pred) >= 3.0


def test_bad_samples_are_counted_not_used():
    est = PlayoutPredictor(joint_names=("a", "b"))
    assert not est.add(1000, {"a": 1.0}, 0.0)  # missing joint
    assert not est.add(1000, {"a": 1.0, "b": float("nan")}, 0.0)
    assert not est.add(1000, {"a": "x", "b": 1.0}, 0.0)
    assert est.rejected == 3
    assert est.pose_at(1.0) is None
    assert est.add(1000, {"a": 1.0, "b": 2.0}, 0.0)
    assert est.pose_at(1.0) == {"a": 1.0, "b": 2.0}  # one sample: nothing to extrapolate from
    est.reset()
    assert est.pose_at(1.0) is None


def test_config_validation_and_factory():
    with pytest.raises(ValueError, match="order"):
        SmoothingConfig(order=3)
    with pytest.raises(ValueError, match="hold"):
        make_estimator("kalman")
    assert isinstance(make_estimator("hold"), HoldLastValue)
    assert isinstance(make_estimator("predict"), PlayoutPredictor)
