"""The code's shape: no function is longer than MAX_FUNCTION_LINES.

Long work is split into named steps, so each function reads as one thing and its name says what it does.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
MAX_FUNCTION_LINES = 60


def checked_files() -> list[Path]:
    return [
        *sorted((REPO_ROOT / "agents").rglob("*.py")),
        *sorted((REPO_ROOT / "stacks").rglob("*.py")),
        REPO_ROOT / "app.py",
    ]


def long_functions(path: Path) -> list[str]:
    """`path:function (N lines)` for each function or method over the limit (decorators not counted)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            assert node.end_lineno is not None
            lines = node.end_lineno - node.lineno + 1
            if lines > MAX_FUNCTION_LINES:
                found.append(f"{path.relative_to(REPO_ROOT)}:{node.name} ({lines} lines)")
    return found


def test_no_function_is_longer_than_the_limit() -> None:
    """Long functions are split into named steps so each reads as one thing."""
    files = checked_files()
    assert len(files) > 10, files
    offenders = [entry for path in files for entry in long_functions(path)]
    assert not offenders, f"functions over {MAX_FUNCTION_LINES} lines: " + ", ".join(offenders)
