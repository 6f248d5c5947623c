"""`twin demo` end to end as a user runs it: a subprocess, real mosquitto, real agent, files checked."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import psutil
import pytest
from conftest import read_rrd, wait_for
from PIL import Image

TWIN = Path(sys.executable).with_name("twin")
# The demo's plain status line (stdout not a terminal): "...  sent 41  received 40  rate ..."
RECEIVED = re.compile(r"\bsent \d+  received (\d+) ")

STATS_FIELDS = {
    "duration_s",
    "interrupted",
    "variant",
    "rate_hz",
    "devices",
    "messages",
    "latency_s",
    "per_device",
    "broker",
    "files",
    "history",
    "servos",
    "story",
    "console",
}
MESSAGE_FIELDS = {
    "sent",
    "received",
    "decoded",
    "applied",
    "rejected",
    "rejected_by_reason",
    "lost",
    "estimated_lost",
    "estimated_loss_ratio",
    "edge_skipped",
}


def demo_env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("MUJOCO_GL", None)  # the demo must choose a headless GL backend itself
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    return env


def assert_not_blank(path: Path) -> None:
    with Image.open(path) as image:
        image.verify()
    with Image.open(path) as image:
        rgb = np.asarray(image.convert("RGB"))
    assert rgb.std() > 10, f"{path} is a flat image"
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    arm = (r > 120) & (g > 80) & (b < 90) & (r - b > 90)
    assert arm.sum() > 500, f"{path} does not show the (yellow) arm"


def assert_broker_gone(stats: dict) -> None:
    pid = stats["broker"]["pid"]
    assert isinstance(pid, int), "the demo did not record its broker pid"
    if psutil.pid_exists(pid):
        try:
            proc = psutil.Process(pid)
            alive = proc.status() != psutil.STATUS_ZOMBIE and "mosquitto" in proc.name()
        except psutil.NoSuchProcess:
            alive = False
        assert not alive, f"mosquitto pid {pid} started by the demo is still running"


def assert_png(path: Path, width: int, min_height: int, max_height: int) -> None:
    """A real PNG of that size, with something drawn in it."""
    with Image.open(path) as image:
        assert image.format == "PNG", path
        image.verify()
    with Image.open(path) as image:
        assert image.width == width and min_height <= image.height <= max_height, (path, image.size)
        rgb = np.asarray(image.convert("RGB"))
    assert rgb.std() > 10, f"{path} is a flat image"


def printed_commands(stdout: str) -> list[list[str]]:
    """The commands the demo prints, between backticks (a span without a space, like the `demo` extra, names
    a thing rather than a command)."""
    return [shlex.split(span) for span in re.findall(r"`([^`\n]+)`", stdout) if " " in span]


def assert_runnable_as_printed(stdout: str, cwd: Path) -> list[list[str]]:
    """Every command the demo printed names a program that exists as printed: a path from `cwd`, the demo's
    directory, or a name on PATH without the venv's bin/ (`make demo` does not activate the venv)."""
    venv_bin = Path(sys.executable).parent.resolve()
    path = os.pathsep.join(
        entry
        for entry in os.environ.get("PATH", "").split(os.pathsep)
        if entry and Path(entry).resolve() != venv_bin
    )
    commands = printed_commands(stdout)
    for argv in commands:
        program = argv[0]
        if os.sep in program:
            exe = cwd / program
            assert exe.is_file() and os.access(exe, os.X_OK), f"{shlex.join(argv)}: no program {exe}"
        else:
            assert shutil.which(program, path=path), f"{shlex.join(argv)}: {program} is not on PATH"
    return commands


