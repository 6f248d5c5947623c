"""Dependencies between the agent's layers point one way (twin/layers.py): checked by parsing every import."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from twin.layers import LAYERS, rank

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "agents" / "twin"
LAYER_NAMES = {name for peers in LAYERS for name in peers}


def module_file(name: str) -> Path | None:
    """The file of the twin module `name` (a package's __init__.py), or None when there is no such module."""
    base = PACKAGE.parent.joinpath(*name.split("."))
    return next((p for p in (base.with_suffix(".py"), base / "__init__.py") if p.is_file()), None)


def imported_modules(source: str, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in `source`, lazy ones inside functions included."""
    found: list[tuple[int, str]] = []
    package_parts = module.split(".") if is_package else module.split(".")[:-1]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package_parts[: len(package_parts) - node.level + 1]
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            found.append((node.lineno, name))
            # `from twin import rig` imports the layer `rig`; `from twin.core import topics` that module.
            if name.split(".")[0] == "twin":
                found.extend(
                    (node.lineno, f"{name}.{alias.name}")
                    for alias in node.names
                    if module_file(f"{name}.{alias.name}") is not None
                )
    return found


def layer_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "twin" and parts[1] in LAYER_NAMES else None


def violations(source: str, module: str, is_package: bool = False) -> list[str]:
    own = layer_of(module)
    problems = []
    seen = set()  # `from twin.viewer import window` names the package and the module: one problem
    for line, target in imported_modules(source, module, is_package):
        other = layer_of(target)
        if other is None or other == own or (line, other) in seen:
            continue
        seen.add((line, other))
        if own is None:
            problems.append(f"{module}:{line} imports {target}, but modules outside the layers import none")
        elif rank(other) > rank(own):
            problems.append(
                f"{module}:{line} imports {target}: layer {own} must not import {other} (above it)"
            )
        elif rank(other) == rank(own):
            problems.append(f"{module}:{line} imports {target}: {own} and {other} are peers, independent")
    return problems


def all_modules() -> list[tuple[Path, str, bool]]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = list(rel.parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        out.append((path, ".".join(parts), is_package))
    return out


def test_every_folder_is_a_layer() -> None:
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert folders == LAYER_NAMES


def test_no_module_imports_a_layer_above_its_own() -> None:
    problems = []
    for path, module, is_package in all_modules():
        problems.extend(violations(path.read_text(), module, is_package))
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize(
    ("source", "module", "problem"),
    [
        ("from twin.service.agent import AgentService\n", "twin.core.twin", "must not import service"),
        ("def f():\n    import twin.cli.main\n", "twin.robot.model", "must not import cli"),
        ("from ..viewer import window\n", "twin.service.agent", "must not import viewer"),
        ("from twin import rig\n", "twin.output.render", "must not import rig"),
        ("from twin.output.sinks import AppliedSample\n", "twin.transport.subscriber", "peers"),
        ("from twin.ops.history import HistoryReader\n", "twin.edge.simulator", "peers"),
        ("from twin.bench.harness import get_state\n", "twin.rig.demo", "must not import bench"),
    ],
)
def test_the_check_catches_upward_and_peer_imports(source: str, module: str, problem: str) -> None:
    found = violations(source, module)
    assert len(found) == 1 and problem in found[0]


def test_downward_imports_pass() -> None:
    source = (
        "from twin.core.topics import topic_filters\nfrom ..robot import so101\nimport twin.output.sinks\n"
    )
    assert violations(source, "twin.service.agent") == []
