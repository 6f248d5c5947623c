"""The served Rerun web viewer in a real headless chromium, while telemetry flows into the sink.

The page and the stream are both on loopback; the browser may reach nothing else. Passing means the viewer
drew the arm: the 3D view is not blank and holds the arm's colour. The screenshot is kept under out/web/ for
a person to look at (docs/web.md shows one).
"""

from __future__ import annotations

import base64
import io
import json
import random
import threading
import time
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest
from PIL import Image
from twin.core.telemetry import DecoderConfig, TelemetryDecoder, Units
from twin.output.rerun_settings import RerunSettings
from twin.output.rerun_sink import RerunSink
from twin.output.sinks import AppliedSample
from twin.robot.model import RobotModel
from twin.tools.edge_sim import make_payload

OUT_DIR = Path(__file__).resolve().parents[1] / "out" / "web"
# Software WebGL on two shared cores: a quiet machine draws the arm within a minute, a loaded one can take
# several (each screenshot waits for the page's busy main thread).
RENDER_TIMEOUT_S = 420.0


def arm_pixels(rgb: np.ndarray) -> int:
    """Pixels in the printed SO-101's yellow (the MJCF's plastic material), under any of the view's light."""
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    return int(((r > 120) & (g > 80) & (b < 90) & (r - b > 90)).sum())


def screenshot(page) -> np.ndarray:
    # Through CDP: Playwright's own screenshot waits for a quiet frame, which a viewer redrawing in software
    # WebGL may never give it.
    cdp = page.context.new_cdp_session(page)
    data = cdp.send("Page.captureScreenshot", {"format": "png"})["data"]
    cdp.detach()
    with Image.open(io.BytesIO(base64.b64decode(data))) as image:
        return np.asarray(image.convert("RGB"))


def publish(sink: RerunSink, stop: threading.Event, devices: list[str]) -> None:
    """The edge's mock motion at 10 Hz per arm, through the real decoder, into the sink."""
    decoder = TelemetryDecoder(DecoderConfig(units=Units.TICKS))
    rng = random.Random(14)
    start = time.monotonic()
    while not stop.is_set():
        t = time.monotonic() - start
        for device in devices:
            telemetry = decoder.decode(json.dumps(make_payload(device, t, "ticks", rng)), topic_device=device)
            sink.applied(
                AppliedSample(device, time.time(), time.monotonic(), telemetry, telemetry.angles_rad)
            )
        stop.wait(0.1)


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_the_served_viewer_shows_the_arm_in_chromium(chromium_page) -> None:
    robot = RobotModel.load()
    sink = RerunSink(robot, RerunSettings(serve=True, grpc_port=0, web_port=0, flush_s=0.2))
    stop = threading.Event()
    feeder = threading.Thread(target=publish, args=(sink, stop, ["arm-001", "arm-002"]), daemon=True)
    feeder.start()
    try:
        url = sink.viewer_url
        assert url is not None and sink.grpc_url is not None
        assert urlsplit(url).hostname == "127.0.0.1" and urlsplit(sink.grpc_url).hostname == "127.0.0.1"
        page = chromium_page
        page.goto(url)
        deadline = time.monotonic() + RENDER_TIMEOUT_S
        rgb = screenshot(page)
        while arm_pixels(rgb[:, : rgb.shape[1] * 3 // 5]) < 1500 and time.monotonic() < deadline:
            time.sleep(5.0)
            rgb = screenshot(page)
        OUT_DIR.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rgb).save(OUT_DIR / "rerun-viewer.png")
        view = rgb[:, : rgb.shape[1] * 3 // 5]  # the fleet's 3D view fills the left three fifths
        assert view.std() > 10, "the 3D view is blank"
        assert arm_pixels(view) >= 1500, f"no arm in the 3D view; see {OUT_DIR / 'rerun-viewer.png'}"
        assert sink.stats().delivered > 0
    finally:
        stop.set()
        feeder.join(5.0)
        sink.close()
    # The sink stopped its web viewer: the port no longer answers.
    import socket

    with socket.socket() as probe:
        assert probe.connect_ex(("127.0.0.1", urlsplit(url).port or 0)) != 0
