"""Session fixtures for the infra tests: each stack variant is synthesized once and shared (synth is slow)."""

from __future__ import annotations

import os
from collections.abc import Callable

import pytest

from .synth import ALL_OPTIONS, Synth, synthesize


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
    def make(region: str | None = None, **overrides: str) -> Synth:
        return synthesize(tmp_path_factory.mktemp("cdk-variant"), region=region, **overrides)

    return make
