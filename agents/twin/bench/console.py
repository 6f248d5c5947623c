"""What the operator console costs and how it feels at fleet scale, measured in Debian's chromium.

Two phases, each against a `twin run` child process on a private broker with the whole fleet publishing:
1. interactive: the Fleet page of a 2,000-arm fleet opened `runs` times in a fresh page; per run, the time
   from navigation to the first full render of every arm (the page marks it: `window.twinReadyAt`, on the
   browser's own clock), the time a search takes to show its match, and how long the page spends on each
   live update (`window.twinUpdateMs`, the mean over the updates it handled). Reported as median, min, max.
2. cpu: the agent's CPU (its process tree) at 1,000 arms for `seconds` with no console open, then the same
   with two Fleet pages open; the difference is what two consoles cost the agent. The browser's own CPU is
   reported too (it runs on the same cores). Then `seconds` with one arm's page open instead. Then
   `seconds` with a reader of the stream `twin view` follows (`/stream?device=<first arm>`), and `seconds`
   with a reader of the whole state's stream (`/stream`, what it followed before): their cost to the agent
   and the frames each delivered.
Publishers, broker, agent and browser share this host's cores: quote the load average with the figures.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import psutil

from twin.bench.harness import ProcessSampler, publishers, running_agent, spread, wait_subscribed
from twin.bench.unavailable import Unavailable
from twin.rig.console_shots import CHROMIUM, CHROMIUM_FLAGS, loopback_only, missing_for_shots
from twin.rig.local import LocalRig

# The fleet must be in the agent's state before the page is timed.
FLEET_TIMEOUT_S = 120.0

_SEARCH_JS = """
async (id) => {
  const input = document.querySelector('input[type=search]');
  const t0 = performance.now();
  input.value = id;
  input.dispatchEvent(new Event('input'));
  while (!document.querySelector(`#fleet-view [data-device="${id}"]`)) {
    await new Promise(r => requestAnimationFrame(r));
  }
  return performance.now() - t0;
}
"""


@contextmanager
def _browser() -> Iterator[Any]:
    from playwright.sync_api import sync_playwright  # noqa: PLC0415 - development dependency

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=list(CHROMIUM_FLAGS))
        try:
            yield browser
        finally:
            browser.close()


def _wait_fleet(base: str, arms: int, proc: Any) -> float:
    """Until /api/fleet lists every arm; returns the seconds it took."""
    import json  # noqa: PLC0415
    import urllib.request  # noqa: PLC0415

    t0 = time.monotonic()
    while time.monotonic() - t0 < FLEET_TIMEOUT_S:
        if proc.poll() is not None:
            raise RuntimeError(f"the agent exited with code {proc.returncode}")
        with urllib.request.urlopen(base + "/api/fleet", timeout=30) as response:
            if json.loads(response.read())["counts"]["devices"] >= arms:
                return time.monotonic() - t0
        time.sleep(0.5)
    raise RuntimeError(f"the agent did not list {arms} arms within {FLEET_TIMEOUT_S:.0f} s")


def _open(context: Any, url: str, ready: str) -> Any:
    """A console page at `url`, loopback only, once the `ready` expression holds in it."""
    page = context.new_page()
    page.route("**/*", loopback_only)
    page.set_default_timeout(FLEET_TIMEOUT_S * 1000)
    page.goto(url)
    page.wait_for_function(f"() => {ready}")
    return page


def _open_fleet(context: Any, base: str, arms: int) -> Any:
    return _open(context, base + "/", f"window.twinReadyAt && window.twinRows >= {arms}")


def _interactive(rig: LocalRig, arms: int, rate: float, runs: int) -> dict[str, Any]:
    seconds = FLEET_TIMEOUT_S + runs * 20.0
    with running_agent(rig, max_devices=max(4096, arms)) as (proc, base):
        wait_subscribed(base, proc)
        pubs = publishers(rig.broker.url, arms, rate, seconds)
        try:
            listed_s = _wait_fleet(base, arms, proc)
            ready, search, update = [], [], []
            with _browser() as browser:
                for _ in range(runs):
                    context = browser.new_context(viewport={"width": 1280, "height": 800})
                    page = _open_fleet(context, base, arms)
                    ready.append(page.evaluate("window.twinReadyAt"))
                    # A few live updates, then a search for the last arm.
                    page.wait_for_function("() => window.twinUpdates >= 4")
                    update.append(page.evaluate("window.twinUpdateMs"))
                    search.append(page.evaluate(_SEARCH_JS, f"arm-{arms:04d}"))
                    context.close()
        finally:
            for p in pubs:
                p.kill()
            collect_quietly(pubs)
    return {
        "arms": arms,
        "rate_hz": rate,
        "runs": runs,
        "fleet_listed_after_s": listed_s,
        "ready_ms": spread(ready),
        "search_ms": spread(search),
        "update_ms": spread(update),
    }


def collect_quietly(procs: list[Any]) -> None:
    for p in procs:
        try:
            p.communicate(timeout=10)
        except Exception:  # a killed publisher has nothing to report
            p.kill()


def _browser_cpu(pid: int) -> float:
    try:
        root = psutil.Process(pid)
        processes = [root, *root.children(recursive=True)]
    except psutil.Error:
        return 0.0
    total = 0.0
    for process in processes:
        try:
            times = process.cpu_times()
        except psutil.Error:
            continue
        total += times.user + times.system
    return total


def _cpu(rig: LocalRig, arms: int, rate: float, seconds: float, consoles: int) -> dict[str, Any]:
    total = FLEET_TIMEOUT_S + 3 * seconds
    with running_agent(rig, max_devices=max(4096, arms)) as (proc, base):
        wait_subscribed(base, proc)
        pubs = publishers(rig.broker.url, arms, rate, total)
        try:
            _wait_fleet(base, arms, proc)
            idle = ProcessSampler(proc.pid).start()
            time.sleep(seconds)
            without = idle.stop()
            with _browser() as browser:
                context = browser.new_context(viewport={"width": 1280, "height": 800})
                pages = [_open_fleet(context, base, arms) for _ in range(consoles)]
                browser_pid = _chromium_pid()
                sampler = ProcessSampler(proc.pid).start()
                browser0 = _browser_cpu(browser_pid) if browser_pid else 0.0
                time.sleep(seconds)
                browser_s = (_browser_cpu(browser_pid) - browser0) if browser_pid else 0.0
                with_consoles = sampler.stop()
                updates = [p.evaluate("window.twinUpdates") for p in pages]
                context.close()
                arm_page = _arm_page_cpu(browser, base, proc.pid, seconds)
            viewer = _stream_cpu(base, "/stream?device=arm-0001", proc.pid, seconds)
            whole = _stream_cpu(base, "/stream", proc.pid, seconds)
        finally:
            for p in pubs:
                p.kill()
            collect_quietly(pubs)
    return {
        "arms": arms,
        "rate_hz": rate,
        "seconds": seconds,
        "consoles": consoles,
        "agent_cpu_percent_without": _figure(without["cpu_percent"]),
        "agent_cpu_percent_with": _figure(with_consoles["cpu_percent"]),
        "agent_cpu_percent_cost": _figure(with_consoles["cpu_percent"]) - _figure(without["cpu_percent"]),
        "browser_cpu_percent": 100.0 * browser_s / seconds,
        # One arm's page instead: the agent reads that arm alone, in the worker that holds it.
        "agent_cpu_percent_with_arm_page": arm_page,
        "arm_page_cpu_percent_cost": arm_page - _figure(without["cpu_percent"]),
        # A viewer (`twin view`) following one arm, and a reader of the whole state's stream.
        "viewer_cpu_percent_cost": viewer[0] - _figure(without["cpu_percent"]),
        "viewer_frames_per_s": viewer[1],
        "whole_state_stream_cpu_percent_cost": whole[0] - _figure(without["cpu_percent"]),
        "whole_state_stream_frames_per_s": whole[1],
        "host_cpu_percent_with": with_consoles["host_cpu_percent"],
        "updates_per_console": updates,
    }


def _arm_page_cpu(browser: Any, base: str, pid: int, seconds: float) -> float:
    """The agent's CPU (% of a core) over `seconds` with one arm's page open (the fleet's first arm)."""
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    _open(context, base + "/arm/arm-0001", "window.twinReadyAt")
    sampler = ProcessSampler(pid).start()
    time.sleep(seconds)
    measured = sampler.stop()
    context.close()
    return _figure(measured["cpu_percent"])


def _stream_cpu(base: str, path: str, pid: int, seconds: float) -> tuple[float, float]:
    """The agent's CPU (% of a core) over `seconds` with one reader of the SSE stream at `path`, and the
    frames a second it delivered."""
    frames = 0
    request = urllib.request.Request(base + path, headers={"Accept": "text/event-stream"})
    response = urllib.request.urlopen(request, timeout=30)

    def read() -> None:
        nonlocal frames
        # Ends when the response is closed below (the read then fails), so the next phase has no reader.
        with contextlib.suppress(OSError, ValueError, AttributeError):
            for line in response:
                if line.startswith(b"event: "):
                    frames += 1

    reader = threading.Thread(target=read, name="bench-stream-reader", daemon=True)
    reader.start()
    time.sleep(1.0)  # past its first frame
    first = frames
    sampler = ProcessSampler(pid).start()
    time.sleep(seconds)
    measured = sampler.stop()
    delivered = frames - first
    with contextlib.suppress(OSError):
        response.close()
    reader.join(5.0)
    return _figure(measured["cpu_percent"]), delivered / seconds


def _figure(value: float | None) -> float:
    return value if value is not None else 0.0


def _chromium_pid() -> int | None:
    """The newest chromium process started by this one (Playwright's browser)."""
    candidates = []
    for p in psutil.Process(os.getpid()).children(recursive=True):
        # Chromium starts and ends helper processes all the time: one may be gone once listed.
        with contextlib.suppress(psutil.Error):
            if "chrom" in p.name():
                candidates.append((p.create_time(), p.pid))
    return min(candidates)[1] if candidates else None


def _require_browser() -> None:
    """Raise Unavailable, naming the fix, when Playwright or Debian's chromium is not installed."""
    # The demo's check, so the two cannot drift; the development setup installs both here.
    missing = missing_for_shots(CHROMIUM, setup="make setup")
    if missing is not None:
        raise Unavailable(missing)


def run(
    *, arms: int = 2000, cpu_arms: int = 1000, rate: float = 2.0, runs: int = 5, seconds: float = 20.0
) -> dict[str, Any]:
    """Both phases as one JSON-ready dict (nothing asserted: a benchmark measures)."""
    # Before the rig and the fleet: otherwise minutes go by before the browser is found missing.
    _require_browser()
    load_before = os.getloadavg()
    with LocalRig() as rig:
        interactive = _interactive(rig, arms, rate, runs)
        cpu = _cpu(rig, cpu_arms, rate, seconds, consoles=2)
    return {
        "scenario": "console",
        "interactive": interactive,
        "cpu": cpu,
        "load_average_1m": {"before": load_before[0], "after": os.getloadavg()[0]},
        "notes": (
            "headless Debian chromium (software rendering) on the same cores as the agent, broker and "
            "publishers; times from the browser's clock; figures taken while other work runs are noisy"
        ),
        "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
