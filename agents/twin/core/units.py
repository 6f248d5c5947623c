"""The contract's units setting and payload cap, standard library only.

The agent config, the stack settings and `twin --help` need these names without loading the decoder, which
needs msgspec; twin.core.telemetry re-exports them, so they have one home.
"""

from __future__ import annotations

from enum import StrEnum


class Units(StrEnum):
    TICKS = "ticks"
    DEGREES = "degrees"
    RANGE100 = "range100"
    AUTO = "auto"


# The values of `units` in the agent config and the stack settings.
UNITS_CHOICES: tuple[str, ...] = tuple(u.value for u in Units)
# IoT Core's cap on one message (docs/aws-facts.md); the decoder's default limit and the config's.
MAX_PAYLOAD_BYTES = 128 * 1024
