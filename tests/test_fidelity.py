"""The fidelity benchmark's truth, checked against a hand-derived oracle (not the decoder it borrows it from).

`twin bench fidelity` turns the mock motion into joint angles with the linear map it probes from the real
decoder, so the decoder under test also defines the truth there. Here the same map is derived by hand from
the telemetry contract: arm joints `(ticks - 2047) * 2 pi / 4095` (LeRobot DEGREES about the homing pose);
the gripper, without a calibration file, maps its tick span 1:1 onto the model's jaw range centred on the
homing pose, so `angle = jaw_mid + (ticks - 2047) * 2 pi / 4095` with jaw_mid = (-0.174533 + 1.7453292) / 2.
"""

from __future__ import annotations

import math

import pytest
from twin.bench import fidelity
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units

K = 2 * math.pi / 4095  # radians per tick, LeRobot's scale
JAW_MID = (-0.174533 + 1.7453292) / 2  # the model's gripper range (so101.xml), 0.7853981 = pi/4


def test_truth_map_matches_the_contract_by_hand() -> None:
    tick_map = fidelity._linear_tick_map(TelemetryDecoder(DecoderConfig(units=Units.TICKS)))
    expected = [(-2047 * K, K)] * 5 + [(JAW_MID - 2047 * K, K)]
    for (offset, slope), (want_offset, want_slope) in zip(tick_map, expected, strict=True):
        assert slope == pytest.approx(want_slope, rel=1e-9)
        assert offset == pytest.approx(want_offset, abs=1e-9)


def test_truth_at_t0_by_hand() -> None:
    tick_map = fidelity._linear_tick_map(TelemetryDecoder(DecoderConfig(units=Units.TICKS)))
    # t = 0: the untruncated mock motion reads 2048 + 500 sin(i pi/3) ticks.
    truth = fidelity._truth(tick_map, 0.0)
    s = 500 * math.sin(math.pi / 3)  # 433.0127
    assert truth[0] == pytest.approx(1 * K)
    assert truth[1] == pytest.approx((1 + s) * K)
    assert truth[3] == pytest.approx(1 * K)  # sin(pi) = 0
    assert truth[4] == pytest.approx((1 - s) * K)
    assert truth[5] == pytest.approx(JAW_MID + (1 - s) * K)


def test_prediction_beats_hold_on_a_short_replay() -> None:
    # The estimators' own oracles are in test_smoothing.py; this checks the replay wiring measures both.
    hold = fidelity.replay("hold", seconds=4, jitter_ms=0)
    ours = fidelity.replay("predict", seconds=4, jitter_ms=0)
    assert hold.frames == ours.frames > 150
    assert ours.mean_error_rad < hold.mean_error_rad
