"""The optional parts of the distribution (pyproject.toml's extras): a command or setting that needs an extra
which is not installed says which one and how to install it, instead of failing with an import error.

Each case runs in a fresh interpreter where the extra's libraries are made unimportable (`sys.modules[name] =
None` is how Python marks a module that must not be imported), as on an install without the extra."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest


def _run_without(libraries: list[str], code: str) -> subprocess.CompletedProcess[str]:
    blocker = "import sys\n" + "".join(f"sys.modules[{name!r}] = None\n" for name in libraries)
    return subprocess.run(
        [sys.executable, "-c", blocker + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


@pytest.mark.slow
def test_twin_history_without_the_history_extra_names_it(tmp_path: Path) -> None:
    proc = _run_without(
        ["polars", "deltalake"],
        f"""
        from twin.cli.main import main
        sys.exit(main(["history", "ls", "--history", {str(tmp_path)!r}]))
        """,
    )
    assert proc.returncode == 1, proc.stderr
    assert "twin history: polars is not installed" in proc.stderr
    assert "pip install 'so101-twin[history]'" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.slow
def test_history_settings_without_deltalake_name_the_extra(tmp_path: Path) -> None:
    proc = _run_without(
        ["deltalake"],
        f"""
        from twin.output.history import HistoryError, HistorySettings
        try:
            HistorySettings(uri={str(tmp_path)!r})
        except HistoryError as exc:
            print(exc)
        """,
    )
    assert proc.returncode == 0, proc.stderr
    assert "deltalake is not installed" in proc.stdout
    assert "so101-twin[history]" in proc.stdout
    assert "[history] enabled = false" in proc.stdout


def test_an_import_error_of_our_own_is_not_mistaken_for_a_missing_extra() -> None:
    from twin.cli.output import missing_extra_message

    assert missing_extra_message(ModuleNotFoundError("no", name="twin.nothing")) is None
    assert "bench extra" in (missing_extra_message(ModuleNotFoundError("no", name="psutil")) or "")
