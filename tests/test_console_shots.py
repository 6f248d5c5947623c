"""twin.rig.console_shots against a stand-in console in real headless Chromium: the moment pictured."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from conftest import CHROMIUM
from PIL import Image
from twin.rig.console_shots import console_screenshots

pytestmark = pytest.mark.slow

STALE_ANSWERS = 3  # the stand-in agent reports the arm STALE this many times, then ONLINE

# A Fleet page's card as the console draws it (class "card <status>"), painted by its status so the picture
# says which one it caught, and polled from the stand-in agent as the console polls /state.
FLEET = b"""<!doctype html><style>body{margin:0} .card{display:block;width:400px;height:400px}
.STALE{background:#ff0000} .ONLINE{background:#00ff00}</style>
<a class="card STALE" data-device="arm-001"></a>
<script>
const card = document.querySelector("[data-device]");
async function poll() {
  const status = await (await fetch("/status")).text();
  card.className = "card " + status;
  if (status !== "ONLINE") setTimeout(poll, 50);
}
poll();
</script>"""
ARM = b"""<!doctype html><canvas data-chart="angles" data-points="20"></canvas>"""


class _Console(BaseHTTPRequestHandler):
    answers = 0

    def do_GET(self) -> None:
        if self.path == "/status":
            type(self).answers += 1
            body = b"STALE" if type(self).answers <= STALE_ANSWERS else b"ONLINE"
        else:
            body = ARM if self.path.startswith("/arm/") else FLEET
        self.send_response(200)
        self.send_header("Content-Type", "text/html" if body in (ARM, FLEET) else "text/plain")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture
def console_url() -> Iterator[str]:
    _Console.answers = 0
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
    edge): the Fleet picture is taken once the page reads it ONLINE again, not at that first draw."""
    if not CHROMIUM.is_file():
        pytest.fail(f"{CHROMIUM} is missing; `make setup` installs Debian's chromium for the browser tests")
    shots = console_screenshots(console_url, tmp_path, device="arm-001", size=(640, 480), timeout_s=60)
    assert _Console.answers > STALE_ANSWERS
    with Image.open(shots.fleet) as picture:
        assert picture.convert("RGB").getpixel((200, 200)) == (0, 255, 0)
