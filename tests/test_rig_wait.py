"""The rig's poll-until wait, and the tests' own (the same loop, failing the test instead of the rig)."""

from __future__ import annotations

import pytest
from conftest import wait_for
from twin.rig.local import RigError, wait_until


def test_wait_until_returns_the_first_truthy_value() -> None:
    values = iter([0, None, "", 3, 4])
    assert wait_until(lambda: next(values), 30.0, "a value", interval=0.0) == 3


def test_a_timeout_names_what_was_awaited_as_the_caller_asked() -> None:
    with pytest.raises(RigError, match=r"timed out after 0\.05 s waiting for the broker"):
        wait_until(lambda: False, 0.05, "the broker", interval=0.01)
    # The tests' wait fails the test (an AssertionError), not the rig.
    with pytest.raises(AssertionError, match=r"timed out after 0\.05 s waiting for the agent"):
        wait_for(lambda: None, 0.05, "the agent", interval=0.01)
