"""Dependencies between the agent's layers point one way, and the CDK app imports only the agent's pure
modules (twin/layers.py): checked by parsing every import, and by importing settings in a fresh process."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest
from twin.layers import LAYERS, STACK_IMPORTS, rank

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "agents" / "twin"
LAYER_NAMES = {name for peers in LAYERS for name in peers}
# The CDK app: its entry point and the stack's constructs.
CDK_APP = [REPO / "app.py", *sorted((REPO / "stacks").rglob("*.py"))]
# Heavy native libraries a config or the stack's settings must never load: synth and `twin` argument checks
# run where they are not installed, and loading them costs seconds and hundreds of MB.
HEAVY = ("awscrt", "mujoco", "pxr")


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


# --- the CDK app -------------------------------------------------------------------------------------------


def stack_import_problems(source: str, module: str, is_package: bool = False) -> list[str]:
    """Imports of the agent that the CDK app may not make: anything but STACK_IMPORTS and their packages."""
    allowed = STACK_IMPORTS | {name.rsplit(".", depth)[0] for name in STACK_IMPORTS for depth in (1, 2)}
    return [
        f"{module}:{line} imports {target}: the CDK app may import only {sorted(STACK_IMPORTS)} "
        "(twin/layers.py, STACK_IMPORTS)"
        for line, target in imported_modules(source, module, is_package)
        if target.split(".")[0] == "twin" and target not in allowed
    ]


def test_the_cdk_app_imports_only_the_agents_pure_modules() -> None:
    problems = []
    for path in CDK_APP:
        module = ".".join(path.relative_to(REPO).with_suffix("").parts)
        problems.extend(stack_import_problems(path.read_text(), module, path.name == "__init__.py"))
    assert not problems, "\n".join(problems)
    # The rule has something to hold: the stack does use the agent's rules rather than copies of them.
    used = {t for p in CDK_APP for _, t in imported_modules(p.read_text(), "stacks.x", False)}
    assert used & STACK_IMPORTS == STACK_IMPORTS


def test_what_the_stack_may_import_imports_nothing_else_of_the_agent() -> None:
    # Closed: a pure module that started importing the client (awscrt) or the twin (MuJoCo) would take the
    # stack with it. Their packages' __init__ files run too, so they are held to the same rule.
    files = {module_file(name) for name in STACK_IMPORTS}
    files |= {module_file(name.rsplit(".", depth)[0]) for name in STACK_IMPORTS for depth in (1, 2)}
    problems = []
    for path in sorted(p for p in files if p is not None):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        is_package = rel.name == "__init__"
        module = ".".join(rel.parts[:-1] if is_package else rel.parts)
        problems.extend(stack_import_problems(path.read_text(), module, is_package))
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize(
    ("source", "problem"),
    [
        ("from twin.core.telemetry import MAX_PAYLOAD_BYTES\n", "imports twin.core.telemetry"),
        ("from twin.transport import client\n", "imports twin.transport.client"),
        ("def f():\n    import twin.service.config\n", "imports twin.service.config"),
    ],
)
def test_the_stack_check_catches_an_impure_import(source: str, problem: str) -> None:
    found = stack_import_problems(source, "stacks.settings")
    assert len(found) == 1 and problem in found[0]


def loaded_in_a_fresh_process(module: str) -> dict[str, list[str]]:
    """Import `module` alone in a new interpreter (from the repository root, as `cdk synth` runs app.py) and
    return which of HEAVY and which twin modules it loaded."""
    probe = (
        "import importlib, json, sys; "
        f"importlib.import_module({module!r}); "
        f"heavy = sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r})); "
        "agent = sorted(m for m in sys.modules if m.split('.')[0] == 'twin'); "
        "print(json.dumps({'heavy': heavy, 'twin': agent}))"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=120, check=True
    )
    return json.loads(out.stdout.splitlines()[-1])


@pytest.mark.parametrize("module", ["twin.service.config", "stacks.settings"])
def test_loading_a_config_or_the_stack_settings_never_imports_awscrt_mujoco_or_pxr(module: str) -> None:
    assert loaded_in_a_fresh_process(module)["heavy"] == []


def test_the_stack_settings_load_only_the_pure_modules_at_run_time() -> None:
    # The same rule as the parse above, seen from the running interpreter (importlib included).
    loaded = set(loaded_in_a_fresh_process("stacks.settings")["twin"])
    packages = {name.rsplit(".", depth)[0] for name in STACK_IMPORTS for depth in (1, 2)}
    assert loaded - packages <= STACK_IMPORTS


def test_the_fresh_process_probe_sees_a_heavy_import() -> None:
    # The probe is able to fail: building an MQTT client does load awscrt.
    assert loaded_in_a_fresh_process("twin.transport.client")["heavy"] == ["awscrt"]
