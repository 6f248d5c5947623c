"""`twin bench all` without its scenarios: what it says while it runs and what it prints (the scenarios
themselves are tests/test_bench.py's, which are slow)."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from twin.cli.commands import bench as cmd
from twin.cli.main import build_parser


def test_bench_all_says_which_scenario_runs_on_stderr_and_prints_only_figures(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # A walk: `twin bench all --json > docs/performance.json`, as the docs reproduce it, sat silent for more
    # than the "about 6 minutes" said, on a busy machine, with no word of where it was.
    ran: list[str] = []

    def scenario(name: str) -> Any:
        def run(**options: Any) -> dict[str, Any]:
            ran.append(name)
            return {"scenario": name, **options}

        def write(results: dict[str, Any], plot: Path) -> Path:
            return plot

        return SimpleNamespace(run=run, write=write)

    monkeypatch.setattr(cmd, "_bench", scenario)
    args = build_parser().parse_args(["bench", "all", "--json", "--plot", str(tmp_path / "p.png")])
    assert cmd.run(args) == 0
    out, err = capsys.readouterr()
    figures = json.loads(out)  # stdout stays the figures alone
    lines = err.splitlines()
    assert (
        lines[0] == "twin bench: 1 of 13: throughput (100 arms)" and lines[-1] == "twin bench: 13 of 13: cost"
    ), err
    assert len(lines) == 13 == len(ran), err
    assert lines[1] == "twin bench: 2 of 13: throughput (2000 arms)", err
    assert [f["arms"] for f in figures["throughput"]] == [100, 2000]
    assert list(figures)[1:] == [
        *("fidelity", "footprint", "ros2", "render", "rerun", "quota", "decode", "usd", "worker", "console"),
        *("cost", "plot"),
    ]
