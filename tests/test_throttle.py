"""The one rule behind the agent's "told at once, then once a minute with the count" log lines."""

from __future__ import annotations

import pytest
from twin.core.throttle import Throttle


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_the_first_is_told_then_one_an_interval_with_how_many_came() -> None:
    clock = Clock()
    lines = Throttle(60.0, clock=clock)
    assert lines.due() == 1
    for _ in range(5):
        clock.now += 10.0
        assert lines.due() is None
    clock.now += 10.0  # 60 s after the first line: the sixth held back, and this one
    assert lines.due() == 6
    assert (lines.streak, lines.told) == (7, 2)


def test_the_first_few_are_each_told_before_the_interval_applies() -> None:
    clock = Clock()
    lines = Throttle(60.0, first=3, clock=clock)
    assert [lines.due() for _ in range(5)] == [1, 1, 1, None, None]
    clock.now += 60.0
    assert lines.due() == 3


def test_a_cleared_streak_tells_the_next_occurrence_at_once_and_says_what_went_untold() -> None:
    clock = Clock()
    lines = Throttle(60.0, clock=clock)
    assert lines.due() == 1
    assert lines.due() is None and lines.due() is None
    assert lines.clear() == 2
    assert (lines.streak, lines.told) == (0, 0)
    assert lines.due() == 1  # within the minute of the last line, but a new streak
    assert lines.clear() == 0


def test_force_tells_within_the_interval_and_a_callers_own_time_is_used() -> None:
    lines = Throttle(10.0, clock=lambda: pytest.fail("the caller's time was given"))
    assert lines.due(now=0.0) == 1
    assert lines.due(now=5.0) is None
    assert lines.due(now=6.0, force=True) == 2
    assert lines.due(now=15.0) is None  # the interval counts from the forced line
    assert lines.due(now=16.0) == 2


@pytest.mark.parametrize(("interval_s", "first"), [(0.0, 1), (-1.0, 1), (60.0, 0)])
def test_a_throttle_that_could_not_tell_is_refused(interval_s: float, first: int) -> None:
    with pytest.raises(ValueError, match="interval_s > 0 and first >= 1"):
        Throttle(interval_s, first=first)
