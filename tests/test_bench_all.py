"""`twin bench all` without its scenarios: what it says while it runs and what it prints (the scenarios
themselves are tests/test_bench.py's, which are slow)."""

from __future__ import annotations

import argparse
import importlib
import json
import os
import shutil
import subprocess
import sys
from importlib.machinery import ModuleSpec
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any

import pytest
from twin.cli.commands import bench as cmd
from twin.cli.main import build_parser, main


def _scenarios(
    ran: list[str], real: tuple[str, ...] = (), broken: str = "", error: BaseException | None = None
) -> Any:
    """A stand-in for cmd._bench: each scenario records that it ran and returns its options, except those
    named in `real` (the real module) and `broken` (raises `error`, by default as a step that ran and
    failed)."""

    def scenario(name: str) -> Any:
        if name in ("unavailable", *real):
            return importlib.import_module(f"twin.bench.{name}")

        def run(**options: Any) -> dict[str, Any]:
            ran.append(name)
            if name == broken:
                raise error or RuntimeError(f"the agent exited during the {name} run (code 1)")
            return {"scenario": name, **options}

        def write(results: dict[str, Any], plot: Path) -> Path:
            if name == broken:
                raise error or ValueError(f"cannot draw {plot}")
            return plot

        return SimpleNamespace(run=run, write=write)

    return scenario


def _installed(monkeypatch: pytest.MonkeyPatch, *names: str) -> None:
    """Stand-in modules, so a test of something else does not depend on what this venv has installed."""
    for name in names:
        module = ModuleType(name)
        module.__spec__ = ModuleSpec(name, loader=None)
        monkeypatch.setitem(sys.modules, name, module)


def _all_args(plot: Path) -> argparse.Namespace:
    # Every test runs `bench all` the same way: figures as JSON on stdout, the plot out of docs/.
    return build_parser().parse_args(["bench", "all", "--json", "--plot", str(plot)])


