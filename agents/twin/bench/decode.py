"""Decode: the cost of decoding and validating one edge message against `json.loads` of the same bytes.

Both are timed in the same process and run, interleaved in rounds, and the best round of each is kept (the
least disturbed by other work on a shared machine), so the ratio compares like with like. Payloads are what
the edge publishes (twin.edge.payload: mock motion with the servo diagnostics), both variants.
"""

from __future__ import annotations

import json
import random
import time
from collections.abc import Callable
from typing import Any

from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
from twin.edge.payload import encode, make_payload

ROUNDS = 15
CALLS_PER_ROUND = 2000


def _best_us(fn: Callable[[], Any], rounds: list[float]) -> None:
    start = time.perf_counter()
    for _ in range(CALLS_PER_ROUND):
        fn()
    rounds.append((time.perf_counter() - start) / CALLS_PER_ROUND * 1e6)


def _case(variant: str, units: Units) -> dict[str, Any]:
    payload = encode(make_payload("arm-0001", 1.0, variant, random.Random(1), timestamp_ms=1_706_000_000_000))
    decoder = TelemetryDecoder(DecoderConfig(units=units, auto_evidence_messages=1))
    decoder.decode(payload, topic_device="arm-0001")  # auto decides here; explicit units change nothing
    loads: list[float] = []
    decode: list[float] = []
    for _ in range(ROUNDS):
        _best_us(lambda: json.loads(payload), loads)
        _best_us(lambda: decoder.decode(payload, topic_device="arm-0001"), decode)
    return {
        "variant": variant,
        "units": str(units),
        "payload_bytes": len(payload),
        "json_loads_us": min(loads),
        "decode_validate_us": min(decode),
        "ratio": min(decode) / min(loads),
    }


def run() -> dict[str, Any]:
    return {
        "scenario": "decode",
        "method": f"best of {ROUNDS} interleaved rounds of {CALLS_PER_ROUND} calls each, one process",
        "cases": [
            _case("ticks", Units.TICKS),
            _case("ticks", Units.AUTO),
            _case("degrees", Units.DEGREES),
        ],
    }
