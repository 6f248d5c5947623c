"""twin.rig.console_shots against a stand-in console in real headless Chromium: the moment pictured."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from conftest import CHROMIUM
from PIL import Image
from twin.rig.console_shots import console_screenshots

pytestmark = pytest.mark.slow

# The stand-in agent reports the arm STALE for this long after it serves the Fleet page, then ONLINE: long
# enough that a picture taken at the page's first draw shows STALE even on a busy machine, well within the
# wait console_shots gives the fleet to settle (SETTLE_S).
STALE_HOLD_S = 2.0

# A Fleet page's arm as the console draws it in each view: a grid card has its status as its class ("card
# <status>") and on a child span, a list row only on the span. The span is painted by its status, so the
# picture says which one it caught, and the status is polled from the stand-in agent as the console polls.
FLEET = """<!doctype html><style>body{margin:0} .status{display:block;width:400px;height:400px}
.status.STALE{background:#ff0000} .status.ONLINE{background:#00ff00}</style>
<a class="%(kind)s" data-device="arm-001"><span class="status STALE">STALE</span></a>
<script>
const item = document.querySelector("[data-device]"), span = item.querySelector(".status");
async function poll() {
  const status = await (await fetch("/status")).text();
  span.className = "status " + status;
  span.textContent = status;
  if (item.classList.contains("card")) item.className = "card " + status;
  if (status !== "ONLINE") setTimeout(poll, 50);
}
poll();
</script>"""
FLEET_VIEWS = {"grid": "card STALE", "list": "row"}
ARM = b"""<!doctype html><canvas data-chart="angles" data-points="20"></canvas>"""


class _Console(BaseHTTPRequestHandler):
    fleet = b""
    served_at: float | None = None  # when the Fleet page went out (time.monotonic)

    def do_GET(self) -> None:
        cls = type(self)
        if self.path == "/status":
            held = cls.served_at is None or time.monotonic() - cls.served_at < STALE_HOLD_S
            body = b"STALE" if held else b"ONLINE"
        elif self.path.startswith("/arm/"):
            body = ARM
        else:
            if self.path == "/":  # not a favicon's request after it, which would put ONLINE off again
                cls.served_at = time.monotonic()
            body = cls.fleet
        self.send_response(200)
        self.send_header("Content-Type", "text/html" if body in (ARM, cls.fleet) else "text/plain")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture(params=sorted(FLEET_VIEWS))
def console_url(request: pytest.FixtureRequest) -> Iterator[str]:
    """The stand-in console, its Fleet page in one view: the console keeps the view a person chose."""
    _Console.fleet = (FLEET % {"kind": FLEET_VIEWS[request.param]}).encode()
    _Console.served_at = None
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Console)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        thread.join()


def test_fleet_picture_waits_for_arms_the_browser_start_held_up(console_url: str, tmp_path: Path) -> None:
    """The page's first draw has the arm STALE (as the demo's often did, the browser's start holding up the
    edge): the Fleet picture is taken once the page reads it ONLINE again, not at that first draw, in the
    grid view and in the list view, where only the status span says STALE."""
    if not CHROMIUM.is_file():
        pytest.fail(f"{CHROMIUM} is missing; `make setup` installs Debian's chromium for the browser tests")
    shots = console_screenshots(console_url, tmp_path, device="arm-001", size=(640, 480), timeout_s=60)
    with Image.open(shots.fleet) as picture:
        assert picture.convert("RGB").getpixel((200, 200)) == (0, 255, 0)