def test_bench_all_says_which_scenario_runs_on_stderr_and_prints_only_figures(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # A walk: `twin bench all --json > docs/performance.json`, as the docs reproduce it, sat silent for more
    # than the "about 6 minutes" said, on a busy machine, with no word of where it was.
    ran: list[str] = []
    monkeypatch.setattr(cmd, "_bench", _scenarios(ran))
    args = _all_args(tmp_path / "p.png")
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


def test_bench_all_without_root_skips_ros2_keeps_the_other_figures_and_exits_3(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # A walk: as a user without root, the ros2 step's namespace error stopped `bench all` at step 5 and the
    # figures of the four steps before it were lost. The real ros2 scenario runs here, with an `unshare` that
    # fails as it does for a user without CAP_SYS_ADMIN.
    tools = tmp_path / "bin"
    tools.mkdir()
    for tool, script in [
        ("unshare", "echo 'unshare: unshare failed: Operation not permitted' >&2; exit 1"),
        ("ip", "exit 0"),
    ]:
        (tools / tool).write_text(f"#!/bin/sh\n{script}\n")
        (tools / tool).chmod(0o755)
    monkeypatch.setenv("PATH", str(tools))
    monkeypatch.setattr(importlib.import_module("twin.bench.netns").os, "geteuid", lambda: 1000)
    # ros2.run looks for cyclonedds first: without it here the step would be skipped for that instead.
    _installed(monkeypatch, "cyclonedds")
    ran: list[str] = []
    monkeypatch.setattr(cmd, "_bench", _scenarios(ran, real=("ros2",)))
    args = _all_args(tmp_path / "p.png")
    assert cmd.run(args) == cmd.EXIT_SKIPPED == 3
    out, err = capsys.readouterr()
    figures = json.loads(out)
    assert "ros2" not in figures and "ros2" not in ran
    assert [f["arms"] for f in figures["throughput"]] == [100, 2000]
    assert {"fidelity", "footprint", "render", "cost", "plot"} <= set(figures), figures
    assert list(figures["skipped"]) == ["ros2"] and "failed" not in figures
    assert "Operation not permitted" in figures["skipped"]["ros2"], figures
    assert "run it as root" in figures["skipped"]["ros2"], figures
    lines = err.splitlines()
    assert (
        lines[-1] == "twin bench: 0 step(s) failed, 1 skipped: ros2; the figures above are the other steps'"
    )
    assert lines[-2].startswith("twin bench: skipped ros2: unshare -n failed"), err
    assert "twin bench: 13 of 13: cost" in lines, err


def test_bench_all_reports_a_step_that_failed_runs_the_rest_and_exits_1(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # A step that ran and broke is a real failure: the run fails, but the other steps' figures are printed.
    ran: list[str] = []
    monkeypatch.setattr(cmd, "_bench", _scenarios(ran, broken="render"))
    args = _all_args(tmp_path / "p.png")
    assert cmd.run(args) == 1
    out, err = capsys.readouterr()
    figures = json.loads(out)
    assert figures["failed"] == {"render": "RuntimeError: the agent exited during the render run (code 1)"}
    assert "render" not in figures and "skipped" not in figures
    assert {"ros2", "rerun", "cost", "plot"} <= set(figures) and ran[-1] == "cost", figures
    assert err.splitlines()[-2:] == [
        "twin bench: FAILED render: RuntimeError: the agent exited during the render run (code 1)",
        "twin bench: 1 step(s) failed, 0 skipped: render; the figures above are the other steps'",
    ], err


def test_bench_all_whose_plot_fails_still_prints_every_step_and_exits_1(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    ran: list[str] = []
    monkeypatch.setattr(cmd, "_bench", _scenarios(ran, broken="plot"))
    args = _all_args(tmp_path / "p.png")
    assert cmd.run(args) == 1
    figures = json.loads(capsys.readouterr().out)
    assert figures["failed"] == {"plot": f"ValueError: cannot draw {tmp_path / 'p.png'}"}
    assert len(ran) == 13 and "cost" in figures, figures


def test_bench_all_interrupted_while_the_plot_is_drawn_prints_every_step_and_exits_130(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # A review: Ctrl-C while the plot was drawn, after every step had finished, lost every figure.
    ran: list[str] = []
    monkeypatch.setattr(cmd, "_bench", _scenarios(ran, broken="plot", error=KeyboardInterrupt()))
    assert cmd.run(_all_args(tmp_path / "p.png")) == cmd.EXIT_INTERRUPTED
    out, err = capsys.readouterr()
    figures = json.loads(out)
    assert figures["interrupted"] == "plot" and "plot" not in figures and "failed" not in figures, figures
    assert len(ran) == 13 and "cost" in figures, figures
    assert err.splitlines()[-1].endswith(
        "interrupted during plot: the figures above are every step's, the plot not drawn"
    )


def test_the_plot_interrupted_while_saved_leaves_the_previous_plot_whole(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # A review: the plot was saved straight over docs/performance.png, so Ctrl-C mid-save left it cut off.
    from matplotlib.figure import Figure

    plot_module = importlib.import_module("twin.bench.plot")
    plot = tmp_path / "performance.png"
    plot.write_bytes(b"the committed plot")

    def cut_off(self: Figure, fname: Any, **kwargs: Any) -> None:
        fname.write(b"\x89PNG half")
        raise KeyboardInterrupt

    monkeypatch.setattr(Figure, "savefig", cut_off)
    with pytest.raises(KeyboardInterrupt):
        plot_module.write({"throughput": []}, plot)
    assert plot.read_bytes() == b"the committed plot"
    assert [p.name for p in tmp_path.iterdir()] == ["performance.png"]


def test_bench_all_without_a_throughput_run_leaves_the_plot_as_it_was(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # A review: a run whose throughput step broke drew the plot all the same, its latency panel empty or
    # half, over the committed docs/performance.png. The real plot module runs here.
    plot = tmp_path / "p.png"
    plot.write_bytes(b"the committed plot")
    ran: list[str] = []
    monkeypatch.setattr(cmd, "_bench", _scenarios(ran, real=("plot",), broken="throughput"))
    args = _all_args(plot)
    assert cmd.run(args) == 1
    figures = json.loads(capsys.readouterr().out)
    assert plot.read_bytes() == b"the committed plot" and "plot" not in figures, figures
    assert list(figures["failed"]) == ["throughput (100 arms)", "throughput (2000 arms)"], figures
    assert figures["skipped"] == {
        "plot": f"not drawn, {plot} is left as it was: it needs the figures of throughput (100 arms) and "
        "throughput (2000 arms)"
    }
    assert figures["throughput"] == [] and ran[-1] == "cost"


def test_bench_all_interrupted_prints_the_finished_steps_figures_as_json_and_exits_130(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # A walk: Ctrl-C in a step of a 6-minute run lost the figures of every step before it. It must end the
    # run (not be reported as that step's failure, the rest not run), print what finished, and exit 130.
    ran: list[str] = []
    monkeypatch.setattr(cmd, "_bench", _scenarios(ran, broken="footprint", error=KeyboardInterrupt()))
    plot = tmp_path / "p.png"
    assert main(["bench", "all", "--json", "--plot", str(plot)]) == cmd.EXIT_INTERRUPTED == 130
    assert ran[-1] == "footprint" and len(ran) == 4, ran
    out, err = capsys.readouterr()
    figures = json.loads(out)
    assert figures["interrupted"] == "footprint" and "failed" not in figures, figures
    assert [f["arms"] for f in figures["throughput"]] == [100, 2000] and "fidelity" in figures, figures
    assert "footprint" not in figures and "plot" not in figures and not plot.exists(), figures
    assert err.splitlines()[-1] == (
        "twin bench: interrupted during footprint: the figures above are the steps before it"
    ), err


def test_bench_all_interrupted_on_the_progress_line_keeps_the_figures_before_it(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # A review: Ctrl-C while the line that names the next step was written, between two steps, escaped the
    # run and lost every figure before it.
    ran: list[str] = []
    monkeypatch.setattr(cmd, "_bench", _scenarios(ran))
    said = cmd.console.err

    def err(message: str) -> None:
        if message.startswith("3 of "):
            raise KeyboardInterrupt
        said(message)

    monkeypatch.setattr(cmd.console, "err", err)
    assert main(["bench", "all", "--json", "--plot", str(tmp_path / "p.png")]) == 130
    figures = json.loads(capsys.readouterr().out)
    assert figures["interrupted"] == "fidelity" and ran == ["throughput", "throughput"], figures
    assert [f["arms"] for f in figures["throughput"]] == [100, 2000], figures


def test_bench_all_interrupted_prints_the_finished_steps_as_text(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    ran: list[str] = []
    monkeypatch.setattr(cmd, "_bench", _scenarios(ran, broken="render", error=KeyboardInterrupt()))
    assert main(["bench", "all", "--plot", str(tmp_path / "p.png")]) == 130
    lines = capsys.readouterr().out.splitlines()
    assert "fidelity:" in lines and "ros2:" in lines and "interrupted: render" in lines, lines
    assert "render:" not in lines, lines


def _console_cannot_start(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> list[str]:
    """The real console scenario, whose rig records that it was started instead of starting."""
    console = importlib.import_module("twin.bench.console")
    started: list[str] = []
    monkeypatch.setattr(console, "LocalRig", lambda: started.append("rig"))
    monkeypatch.setattr(console, "CHROMIUM", tmp_path / "chromium")
    return started


@pytest.mark.parametrize("missing", ["chromium", "playwright"])
def test_bench_all_without_a_browser_skips_console_before_starting_its_fleet(
    missing: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # A review: without chromium the console step started the rig and a 2,000-arm fleet and waited for it
    # (minutes, and a timeout on a busy machine was a failure) before it found out; without Playwright it
    # failed where a missing chromium was skipped.
    started = _console_cannot_start(monkeypatch, tmp_path)
    if missing == "chromium":
        # Playwright is looked for first: without it here the step would be skipped for that instead.
        _installed(monkeypatch, "playwright", "playwright.sync_api")
        why = f"{tmp_path / 'chromium'} is missing: `make setup` installs Debian's chromium"
    else:
        (tmp_path / "chromium").write_text("")
        monkeypatch.setitem(sys.modules, "playwright.sync_api", None)
        why = "Playwright is not installed"
    ran: list[str] = []
    monkeypatch.setattr(cmd, "_bench", _scenarios(ran, real=("console",)))
    args = _all_args(tmp_path / "p.png")
    assert cmd.run(args) == cmd.EXIT_SKIPPED
    figures = json.loads(capsys.readouterr().out)
    assert started == [] and list(figures["skipped"]) == ["console"], figures
    assert figures["skipped"]["console"].startswith(why) and "make setup" in figures["skipped"]["console"]
    assert "failed" not in figures and "console" not in figures and "plot" in figures


def test_bench_all_without_cyclonedds_skips_ros2_before_making_its_namespace(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    # Inside the namespace a missing cyclonedds surfaced only as the child's error: a failure, not a skip.
    netns = importlib.import_module("twin.bench.netns")
    made: list[str] = []
    monkeypatch.setattr(netns, "run_in_loopback_namespace", lambda *a, **k: made.append("netns"))
    monkeypatch.setitem(sys.modules, "cyclonedds", None)
    monkeypatch.setattr(cmd, "_bench", _scenarios([], real=("ros2",)))
    args = _all_args(tmp_path / "p.png")
    assert cmd.run(args) == cmd.EXIT_SKIPPED
    figures = json.loads(capsys.readouterr().out)
    assert made == [] and "failed" not in figures, figures
    assert figures["skipped"] == {
        "ros2": "cyclonedds is not installed: `make setup` installs it (the `ros2` extra of the agent "
        "package: pip install 'so101-twin[ros2]')"
    }


def test_unshare_failing_as_root_names_the_missing_capability_not_root(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # A review: root in a container without CAP_SYS_ADMIN was told to run it as root.
    netns = importlib.import_module("twin.bench.netns")
    fails = "echo 'unshare: Operation not permitted' >&2; exit 1"
    for tool, script in [("unshare", fails), ("ip", "exit 0")]:
        (tmp_path / tool).write_text(f"#!/bin/sh\n{script}\n")
        (tmp_path / tool).chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setattr(netns.os, "geteuid", lambda: 0)
    why = netns.missing_prerequisites()
    assert why is not None and "run it as root" not in why, why
    assert why.startswith("unshare -n failed (unshare: Operation not permitted)"), why
    assert "this root lacks CAP_SYS_ADMIN" in why and "CAP_NET_ADMIN" not in why, why
    assert why.endswith("(docker run --cap-add SYS_ADMIN --cap-add NET_ADMIN: the namespace needs both)"), why


def test_ip_failing_in_the_namespace_as_root_names_cap_net_admin_not_cap_sys_admin(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # A review: root without CAP_NET_ADMIN (Docker drops it by default) makes the namespace but cannot bring
    # lo up, and was told to add CAP_SYS_ADMIN, which it had.
    netns = importlib.import_module("twin.bench.netns")
    for tool, script in [
        ("unshare", 'shift; exec "$@"'),  # the namespace is made: run the probe's command
        ("ip", "echo 'RTNETLINK answers: Operation not permitted' >&2; exit 2"),
    ]:
        (tmp_path / tool).write_text(f"#!/bin/sh\n{script}\n")
        (tmp_path / tool).chmod(0o755)
    monkeypatch.setenv("PATH", f"{tmp_path}:/usr/bin:/bin")
    monkeypatch.setattr(netns.os, "geteuid", lambda: 0)
    why = netns.missing_prerequisites()
    assert why is not None and "run it as root" not in why, why
    assert "(RTNETLINK answers: Operation not permitted)" in why, why
    assert "this root lacks CAP_NET_ADMIN" in why and "lacks CAP_SYS_ADMIN" not in why, why
    assert "--cap-add NET_ADMIN" in why, why


@pytest.mark.parametrize(
    ("dropped", "lacks"), [("cap_net_admin", "CAP_NET_ADMIN"), ("cap_sys_admin", "CAP_SYS_ADMIN")]
)
def test_root_without_a_capability_is_told_that_one(dropped: str, lacks: str) -> None:
    # The same as the two tests above with the real unshare and ip, in a root with one capability dropped.
    capsh = shutil.which("capsh")
    if (
        os.geteuid() != 0
        or capsh is None
        or importlib.import_module("twin.bench.netns").missing_prerequisites()
    ):
        pytest.skip("needs root with both capabilities to drop one, and capsh (package libcap2-bin)")
    code = "from twin.bench.netns import missing_prerequisites as m; print(m())"
    dropped_run = subprocess.run(
        [capsh, f"--drop={dropped}", "--", "-c", f'exec "{sys.executable}" -c "{code}"'],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    assert f"this root lacks {lacks}" in dropped_run.stdout, dropped_run


@pytest.mark.parametrize("missing", ["chromium", "playwright"])
def test_bench_console_says_what_the_demo_says_with_its_own_setup_target(
    missing: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    # A review: the bench's browser check repeated the demo's with other words, so the two could drift.
    console = importlib.import_module("twin.bench.console")
    shots = importlib.import_module("twin.rig.console_shots")
    chromium = tmp_path / "chromium"
    monkeypatch.setattr(console, "CHROMIUM", chromium)
    if missing == "chromium":
        _installed(monkeypatch, "playwright", "playwright.sync_api")
    else:
        chromium.write_text("")
        monkeypatch.setitem(sys.modules, "playwright.sync_api", None)
    with pytest.raises(console.Unavailable) as raised:
        console._require_browser()
    demo = shots.missing_for_shots(chromium)
    assert demo is not None and "`make setup-demo`" in demo, demo
    assert str(raised.value) == demo.replace("`make setup-demo`", "`make setup`"), (str(raised.value), demo)


def test_bench_all_help_says_what_its_exit_codes_mean(capsys: pytest.CaptureFixture[str]) -> None:
    # A script that runs `bench all` tells a complete run from a partial one only by its exit code.
    with pytest.raises(SystemExit):
        build_parser().parse_args(["bench", "all", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert f"{cmd.EXIT_SKIPPED} none failed, but a step that cannot run here was skipped" in help_text
    assert "1 a step failed" in help_text
    assert f"{cmd.EXIT_INTERRUPTED} interrupted (Ctrl-C): the figures of the steps that finished" in help_text
