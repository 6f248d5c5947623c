"""`twin demo`: the whole pipeline on one machine, then the evidence on disk.

A private mosquitto on a free loopback port, the edge simulator publishing the edge's mock motion, and the
agent service (subscriber, decoder, MuJoCo twin, health, HTTP, USD recording) run in this process for a set
time. The caller gets a status snapshot about four times a second. Afterwards the output directory holds:
  twin.png    the twin's final pose (twin.output.render.render_png)
  twin.gif    a ~30-frame animation of the run (first device), rendered offscreen
  session-*.usda  the agent's USD session recording
  stats.json  what was sent, received, rejected (by reason), latencies, per-device health
Everything started here is stopped in `finally`, also on Ctrl-C / SIGTERM (the caller sets `stop`).
docs/viewer.md explains stats.json.
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

# Files this module writes into the output directory; earlier runs' copies are removed first so the directory
# always describes one run. Nothing else in the directory is touched.
OUTPUT_PATTERNS = ("twin.png", "twin.gif", "stats.json", "session-*.usda")
STATUS_INTERVAL_S = 0.25


class DemoError(RuntimeError):
    """The demo could not run or produced nothing; the message says what failed and what to do."""


@dataclass(frozen=True)
class DemoConfig:
    seconds: float = 20.0
    out_dir: Path = Path("out/demo")
    variant: str = "ticks"  # ticks | degrees (the two edge payload variants)
    devices: int = 1
    rate_hz: float = 10.0
    gif_frames: int = 30
    gif_size: tuple[int, int] = (320, 240)

    def __post_init__(self) -> None:
        if not 0 < self.seconds <= 3600:
            raise ValueError(f"--seconds {self.seconds} must be in (0, 3600]")
        if self.variant not in ("ticks", "degrees"):
            raise ValueError(f"--variant {self.variant!r} must be ticks or degrees")
        if not 1 <= self.devices <= 100:
            raise ValueError(f"--devices {self.devices} must be between 1 and 100")
        if not 0 < self.rate_hz <= 1000:
            raise ValueError(f"--rate {self.rate_hz} must be in (0, 1000] Hz")


@dataclass
class DemoStatus:
    """One live snapshot for the status line."""

    elapsed_s: float
    sent: int
    received: int
    rejected: int
    rate_hz: float
    latency_p50_s: float | None
    latency_p99_s: float | None
    statuses: dict[str, str] = field(default_factory=dict)


def _totals(state: dict[str, Any]) -> dict[str, Any]:
    devices = state.get("devices", {})
    rejected: dict[str, int] = {}
    for d in devices.values():
        for reason, n in d["counters"].get("rejected", {}).items():
            rejected[reason] = rejected.get(reason, 0) + n
    for reason, n in state.get("untracked_rejected", {}).items():
        rejected[reason] = rejected.get(reason, 0) + n
    return {
        "received": sum(d["counters"]["received"] for d in devices.values()),
        "decoded": sum(d["counters"]["decoded"] for d in devices.values()),
        "applied": sum(d["counters"]["applied"] for d in devices.values()),
        "ignored_stale": sum(d["counters"]["ignored_stale"] for d in devices.values()),
        "overwritten": sum(d["counters"]["overwritten"] for d in devices.values()),
        "rejected": rejected,
        "rejected_total": sum(rejected.values()),
        "rate_hz": sum(d.get("rate_hz") or 0.0 for d in devices.values()),
    }


def _worst(devices: dict[str, Any], key: str, pct: str) -> float | None:
    values = [(d.get(key) or {}).get(pct) for d in devices.values()]
    values = [v for v in values if v is not None]
    return max(values) if values else None


def _clear_outputs(out_dir: Path) -> None:
    for pattern in OUTPUT_PATTERNS:
        for path in out_dir.glob(pattern):
            path.unlink()


def _broker_pid() -> int | None:
    """The mosquitto child of this process (recorded so a caller can prove it is gone afterwards)."""
    import psutil  # noqa: PLC0415

    for child in psutil.Process().children():
        try:
            if "mosquitto" in child.name():
                return child.pid
        except psutil.Error:
            continue
    return None


def run_demo(
    config: DemoConfig,
    *,
    on_status: Callable[[DemoStatus], None] | None = None,
    stop: threading.Event | None = None,
) -> dict[str, Any]:
    """Run the demo; returns the stats written to stats.json. Raises DemoError on any failure."""
    from twin.service.agent import AgentService  # noqa: PLC0415
    from twin.service.config import ConfigError, config_from_mapping  # noqa: PLC0415
    from twin.tools.edge_sim import EdgeSimConfig, EdgeSimulator, device_ids  # noqa: PLC0415
    from twin.tools.mosquitto import MosquittoBroker, MosquittoNotFound, free_port  # noqa: PLC0415
    from twin.transport.subscriber import BrokerConfig  # noqa: PLC0415

    stop = stop or threading.Event()
    out_dir = Path(config.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    _clear_outputs(out_dir)
    devices = device_ids(config.devices)
    workdir = Path(tempfile.mkdtemp(prefix="so101-demo-"))
    try:
        broker = MosquittoBroker(workdir=workdir / "mosquitto")
    except MosquittoNotFound as exc:
        shutil.rmtree(workdir, ignore_errors=True)
        raise DemoError(f"{exc}. The demo needs mosquitto: run `make setup`.") from exc

    service: Any = None
    sim_thread: threading.Thread | None = None
    sim_stop = threading.Event()
    sim_result: dict[str, Any] = {}
    frames: list[dict[str, float]] = []
    final_state: dict[str, Any] | None = None
    running_statuses: dict[str, str] = {}
    started = time.monotonic()
    broker_pid: int | None = None
    try:
        broker.start()
        broker_pid = _broker_pid()
        try:
            agent_config = config_from_mapping(
                {
                    "broker": {"url": broker.url, "client_id_prefix": "so101-demo-agent-"},
                    "telemetry": {"devices": devices, "units": config.variant},
                    "twin": {"record_dir": str(out_dir), "record_format": "usda"},
                    "health": {"expected_rate_hz": config.rate_hz},
                    "http": {"listen": f"127.0.0.1:{free_port()}"},
                }
            )
        except ConfigError as exc:  # a bug here, not a user error: the values above are ours
            raise DemoError(f"internal agent configuration rejected: {exc}") from exc
        service = AgentService(agent_config)
        service.start()
        if not service.wait_subscribed(15.0):
            raise DemoError(f"the agent did not subscribe on {broker.url} within 15 s (see the log above)")

        sim = EdgeSimulator(
            EdgeSimConfig(
                broker=BrokerConfig(url=broker.url, client_id_prefix="so101-demo-edge-"),
                devices=devices,
                variant=config.variant,
                rate_hz=config.rate_hz,
                seconds=config.seconds,
                seed=101,
            )
        )

        def _simulate() -> None:
            try:
                sim_result["report"] = sim.run(sim_stop)
            except Exception as exc:  # reported by the main thread as the demo's failure
                sim_result["error"] = exc

        sim_thread = threading.Thread(target=_simulate, name="demo-edge-sim", daemon=True)
        started = time.monotonic()
        sim_thread.start()
        frame_period = config.seconds / max(1, config.gif_frames)
        next_frame = started
        while sim_thread.is_alive() and not stop.is_set():
            stop.wait(STATUS_INTERVAL_S)
            now = time.monotonic()
            state = service.state()
            running_statuses = {device: d["status"] for device, d in state["devices"].items()}
            if now >= next_frame:
                joints = state["devices"].get(devices[0], {}).get("joints_rad")
                if joints:
                    frames.append(dict(joints))
                    next_frame += frame_period
            if on_status is not None:
                on_status(_status(state, sim.report.published, now - started))
        sim_stop.set()
        sim_thread.join(10.0)
        # Messages published in the last instant are still in flight through the broker and the worker.
        time.sleep(0.5)
        final_state = service.state()
        if on_status is not None:
            on_status(_status(final_state, sim.report.published, time.monotonic() - started))
    finally:
        sim_stop.set()
        if sim_thread is not None:
            sim_thread.join(10.0)
        if service is not None:
            service.stop()  # closes the USD recording (final save)
        broker.stop()
        shutil.rmtree(workdir, ignore_errors=True)
    duration = time.monotonic() - started

    if "error" in sim_result:
        raise DemoError(f"the edge simulator failed: {sim_result['error']}")
    assert final_state is not None
    report = sim_result.get("report") or sim.report
    totals = _totals(final_state)
    interrupted = stop.is_set()
    if totals["received"] == 0:
        raise DemoError(
            f"the agent received no telemetry in {duration:.1f} s although the edge simulator published "
            f"{report.published} messages to {broker.url}: check the broker log and the agent log lines above"
        )
    stats = _stats(
        config=config,
        state=final_state,
        running_statuses=running_statuses,
        report=report,
        totals=totals,
        duration=duration,
        interrupted=interrupted,
        broker=broker,
        broker_pid=broker_pid,
        service=service,
    )
    _write_outputs(
        config=config,
        service=service,
        state=final_state,
        frames=frames,
        devices=devices,
        stats=stats,
        out_dir=out_dir,
    )
    return stats


def _status(state: dict[str, Any], sent: int, elapsed: float) -> DemoStatus:
    totals = _totals(state)
    devices = state["devices"]
    return DemoStatus(
        elapsed_s=elapsed,
        sent=sent,
        received=totals["received"],
        rejected=totals["rejected_total"],
        rate_hz=totals["rate_hz"],
        latency_p50_s=_worst(devices, "edge_clock_latency_s", "p50"),
        latency_p99_s=_worst(devices, "edge_clock_latency_s", "p99"),
        statuses={device: d["status"] for device, d in devices.items()},
    )


def _stats(
    *,
    config: DemoConfig,
    state: dict[str, Any],
    running_statuses: dict[str, str],
    report: Any,
    totals: dict[str, Any],
    duration: float,
    interrupted: bool,
    broker: Any,
    broker_pid: int | None,
    service: Any,
) -> dict[str, Any]:
    devices = state["devices"]
    per_device = {
        device: {
            # Health at the end of the publishing run (a moment later every arm is STALE: the edge stopped).
            "status": running_statuses.get(device, d["status"]),
            "status_after_stop": d["status"],
            "received": d["counters"]["received"],
            "applied": d["counters"]["applied"],
            "rejected": d["counters"].get("rejected", {}),
            "rate_hz": d.get("rate_hz"),
            "end_to_end_latency_s": {k: d["edge_clock_latency_s"].get(k) for k in ("p50", "p99")},
            "internal_latency_s": {k: d["internal_latency_s"].get(k) for k in ("p50", "p99")},
            "joints_rad": d.get("joints_rad"),
        }
        for device, d in devices.items()
    }
    return {
        "duration_s": round(duration, 3),
        "interrupted": interrupted,
        "variant": config.variant,
        "rate_hz": config.rate_hz,
        "devices": sorted(devices),
        "messages": {
            "sent": report.published,
            "generated": report.generated,
            "publish_failures": report.publish_failures,
            "received": totals["received"],
            "decoded": totals["decoded"],
            "applied": totals["applied"],
            "ignored_stale": totals["ignored_stale"],
            "overwritten": totals["overwritten"],
            "rejected": totals["rejected_total"],
            "rejected_by_reason": totals["rejected"],
            "lost": max(0, report.published - totals["received"]),
        },
        # Percentiles over the agent's health window (the last seconds of the run), worst device. The edge
        # simulator stamps messages with this host's clock, so end-to-end latency here has no skew in it.
        "latency_s": {
            "end_to_end": {
                "p50": _worst(devices, "edge_clock_latency_s", "p50"),
                "p99": _worst(devices, "edge_clock_latency_s", "p99"),
            },
            "internal": {
                "p50": _worst(devices, "internal_latency_s", "p50"),
                "p99": _worst(devices, "internal_latency_s", "p99"),
            },
            "window_s": service.config.health.window_s,
        },
        "per_device": per_device,
        "broker": {"url": broker.url, "pid": broker_pid},
        "files": {},
    }


def _write_outputs(
    *,
    config: DemoConfig,
    service: Any,
    state: dict[str, Any],
    frames: list[dict[str, float]],
    devices: list[str],
    stats: dict[str, Any],
    out_dir: Path,
) -> None:
    from twin.output.render import RenderError, render_png  # noqa: PLC0415

    first = state["devices"].get(devices[0], {})
    joints = first.get("joints_rad")
    if not joints:
        raise DemoError(f"device {devices[0]} was never mirrored: nothing to render (see stats above)")
    files: dict[str, str] = {}
    status = stats["per_device"][devices[0]]["status"]
    try:
        png = render_png(
            service.robot,
            joints,
            out_dir / "twin.png",
            text=f"{devices[0]}  {status}  after {stats['duration_s']:.0f} s",
        )
        files["png"] = png.name
        if len(frames) >= 2:
            files["gif"] = _write_gif(service.robot, frames, out_dir / "twin.gif", config.gif_size).name
    except RenderError as exc:
        raise DemoError(f"rendering failed: {exc}") from exc
    recording = service.recording_path
    if recording is None or not Path(recording).is_file():
        raise DemoError(f"the agent did not leave its USD session recording in {out_dir}")
    files["usd"] = Path(recording).name
    stats["files"] = files
    (out_dir / "stats.json").write_text(json.dumps(stats, indent=2, sort_keys=False) + "\n")


def _write_gif(robot: Any, frames: list[dict[str, float]], path: Path, size: tuple[int, int]) -> Path:
    """An animated GIF of the mirrored poses: one offscreen renderer for all (~30 small) frames."""
    import mujoco  # noqa: PLC0415
    from PIL import Image  # noqa: PLC0415

    from twin.output.render import RenderError  # noqa: PLC0415

    width, height = size
    model = robot.model
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
    model.vis.global_.offheight = max(model.vis.global_.offheight, height)
    data = mujoco.MjData(model)
    camera = "overview" if "overview" in robot.camera_names else -1
    try:
        renderer = mujoco.Renderer(model, height=height, width=width)
    except Exception as exc:  # GL backends raise assorted types
        raise RenderError(f"no OpenGL context for the animation (set MUJOCO_GL=egl): {exc}") from exc
    images = []
    with renderer:
        for angles in frames:
            for name, value in angles.items():
                if name in robot.qpos_addr:
                    lo, hi = robot.joint_ranges[name]
                    data.qpos[robot.qpos_addr[name]] = min(max(value, lo), hi)
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=camera)
            images.append(Image.fromarray(renderer.render()))
    images[0].save(path, save_all=True, append_images=images[1:], duration=100, loop=0)
    return path