def arm_box(path: Path, frame: int = 0) -> tuple[float, float, float, float]:
    """Where the (yellow) arm is in a picture or a GIF frame, as fractions of its height and width: top,
    bottom, left, right. The top twelfth, where the PNG's label is, does not count."""
    with Image.open(path) as image:
        image.seek(frame)
        rgb = np.asarray(image.convert("RGB"))
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    arm = (r > 120) & (g > 80) & (b < 90) & (r - b > 90)
    arm[: rgb.shape[0] // 12] = False
    rows, cols = np.nonzero(arm)
    assert rows.size > 100, f"{path} frame {frame} does not show the arm"
    height, width = arm.shape
    return rows.min() / height, (rows.max() + 1) / height, cols.min() / width, (cols.max() + 1) / width


def assert_framed_like_the_gif(png: Path, gif: Path) -> None:
    """The final picture shows the whole arm as the GIF's last frame, the same pose, does: the same place and
    size in the picture, clear of its borders, not a close-up of it."""
    with Image.open(gif) as image:
        last = image.n_frames - 1
    final, animated = arm_box(png), arm_box(gif, last)
    assert all(abs(a - b) < 0.03 for a, b in zip(final, animated, strict=True)), (final, animated)
    _, bottom, left, right = final  # the top is the GIF's: the PNG's label covers its top twelfth
    assert bottom < 1 and left > 0 and right < 1, final


@pytest.mark.slow
@pytest.mark.long(seconds=50)
@pytest.mark.timeout(300)
def test_demo_tells_the_story_leaves_valid_files_and_stops_its_broker(tmp_path):
    """`twin demo` as `make demo` runs it (the defaults): the first arm's shoulder overheats until the agent
    raises its alarm, the console is photographed while it is up, and every file is left behind."""
    from pxr import Usd
    from twin.rig.demo import STORY_JOINT

    out = tmp_path / "demo"
    proc = subprocess.run(
        [str(TWIN), "demo", "--out", str(out)],
        check=False,
        env=demo_env(),
        capture_output=True,
        text=True,
        timeout=280,
    )
    assert proc.returncode == 0, f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    # Not a TTY: periodic plain status lines, the story's steps, then the summary.
    assert "received" in proc.stdout and "done in" in proc.stdout
    assert "\r" not in proc.stdout

    stats = json.loads((out / "stats.json").read_text())
    assert stats.keys() >= STATS_FIELDS
    devices = [f"arm-{i:03d}" for i in range(1, 7)]
    assert stats["devices"] == devices and stats["servos"] == "physical"
    assert stats["interrupted"] is False
    # The story: the first arm's shoulder_lift raised the over-temperature warning, and the pictures were
    # taken while the alarm was up.
    story = stats["story"]
    assert (story["device"], story["joint"]) == ("arm-001", STORY_JOINT)
    raised = {a["kind"]: a for a in story["alarms"]}
    assert "over_temperature" in raised, story
    warning = raised["over_temperature"]
    assert warning["alarm_id"] == f"arm-001/{STORY_JOINT}/over_temperature"
    assert warning["severity"] == "warning" and warning["state"] == "ACTIVE"
    assert 0 < warning["raised_after_s"] < stats["duration_s"]
    # The payload's overload warning (it comes and goes from the first seconds) is the story's too, and the
    # closing line names every alarm the story's servo raised.
    assert set(raised) <= {"overload", "over_temperature", "over_temperature_critical"}, story
    assert raised["overload"]["raised_after_s"] < warning["raised_after_s"], story
    assert "its alarms raised: overload after" in proc.stdout, proc.stdout
    assert 60.0 <= story["peak_temperature_c"] < 70.0
    assert f"alarm arm-001/{STORY_JOINT}/over_temperature ACTIVE" in proc.stdout
    # Where to open the console while it runs (the agent takes a free port).
    assert re.search(r"console at http://127\.0\.0\.1:\d+/ while the demo runs", proc.stdout), proc.stdout
    console = stats["console"]
    assert console["taken"] is True and console["skipped"] is None, console
    assert console["console_errors"] == []
    assert f"arm-001/{STORY_JOINT}/over_temperature" in console["alarms_at_pictures"]
    files = stats["files"]
    assert (files["console_fleet"], files["console_arm"]) == ("console-fleet.png", "console-arm.png")
    assert_png(out / "console-fleet.png", 1280, 800, 800)
    assert_png(out / "console-arm.png", 1280, 800, 4000)  # the whole page

    messages = stats["messages"]
    assert messages.keys() >= MESSAGE_FIELDS
    # The edge publishes for the run's 30 s at least, and on while the pictures are taken.
    assert stats["duration_s"] >= 30.0 and messages["sent"] > 0
    assert messages["rejected"] == 0 and messages["rejected_by_reason"] == {}
    assert messages["received"] == messages["sent"], "loopback QoS 0 without faults should lose nothing"
    # The agent's own loss estimate (edge timestamp gaps) agrees: nothing went missing in transit. Only the
    # samples the edge itself skipped (it skips ahead when over a second behind, on an overloaded machine)
    # leave gaps, and those gaps are all the estimate may count.
    assert messages["estimated_lost"] <= messages["edge_skipped"], messages
    if messages["edge_skipped"] == 0:
        assert messages["estimated_lost"] == 0 and messages["estimated_loss_ratio"] == 0.0
    for kind in ("end_to_end", "internal"):
        lat = stats["latency_s"][kind]
        # Seconds (milliseconds on loopback; the bound is loose because the cores may be busy with other runs:
        # speed is what `twin bench` measures, not this test).
        assert 0 <= lat["p50"] <= lat["p99"] < 10.0, lat
    # Each arm's health at the demo's last poll while the edge simulator ran: ONLINE, or STALE when that poll
    # came during the simulator's shutdown, 0.3 s (three periods) after its last message, which a busy
    # machine makes likely. Never OFFLINE.
    assert {stats["per_device"][d]["status"] for d in devices} <= {"ONLINE", "STALE"}
    # Once the edge stopped, the agent noticed the silence (docs/viewer.md, stats.json).
    assert {stats["per_device"][d]["status_after_stop"] for d in devices} == {"STALE"}

    assert_not_blank(out / files["png"])
    assert_framed_like_the_gif(out / files["png"], out / files["gif"])
    with Image.open(out / files["gif"]) as gif:
        # A frame each time the demo's status poll (every 0.25 s) finds the next one due, one a second over
        # the 30 s run: fewer when the machine is busy.
        assert gif.n_frames >= 10
        first = np.asarray(gif.convert("RGB"))
        gif.seek(gif.n_frames - 1)
        last = np.asarray(gif.convert("RGB"))
    assert np.abs(first.astype(int) - last.astype(int)).sum() > 0, "the animation does not move"
    # The twin's picture was the first one written, long before the console's.
    first_picture = proc.stdout.index("picture: ")
    assert first_picture < proc.stdout.index("taking the console pictures")

    stage = Usd.Stage.Open(str(out / files["usd"]))
    assert stage is not None
    sampled = [
        attr for prim in stage.Traverse() for attr in prim.GetAttributes() if attr.GetNumTimeSamples() > 1
    ]
    assert sampled, "the USD session has no time-sampled attributes"
    assert max(a.GetNumTimeSamples() for a in sampled) >= 10

    # The history beside the other outputs: every decoded message as a row (those the mirror coalesced while
    # it was busy too), and its plot.
    history = stats["history"]
    assert history["rows"] == {d: stats["per_device"][d]["received"] for d in devices}
    assert sum(history["rows"].values()) == messages["decoded"]
    assert history["rejected"] == {}
    assert (out / history["uri"] / "telemetry" / "_delta_log").is_dir()
    assert_not_blank(out / history["plot"])

    # The Rerun recording: the arm's tree, a pose per applied message (Rerun's own reader; the values are
    # checked against MuJoCo in test_rerun_sink.py).
    assert files["rrd"] == "twin.rrd"
    commands = assert_runnable_as_printed(proc.stdout, Path.cwd())
    # Run without a display (demo_env), where Rerun's native viewer exits at once: `twin web` serves it.
    assert [argv[1:] for argv in commands if argv[-1].endswith(".rrd")] == [["web", str(out / "twin.rrd")]]
    assert ["history", "ls", "--history", str(out / "history")] in [argv[1:] for argv in commands]
    temporal, static = read_rrd(out / "twin.rrd")
    assert "/arms/arm-001:Transform3D:translation" in static.schema.names
    poses = [v for v in temporal.column("/arms/arm-001/wrist:Transform3D:translation").to_pylist() if v]
    assert len(poses) == stats["per_device"]["arm-001"]["applied"]

    assert_broker_gone(stats)


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_demo_without_chromium_says_so_and_skips_only_the_console_pictures(tmp_path):
    out = tmp_path / "demo"
    missing = tmp_path / "no-such" / "chromium"
    args = ["--seconds", "3", "--devices", "1", "--no-rerun", "--out", str(out), "--chromium", str(missing)]
    proc = subprocess.run(
        [str(TWIN), "demo", *args],
        check=False,
        env=demo_env(),
        capture_output=True,
        text=True,
        timeout=150,
    )
    assert proc.returncode == 0, f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    expected = f"console pictures skipped: {missing} is missing: `make setup-demo` installs Debian's chromium"
    assert expected in proc.stdout
    stats = json.loads((out / "stats.json").read_text())
    assert stats["console"]["taken"] is False and "is missing" in stats["console"]["skipped"]
    assert not list(out.glob("console-*.png"))
    assert "console_fleet" not in stats["files"]
    assert_not_blank(out / stats["files"]["png"])
    # Nothing tries, or waits for, pictures that cannot be taken.
    assert "taking the console pictures" not in proc.stdout
    assert stats["messages"]["received"] > 0
    assert stats["per_device"]["arm-001"]["status_after_stop"] == "STALE"
    assert_runnable_as_printed(proc.stdout, Path.cwd())
    assert_broker_gone(stats)


def test_the_summary_names_its_programs_by_paths_that_run_from_here(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """From the directory holding the venv, as `make demo` runs in the repository beside .venv, the commands
    the summary prints name twin and rerun by their paths from there: without an activated venv a bare
    `twin` or `rerun` is not found."""
    from twin.cli.commands.demo import _summary

    here = Path(sys.executable).parent.parent.parent
    monkeypatch.chdir(here)
    monkeypatch.setenv("DISPLAY", ":0")  # where Rerun's native viewer can open a window
    stats = {
        "duration_s": 30.0,
        "messages": {"sent": 10, "received": 10, "rejected": 0},
        "latency_s": {"end_to_end": {"p50": 0.004, "p99": 0.05}},
        "files": {"png": "twin.png", "rrd": "twin.rrd"},
        "history": {"uri": "history", "plot": "history.png"},
        "story": None,
        "console": {"taken": False, "skipped": None},
    }
    _summary(stats, Path("out/demo"))
    commands = assert_runnable_as_printed(capsys.readouterr().out, here)
    twin = os.path.relpath(Path(sys.executable).with_name("twin"), here)
    rerun = os.path.relpath(Path(sys.executable).with_name("rerun"), here)
    assert sorted(commands) == sorted(
        [[twin, "history", "ls", "--history", "out/demo/history"], [rerun, "out/demo/twin.rrd"]]
    )


def test_without_a_display_the_summary_opens_the_recording_with_twin_web(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Rerun's native viewer stops at once with no display ("neither WAYLAND_DISPLAY nor ... DISPLAY is
    set"), as on the headless machines make demo runs on, so the summary offers twin web, which serves the
    same file to a browser."""
    from twin.cli.commands.demo import _summary

    here = Path(sys.executable).parent.parent.parent
    monkeypatch.chdir(here)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    stats = {
        "duration_s": 30.0,
        "messages": {"sent": 10, "received": 10, "rejected": 0},
        "latency_s": {"end_to_end": {"p50": 0.004, "p99": 0.05}},
        "files": {"rrd": "twin.rrd"},
        "story": None,
        "console": {"taken": False, "skipped": None},
    }
    _summary(stats, Path("out/demo"))
    twin = os.path.relpath(Path(sys.executable).with_name("twin"), here)
    assert assert_runnable_as_printed(capsys.readouterr().out, here) == [[twin, "web", "out/demo/twin.rrd"]]


def test_missing_playwright_is_named_with_the_way_to_install_it():
    code = (
        "import sys\nsys.modules['playwright'] = None\n"
        "from twin.rig.console_shots import missing_for_shots\nprint(missing_for_shots())"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], check=True, capture_output=True, text=True, timeout=60
    )
    assert "Playwright is not installed: `make setup-demo` installs it" in proc.stdout
    assert "so101-twin[demo]" in proc.stdout


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_demo_on_sigint_cleans_up_and_keeps_partial_results(tmp_path):
    out = tmp_path / "demo"
    stderr_path = tmp_path / "demo.stderr"
    with stderr_path.open("w") as stderr_file:
        proc = subprocess.Popen(
            [
                str(TWIN),
                "demo",
                "--seconds",
                "60",
                "--out",
                str(out),
                "--devices",
                "2",
                "--variant",
                "degrees",
            ],
            env=demo_env(),
            stdout=subprocess.PIPE,
            stderr=stderr_file,
            text=True,
        )
    lines: list[str] = []

    def read_stdout() -> None:
        for line in proc.stdout or ():
            lines.append(line)

    reader = threading.Thread(target=read_stdout, daemon=True)
    reader.start()
    try:
        # Interrupt once the agent has received telemetry: the demo prints a status line every 2 s.
        def receiving() -> bool:
            assert proc.poll() is None, f"twin demo exited {proc.returncode}:\n{''.join(lines)}"
            return any(int(m.group(1)) > 0 for m in map(RECEIVED.search, list(lines)) if m)

        wait_for(receiving, 120, "a status line with telemetry received", interval=0.1)
        proc.send_signal(signal.SIGINT)
        proc.wait(60)
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.join(30)
    stdout, stderr = "".join(lines), stderr_path.read_text()
    assert proc.returncode == 130, f"stdout:\n{stdout}\nstderr:\n{stderr}"
    assert "interrupted" in stderr
    stats = json.loads((out / "stats.json").read_text())
    assert stats["interrupted"] is True
    assert stats["variant"] == "degrees"
    assert stats["devices"] == ["arm-001", "arm-002"]
    assert stats["messages"]["received"] > 0 and stats["messages"]["rejected"] == 0
    assert stats["duration_s"] < 60  # stopped before the 60 s it was asked to run
    # Interrupted before the hot servo's alarm: no pictures, and no wait for them.
    assert stats["console"] == {"taken": False, "skipped": "interrupted"}
    assert not list(out.glob("console-*.png"))
    assert_broker_gone(stats)


def test_demo_rejects_bad_arguments():
    proc = subprocess.run(
        [str(TWIN), "demo", "--seconds", "0"],
        check=False,
        env=demo_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert "--seconds 0" in proc.stderr


def test_a_served_demo_takes_any_free_port_when_rerun_s_own_is_taken(tmp_path):
    """A walk ran `twin demo --rerun-serve` with a viewer already on 9876: the demo stopped, naming a config
    key and a flag it does not have, and left a cut twin.rrd."""
    import socket

    from twin.output.rerun_settings import DEFAULT_GRPC_PORT
    from twin.rig.demo import DemoConfig, _agent_overrides

    held = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        with contextlib.suppress(OSError):  # already taken by something else: as good for this test
            held.bind(("127.0.0.1", DEFAULT_GRPC_PORT))
            held.listen()
        overrides = _agent_overrides(DemoConfig(rerun_serve=True), ["arm-001"], tmp_path)
        assert overrides["rerun.serve"] is True and overrides["rerun.grpc_port"] == 0, overrides
        assert "rerun.grpc_port" not in _agent_overrides(DemoConfig(), ["arm-001"], tmp_path)
    finally:
        held.close()


class _AgentBetweenLooks:
    """The two things the demo's story asks of the agent: its list of alarms (`alarms`, what is up at the
    look) and its events (`events`), both from a real alarm engine, the events through the agent's own
    emitter into a store stamped with a clock the test moves."""

    def __init__(self, latch: bool) -> None:
        from twin.core.alarms import AlarmThresholds, ServoAlarms
        from twin.service.events import EventStore, FleetWatch

        self.wall = 1000.0
        self.engine = ServoAlarms(AlarmThresholds(latch=latch))
        self.store = EventStore(wall_clock=lambda: self.wall)
        self._watch = FleetWatch(self.store)

    def load(self, device: str, joint: str, seconds: list[float], percent: float) -> None:
        """The servo's load reading at each of `seconds` after the wall clock's start, the others idle."""
        from twin.core.telemetry import JointDiagnostics
        from twin.robot import so101

        still = {"velocity_rad_s": 0.0, "moving": False}
        for t in seconds:
            self.wall = 1000.0 + t
            readings = {
                name: JointDiagnostics(load_percent=percent if name == joint else 5.0, **still)
                for name in so101.JOINT_NAMES
            }
            for event in self.engine.evaluate(device, readings, {}, t):
                self._watch.alarm(event)

    def events(self, query):
        return self.store.query(query)

    def alarms(self, *, include_normal: bool = False):
        return tuple(self.engine.views(include_normal=include_normal))


@pytest.mark.parametrize("case", ["unlatched", "latched", "acknowledged"])
def test_an_alarm_raised_and_cleared_between_two_looks_is_in_the_story_as_raised(case):
    """The demo looked at the agent's list of alarms every quarter second (longer while its first picture
    rendered) and recorded a story alarm when a look found it: one raised and cleared in between was missed
    when it did not latch or a person acknowledged it, and one found latched was recorded LATCHED, dated by
    the look. The raise event tells it as it happened."""
    from types import SimpleNamespace

    from twin.rig.demo import STORY_JOINT, _follow_story, _Story

    agent = _AgentBetweenLooks(latch=case != "unlatched")
    story = _Story("arm-001", STORY_JOINT)
    notes: list[str] = []
    no_state = SimpleNamespace(devices={})  # the servo's temperature is not what this test is about
    _follow_story(story, agent, no_state, 1000.0, notes.append)  # the first look: nothing yet
    assert story.alarms == [] and notes == []
    # Between the looks: 85 % held for a second raises the overload warning at 1 s, 50 % for 2 s clears it.
    agent.load("arm-001", STORY_JOINT, [0.0, 0.5, 1.0], 85.0)
    agent.load("arm-001", STORY_JOINT, [1.5, 3.5], 50.0)
    overload = f"arm-001/{STORY_JOINT}/overload"
    if case == "acknowledged":
        agent.engine.acknowledge(overload, 3.6)  # LATCHED -> NORMAL: a person saw it in the console
    up = [a.alarm_id for a in agent.alarms()]
    assert up == ([overload] if case == "latched" else []), up
    _follow_story(story, agent, no_state, 1000.0, notes.append)  # the second look, at 3.6 s
    assert [(a["alarm_id"], a["state"], a["raised_after_s"]) for a in story.alarms] == [
        (overload, "ACTIVE", 1.0)
    ], story.alarms
    assert story.alarms[0]["severity"] == "warning" and "load 85.0 %" in story.alarms[0]["message"]
    assert notes == [f"  1.0s  alarm {overload} ACTIVE (warning): {story.alarms[0]['message']}"], notes
    # Raised again later: the story keeps the first raise, and a third look reads no event twice.
    agent.load("arm-001", STORY_JOINT, [10.0, 11.0], 85.0)
    _follow_story(story, agent, no_state, 1000.0, notes.append)
    _follow_story(story, agent, no_state, 1000.0, notes.append)
    assert len(story.alarms) == 1 and len(notes) == 1


def test_demo_refuses_to_replace_a_history_it_did_not_write(tmp_path):
    """A walk ran `twin run --history out/history` as the guide shows, then `twin demo --out out`: the demo
    deleted the agent's history to make room for its own."""
    table = tmp_path / "history" / "telemetry" / "_delta_log"
    table.mkdir(parents=True)
    (table / "00000000000000000000.json").write_text("{}\n")
    proc = subprocess.run(
        [str(TWIN), "demo", "--out", str(tmp_path), "--seconds", "1"],
        check=False,
        env=demo_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1, proc.stderr
    assert f"{tmp_path / 'history'} holds a history the demo did not write" in proc.stderr
    assert "another --out" in proc.stderr
    assert (table / "00000000000000000000.json").read_text() == "{}\n"


def test_a_history_an_earlier_demo_wrote_is_replaced(tmp_path):
    """Its mark, or an earlier run's stats.json beside it (a demo from before the mark), lets a run
    replace it."""
    from twin.rig import demo as rig_demo

    for witness in (Path("history") / rig_demo.HISTORY_MARK, Path("stats.json")):
        log = tmp_path / "history" / "telemetry" / "_delta_log"
        log.mkdir(parents=True)
        (log / "00000000000000000000.json").write_text("{}\n")
        os.utime(log / "00000000000000000000.json", ns=(0, 0))  # the run's commits, older than its witness
        (tmp_path / witness).write_text("{}")
        rig_demo._clear_outputs(tmp_path)
        assert [p.name for p in (tmp_path / "history").iterdir()] == [rig_demo.HISTORY_MARK]
        shutil.rmtree(tmp_path / "history")


def test_a_history_written_after_the_demo_is_not_taken_for_its(tmp_path):
    """A walk ran `twin demo --out out`, then `rm -rf out/history; twin run --history out/history`, then the
    demo again: the old stats.json made it delete the agent's history. An agent writing into the demo's own
    folder after it (its mark there) lost its history the same way."""
    from twin.rig import demo as rig_demo

    log = tmp_path / "history" / "telemetry" / "_delta_log"
    log.mkdir(parents=True)
    commit = log / "00000000000000000001.json"
    commit.write_text("{}\n")
    for witness in (Path("history") / rig_demo.HISTORY_MARK, Path("stats.json")):
        (tmp_path / witness).write_text("{}")
        os.utime(tmp_path / witness, ns=(0, 0))  # from a run before the agent's commit
        with pytest.raises(rig_demo.DemoError, match="holds a history the demo did not write"):
            rig_demo._clear_outputs(tmp_path)
        assert commit.read_text() == "{}\n"
        (tmp_path / witness).unlink()


def test_a_run_marks_its_history_again_once_its_agent_stopped(tmp_path, monkeypatch):
    """The mark written at the start is older than the run's own commits: without a new one after them, the
    next run would refuse the demo's own history."""
    from twin.rig import demo as rig_demo

    theirs = tmp_path / "session-20261201T080000Z.usda"  # an agent's own, from before the run
    theirs.write_text("#usda 1.0\n")

    def agent(config, devices, out_dir, run, **_):
        os.utime(out_dir / "history" / rig_demo.HISTORY_MARK, ns=(0, 0))
        log = out_dir / "history" / "telemetry" / "_delta_log"
        log.mkdir(parents=True)
        (log / "00000000000000000000.json").write_text("{}\n")
        (out_dir / "session-20261206T090000Z.usda").write_text("#usda 1.0\n")  # the run's recording
        raise rig_demo.DemoError("the agent stopped")  # a failed run marks it too

    monkeypatch.setattr(rig_demo, "_run_on_rig", agent)
    config = rig_demo.DemoConfig(out_dir=tmp_path, console=False)
    with pytest.raises(rig_demo.DemoError, match="the agent stopped"):
        rig_demo.run_demo(config)
    # No stats.json from the failed run: the mark names its recording, for the next run to remove.
    rig_demo._clear_outputs(tmp_path)
    assert [p.name for p in (tmp_path / "history").iterdir()] == [rig_demo.HISTORY_MARK]
    assert sorted(p.name for p in tmp_path.glob("session-*.usda")) == [theirs.name]


def test_a_history_an_earlier_version_of_the_demo_left_is_replaced(tmp_path):
    """The version before wrote its mark at a run's start only, then the run's commits, then stats.json: the
    newest of the mark and stats.json is what the commits are older than."""
    from twin.rig import demo as rig_demo

    history = tmp_path / "history"
    log = history / "telemetry" / "_delta_log"
    log.mkdir(parents=True)
    (history / rig_demo.HISTORY_MARK).write_text("made by twin demo; the next run replaces this directory\n")
    os.utime(history / rig_demo.HISTORY_MARK, ns=(0, 0))
    (log / "00000000000000000000.json").write_text("{}\n")
    os.utime(log / "00000000000000000000.json", ns=(10**9, 10**9))
    (tmp_path / "stats.json").write_text("{}")
    rig_demo._clear_outputs(tmp_path)
    assert [p.name for p in history.iterdir()] == [rig_demo.HISTORY_MARK]


def test_a_history_folder_holding_no_table_is_not_taken_for_the_demos(tmp_path):
    """Only the table's log was compared with the witness: a history/ with a person's own file in it and no
    table, next to an old stats.json, was removed whole."""
    from twin.rig import demo as rig_demo

    (tmp_path / "history").mkdir()
    mine = tmp_path / "history" / "export.csv"
    mine.write_text("received_at,device_id\n")
    os.utime(mine, ns=(0, 0))
    (tmp_path / "stats.json").write_text("{}")
    with pytest.raises(rig_demo.DemoError, match="holds a history the demo did not write"):
        rig_demo._clear_outputs(tmp_path)
    assert mine.is_file() and (tmp_path / "stats.json").is_file()


def test_a_history_the_demo_cannot_make_anew_is_named(tmp_path, monkeypatch):
    """A file named history, or a history rmtree could not remove all of, was a FileExistsError traceback."""
    from twin.rig import demo as rig_demo

    (tmp_path / "stats.json").write_text("{}")
    (tmp_path / "history").write_text("notes\n")
    with pytest.raises(rig_demo.DemoError, match=f"{tmp_path / 'history'} is a file"):
        rig_demo._clear_outputs(tmp_path)
    assert (tmp_path / "history").read_text() == "notes\n"
    (tmp_path / "history").unlink()
    (tmp_path / "history").mkdir()
    (tmp_path / "history" / rig_demo.HISTORY_MARK).write_text("")
    monkeypatch.setattr(rig_demo.shutil, "rmtree", lambda *_, **__: None)  # as if a file in it stayed
    with pytest.raises(rig_demo.DemoError, match=f"could not remove the last run's history {tmp_path}"):
        rig_demo._clear_outputs(tmp_path)


def test_only_the_recording_the_last_run_named_is_removed(tmp_path):
    """An agent of the user's may record its USD sessions into the demo's directory (its twin.record_dir):
    a run removes only the recording the last run's stats.json names, never another session file there."""
    from twin.rig import demo as rig_demo

    theirs = tmp_path / "session-20261201T080000Z.usda"
    theirs.write_text("#usda 1.0\n")
    demos = tmp_path / "session-20261206T090000Z.usda"
    demos.write_text("#usda 1.0\n")
    (tmp_path / "stats.json").write_text(json.dumps({"files": {"usd": demos.name}}))
    rig_demo._clear_outputs(tmp_path)
    assert theirs.is_file() and not demos.exists() and not (tmp_path / "stats.json").exists()
    # A stats.json that names no file, one in another directory, or one that is no session, removes nothing.
    elsewhere = tmp_path / "kept" / "session-20261130T080000Z.usda"
    elsewhere.parent.mkdir()
    others = [theirs, elsewhere, tmp_path / "notes.txt"]
    for path in others[1:]:
        path.write_text("#usda 1.0\n")
    for named in ({}, {"files": {"usd": "kept/" + elsewhere.name}}, {"files": {"usd": "notes.txt"}}):
        (tmp_path / "stats.json").write_text(json.dumps(named))
        rig_demo._clear_outputs(tmp_path)
        assert all(path.is_file() for path in others), named
