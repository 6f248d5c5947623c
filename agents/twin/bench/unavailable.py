"""Why a scenario cannot run here: a reason of the machine, not a fault of the code it measures."""

from __future__ import annotations


class Unavailable(RuntimeError):  # noqa: N818 - reads as what the scenario is here: unavailable
    """The scenario cannot run in this environment; the message names what is missing and the fix.

    `twin bench all` reports such a step as skipped and goes on with the others, where any other error is a
    failure of the step (docs/performance.md, "Reproduce")."""
