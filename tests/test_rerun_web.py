"""The served Rerun web viewer in a real headless chromium, while the local rig's edge publishes.

The whole pipeline runs: mosquitto, the edge simulator (two arms at 10 Hz), the agent with its Rerun sink
serving on loopback (as `twin web` runs it). The browser may reach loopback addresses only. Passing means the
viewer drew the arm: the 3D view is not blank and holds the arm's colour. The screenshot is kept under
out/web/ for a person to look at (docs/web.md shows one).
"""

from __future__ import annotations

import base64
import io
import socket
import time
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest
from PIL import Image
from twin.service.outputs import configured_sinks

OUT_DIR = Path(__file__).resolve().parents[1] / "out" / "web"
# Software WebGL on two shared cores: a quiet machine draws the arm within a minute, a loaded one can take
# several (each screenshot waits for the page's busy main thread).
RENDER_TIMEOUT_S = 480.0


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


@pytest.mark.slow
@pytest.mark.timeout(720)
def test_the_served_viewer_shows_the_arm_in_chromium(rig, chromium_page) -> None:
    config = rig.agent_config(
        {
            "telemetry.devices": ["arm-001", "arm-002"],
            "telemetry.units": "ticks",
            "rerun.serve": True,
            "rerun.grpc_port": 0,
            "rerun.web_port": 0,
            "rerun.flush_s": 0.2,
        }
    )
    service = rig.start_agent(config, sinks=configured_sinks(config))
    sink = next(s for s in service.sinks if s.name == "rerun")
    url = sink.viewer_url
    assert url is not None and sink.grpc_url is not None
    assert urlsplit(url).hostname == "127.0.0.1" and urlsplit(sink.grpc_url).hostname == "127.0.0.1"
    edge = rig.start_edge(["arm-001", "arm-002"], seconds=None)  # publishes until the rig stops it
    page = chromium_page
    page.goto(url)
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    shot = OUT_DIR / "rerun-viewer.png"
    deadline = time.monotonic() + RENDER_TIMEOUT_S
    rgb = screenshot(page)
    while arm_pixels(fleet_view(rgb)) < 1500 and time.monotonic() < deadline:
        Image.fromarray(rgb).save(shot)  # the latest view, for a person to look at if this fails
        time.sleep(5.0)
        rgb = screenshot(page)
    Image.fromarray(rgb).save(shot)
    assert edge.alive, "the edge simulator stopped while the viewer loaded"
    view = fleet_view(rgb)
    assert view.std() > 10, "the 3D view is blank"
    assert arm_pixels(view) >= 1500, f"no arm in the 3D view after {RENDER_TIMEOUT_S:.0f} s; see {shot}"
    # The viewer lags far behind on software WebGL; the mirror does not wait for it: the sink kept every
    # applied sample (nothing dropped or skipped) and the agent handled every message without an error.
    state = service.state()
    stats = sink.stats()
    assert stats.delivered > 0 and (stats.errors, stats.dropped, stats.skipped) == (0, 0, 0)
    assert state.agent.worker.errors == 0
    for device in ("arm-001", "arm-002"):
        counters = state.devices[device].health.counters
        assert counters.applied > 0 and counters.rejected_total == 0
    web_port = urlsplit(url).port or 0
    service.stop()  # closes the sink, which stops its web viewer
    with socket.socket() as probe:
        assert probe.connect_ex(("127.0.0.1", web_port)) != 0


def fleet_view(rgb: np.ndarray) -> np.ndarray:
    """The fleet's 3D view: the blueprint gives it the left three fifths of the page."""
    return rgb[:, : rgb.shape[1] * 3 // 5]
