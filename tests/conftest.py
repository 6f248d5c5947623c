"""Shared fixtures: a private mosquitto per test (real broker, free loopback port)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from twin.tools.mosquitto import MosquittoBroker, MosquittoNotFound


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[MosquittoBroker]:
    """A started mosquitto on 127.0.0.1:<free port>; its config and log live in tmp_path/mosquitto."""
    try:
        broker = MosquittoBroker(workdir=tmp_path / "mosquitto")
    except MosquittoNotFound as exc:
        pytest.fail(f"{exc} (the transport tests need a real broker)")
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()
