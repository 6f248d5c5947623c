"""`twin demo` end to end as a user runs it: a subprocess, real mosquitto, real agent, files checked."""

from __future__ import annotations

import json
import os
import re
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
}


def demo_env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("MUJOCO_GL", None)  # the demo must choose a headless GL backend itself
    env.pop("DISPLAY", None)
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


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_demo_leaves_valid_files_and_stops_its_broker(tmp_path):
    from pxr import Usd

    out = tmp_path / "demo"
    proc = subprocess.run(
        [str(TWIN), "demo", "--seconds", "4", "--out", str(out)],
        check=False,
        env=demo_env(),
        capture_output=True,
        text=True,
        timeout=150,
    )
    assert proc.returncode == 0, f"stdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    # Not a TTY: periodic plain status lines, then the summary.
    assert "received" in proc.stdout and "done in" in proc.stdout
    assert "\r" not in proc.stdout

    stats = json.loads((out / "stats.json").read_text())
    assert stats.keys() >= STATS_FIELDS
    messages = stats["messages"]
    assert messages.keys() >= MESSAGE_FIELDS
    assert messages["received"] > 0
    # 4 s at 10 Hz; the scheduler may drift by a tick or two on a busy machine.
    assert 35 <= messages["sent"] <= 45
    assert messages["rejected"] == 0 and messages["rejected_by_reason"] == {}
    assert messages["received"] == messages["sent"], "loopback QoS 0 without faults should lose nothing"
    # The agent's own loss estimate (edge timestamp gaps) agrees: nothing went missing.
    assert messages["estimated_lost"] == 0 and messages["estimated_loss_ratio"] == 0.0
    for kind in ("end_to_end", "internal"):
        lat = stats["latency_s"][kind]
        # Seconds (milliseconds on loopback; the bound is loose because the cores may be busy with other runs:
        # speed is what `twin bench` measures, not this test).
        assert 0 <= lat["p50"] <= lat["p99"] < 10.0, lat
    assert stats["devices"] == ["arm-001"]
    # The arm's health at the demo's last poll while the edge simulator ran: ONLINE, or STALE when that poll
    # came during the simulator's shutdown, 0.3 s (three periods) after its last message, which a busy
    # machine makes likely. Never OFFLINE.
    assert stats["per_device"]["arm-001"]["status"] in ("ONLINE", "STALE")
    assert stats["interrupted"] is False

    files = stats["files"]
    assert_not_blank(out / files["png"])
    with Image.open(out / files["gif"]) as gif:
        # A frame each time the demo's status poll (every 0.25 s) finds the next frame due: about 16 in 4 s,
        # fewer when the machine is busy.
        assert gif.n_frames >= 5
        first = np.asarray(gif.convert("RGB"))
        gif.seek(gif.n_frames - 1)
        last = np.asarray(gif.convert("RGB"))
    assert np.abs(first.astype(int) - last.astype(int)).sum() > 0, "the animation does not move"

    stage = Usd.Stage.Open(str(out / files["usd"]))
    assert stage is not None
    sampled = [
        attr for prim in stage.Traverse() for attr in prim.GetAttributes() if attr.GetNumTimeSamples() > 1
    ]
    assert sampled, "the USD session has no time-sampled attributes"
    assert max(a.GetNumTimeSamples() for a in sampled) >= 10

    # The history beside the other outputs: every decoded message as a row (applied ones, and any a worker
    # behind coalesced into a newer one), and its plot.
    history = stats["history"]
    assert history["rows"] == {"arm-001": messages["decoded"]}
    assert history["rejected"] == {}
    assert (out / history["uri"] / "telemetry" / "_delta_log").is_dir()
    assert_not_blank(out / history["plot"])

    # The Rerun recording: the arm's tree, a pose per applied message (Rerun's own reader; the values are
    # checked against MuJoCo in test_rerun_sink.py).
    assert files["rrd"] == "twin.rrd"
    assert "rerun " + str(out / "twin.rrd") in proc.stdout
    assert f"twin history ls --history {out / 'history'}" in proc.stdout
    temporal, static = read_rrd(out / "twin.rrd")
    assert "/arms/arm-001:Transform3D:translation" in static.schema.names
    poses = [v for v in temporal.column("/arms/arm-001/wrist:Transform3D:translation").to_pylist() if v]
    assert len(poses) == messages["applied"]

    assert_broker_gone(stats)


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
