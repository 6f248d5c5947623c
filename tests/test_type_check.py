"""What `make lint`'s mypy checks the stacks against.

mypy follows only the aws_cdk modules the stacks import (pyproject.toml says why); a module imported but
not on that list would be Any to mypy, and every call into it unchecked. This keeps the list and the imports
equal.
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CHECKED = [*sorted((REPO / "stacks").glob("*.py")), REPO / "app.py"]


def _aws_cdk_modules_imported(path: Path) -> set[str]:
    """The aws_cdk modules (the root and submodules) a source file imports, as dotted names."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.split(".")[0] == "aws_cdk")
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "aws_cdk":
            found.add(node.module)
            # `from aws_cdk import aws_iam` imports a module; `from aws_cdk import Stack` a name of the root.
            found.update(f"{node.module}.{alias.name}" for alias in node.names if alias.name[0].islower())
    return found


def _followed_aws_cdk_modules() -> set[str]:
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["mypy"]
    followed: set[str] = set()
    for override in config["overrides"]:
        modules = override["module"]
        modules = [modules] if isinstance(modules, str) else modules
        if override.get("follow_imports") == "normal":
            followed.update(m for m in modules if m.split(".")[0] == "aws_cdk")
    return followed


def test_the_helper_sees_both_kinds_of_import(tmp_path: Path) -> None:
    source = tmp_path / "s.py"
    source.write_text("import aws_cdk as cdk\nfrom aws_cdk import Stack, aws_ec2 as ec2\nimport json\n")
    assert _aws_cdk_modules_imported(source) == {"aws_cdk", "aws_cdk.aws_ec2"}


def test_mypy_follows_exactly_the_aws_cdk_modules_the_stacks_import() -> None:
    imported = set().union(*(_aws_cdk_modules_imported(path) for path in CHECKED))
    followed = _followed_aws_cdk_modules()
    assert "aws_cdk.aws_ec2" in imported, "the stacks' imports were not found: has stacks/ moved?"
    missing = sorted(imported - followed)
    assert not missing, (
        f"the stacks import {missing}, which mypy skips (Any): add them to the follow_imports = 'normal' "
        "override for aws_cdk in pyproject.toml"
    )
    unused = sorted(followed - imported)
    assert not unused, f"mypy follows {unused}, which nothing imports: drop them from pyproject.toml"
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["mypy"]
    skipped = [o for o in config["overrides"] if o.get("follow_imports") == "skip"]
    assert any("aws_cdk.*" in o["module"] for o in skipped), "the rest of aws_cdk is no longer skipped"
