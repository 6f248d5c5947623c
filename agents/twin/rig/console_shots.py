"""Pictures of a running operator console, taken in headless Chromium through Playwright.

`console_screenshots(url, out_dir, device=...)` opens the Fleet page and one arm's page of the console at
`url` (an agent's HTTP address), waits until each has drawn its live data, and saves `console-fleet.png`
and `console-arm.png`. docs/console.md's pictures are made this way, and `twin demo` takes its two so.

The browser is Debian's chromium (`make setup-demo` and `make setup` install it), never one Playwright
downloads; the page may reach loopback addresses only. Playwright comes with the `demo` extra and the
development tools: without it, or without the browser, this raises ConsoleShotError with the way to get
them (`missing_for_shots` says so beforehand).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import quote, urlsplit

if TYPE_CHECKING:
    from playwright.sync_api import Page, Route

log = logging.getLogger(__name__)

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1", "[::1]")
# How long the Fleet picture waits for arms the browser's start held up to read ONLINE again: seconds at most,
# since the demo's story goes on meanwhile.
SETTLE_S = 10.0


class ConsoleShotError(RuntimeError):
    """The pictures could not be taken; the message says why and what to do."""


@dataclass
class ConsoleShots:
    fleet: Path
    arm: Path
    console_errors: list[str] = field(default_factory=list)


def loopback_only(route: Route) -> None:
    """A Playwright route handler: loopback and inline URLs pass, anything else is refused."""
    url = route.request.url
    if url.startswith(("data:", "blob:")) or (urlsplit(url).hostname or "") in LOOPBACK_HOSTS:
        route.continue_()
    else:
        route.abort()


def wait_for_charts(page: Page, timeout_s: float, readings: int = 2) -> None:
    """Until every chart of an arm page has drawn at least `readings` readings (the page takes two a
    second, `[http] console_rate_hz`)."""
    page.wait_for_function(
        f"() => [...document.querySelectorAll('canvas[data-chart]')]"
        f".every(c => Number(c.dataset.points) >= {int(readings)})",
        timeout=timeout_s * 1000,
    )


def wait_for_settled_fleet(page: Page, timeout_s: float) -> bool:
    """Until no card on the Fleet page reads STALE, for at most `timeout_s`; whether it came to that.

    Starting the browser can hold up a small machine's edge for longer than the stale time (0.3 s at 10 Hz),
    so the page's first draw often shows every arm STALE "now". A fleet that really is stale is pictured
    all the same, once the time is up."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout  # noqa: PLC0415 - optional dependency

    try:
        # A grid card carries its status as a class, a list row only on its status span (fleet.js): the
        # span's class holds in both views, whichever one the browser's stored choice opens.
        page.wait_for_function(
            "() => !document.querySelector('[data-device] .status.STALE')", timeout=timeout_s * 1000
        )
    except PlaywrightTimeout:
        return False
    return True


def missing_for_shots(chromium: Path = CHROMIUM, *, setup: str = "make setup-demo") -> str | None:
    """Why the pictures cannot be taken here (what to install, and how), or None when they can.

    `setup` is the make target that installs both for the caller's users (`twin bench console`: make setup).
    """
    try:
        import playwright.sync_api  # noqa: F401, PLC0415 - an optional dependency: is it there?
    except ImportError:
        return (
            f"Playwright is not installed: `{setup}` installs it (the `demo` extra of the agent "
            "package: pip install 'so101-twin[demo]')"
        )
    if not chromium.is_file():
        return f"{chromium} is missing: `{setup}` installs Debian's chromium (apt package chromium)"
    return None


def console_screenshots(
    url: str,
    out_dir: Path,
    *,
    device: str,
    size: tuple[int, int] = (1280, 800),
    timeout_s: float = 60.0,
    chromium: Path = CHROMIUM,
) -> ConsoleShots:
    """`console-fleet.png` and `console-arm.png` of the console at `url` in `out_dir` (module doc)."""
    missing = missing_for_shots(chromium)
    if missing is not None:
        raise ConsoleShotError(missing)
    from playwright.sync_api import Error as PlaywrightError  # noqa: PLC0415 - an optional dependency
    from playwright.sync_api import sync_playwright  # noqa: PLC0415

    out_dir.mkdir(parents=True, exist_ok=True)
    shots = ConsoleShots(fleet=out_dir / "console-fleet.png", arm=out_dir / "console-arm.png")
    base = url.rstrip("/")
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(
                executable_path=str(chromium), headless=True, args=list(CHROMIUM_FLAGS)
            )
            try:
                page = browser.new_page(viewport={"width": size[0], "height": size[1]})
                page.route("**/*", loopback_only)
                page.on(
                    "console", lambda m: shots.console_errors.append(m.text) if m.type == "error" else None
                )
                page.goto(base + "/", wait_until="load")
                page.wait_for_selector(f'[data-device="{device}"]', timeout=timeout_s * 1000)
                wait_for_settled_fleet(page, SETTLE_S)
                page.screenshot(path=str(shots.fleet))
                page.goto(f"{base}/arm/{quote(device, safe='')}", wait_until="load")
                # Some seconds of readings, so the pictures show lines rather than their first points.
                wait_for_charts(page, timeout_s, readings=20)
                page.screenshot(path=str(shots.arm), full_page=True)
            finally:
                browser.close()
    except PlaywrightError as exc:
        raise ConsoleShotError(f"taking the console pictures failed: {exc}") from exc
    log.info("console pictures", extra={"fleet": str(shots.fleet), "arm": str(shots.arm)})
    return shots
