"""The layers of the `twin` package, lowest first: the one definition of which folder may import which.

A module may import from its own layer and from the layers below it, never from a layer above, and never
from a different layer of the same rank (transport and output are independent of each other). The test
tests/test_layers.py parses every module's imports and enforces this; docs/architecture.md draws it.
The layers `rig` and `bench` are development tooling, left out of what the instance installs.
"""

from __future__ import annotations

LAYERS: tuple[tuple[str, ...], ...] = (
    ("robot",),  # SO-101 constants, calibration, MuJoCo model loading
    ("core",),  # telemetry contract and decoding, topic rules, per-device twin, smoothing, health, latency
    ("transport", "output"),  # MQTT settings/client/subscriber/mailbox | sinks, USD recording, PNG render
    ("service",),  # the agent: typed state, config, HTTP API, Prometheus rendering, logs
    # Peers: `twin view` (state feed, fleet model, window) | what the SO-101 edge publishes, its servo faults
    # and the simulator | the deployed twin from outside: instance control and checks, history, replay
    ("viewer", "edge", "ops"),
    ("rig",),  # the whole pipeline on one machine: private mosquitto, quota proxy, local rig, `twin demo`
    ("bench",),  # `twin bench`: benchmarks that print figures
    ("cli",),  # the `twin` command and its subcommands
)

# What the CDK app (app.py, stacks/) may import from the agent: pure modules only, so a value the stack
# accepts is one the agent it deploys accepts, and synth never loads awscrt, MuJoCo or USD. The set is closed
# under these modules' own imports of twin; tests/test_layers.py checks both.
STACK_IMPORTS: frozenset[str] = frozenset(
    {"twin.core.topics", "twin.core.units", "twin.transport.broker", "twin.transport.plan"}
)


def rank(layer: str) -> int:
    """The position of `layer` in LAYERS (0 = lowest); KeyError for a folder that is not a layer."""
    for index, peers in enumerate(LAYERS):
        if layer in peers:
            return index
    raise KeyError(f"{layer!r} is not a layer of twin; add it to twin.layers.LAYERS")
