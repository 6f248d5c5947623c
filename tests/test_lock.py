"""The locks: every environment the project builds comes from a file that pins each package by version and
hash, and each file still says what it is built from says (pyproject.toml, requirements/*.in).

`make check-lock` (part of `make test`) compares uv.lock with pyproject.toml and requirements/host.txt with
uv.lock's export; these tests check the parts a re-resolution would need the network for, offline."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

REPO = Path(__file__).resolve().parent.parent
REQUIREMENTS = REPO / "requirements"
UV = REPO / ".venv-uv" / "bin" / "uv"
PIN = re.compile(r"^([A-Za-z0-9_.\-]+)(?:\[[^\]]*\])?==([^\s;\\]+)")


def _entries(path: Path) -> list[tuple[str, str, list[str]]]:
    """(name, version, hashes) of each requirement in a hashed requirements file."""
    text = re.sub(r"\\\n\s*", " ", path.read_text())
    entries = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        match = PIN.match(line)
        assert match, f"{path.name}: not an exact pin: {line[:80]!r}"
        entries.append(
            (canonicalize_name(match[1]), match[2], re.findall(r"--hash=sha256:([0-9a-f]{64})", line))
        )
    return entries


LOCKED_FILES = sorted(REQUIREMENTS.glob("*.txt"))


@pytest.mark.parametrize("path", LOCKED_FILES, ids=lambda p: p.name)
def test_every_locked_package_is_pinned_with_a_hash(path: Path) -> None:
    entries = _entries(path)
    assert entries, f"{path.name} pins nothing"
    for name, version, hashes in entries:
        assert hashes, f"{path.name}: {name}=={version} has no --hash (pip --require-hashes would refuse it)"


@pytest.mark.parametrize("source", sorted(REQUIREMENTS.glob("*.in")), ids=lambda p: p.name)
def test_each_tool_lock_satisfies_what_its_in_file_asks(source: Path) -> None:
    pins = {name: version for name, version, _ in _entries(source.with_suffix(".txt"))}
    for raw in source.read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        wanted = Requirement(line)
        name = canonicalize_name(wanted.name)
        assert name in pins, f"{source.name} asks for {wanted}; {source.stem}.txt lacks it: run make lock"
        assert wanted.specifier.contains(pins[name], prereleases=True), (
            f"{source.name} asks for {wanted}; {source.stem}.txt pins {pins[name]}: run make lock"
        )


def test_the_host_requirements_are_the_lock_export_with_the_build_backend() -> None:
    """What the instance installs with --require-hashes: the runtime, its extras and the build backend."""
    names = {name for name, _, _ in _entries(REQUIREMENTS / "host.txt")}
    assert {
        "mujoco",
        "usd-core",
        "awsiotsdk",
        "msgspec",
        "deltalake",
        "cyclonedds",
        "setuptools",
        "wheel",
    } <= names
    # Test and benchmark tools never reach the instance.
    assert not names & {"pytest", "moto", "aws-cdk-lib", "playwright", "ruff"}
    assert "so101-twin" not in names  # the agent itself is installed from its source, with --no-deps


@pytest.mark.slow
def test_uv_lock_matches_pyproject_and_host_txt_is_its_export() -> None:
    assert UV.exists(), "make setup installs uv into .venv-uv"
    check = subprocess.run(
        [str(UV), "lock", "--check", "--offline"],
        check=False,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert check.returncode == 0, check.stderr
    export = subprocess.run(
        [
            str(UV),
            "export",
            "--frozen",
            "--quiet",
            "--no-dev",
            "--extra",
            "history",
            "--extra",
            "ros2",
            "--group",
            "build",
            "--no-emit-project",
            "--no-header",
            "--format",
            "requirements.txt",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    assert export.stdout == (REQUIREMENTS / "host.txt").read_text()
