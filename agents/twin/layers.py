"""The layers of the `twin` package, lowest first: the one definition of which folder may import which.

A module may import from its own layer and from the layers below it, never from a layer above, and never
from a different layer of the same rank (transport and output are independent of each other). The test
tests/test_layers.py parses every module's imports and enforces this; docs/architecture.md draws it.
"""

from __future__ import annotations

LAYERS: tuple[tuple[str, ...], ...] = (
    ("robot",),  # SO-101 constants, calibration, MuJoCo model loading
    ("core",),  # telemetry contract and decoding, topic rules, per-device twin, smoothing, health, latency
    ("transport", "output"),  # MQTT settings/client/subscriber/mailbox | sinks, USD recording, PNG render
    ("service",),  # the agent: typed state, config, HTTP API, Prometheus rendering, logs
    ("viewer",),  # `twin view`: state feed, fleet model, window
    ("tools",),  # edge simulator, local rig, mosquitto, demo, instance control, benchmarks
    ("cli",),  # the `twin` command and its subcommands
)


def rank(layer: str) -> int:
    """The position of `layer` in LAYERS (0 = lowest); KeyError for a folder that is not a layer."""
    for index, peers in enumerate(LAYERS):
        if layer in peers:
            return index
    raise KeyError(f"{layer!r} is not a layer of twin; add it to twin.layers.LAYERS")
