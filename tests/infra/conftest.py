"""Session fixtures for the infra tests: each stack variant is synthesized once and shared (synth is slow)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from .synth import ALL_OPTIONS, Synth, synthesize

# A test that needs a synthesized stack waits for `cdk synth` (tens of seconds on the dev machine): slow.
SYNTH_FIXTURES = frozenset({"synth_default", "synth_all_options", "synth_factory"})


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if SYNTH_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session", autouse=True)
def _jsii_quiet() -> None:
    os.environ.setdefault("JSII_SILENCE_WARNING_END_OF_LIFE_NODE_VERSION", "20")


@pytest.fixture(scope="session")
def synth_default(tmp_path_factory: pytest.TempPathFactory) -> Synth:
    return synthesize(tmp_path_factory.mktemp("cdk-default"))


@pytest.fixture(scope="session")
def synth_all_options(tmp_path_factory: pytest.TempPathFactory) -> Synth:
    return synthesize(tmp_path_factory.mktemp("cdk-all"), **ALL_OPTIONS)


@pytest.fixture(scope="session")
def synth_factory(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Synth]:
    def make(region: str | None = None, agent_source: Path | None = None, **overrides: Any) -> Synth:
        return synthesize(
            tmp_path_factory.mktemp("cdk-variant"), region=region, agent_source=agent_source, **overrides
        )

    return make
