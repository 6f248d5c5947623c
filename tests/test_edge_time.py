"""twin.output.edge_time: the one rule that places an arm's samples on its time line in Rerun, ROS 2 and the
USD recording, across an edge clock reset."""

from __future__ import annotations

import logging

import pytest
from twin.output.edge_time import EdgeTime


def place_all(line: EdgeTime, samples: list[tuple[int, float]]) -> list[int]:
    return [line.place(edge, received, device="arm-001", output="test") for edge, received in samples]


def test_the_edge_time_as_is_while_it_runs_forward() -> None:
    samples = [(1_000_000 + 100 * i, 50.0 + 0.1 * i + (0.03 if i % 3 else 0.0)) for i in range(20)]
    assert place_all(EdgeTime(), samples) == [edge for edge, _ in samples]


def test_after_a_reset_the_line_goes_on_by_the_time_that_passed_then_back_at_the_edge_time(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Reset 30 s back, 2.5 s after the last sample (the mirror ignores older ones that long first): the next
    sample is 2.5 s after the last one, the rest at the edge's spacing; once the edge clock is set right (a
    step past the line), its own time again."""
    steady = [(1_000_000 + 100 * i, 50.0 + 0.1 * i) for i in range(10)]
    reset = [(973_400 + 100 * i, 53.4 + 0.1 * i) for i in range(10)]
    set_right = [(1_010_000 + 100 * i, 54.4 + 0.1 * i) for i in range(5)]
    caplog.set_level(logging.WARNING, logger="twin.output.edge_time")
    placed = place_all(EdgeTime(), steady + reset + set_right)
    assert placed[:10] == [edge for edge, _ in steady]
    assert placed[10:20] == [1_000_900 + 2_500 + 100 * i for i in range(10)]
    assert placed[20:] == [edge for edge, _ in set_right]
    [warning] = [r.getMessage() for r in caplog.records]
    assert "arm-001" in warning and "(30.0 s behind" in warning and warning.startswith("test:")
    assert "NTP" in warning


def test_a_reset_with_no_receive_time_passed_still_moves_on() -> None:
    placed = place_all(EdgeTime(), [(5_000, 1.0), (4_000, 1.0), (4_000, 1.0)])
    assert placed == [5_000, 5_001, 5_002]


def test_a_stamp_equal_to_the_last_one_moves_on_by_the_time_that_passed() -> None:
    """An edge clock that stood still (the mirror rebuilds the twin after 2 s of such samples) gave the same
    stamp twice: one frame twice to tf, a bag player and Rerun."""
    placed = place_all(EdgeTime(), [(1_000, 0.0), (1_100, 0.1), (1_100, 2.2), (1_100, 2.3)])
    assert placed == [1_000, 1_100, 3_200, 3_300]


def test_a_clock_that_stands_still_is_told_once_a_minute_with_the_count_between(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A review: the mirror rebuilds a stood-still clock's twin every 2 s, and each output warned each time,
    three warnings every 2 s beside the mirror's own."""
    line = EdgeTime()
    caplog.set_level(logging.WARNING, logger="twin.output.edge_time")
    line.place(1_000, 0.0, device="arm-001", output="test")
    for n in range(1, 32):  # the same stamp every 2 s for a minute
        line.place(1_000, 2.0 * n, device="arm-001", output="test")
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 2, warnings
    assert "more such" not in warnings[0]
    assert "; 29 more such since the last warning)" in warnings[1], warnings[1]


def test_a_receive_clock_stepped_back_does_not_silence_the_warning(caplog: pytest.LogCaptureFixture) -> None:
    """A review: a session export passes wall-clock receive times; one stepped back an hour kept every reset
    untold for that hour."""
    line = EdgeTime()
    caplog.set_level(logging.WARNING, logger="twin.output.edge_time")
    place_all(line, [(5_000, 7_200.0), (4_000, 7_201.0), (4_000, 3_600.0)])
    assert len(caplog.records) == 2, [r.getMessage() for r in caplog.records]
